"""What a report's figures draw of a cloud: the samples, in a module without matplotlib, so that
a command can take them from a cloud it is about to let go and draw the figure later."""

from __future__ import annotations

import numpy as np

#: Points of each cloud the co-registration figure's profile panel draws from (a random sample
#: of a larger cloud).
PROFILE_POINTS = 400_000


def profile_sample(points: np.ndarray, source: str) -> np.ndarray:
    """The points (N, 3) of a cloud, ``source`` "ground" or "uav", that the co-registration
    figure's profile panel draws: all of a cloud of at most :data:`PROFILE_POINTS`, else a
    seeded random sample of that many (the same every time). Given to
    :func:`~forestreg.engine.report.coregistration_report.write_coregistration_report` instead of
    the whole cloud, it draws the same figure."""
    pts = np.asarray(points)
    if len(pts) <= PROFILE_POINTS:
        return pts
    rng = np.random.default_rng({"ground": 0, "uav": 1}[source])
    return pts[rng.choice(len(pts), PROFILE_POINTS, replace=False)]
