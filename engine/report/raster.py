"""Many small points on a matplotlib axes, drawn as one image.

``Axes.scatter`` keeps a path, a transform and a colour per point and draws each marker through
Agg: a plot map of 150,000 points cost 0.9 s and 34 MB of peak memory in every ``trees`` run.
:class:`PointRaster` paints the points straight into an RGBA image the size of the axes, in
screen pixels, when the figure is drawn (so at the final layout and dpi), and hands it to the
renderer as one image: that map figure, all of it, 0.9 -> 0.35 s and 34 -> 25 MB of peak memory (most
of what is left is matplotlib's own: the canvas, the text, the PNG). A point is a disc of the diameter a scatter marker of
the same size ``s`` (points squared) would have, at least one pixel; later points and layers
cover earlier ones, as in a scatter (:func:`~forestreg.engine.report.pixels.paint_discs`).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from matplotlib.artist import Artist, allow_rasterization
from matplotlib.colors import to_rgba_array

from .pixels import paint_discs

__all__ = ["PointRaster", "add_points"]


class PointRaster(Artist):
    """Layers of points drawn as one image in the data coordinates of an axes.

    Parameters
    ----------
    layers : ``(xy (N, 2), colours, size)`` per layer, drawn in order: ``xy`` in data units;
        ``colours`` one matplotlib colour, or one per point (colours, or an (N, 4) uint8 RGBA
        array, used as it is); ``size`` the marker area in points squared (as ``scatter``'s
        ``s``).
    """

    def __init__(self, layers: Sequence[tuple[np.ndarray, Any, float]]) -> None:
        super().__init__()
        self._layers = []
        for xy, colours, size in layers:
            xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
            if (
                isinstance(colours, np.ndarray)
                and colours.dtype == np.uint8
                and colours.ndim == 2
                and colours.shape[1] == 4
            ):
                rgba = colours  # RGBA bytes already: 4 bytes a point, not 32
            else:
                rgba = (to_rgba_array(colours) * 255.0 + 0.5).astype(np.uint8)
            if len(rgba) not in (1, len(xy)):
                raise ValueError(f"{len(rgba)} colours for {len(xy)} points")
            self._layers.append((xy, rgba, float(size)))
        self.set_zorder(1.0)  # under lines, patches and text, as a scatter (zorder 1)

    def extent(self) -> np.ndarray | None:
        """(2, 2) lower-left and upper-right corner of all points (data units), None if none."""
        xy = [layer[0] for layer in self._layers if len(layer[0])]
        if not xy:
            return None
        lo = np.min([p.min(axis=0) for p in xy], axis=0)
        hi = np.max([p.max(axis=0) for p in xy], axis=0)
        return np.array([lo, hi])

    @allow_rasterization
    def draw(self, renderer) -> None:
        if not self.get_visible():
            return
        ax = self.axes
        box = ax.bbox  # the axes in display pixels (after the layout and the aspect)
        x0, y0 = int(np.floor(box.x0)), int(np.floor(box.y0))
        width, height = int(np.ceil(box.x1)) - x0, int(np.ceil(box.y1)) - y0
        if width <= 0 or height <= 0:
            return
        image = np.zeros((height, width, 4), dtype=np.uint8)  # row 0 at the bottom (y0), as the renderer takes it
        to_pixels = ax.transData
        dots_per_point = renderer.points_to_pixels(1.0)
        for xy, rgba, size in self._layers:
            if not len(xy):
                continue
            pixels = to_pixels.transform(xy)
            pixels[:, 0] -= x0
            pixels[:, 1] -= y0
            radius = 0.5 * np.sqrt(max(size, 0.0)) * dots_per_point  # a scatter marker's radius
            paint_discs(image, pixels, rgba[0], radius, rgba if len(rgba) > 1 else None)
        gc = renderer.new_gc()
        gc.set_clip_rectangle(box)
        gc.set_gid(self.get_gid())
        renderer.draw_image(gc, x0, y0, image)
        gc.restore()
        self.stale = False


def add_points(ax, layers: Sequence[tuple[np.ndarray, Any, float]]) -> PointRaster:
    """Add a :class:`PointRaster` of ``layers`` to ``ax``; its points count in the axes' data
    limits, as a scatter's do."""
    artist = PointRaster(layers)
    ax.add_artist(artist)
    corners = artist.extent()
    if corners is not None:
        ax.update_datalim(corners)
        ax.autoscale_view()
    return artist
