"""System A: marker-free registration of terrestrial laser scans from trunk shadows (Guan et al.
2020), for pairs, whole plots and manual (target) registration.

* :mod:`.prepare`, :mod:`.ground`, :mod:`.level`, :mod:`.vop` - reduce, ground, levelling, slice,
  visual occlusion points (VOPs);
* :mod:`.coarse` - the exact horizontal matcher (and the paper's literal enumeration);
* :mod:`.evidence` - free-space checks that tell right from wrong solutions;
* :mod:`.pair` - the pair pipeline and its :class:`~.pair.PairResult`;
* :mod:`.project`, :mod:`.plot` - plot projects, linking, retries, pose graph;
* :mod:`.manual`, :mod:`.compare` - targets, manual registration, manual-vs-auto comparison;
* :mod:`.scanner_position` - where the scanner stood, from the data (georeferenced exports);
* :mod:`.survey`, :mod:`.uncertainty` - whole surveys: every pair, consistency, pose graph,
  uncertainty and quality without ground truth.
"""

__all__ = ["CoarseMatch", "match_vops", "match_vops_literal"]


def __getattr__(name: str):
    # imported on first use: ``forestreg.engine.tls.params`` stays light (no compiled kernels)
    if name in __all__:
        from . import coarse

        return getattr(coarse, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
