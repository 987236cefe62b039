"""forestreg.engine.match: registration of scans from their visual occlusion points (VOPs)."""

from .coarse import CoarseMatch, match_vops, match_vops_literal

__all__ = ["CoarseMatch", "match_vops", "match_vops_literal"]
