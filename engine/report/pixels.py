"""Points painted straight into an image array (NumPy only): the one implementation behind the
matplotlib point layers (:class:`~forestreg.engine.report.raster.PointRaster`) and the Pillow
top views (:mod:`~forestreg.engine.report.topview`).

A point is a disc of ``radius_px`` (the ink of an antialiased marker of that size), at least its
own pixel; later points cover earlier ones, as in a scatter plot. Discs are opaque and not
antialiased: these are clouds of thousands of one- or two-pixel dots, where neither is seen.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["paint_discs"]


def paint_discs(
    image: np.ndarray, pixels: np.ndarray, colour: np.ndarray, radius_px: float, colours: Optional[np.ndarray] = None
) -> None:
    """Paint a disc at each of ``pixels`` (N, 2: column, row as floats in the image's own pixel
    coordinates, a pixel ``(c, r)`` spanning ``[c, c + 1) x [r, r + 1)``) into ``image`` (H, W, C)
    uint8, in place: the pixels whose centres lie within ``radius_px`` of the point, and the
    point's own pixel always. ``colour`` (C,) uint8 for every point, or ``colours`` (N, C) one
    each. Points outside the image are left out. The outer rings are painted first, so that each
    point's own pixel is not covered by its neighbours' rims."""
    height, width = image.shape[:2]
    if not len(pixels):
        return
    col, row = np.floor(pixels[:, 0]).astype(np.int64), np.floor(pixels[:, 1]).astype(np.int64)
    reach = int(np.ceil(radius_px))

    def reachable(o: int) -> float:  # how far the offset pixel's centre is at least from the point's pixel
        return max(0.0, abs(o) - 0.5)

    rings = sorted(
        (
            (dc, dr)
            for dr in range(-reach, reach + 1)
            for dc in range(-reach, reach + 1)
            if reachable(dc) ** 2 + reachable(dr) ** 2 <= radius_px * radius_px
        ),
        key=lambda o: -(o[0] ** 2 + o[1] ** 2),
    )
    for dc, dr in rings:
        c, r = col + dc, row + dr
        inside = (c >= 0) & (c < width) & (r >= 0) & (r < height)
        if dc or dr:
            inside &= (c + 0.5 - pixels[:, 0]) ** 2 + (r + 0.5 - pixels[:, 1]) ** 2 <= radius_px * radius_px
        image[r[inside], c[inside]] = colour if colours is None else colours[inside]
