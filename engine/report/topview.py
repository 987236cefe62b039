"""Top-view panels drawn with Pillow: points, markers, circles and segments in data units
(metres) on equal-aspect axes with ticks, grid, titles and legends.

The pair figure (:func:`~forestreg.engine.report.figures.pair_figure`) is drawn with these for
``forestreg register``, the command run most often: matplotlib's import alone cost ~0.3 s of
CPU in every run, and its drawing 0.2 s (the pair took 9 % longer with them). The figure is
drawn at twice its size and reduced (each pixel the mean of four): lines, circles and text are smooth; the points
are painted as discs (:func:`~forestreg.engine.report.pixels.paint_discs`).

Sizes follow matplotlib's conventions so that the figures look alike: marker areas ``s`` in
points squared, line widths and font sizes in points, converted at the figure's ``dpi``.
"""

from __future__ import annotations

import importlib.util
import math
import os
import textwrap
from dataclasses import dataclass
from functools import lru_cache
from typing import Optional, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .pixels import paint_discs

#: The pair figures' colours of the reference and the moving scan.
REFERENCE_COLOUR = "#1f77b4"
MOVING_COLOUR = "#d95f02"

__all__ = ["Canvas", "Panel", "rgb"]

#: The figure is drawn this many times larger, then reduced: smooth lines and text.
SUPERSAMPLE = 2


def rgb(colour: str) -> tuple[int, int, int]:
    """``"#rrggbb"`` or a grey level ``"0.45"`` (matplotlib's notation) as an RGB tuple."""
    if colour.startswith("#") and len(colour) == 7:
        return tuple(int(colour[i : i + 2], 16) for i in (1, 3, 5))  # type: ignore[return-value]
    level = float(colour)
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"not a colour: {colour!r}")
    v = int(round(255 * level))
    return (v, v, v)


@lru_cache(maxsize=None)
def _font(size_px: int) -> ImageFont.FreeTypeFont:
    """DejaVu Sans (matplotlib's font, from its package data, found without importing it) at
    ``size_px`` pixels; Pillow's own font where matplotlib is not installed."""
    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = os.path.join(folder, "mpl-data", "fonts", "ttf", "DejaVuSans.ttf")
        if os.path.exists(path):
            return ImageFont.truetype(path, size_px)
    return ImageFont.load_default(size=size_px)


def nice_step(span: float, target: int = 9) -> float:
    """A tick step of 1, 2, 2.5 or 5 times a power of ten giving about ``target`` ticks over
    ``span`` (data units)."""
    if not span > 0 or not math.isfinite(span):
        return 1.0
    raw = span / target
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * power >= raw)


def _tick_label(value: float, step: float) -> str:
    """A tick's label with the decimals its step needs (2.5 m steps: one), a minus sign for a
    negative value."""
    decimals = 0
    while decimals < 6 and abs(step * 10**decimals - round(step * 10**decimals)) > 1e-9 * max(1.0, step * 10**decimals):
        decimals += 1
    text = f"{value:.{decimals}f}"
    return "\u2212" + text[1:] if text.startswith("-") else text  # a minus sign, as matplotlib


class Canvas:
    """A white figure ``width_in`` x ``height_in`` inches at ``dpi``, drawn at
    :data:`SUPERSAMPLE` times its size. Points are painted into :attr:`pixels` first (under
    everything), then :meth:`draw` gives the Pillow drawing for lines, markers and text."""

    def __init__(self, width_in: float, height_in: float, dpi: int) -> None:
        self.dpi = dpi
        self.scale = SUPERSAMPLE
        self.width = int(round(width_in * dpi))
        self.height = int(round(height_in * dpi))
        self.pixels = np.full((self.height * self.scale, self.width * self.scale, 3), 255, dtype=np.uint8)
        self._image: Optional[Image.Image] = None

    def px(self, points: float) -> float:
        """Points (1/72 inch) in drawing pixels."""
        return points * self.dpi / 72.0 * self.scale

    def draw(self) -> ImageDraw.ImageDraw:
        """The drawing on the canvas (after the points: nothing is painted into :attr:`pixels`
        from then on)."""
        return ImageDraw.Draw(self.image)

    @property
    def image(self) -> Image.Image:
        """The figure at its drawing size (:data:`SUPERSAMPLE` times the figure's)."""
        if self._image is None:
            self._image = Image.fromarray(self.pixels)
        return self._image

    def text(
        self,
        xy: tuple[float, float],
        text: str,
        size_pt: float,
        *,
        anchor: str = "mm",
        fill=(0, 0, 0),
        rotate: bool = False,
    ) -> None:
        """``text`` at drawing pixel ``xy`` (Pillow's ``anchor``), ``size_pt`` points; ``rotate``:
        turned 90 degrees counter-clockwise (a y-axis label), centred on ``xy``."""
        font = _font(max(1, int(round(self.px(size_pt)))))
        if not rotate:
            self.draw().multiline_text(
                xy, text, font=font, fill=fill, anchor=anchor, align="center", spacing=self.px(size_pt) * 0.25
            )
            return
        left, top, right, bottom = font.getbbox(text)
        label = Image.new("L", (right - left + 4, bottom - top + 4), 0)
        ImageDraw.Draw(label).text((2 - left, 2 - top), text, font=font, fill=255)
        label = label.rotate(90, expand=True)
        corner = (int(round(xy[0] - label.width / 2)), int(round(xy[1] - label.height / 2)))
        self.image.paste(Image.new("RGB", label.size, fill), corner, label)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Reduce to the figure's size (each pixel the mean of its :data:`SUPERSAMPLE` squared)
        and write a PNG (zlib's fastest level)."""
        self.image.reduce(self.scale).save(path, format="PNG", compress_level=1)


@dataclass
class _Entry:
    label: str
    marker: str
    colour: tuple[int, int, int]
    size: float
    line_pt: float


class Panel:
    """An equal-aspect axes in the box ``(left, top, right, bottom)`` (fractions of the
    figure, top down) showing data within ``lo``-``hi`` (x, y metres, expanded by 5 % as
    matplotlib's margins; the axes shrink to keep one metre as long across as up, centred in the
    box)."""

    def __init__(
        self, canvas: Canvas, box: tuple[float, float, float, float], lo: Sequence[float], hi: Sequence[float]
    ) -> None:
        self.canvas = canvas
        w, h = canvas.width * canvas.scale, canvas.height * canvas.scale
        x0, y0, x1, y1 = box[0] * w, box[1] * h, box[2] * w, box[3] * h
        lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        span = np.maximum(hi - lo, 1e-6)
        lo, hi = lo - 0.05 * span, hi + 0.05 * span
        span = hi - lo
        self.unit = min((x1 - x0) / span[0], (y1 - y0) / span[1])  # drawing pixels per metre
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        self.left, self.right = cx - span[0] * self.unit / 2, cx + span[0] * self.unit / 2
        self.top, self.bottom = cy - span[1] * self.unit / 2, cy + span[1] * self.unit / 2
        self.lo, self.hi = lo, hi
        self._legend: list[_Entry] = []
        #: The title's box (left, top, right, bottom; drawing pixels) once :meth:`frame` drew it.
        self.title_box: Optional[tuple[float, float, float, float]] = None

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) metres -> drawing pixels (column, row; rows grow downwards)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        return np.column_stack(
            [self.left + (xy[:, 0] - self.lo[0]) * self.unit, self.bottom - (xy[:, 1] - self.lo[1]) * self.unit]
        )

    def points(self, xy: np.ndarray, colour: str, size: float) -> None:
        """Paint points (N, 2) as discs of a scatter marker's area ``size`` (points squared),
        clipped to the axes. Call before any other drawing."""
        pix = self.to_px(xy)
        inside = (
            (pix[:, 0] >= self.left) & (pix[:, 0] < self.right) & (pix[:, 1] >= self.top) & (pix[:, 1] < self.bottom)
        )
        paint_discs(
            self.canvas.pixels,
            pix[inside],
            np.array(rgb(colour), dtype=np.uint8),
            0.5 * math.sqrt(max(size, 0.0)) * self.canvas.px(1.0),
        )

    def frame(self, title: str, *, wrap: int = 62, grid_pt: float = 0.3) -> None:
        """Grid, frame, ticks, tick labels, axis labels (x (m), y (m)) and the title (wrapped at
        ``wrap`` characters, at most two lines)."""
        c, d = self.canvas, self.canvas.draw()
        for axis in (0, 1):
            step = nice_step(float(self.hi[axis] - self.lo[axis]))
            first = math.ceil(self.lo[axis] / step - 1e-9)
            for k in range(first, int(math.floor(self.hi[axis] / step + 1e-9)) + 1):
                value = k * step
                if axis == 0:
                    x = float(self.to_px(np.array([[value, self.lo[1]]]))[0, 0])
                    d.line([(x, self.top), (x, self.bottom)], fill=(176, 176, 176), width=max(1, round(c.px(grid_pt))))
                    d.line(
                        [(x, self.bottom), (x, self.bottom + c.px(3.5))], fill=(0, 0, 0), width=max(1, round(c.px(0.8)))
                    )
                    c.text((x, self.bottom + c.px(5.0)), _tick_label(value, step), 10, anchor="mt")
                else:
                    y = float(self.to_px(np.array([[self.lo[0], value]]))[0, 1])
                    d.line([(self.left, y), (self.right, y)], fill=(176, 176, 176), width=max(1, round(c.px(grid_pt))))
                    d.line([(self.left - c.px(3.5), y), (self.left, y)], fill=(0, 0, 0), width=max(1, round(c.px(0.8))))
                    c.text((self.left - c.px(5.0), y), _tick_label(value, step), 10, anchor="rm")
        d.rectangle([self.left, self.top, self.right, self.bottom], outline=(0, 0, 0), width=max(1, round(c.px(0.8))))
        c.text(((self.left + self.right) / 2, self.bottom + c.px(19.0)), "x (m)", 10, anchor="mt")
        c.text((self.left - c.px(30.0), (self.top + self.bottom) / 2), "y (m)", 10, rotate=True)
        title = textwrap.fill(title, wrap, max_lines=2, placeholder=" ...")
        at = ((self.left + self.right) / 2, self.top - c.px(6.0))
        c.text(at, title, 12, anchor="md")
        self.title_box = d.multiline_textbbox(
            at, title, font=_font(max(1, int(round(c.px(12))))), anchor="md", align="center", spacing=c.px(12) * 0.25
        )

    def markers(
        self,
        xy: np.ndarray,
        marker: str,
        colour: str,
        *,
        size: float,
        line_pt: float = 1.0,
        label: Optional[str] = None,
    ) -> None:
        """Markers at (N, 2) metres: ``"o"`` open circle, ``"x"``, ``"+"``, ``"^"`` filled
        triangle; ``size`` the marker area in points squared (a triangle's ``size``: its
        matplotlib ``markersize`` squared). ``label`` adds a legend entry."""
        c, d = self.canvas, self.canvas.draw()
        fill, width = rgb(colour), max(1, round(c.px(line_pt)))
        half = 0.5 * math.sqrt(max(size, 0.0)) * c.px(1.0)
        for x, y in self.to_px(xy):
            if not (self.left <= x <= self.right and self.top <= y <= self.bottom):
                continue
            _marker(d, x, y, marker, half, fill, width)
        if label is not None:
            self._legend.append(_Entry(label, marker, fill, size, line_pt))

    def dashed_circle(self, centre: Sequence[float], radius_m: float, colour: str, *, line_pt: float = 0.8) -> None:
        """A dashed circle of ``radius_m`` metres (matplotlib's ``--``)."""
        c, d = self.canvas, self.canvas.draw()
        (x, y), r = self.to_px(np.asarray(centre, dtype=float)[None, :2])[0], radius_m * self.unit
        width, fill = max(1, round(c.px(line_pt))), rgb(colour)
        # dashes of 3.7 and gaps of 1.6 line widths (matplotlib's "--"), each a short polyline
        dash, gap = c.px(3.7 * line_pt * 1.6), c.px(1.6 * line_pt * 1.6)
        step, on = (dash + gap) / max(r, 1e-9), dash / max(r, 1e-9)
        for a in np.arange(0.0, 2 * math.pi, step):
            t = np.linspace(a, min(a + on, 2 * math.pi), 4)
            d.line(list(zip(x + r * np.cos(t), y - r * np.sin(t))), fill=fill, width=width)

    def segments(self, a: np.ndarray, b: np.ndarray, colour: str, *, line_pt: float) -> None:
        """Straight segments from each row of ``a`` to the same row of ``b`` (N, 2 metres)."""
        d = self.canvas.draw()
        fill, width = rgb(colour), max(1, round(self.canvas.px(line_pt)))
        for (x0, y0), (x1, y1) in zip(self.to_px(a), self.to_px(b)):
            d.line([(x0, y0), (x1, y1)], fill=fill, width=width)

    def legend(self) -> None:
        """The legend of the labelled markers in the upper right corner (8 points)."""
        if not self._legend:
            return
        c, d = self.canvas, self.canvas.draw()
        font = _font(max(1, int(round(c.px(8)))))
        pad, row, sample = c.px(4.0), c.px(11.0), c.px(14.0)
        text_w = max(font.getbbox(e.label)[2] for e in self._legend)
        w, h = pad * 3 + sample + text_w, pad * 2 + row * len(self._legend)
        x1, y0 = self.right - c.px(5.0), self.top + c.px(5.0)
        x0, y1 = x1 - w, y0 + h
        d.rounded_rectangle(
            [x0, y0, x1, y1],
            radius=c.px(3.0),
            fill=(255, 255, 255),
            outline=(204, 204, 204),
            width=max(1, round(c.px(0.8))),
        )
        for k, e in enumerate(self._legend):
            y = y0 + pad + row * (k + 0.5)
            _marker(
                d,
                x0 + pad + sample / 2,
                y,
                e.marker,
                0.5 * math.sqrt(max(e.size, 0.0)) * c.px(1.0),
                e.colour,
                max(1, round(c.px(e.line_pt))),
            )
            d.text((x0 + pad * 2 + sample, y), e.label, font=font, fill=(0, 0, 0), anchor="lm")


def _marker(d: ImageDraw.ImageDraw, x: float, y: float, marker: str, half: float, fill, width: int) -> None:
    if marker == "o":
        d.ellipse([x - half, y - half, x + half, y + half], outline=fill, width=width)
    elif marker == "x":
        k = half * 0.7071
        d.line([(x - k, y - k), (x + k, y + k)], fill=fill, width=width)
        d.line([(x - k, y + k), (x + k, y - k)], fill=fill, width=width)
    elif marker == "+":
        d.line([(x - half, y), (x + half, y)], fill=fill, width=width)
        d.line([(x, y - half), (x, y + half)], fill=fill, width=width)
    elif marker == "^":
        d.polygon([(x, y - half), (x - half, y + half), (x + half, y + half)], fill=fill)  # matplotlib's "^"
    else:
        raise ValueError(f"unknown marker {marker!r}")
