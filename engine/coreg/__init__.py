"""Ground-based / UAV co-registration by canopy keypoints (System B, paper section 4.1).

* :mod:`.keypoints` - HDBSCAN clusters of the canopy and their density peaks on the DEM;
* :mod:`.matching` - one-to-one keypoint correspondences by graph matching, tolerant of missing
  and extra keypoints, and the rigid transform;
* :mod:`.coregister` - the pipeline: DEMs, keypoints, matching, coarse ICP of the best candidates
  and verification after it, fine ICP, evidence (standard errors, quality without truth).

Example::

    from forestreg.engine.coreg import coregister
    result = coregister(ground_scan, uav_scan)       # p_uav = result.matrix @ p_ground
"""

from .coregister import (
    CoregistrationParams,
    CoregistrationResult,
    coregister,
    coregister_points,
    coregistration_quality,
    jackknife_standard_errors,
)
from .keypoints import KeypointParams, Keypoints, extract_keypoints
from .matching import KeypointMatch, MatchingParams, match_keypoints, residual_statistics

__all__ = [
    "CoregistrationParams",
    "CoregistrationResult",
    "KeypointMatch",
    "KeypointParams",
    "Keypoints",
    "MatchingParams",
    "coregister",
    "coregister_points",
    "coregistration_quality",
    "jackknife_standard_errors",
    "extract_keypoints",
    "match_keypoints",
    "residual_statistics",
]
