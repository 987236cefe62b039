"""Synthetic forest plots: terrain, trees, shrubs, lianas, reflector targets and buildings.

A :class:`ForestScene` is pure geometry description (no meshes); :mod:`.mesh` turns it into
triangles and :mod:`.scanner` casts TLS rays at them.

Frames and angles
-----------------
The scene frame ("world") is a local metric frame with x east, y north, z up. The plot is the
square ``[-size/2, size/2]^2`` centred on the origin, and the terrain passes through ``z = 0`` at
the plot centre (plus roughness). Every horizontal direction in this package (slope direction,
lean direction, scanner yaw, tilt direction) is a *mathematical* azimuth in degrees: measured
counter-clockwise from +x.

Presets
-------
:data:`PRESETS` maps a preset name to a :class:`PresetConfig`; ``make_scene(name, seed=...)``
draws a plot from it, deterministically per seed. Any config field can be overridden with a
keyword (``make_scene("sloped", slope_deg=25)``; a scalar given for a ``(low, high)`` range
field means exactly that value).

===============  ========  =========  ========  ===============  =======  ==========================
preset           stems/ha  DBH m      height m  shrubs/ha        slope    other
===============  ========  =========  ========  ===============  =======  ==========================
planted_conifer  ~980      0.20-0.40  15-20     50, 0.3-1.0 m    0-2 deg  3 m grid turned at random,
                                                                          jitter 0.2-0.5 m, 10 %
                                                                          missing; cone crowns from
                                                                          50-65 % of the height;
                                                                          crown cover ~0.75
mixed_temperate  900       0.10-0.60  12-28     400, 0.5-2.0 m   0-3 deg  half clustered (Thomas),
                                                                          half random; 45 % conifer,
                                                                          55 % broadleaf (ellipsoid)
rainforest       2400      0.08-0.80  6-40      2500, 0.5-3.0 m  0-5 deg  reverse-J DBH (median
                                                                          0.15 m), lianas 120/ha,
                                                                          broadleaf, cover ~1.0,
                                                                          roughness 0.2 m
sloped           800       0.10-0.55  12-26     300, 0.4-1.8 m   15-20    mixed; roughness 0.3 m;
                                                                 deg      lean up to 10 deg
plantation_rows  ~830      0.20-0.40  15-20     20, 0.3-1.0 m    0-2 deg  exact rows: 3 m along rows
                                                                          4 m apart, turned at random,
                                                                          jitter 0-8 cm, 3 % missing
open_field       0         -          -         60, 0.3-1.2 m    0-3 deg  building 8 x 6 x 4 m and a
                                                                          post-and-rail fence; no
                                                                          trees
===============  ========  =========  ========  ===============  =======  ==========================

Heights grow with DBH (``h = low + (high - low) * sqrt(dbh fraction)``, +-10 %, then times
``exp(N(0, height_scatter))``); trees lean by ``lean_max_deg * U^2`` in a random direction; stems
keep at least ``r_i + r_j + 0.3 m`` apart.

Stems are round (a circle in section) unless ``make_scene(..., stem_shapes="real")``: then each
tree gets an ovality of 0-10 % (major axis at a random angle), a bark relief of 1-3 mm and, on a
broadleaf of more than 0.45 m DBH, 3-6 buttress lobes at its base (see :class:`Tree` and
:func:`with_stem_shapes`); ``dbh_m`` stays the tape (girth) diameter at 1.3 m, and every other
draw of the scene is the same as with round stems.

Built scenes (walls, posts in rows, a corridor, a courtyard, a park) are presets too:
``make_scene("corridor", seed=...)`` draws them with :func:`~.built.make_built_scene` (see
:mod:`.built` and :data:`~.built.BUILT_PRESETS`).

Every forest preset places 6-8 reflector targets (10 cm reflective cylinders) on poles 1.2-2.0 m high,
spread over the central part of the plot (3 m to 30 % of the plot size from the centre).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np
from scipy import ndimage

from ..core.errors import ParameterError

#: Crown shapes.
CONIFER = "conifer"
BROADLEAF = "broadleaf"

#: Breast height (m) along the stem axis from the stem base, where DBH is defined.
BREAST_HEIGHT_M = 1.3

#: Facets around a shaped (not round) stem, as meshed; the vertices of a section lie at the
#: stem-frame angles ``2 pi j / SHAPED_STEM_SEGMENTS``.
SHAPED_STEM_SEGMENTS = 64

#: Largest ovality (``1 - b / a``) and bark relief (m, 1-sigma) a :class:`Tree` accepts.
MAX_OVALITY = 0.15
MAX_BARK_ROUGHNESS_M = 0.004

#: Stem shape options of :func:`make_scene`.
STEM_SHAPES = ("round", "real")

#: Cosine modes of a bark relief field.
_BARK_MODES = 32


def _section_angles(n: int = SHAPED_STEM_SEGMENTS) -> np.ndarray:
    return np.arange(n) * (2.0 * math.pi / n)


def _polygon_perimeter(r: np.ndarray) -> float:
    """Perimeter of the polygon with radii ``r`` at equally spaced angles."""
    n = len(r)
    rn = np.roll(r, -1)
    return float(np.sum(np.sqrt(r * r + rn * rn - 2.0 * r * rn * math.cos(2.0 * math.pi / n))))


def _polygon_area(r: np.ndarray) -> float:
    """Area of the polygon with radii ``r`` at equally spaced angles."""
    n = len(r)
    return float(0.5 * math.sin(2.0 * math.pi / n) * np.sum(r * np.roll(r, -1)))


_PATTERNS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}


def _stem_pattern(bark_seed: int, tree_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A tree's stem pattern from ``(bark_seed, tree_id)``: the bark relief's modes (integer
    wave numbers around the stem, wave numbers along it in rad/m, phases) and the phase (rad) of
    the buttress lobes."""
    key = (int(bark_seed), int(tree_id))
    hit = _PATTERNS.get(key)
    if hit is None:
        rng = np.random.default_rng([key[0] & 0xFFFFFFFF, key[1] & 0xFFFFFFFF, 8111])
        m = _BARK_MODES
        around = rng.integers(6, 25, size=m) * rng.choice([-1, 1], size=m)
        along = 2.0 * math.pi / rng.uniform(0.12, 0.60, size=m) * rng.choice([-1.0, 1.0], size=m)
        phase = rng.uniform(0.0, 2.0 * math.pi, size=m)
        hit = (around.astype(np.float64), along, phase, float(rng.uniform(0.0, 2.0 * math.pi)))
        if len(_PATTERNS) > 4096:
            _PATTERNS.clear()
        _PATTERNS[key] = hit
    return hit


def _bark_field(bark_seed: int, tree_id: int, theta: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The unit bark relief field (1-sigma 1, zero mean around every section) at ``(theta, s)``."""
    around, along, phase, _ = _stem_pattern(bark_seed, tree_id)
    th, ss = np.broadcast_arrays(np.asarray(theta, dtype=np.float64), np.asarray(s, dtype=np.float64))
    out = np.zeros(th.shape)
    for k in range(len(around)):
        out += np.cos(around[k] * th + along[k] * ss + phase[k])
    return out * math.sqrt(2.0 / len(around))


# --------------------------------------------------------------------------------------------
# Terrain
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Terrain:
    """A height field z(x, y) on a regular grid, triangulated exactly as the terrain mesh.

    Attributes
    ----------
    x0, y0 : the grid's lower-left corner (m).
    cell_m : grid spacing (m).
    heights : (ny, nx) float64 heights at the grid nodes, ``heights[j, i]`` at
        ``(x0 + i * cell, y0 + j * cell)``.
    slope_deg : the plane's slope (degrees).
    slope_azimuth_deg : the direction (mathematical azimuth) in which the ground *rises*.
    roughness_m : amplitude of the smooth roughness added to the plane (max |deviation|).
    """

    x0: float
    y0: float
    cell_m: float
    heights: np.ndarray
    slope_deg: float = 0.0
    slope_azimuth_deg: float = 0.0
    roughness_m: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.heights.shape)  # type: ignore[return-value]

    @property
    def x1(self) -> float:
        return self.x0 + (self.heights.shape[1] - 1) * self.cell_m

    @property
    def y1(self) -> float:
        return self.y0 + (self.heights.shape[0] - 1) * self.cell_m

    def z(self, x: Any, y: Any) -> Any:
        """Ground height at (x, y): piecewise-linear on the mesh's triangles (clamped at the edge).

        Each grid cell is split along its diagonal from (i, j) to (i+1, j+1), as in
        :func:`forestreg.engine.simulate.mesh.terrain_mesh`, so this is the height of the mesh.
        Scalars in give a float out; arrays give an array.
        """
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        ny, nx = self.heights.shape
        u = np.clip((xa - self.x0) / self.cell_m, 0.0, nx - 1 - 1e-9)
        v = np.clip((ya - self.y0) / self.cell_m, 0.0, ny - 1 - 1e-9)
        i = np.floor(u).astype(np.int64)
        j = np.floor(v).astype(np.int64)
        fu = u - i
        fv = v - j
        h = self.heights
        z00 = h[j, i]
        z10 = h[j, i + 1]
        z01 = h[j + 1, i]
        z11 = h[j + 1, i + 1]
        # lower triangle (fu >= fv): (0,0), (1,0), (1,1); upper: (0,0), (1,1), (0,1)
        lower = z00 + fu * (z10 - z00) + fv * (z11 - z10)
        upper = z00 + fv * (z01 - z00) + fu * (z11 - z01)
        out = np.where(fu >= fv, lower, upper)
        if out.ndim == 0:
            return float(out)
        return out

    def normal(self, x: float, y: float, eps: float = 0.25) -> np.ndarray:
        """Unit upward normal of the ground near (x, y) (central differences over ``eps``)."""
        dzdx = (self.z(x + eps, y) - self.z(x - eps, y)) / (2 * eps)
        dzdy = (self.z(x, y + eps) - self.z(x, y - eps)) / (2 * eps)
        n = np.array([-dzdx, -dzdy, 1.0])
        return n / np.linalg.norm(n)


def make_terrain(
    extent: tuple[float, float, float, float],
    *,
    slope_deg: float,
    slope_azimuth_deg: float,
    roughness_m: float,
    roughness_length_m: float,
    cell_m: float,
    rng: np.random.Generator,
) -> Terrain:
    """A tilted plane through the origin plus smooth noise of amplitude ``roughness_m``."""
    xmin, xmax, ymin, ymax = extent
    nx = int(math.ceil((xmax - xmin) / cell_m)) + 1
    ny = int(math.ceil((ymax - ymin) / cell_m)) + 1
    xs = xmin + np.arange(nx) * cell_m
    ys = ymin + np.arange(ny) * cell_m
    gx, gy = np.meshgrid(xs, ys)
    az = math.radians(slope_azimuth_deg)
    grad = math.tan(math.radians(slope_deg))
    heights = grad * (gx * math.cos(az) + gy * math.sin(az))
    if roughness_m > 0.0:
        noise = rng.standard_normal((ny, nx))
        sigma = max(roughness_length_m / cell_m, 0.5)
        smooth = ndimage.gaussian_filter(noise, sigma=sigma, mode="reflect")
        peak = float(np.abs(smooth).max())
        if peak > 0:
            smooth *= roughness_m / peak
        # keep the plot centre at z = 0
        ci = int(round((0.0 - xmin) / cell_m))
        cj = int(round((0.0 - ymin) / cell_m))
        if 0 <= ci < nx and 0 <= cj < ny:
            smooth -= smooth[cj, ci]
        heights = heights + smooth
    heights = np.ascontiguousarray(heights)
    heights.setflags(write=False)
    return Terrain(
        x0=float(xmin),
        y0=float(ymin),
        cell_m=float(cell_m),
        heights=heights,
        slope_deg=float(slope_deg),
        slope_azimuth_deg=float(slope_azimuth_deg),
        roughness_m=float(roughness_m),
    )


# --------------------------------------------------------------------------------------------
# Objects
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Tree:
    """One tree.

    The stem is a straight, leaning axis from the base ``(x, y, z)`` (on the ground) in the
    direction given by ``lean_deg`` from vertical towards ``lean_azimuth_deg``. The stem radius
    along the axis follows :meth:`radius_at` (butt flare below 1 m, then linear taper), so that
    ``2 * radius_at(1.3) == dbh_m``. ``height_m`` is the vertical height of the top above the base.
    The crown starts at ``crown_base_m`` (vertical, above the base) and has radius
    ``crown_radius_m``: a cone (``shape == "conifer"``) or an ellipsoid (``"broadleaf"``).

    Stem shape
    ----------
    By default the stem is round: its section at ``s`` (along the axis) is the circle of radius
    :meth:`radius_at`. A stem with ``ovality``, buttress lobes or bark relief (not
    :attr:`is_round`) has the section

        ``r(theta, s) = radius_at(s) * k * e(theta) * (1 + A(s) * L(theta)) + rough(theta, s)``

    in its stem frame (:meth:`stem_frame`: ``theta`` in radians about the axis, measured from the
    world +x projected into the section plane, counter-clockwise seen from above, i.e.
    right-handed about the axis; for a vertical stem ``theta`` is the mathematical azimuth):

    * ``e(theta)``: the polar radius of an ellipse of semi-axes 1 and ``1 - ovality``, its major
      axis at ``theta = radians(ovality_azimuth_deg)`` (the same at every height);
    * ``L(theta) = ((1 + cos(n (theta - phase))) / 2)^3``: ``n = buttress_lobes`` peaked lobes
      (0 between them), ``phase`` drawn from the tree's pattern seed; ``A(s) =
      buttress_amplitude * (1 - s / flare_height)^2`` below the flare height (``flare_height_m``,
      at most 1.3 m), 0 above it, so the lobes never reach breast height;
    * ``k``: the scale that makes the smooth section at breast height as meshed (the polygon of
      :data:`SHAPED_STEM_SEGMENTS` vertices at ``theta_j = 2 pi j / n``) have the perimeter
      ``pi * dbh_m``: ``dbh_m`` is the tape (girth) diameter (:meth:`girth_diameter_m`), and
      ``radius_at(s)`` half the girth diameter wherever there are no lobes;
    * ``rough``: the bark relief, a zero-mean random field of 1-sigma ``bark_roughness_m`` (full
      on stems over 0.1 m thick, fading to the thin top), correlated over a few cm around and along
      the stem (wavelengths 12-60 cm along it), drawn from ``(bark_seed, id)`` only: a tree that grows
      (a larger ``dbh_m``) keeps its bark pattern, lobes and ellipse.
    """

    id: int
    x: float
    y: float
    z: float
    dbh_m: float
    height_m: float
    lean_deg: float = 0.0
    lean_azimuth_deg: float = 0.0
    crown_base_m: float = 8.0
    crown_radius_m: float = 2.0
    shape: str = CONIFER
    #: stem radius at the stem top, as a fraction of the breast-height radius
    top_radius_fraction: float = 0.05
    #: fraction of the tree height the stem reaches (1 for conifers, less for broadleaves)
    stem_height_fraction: float = 1.0
    #: butt flare: radius at the base is ``(1 + flare) * r_bh``
    flare: float = 0.15
    #: height (along the axis) up to which the flare reaches: 1 m for ordinary trees, up to
    #: 1.3 m for buttressed giants (above breast height the DBH would no longer be ``dbh_m``)
    flare_height_m: float = 1.0
    #: number of main branches
    n_branches: int = 4
    #: leaf area density of the crown, m^2 of leaf per m^3 of crown
    leaf_area_density: float = 0.5
    #: leaders the stem forks into at its top (a forked trunk: the stem ends at the fork, each
    #: leader takes 1/n of its cross-section and reaches the tree's height; the main branches
    #: grow from the leaders); 0: an ordinary stem
    fork_leaders: int = 0
    #: stem section: ovality ``1 - b / a`` of its ellipse (0 = round; 0..0.15)
    ovality: float = 0.0
    #: direction of the ellipse's major axis (deg): angle in the stem frame (:meth:`stem_frame`;
    #: for a vertical stem, the mathematical azimuth), the same at every height
    ovality_azimuth_deg: float = 0.0
    #: buttress lobes around the stem base: 0 (none) or 3..6
    buttress_lobes: int = 0
    #: height of a lobe as a fraction of the section radius at the base (s <= 0), decaying to 0 by
    #: the flare height (0..1)
    buttress_amplitude: float = 0.0
    #: bark relief (m): 1-sigma of the radial deviation, zero mean (0..0.004)
    bark_roughness_m: float = 0.0
    #: seed of the tree's stem pattern (bark relief, lobe phase) together with ``id``: the
    #: scene's seed for drawn scenes
    bark_seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.ovality <= MAX_OVALITY:
            raise ParameterError(f"tree {self.id}: ovality must be within 0-{MAX_OVALITY}, got {self.ovality}")
        if self.buttress_lobes not in (0, 3, 4, 5, 6):
            raise ParameterError(f"tree {self.id}: buttress_lobes must be 0 or 3-6, got {self.buttress_lobes}")
        if not 0.0 <= self.buttress_amplitude <= 1.0:
            raise ParameterError(
                f"tree {self.id}: buttress_amplitude must be within 0-1, got {self.buttress_amplitude}"
            )
        if not 0.0 <= self.bark_roughness_m <= MAX_BARK_ROUGHNESS_M:
            raise ParameterError(
                f"tree {self.id}: bark_roughness_m must be within 0-{MAX_BARK_ROUGHNESS_M} m, got {self.bark_roughness_m}"
            )

    @property
    def axis(self) -> np.ndarray:
        """Unit vector of the stem axis (pointing up)."""
        lean = math.radians(self.lean_deg)
        az = math.radians(self.lean_azimuth_deg)
        return np.array([math.sin(lean) * math.cos(az), math.sin(lean) * math.sin(az), math.cos(lean)])

    @property
    def base(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z], dtype=np.float64)

    @property
    def stem_length_m(self) -> float:
        """Length of the stem along its axis."""
        return self.stem_height_fraction * self.height_m / math.cos(math.radians(self.lean_deg))

    def point_at(self, s: Any) -> np.ndarray:
        """Point(s) on the stem axis at distance ``s`` along the axis from the base."""
        s = np.asarray(s, dtype=np.float64)
        return self.base + s[..., None] * self.axis

    def point_at_height(self, h: float) -> np.ndarray:
        """The stem axis point at vertical height ``h`` above the base."""
        return self.point_at(h / math.cos(math.radians(self.lean_deg)))

    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """(s, r): the stem radius profile as meshed, piecewise linear in ``s`` (along the axis)."""
        r_bh = self.dbh_m / 2.0
        length = self.stem_length_m
        r_top = max(self.top_radius_fraction * r_bh, 0.005)
        below = length - BREAST_HEIGHT_M
        if below < -1e-6:  # a stem ending below breast height (a trunk forked low): the same line
            slope = (r_bh - r_top) / below
        else:
            slope = (r_bh - r_top) / max(below, 1e-6)  # taper per metre

        def lin(s: float) -> float:
            return r_bh + (BREAST_HEIGHT_M - s) * slope

        fh = min(max(self.flare_height_m, 0.1), BREAST_HEIGHT_M)
        s_list = [0.0, 0.3 * fh, 0.6 * fh, fh]
        r_list = [
            lin(0.0) + self.flare * r_bh,
            lin(0.3 * fh) + self.flare * r_bh * 0.45,
            lin(0.6 * fh) + self.flare * r_bh * 0.15,
            lin(fh),
        ]
        step = 2.0
        s = fh + step
        while s < length - 0.5:
            s_list.append(s)
            r_list.append(lin(s))
            s += step
        s_list.append(length)
        r_list.append(r_top)
        return np.asarray(s_list), np.asarray(r_list)

    def radius_at(self, s: Any) -> Any:
        """Stem radius (m) at distance ``s`` along the axis from the base: exactly as meshed for a
        round stem; for a shaped stem, half the girth diameter of the section wherever there are
        no buttress lobes (the ring radius before the shape, see the class docstring)."""
        ss, rr = self.profile()
        out = np.interp(np.asarray(s, dtype=np.float64), ss, rr, right=0.0)
        return float(out) if np.ndim(out) == 0 else out

    # -- stem shape ------------------------------------------------------------------------

    @property
    def is_round(self) -> bool:
        """Whether the stem is the default round one (no ovality, lobes or bark relief): meshed
        as a ``trunk_segments``-gon of the circle's area, exactly as before shapes existed."""
        return (
            self.ovality == 0.0
            and (self.buttress_lobes == 0 or self.buttress_amplitude == 0.0)
            and self.bark_roughness_m == 0.0
        )

    def stem_frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(u, v, d)``: unit vectors of the stem frame (world frame). ``d`` is the axis
        (:attr:`axis`), ``u`` the world +x projected into the section plane (+y if the axis lies
        along x), ``v = d x u``. A section angle ``theta`` (radians) is the direction
        ``cos(theta) u + sin(theta) v``."""
        d = self.axis
        u = np.array([1.0, 0.0, 0.0]) - d * d[0]
        n = math.sqrt(float(u @ u))
        if n < 1e-9:
            u = np.array([0.0, 1.0, 0.0]) - d * d[1]
            n = math.sqrt(float(u @ u))
        u = u / n
        v = np.array([d[1] * u[2] - d[2] * u[1], d[2] * u[0] - d[0] * u[2], d[0] * u[1] - d[1] * u[0]])
        return u, v, d

    def _shape_factor(self, theta: np.ndarray, s: np.ndarray) -> np.ndarray:
        """``e(theta) * (1 + A(s) L(theta))`` (dimensionless, broadcast over theta and s)."""
        phi = theta - math.radians(self.ovality_azimuth_deg)
        b = 1.0 - self.ovality
        out = b / np.sqrt((b * np.cos(phi)) ** 2 + np.sin(phi) ** 2)
        if self.buttress_lobes and self.buttress_amplitude > 0.0:
            fh = min(max(self.flare_height_m, 0.1), BREAST_HEIGHT_M)
            a = self.buttress_amplitude * np.clip(1.0 - s / fh, 0.0, 1.0) ** 2
            lobe = (
                (1.0 + np.cos(self.buttress_lobes * (theta - _stem_pattern(self.bark_seed, self.id)[3]))) / 2.0
            ) ** 3
            out = out * (1.0 + a * lobe)
        return out

    def _ring_scale(self) -> float:
        """``k``: the scale that gives the smooth meshed section at breast height the perimeter
        ``pi * dbh_m`` (the lobes are 0 there)."""
        th = _section_angles()
        e = self._shape_factor(th, np.full_like(th, BREAST_HEIGHT_M))
        return 2.0 * math.pi / _polygon_perimeter(e)

    def section_radius(self, theta: Any, s: Any, *, smooth: bool = False) -> Any:
        """Radius (m) of the stem section at angle ``theta`` (radians, stem frame: see
        :meth:`stem_frame`) and distance ``s`` (m) along the axis from the base, broadcast over
        both; with ``smooth`` without the bark relief. A round stem gives :meth:`radius_at`."""
        th = np.asarray(theta, dtype=np.float64)
        sa = np.asarray(s, dtype=np.float64)
        r_ring = np.asarray(self.radius_at(sa), dtype=np.float64)
        if self.is_round:
            out = np.broadcast_to(r_ring, np.broadcast_shapes(th.shape, sa.shape)).copy()
            return float(out) if out.ndim == 0 else out
        smooth_r = r_ring * self._ring_scale() * self._shape_factor(th, sa)
        out = smooth_r
        if not smooth and self.bark_roughness_m > 0.0:
            rough = (
                self.bark_roughness_m * _bark_field(self.bark_seed, self.id, th, sa) * np.clip(r_ring / 0.05, 0.0, 1.0)
            )
            out = np.maximum(smooth_r + rough, 0.5 * smooth_r)
        out = np.asarray(out)
        return float(out) if out.ndim == 0 else out

    def section_polygon(self, s: float = BREAST_HEIGHT_M) -> np.ndarray:
        """The smooth section at ``s`` as meshed: radii (m) at the :data:`SHAPED_STEM_SEGMENTS`
        angles ``theta_j = 2 pi j / n`` of the stem frame (for a round stem, ``radius_at(s)``
        at every angle)."""
        th = _section_angles()
        return np.asarray(self.section_radius(th, np.full_like(th, float(s)), smooth=True), dtype=np.float64)

    def girth_diameter_m(self, s: float = BREAST_HEIGHT_M) -> float:
        """Tape diameter (m) at ``s`` along the axis: the perimeter of the smooth section as meshed
        divided by pi (equal to ``dbh_m`` at breast height); a round stem gives
        ``2 * radius_at(s)`` (the circle)."""
        if self.is_round:
            return 2.0 * float(self.radius_at(s))
        return _polygon_perimeter(self.section_polygon(s)) / math.pi

    def area_diameter_m(self, s: float = BREAST_HEIGHT_M) -> float:
        """Diameter (m) of the circle with the area of the smooth section at ``s`` as meshed (at
        most the girth diameter); a round stem gives ``2 * radius_at(s)``."""
        if self.is_round:
            return 2.0 * float(self.radius_at(s))
        return 2.0 * math.sqrt(_polygon_area(self.section_polygon(s)) / math.pi)

    def section_area_m2(self, s: float) -> float:
        """Area (m^2) of the smooth section at ``s`` (the circle for a round stem, the meshed
        polygon for a shaped one)."""
        if self.is_round:
            return math.pi * float(self.radius_at(s)) ** 2
        return _polygon_area(self.section_polygon(s))

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["stem_length_m"] = self.stem_length_m
        return d


@dataclass(frozen=True)
class Shrub:
    """A shrub (ellipsoid of foliage and a few twigs) standing on the ground at (x, y, z)."""

    id: int
    x: float
    y: float
    z: float
    radius_m: float
    height_m: float
    leaf_area_density: float = 1.0


@dataclass(frozen=True)
class Liana:
    """A thin woody climber/clutter: a polyline of control points with a constant radius."""

    id: int
    points: tuple[tuple[float, float, float], ...]
    radius_m: float = 0.02


@dataclass(frozen=True)
class Target:
    """A reflector target on a pole: a vertical reflective cylinder centred at (x, y, z).

    ``ground_z`` is the ground height under the pole; the pole runs from there to the reflector.
    """

    id: int
    x: float
    y: float
    z: float
    ground_z: float
    radius_m: float = 0.05
    height_m: float = 0.10
    pole_radius_m: float = 0.015

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z], dtype=np.float64)


@dataclass(frozen=True)
class Post:
    """A vertical round post or column: a cylinder of ``radius_m`` standing on the ground at
    ``(x, y, z)`` up to ``height_m`` above it (meshed like a stem, sunk 0.2 m into the ground).

    Built structures stand in rows at a regular spacing (a colonnade, a fence, a pergola); each
    post casts a shadow just like a trunk. Posts are not trees: they are kept in
    :attr:`ForestScene.posts`, apart from :attr:`ForestScene.trees` (the stems' truth)."""

    id: int
    x: float
    y: float
    z: float
    radius_m: float
    height_m: float
    kind: str = "post"


#: Box kinds a scanner never stands in and :meth:`ForestScene.cleared` never removes (built walls
#: and building blocks: an operator sets up beside them, not in them).
FIXED_BOX_KINDS = frozenset({"wall", "block"})


@dataclass(frozen=True)
class Box:
    """An oriented box (a building, a wall, a fence post or rail), standing on its bottom face.

    ``(x, y, z)`` is the centre of the bottom face, ``size`` the (length, width, height) along its
    own axes, ``yaw_deg`` the azimuth of its length axis.
    """

    id: int
    x: float
    y: float
    z: float
    size: tuple[float, float, float]
    yaw_deg: float = 0.0
    kind: str = "building"


# --------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PresetConfig:
    """The recipe for one kind of plot. Ranges are ``(low, high)`` and drawn uniformly unless
    stated. Densities are per hectare."""

    description: str
    #: "none" | "grid" | "rows" | "random" | "clustered"
    layout: str = "random"
    #: nominal stem density (stems/ha) for random/clustered layouts; for "grid" it follows
    #: from ``grid_spacing_m`` and ``missing_fraction``
    stems_per_ha: float = 900.0
    #: grid layouts: the spacing of the trees (along the rows for "rows")
    grid_spacing_m: float = 3.0
    #: "rows": the spacing of the rows (0 = ``grid_spacing_m``)
    row_spacing_m: float = 0.0
    #: per-tree jitter of grid positions: a random direction and a distance in this range
    grid_jitter_m: tuple[float, float] = (0.2, 0.5)
    #: fraction of grid positions left empty (dead/thinned trees)
    missing_fraction: float = 0.10
    #: clustered layouts: fraction of trees in clusters, cluster radius (m), trees per cluster
    cluster_fraction: float = 0.5
    cluster_radius_m: float = 3.0
    cluster_size: float = 6.0
    dbh_m: tuple[float, float] = (0.2, 0.4)
    #: DBH density ~ d^(-dbh_power) on dbh_m; 0 = uniform, 2 = reverse-J (many thin stems)
    dbh_power: float = 0.0
    height_m: tuple[float, float] = (15.0, 20.0)
    #: each tree's height (and crown base) times exp(N(0, height_scatter)): a wider scatter about
    #: the height-diameter relation than the presets' (about 3 %), as of a stand of several
    #: species or ages (0 = the preset's relation alone)
    height_scatter: float = 0.0
    #: fraction of conifers (cone crowns, stem to the top); the rest are broadleaves
    conifer_fraction: float = 1.0
    #: crown base as a fraction of the tree height
    crown_base_fraction: tuple[float, float] = (0.5, 0.65)
    #: crown radius (m) = a + b * DBH(m), times a random factor in crown_radius_jitter
    crown_radius_ab: tuple[float, float] = (0.8, 4.0)
    crown_radius_jitter: tuple[float, float] = (0.8, 1.2)
    lean_max_deg: float = 3.0
    branches_per_tree: tuple[int, int] = (3, 6)
    #: crown leaf area density (m^2/m^3): sets how many rays a crown stops
    leaf_area_density: float = 0.5
    shrubs_per_ha: float = 50.0
    shrub_height_m: tuple[float, float] = (0.3, 1.0)
    shrub_radius_m: tuple[float, float] = (0.3, 0.8)
    shrub_leaf_area_density: float = 1.0
    lianas_per_ha: float = 0.0
    slope_deg: tuple[float, float] = (0.0, 2.0)
    roughness_m: float = 0.05
    roughness_length_m: float = 6.0
    terrain_cell_m: float = 0.5
    n_targets: tuple[int, int] = (6, 8)
    target_height_m: tuple[float, float] = (1.2, 2.0)
    #: open field: a building-like box and a fence
    structures: bool = False
    #: crowns do not grow into each other: a tree whose top would stand inside a taller
    #: neighbour's crown is suppressed to this distance (m) below that crown's lower surface
    #: (its crown base scaled with it); 0 = crowns may interpenetrate
    suppressed_clearance_m: float = 0.0


#: The forest presets' stands, one row a preset: the :class:`PresetConfig` fields named in
#: :data:`_STAND_FIELDS`, in that order.
_STAND_FIELDS = (
    "dbh_m",
    "dbh_power",
    "height_m",
    "conifer_fraction",
    "crown_base_fraction",
    "crown_radius_ab",
    "lean_max_deg",
    "branches_per_tree",
    "leaf_area_density",
    "shrubs_per_ha",
    "shrub_height_m",
    "shrub_radius_m",
    "slope_deg",
    "roughness_m",
)
_STANDS: dict[str, tuple[Any, ...]] = {
    #                  DBH m         DBH^-p height m      conifer crown base    crown r a+bD lean  branches LAD   shrubs  shrub h     shrub r     slope deg     rough m
    "planted_conifer": (
        (0.20, 0.40),
        0.0,
        (15.0, 20.0),
        1.0,
        (0.50, 0.65),
        (1.0, 3.5),
        2.0,
        (3, 5),
        0.6,
        50.0,
        (0.3, 1.0),
        (0.3, 0.7),
        (0.0, 2.0),
        0.05,
    ),
    "mixed_temperate": (
        (0.10, 0.60),
        1.0,
        (12.0, 28.0),
        0.45,
        (0.35, 0.55),
        (0.8, 5.0),
        6.0,
        (3, 6),
        0.5,
        400.0,
        (0.5, 2.0),
        (0.4, 1.2),
        (0.0, 3.0),
        0.10,
    ),
    "rainforest": (
        (0.08, 0.80),
        2.0,
        (6.0, 40.0),
        0.0,
        (0.45, 0.70),
        (0.8, 7.0),
        8.0,
        (2, 6),
        0.45,
        2500.0,
        (0.5, 3.0),
        (0.4, 1.2),
        (0.0, 5.0),
        0.20,
    ),
    "sloped": (
        (0.10, 0.55),
        1.0,
        (12.0, 26.0),
        0.5,
        (0.40, 0.60),
        (0.8, 4.5),
        10.0,
        (3, 6),
        0.5,
        300.0,
        (0.4, 1.8),
        (0.4, 1.0),
        (15.0, 20.0),
        0.30,
    ),
}


def _stand(preset: str) -> dict[str, Any]:
    """The :data:`_STANDS` row of ``preset`` as :class:`PresetConfig` keywords."""
    return dict(zip(_STAND_FIELDS, _STANDS[preset], strict=True))


#: The preset recipes (see the module docstring for a table).
PRESETS: dict[str, PresetConfig] = {
    "planted_conifer": PresetConfig(
        description="even-aged conifer plantation on a jittered 3 m grid (~1000 stems/ha), "
        "pruned stems, cone crowns, few low shrubs, nearly flat",
        layout="grid",
        grid_spacing_m=3.0,
        grid_jitter_m=(0.2, 0.5),
        missing_fraction=0.10,
        **_stand("planted_conifer"),
    ),
    "mixed_temperate": PresetConfig(
        description="uneven-aged mixed temperate forest (~900 stems/ha, clustered and random), "
        "conifer and broadleaf crowns, moderate shrub layer up to 2 m",
        layout="clustered",
        stems_per_ha=900.0,
        cluster_fraction=0.5,
        cluster_radius_m=3.0,
        cluster_size=6.0,
        **_stand("mixed_temperate"),
    ),
    "rainforest": PresetConfig(
        description="tropical rainforest: >2000 stems/ha, mostly thin (reverse-J DBH 0.08-0.8 m), "
        "dense understory, lianas and high canopy cover",
        layout="random",
        stems_per_ha=2400.0,
        shrub_leaf_area_density=0.9,
        lianas_per_ha=120.0,
        **_stand("rainforest"),
    ),
    "sloped": PresetConfig(
        description="mixed forest on a 15-20 deg slope with rough ground and leaning trees",
        layout="random",
        stems_per_ha=800.0,
        roughness_length_m=5.0,
        **_stand("sloped"),
    ),
    "plantation_rows": PresetConfig(
        description="conifer plantation planted in exact rows: a tree every 3 m along rows 4 m "
        "apart (the rows turned at random), jitter up to 8 cm, 3 % missing: a near-perfect "
        "lattice of trunks, where one row or one tree along it looks like the next",
        layout="rows",
        grid_spacing_m=3.0,
        row_spacing_m=4.0,
        grid_jitter_m=(0.0, 0.08),
        missing_fraction=0.03,
        **{**_stand("planted_conifer"), "lean_max_deg": 1.0, "shrubs_per_ha": 20.0},
    ),
    "open_field": PresetConfig(
        description="non-forest scene: open ground with low shrubs, a building-like box and a "
        "fence; no trees (a registration by trunk shadows must refuse it)",
        layout="none",
        stems_per_ha=0.0,
        shrubs_per_ha=60.0,
        shrub_height_m=(0.3, 1.2),
        shrub_radius_m=(0.3, 1.0),
        slope_deg=(0.0, 3.0),
        roughness_m=0.10,
        structures=True,
    ),
}


# --------------------------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ForestScene:
    """A synthetic plot: terrain, trees, shrubs, lianas, reflector targets, boxes and posts.

    ``extent`` is ``(xmin, xmax, ymin, ymax)`` of the plot (m, scene frame). ``config`` is the
    preset recipe the scene was drawn from (with overrides applied).
    """

    preset: str
    seed: int
    extent: tuple[float, float, float, float]
    terrain: Terrain
    trees: tuple[Tree, ...] = ()
    shrubs: tuple[Shrub, ...] = ()
    lianas: tuple[Liana, ...] = ()
    targets: tuple[Target, ...] = ()
    boxes: tuple[Box, ...] = ()
    #: the preset recipe: a :class:`PresetConfig`, or a :class:`~.built.BuiltConfig` for a built scene
    config: Optional[Any] = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    #: posts and columns (built scenes)
    posts: tuple[Post, ...] = ()

    @property
    def area_ha(self) -> float:
        xmin, xmax, ymin, ymax = self.extent
        return (xmax - xmin) * (ymax - ymin) / 1.0e4

    @property
    def stems_per_ha(self) -> float:
        return len(self.trees) / self.area_ha

    def ground_z(self, x: Any, y: Any) -> Any:
        """Ground height at (x, y)."""
        return self.terrain.z(x, y)

    def tree(self, tree_id: int) -> Tree:
        for t in self.trees:
            if t.id == tree_id:
                return t
        from ..core.errors import UnknownNameError

        raise UnknownNameError(f"no tree with id {tree_id!r} in the scene")

    def cleared(self, positions: Sequence[Sequence[float]], radius_m: float = 1.0) -> "ForestScene":
        """A copy without the objects standing within ``radius_m`` of the given (x, y) positions.

        An operator sets a scanner up in a gap; this removes trees whose stem (at 0-2 m) passes
        within ``radius_m`` of a position, and shrubs, lianas, targets, boxes and posts likewise;
        walls and building blocks (:data:`FIXED_BOX_KINDS`) stay.
        """
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        if len(pos) == 0 or radius_m <= 0:
            return self

        def near(xy: np.ndarray, extra: float) -> bool:
            return bool((np.linalg.norm(pos - xy[None, :2], axis=1) < radius_m + extra).any())

        trees = []
        for t in self.trees:
            r = t.dbh_m / 2.0 * (1.0 + t.flare) * (1.0 + t.buttress_amplitude)
            if any(near(t.point_at_height(h), r) for h in (0.0, 1.0, 2.0)):
                continue
            trees.append(t)
        shrubs = [s for s in self.shrubs if not near(np.array([s.x, s.y]), s.radius_m)]
        lianas = [li for li in self.lianas if not any(near(np.asarray(p[:2]), li.radius_m) for p in li.points[:2])]
        targets = [t for t in self.targets if not near(np.array([t.x, t.y]), t.radius_m)]
        boxes = [
            b
            for b in self.boxes
            if b.kind in FIXED_BOX_KINDS or not near(np.array([b.x, b.y]), 0.5 * math.hypot(b.size[0], b.size[1]))
        ]
        posts = [p for p in self.posts if not near(np.array([p.x, p.y]), p.radius_m)]
        meta = dict(self.meta)
        meta["cleared_positions"] = pos.tolist()
        meta["cleared_radius_m"] = radius_m
        return dataclasses.replace(
            self,
            trees=tuple(trees),
            shrubs=tuple(shrubs),
            lianas=tuple(lianas),
            targets=tuple(targets),
            boxes=tuple(boxes),
            posts=tuple(posts),
            meta=meta,
        )

    def summary(self) -> dict[str, Any]:
        """A small JSON-able description of the plot (counts, densities, slope)."""
        dbh = np.array([t.dbh_m for t in self.trees]) if self.trees else np.zeros(0)
        h = np.array([t.height_m for t in self.trees]) if self.trees else np.zeros(0)
        return {
            "preset": self.preset,
            "seed": self.seed,
            "extent": list(self.extent),
            "area_ha": self.area_ha,
            "n_trees": len(self.trees),
            "stems_per_ha": self.stems_per_ha,
            "dbh_m": [float(dbh.min()), float(dbh.mean()), float(dbh.max())] if len(dbh) else None,
            "height_m": [float(h.min()), float(h.mean()), float(h.max())] if len(h) else None,
            "n_shrubs": len(self.shrubs),
            "n_lianas": len(self.lianas),
            "n_targets": len(self.targets),
            "n_boxes": len(self.boxes),
            "slope_deg": self.terrain.slope_deg,
            "slope_azimuth_deg": self.terrain.slope_azimuth_deg,
            "roughness_m": self.terrain.roughness_m,
            **({"n_posts": len(self.posts)} if self.posts else {}),
        }


def _as_range(name: str, value: Any, current: Any) -> Any:
    if isinstance(current, tuple) and not isinstance(value, (tuple, list)):
        return (type(current[0])(value), type(current[1])(value))
    if isinstance(current, tuple):
        if len(value) != 2:
            raise ParameterError(f"{name} must be a (low, high) pair, got {value!r}")
        return tuple(value)
    return value


#: Scene presets drawn by other modules, by name: ``maker(seed=..., size_m=..., **overrides)``
#: returning a :class:`ForestScene` (the built scenes of :mod:`.built` enter theirs when the
#: package is imported).
SCENE_MAKERS: dict[str, Callable[..., "ForestScene"]] = {}


def preset_names() -> tuple[str, ...]:
    """Every scene preset :func:`make_scene` takes: the forest presets (:data:`PRESETS`), then the
    others (:data:`SCENE_MAKERS`: the built scenes of :data:`~.built.BUILT_PRESETS`)."""
    return tuple(PRESETS) + tuple(k for k in SCENE_MAKERS if k not in PRESETS)


def preset_config(preset: str, **overrides: Any) -> PresetConfig:
    """The :class:`PresetConfig` of ``preset`` with keyword overrides applied."""
    if preset not in PRESETS:
        raise ParameterError(f"unknown scene preset {preset!r}; choose one of {', '.join(preset_names())}")
    return with_overrides(PRESETS[preset], overrides, "scene option(s)")


def with_overrides(cfg: Any, overrides: dict[str, Any], what: str) -> Any:
    """A scene recipe (a :class:`PresetConfig` or a built scene's config) with keyword overrides
    applied (a scalar for a range field means exactly that value); an unknown name is a
    :class:`~forestreg.engine.core.errors.ParameterError` listing ``what`` the options are."""
    if not overrides:
        return cfg
    names = {f.name for f in dataclasses.fields(cfg)}
    bad = sorted(set(overrides) - names)
    if bad:
        raise ParameterError(f"unknown {what} {', '.join(bad)}; options are: {', '.join(sorted(names))}")
    return dataclasses.replace(cfg, **{k: _as_range(k, v, getattr(cfg, k)) for k, v in overrides.items()})


def make_scene(
    preset: str, *, seed: int = 0, size_m: float = 60.0, stem_shapes: str = "round", **overrides: Any
) -> ForestScene:
    """Draw a plot of ``size_m`` x ``size_m`` metres from a preset (deterministic per seed).

    Parameters
    ----------
    preset : one of :data:`PRESETS` ("planted_conifer", "mixed_temperate", "rainforest",
        "sloped", "plantation_rows", "open_field") or a built scene of
        :data:`~.built.BUILT_PRESETS` ("corridor", "colonnade", "fence", "courtyard", "park",
        "campus"; drawn by :func:`~.built.make_built_scene`).
    seed : random seed; the same (preset, seed, size_m, overrides) give the same scene.
    size_m : side of the square plot, centred on the origin.
    stem_shapes : "round" (every stem a circle in section, as the other draws of the preset
        give it) or "real": the same trees with real stem shapes drawn from a stream of their
        own (:func:`with_stem_shapes`: ovality, bark relief, buttress lobes on big broadleaves);
        every other draw of the scene is unchanged.
    overrides : any :class:`PresetConfig` field, e.g. ``slope_deg=18`` or ``stems_per_ha=500``
        (for a built scene: any :class:`~.built.BuiltConfig` field).

    Raises
    ------
    ParameterError
        Unknown preset, option or stem shape, or a plot size outside 10-500 m.
    """
    if not (10.0 <= float(size_m) <= 500.0):
        raise ParameterError(f"plot size must be between 10 and 500 m, got {size_m}")
    if stem_shapes not in STEM_SHAPES:
        raise ParameterError(f"stem_shapes must be one of {', '.join(STEM_SHAPES)}, got {stem_shapes!r}")
    if preset not in PRESETS and preset in SCENE_MAKERS:
        made = SCENE_MAKERS[preset](seed=seed, size_m=size_m, **overrides)
        return with_stem_shapes(made) if stem_shapes == "real" else made
    cfg = preset_config(preset, **overrides)
    rng = np.random.default_rng([int(seed), _stable_hash(preset)])
    half = float(size_m) / 2.0
    extent = (-half, half, -half, half)

    slope = float(rng.uniform(*cfg.slope_deg))
    slope_az = float(rng.uniform(0.0, 360.0))
    terrain = make_terrain(
        extent,
        slope_deg=slope,
        slope_azimuth_deg=slope_az,
        roughness_m=cfg.roughness_m,
        roughness_length_m=cfg.roughness_length_m,
        cell_m=cfg.terrain_cell_m,
        rng=rng,
    )

    # separate streams so that e.g. changing shrub density does not move the trees
    r_trees, r_shrubs, r_lianas, r_targets, r_boxes = rng.spawn(5)
    trees = _make_trees(cfg, extent, terrain, r_trees)
    if stem_shapes == "real":  # a stream of its own: the other draws stay those of the round scene
        trees = _real_stems(trees, int(seed), preset)
    boxes = _make_boxes(cfg, extent, terrain, r_boxes) if cfg.structures else []
    shrubs = _make_shrubs(cfg, extent, terrain, trees, boxes, r_shrubs)
    lianas = _make_lianas(cfg, extent, terrain, trees, r_lianas)
    targets = _make_targets(cfg, size_m, terrain, trees, shrubs, boxes, r_targets)
    return ForestScene(
        preset=preset,
        seed=int(seed),
        extent=extent,
        terrain=terrain,
        trees=tuple(trees),
        shrubs=tuple(shrubs),
        lianas=tuple(lianas),
        targets=tuple(targets),
        boxes=tuple(boxes),
        config=cfg,
        meta={
            "size_m": float(size_m),
            "overrides": {k: v for k, v in overrides.items()},
            **({"stem_shapes": stem_shapes} if stem_shapes != "round" else {}),
        },
    )


#: Ranges of the real stem shapes (:func:`with_stem_shapes`): ovality, bark relief (m), buttress
#: lobe amplitude; the DBH (m) above which a broadleaf has buttress lobes.
REAL_OVALITY = (0.0, 0.10)
REAL_BARK_ROUGHNESS_M = (0.001, 0.003)
REAL_BUTTRESS_AMPLITUDE = (0.15, 0.40)
REAL_BUTTRESS_MIN_DBH_M = 0.45


def real_stem_shape(tree: Tree, seed: int, preset: str) -> Tree:
    """``tree`` with a real stem shape drawn from ``(seed, preset, tree.id)`` alone (the same tree
    of the same scene always gets the same shape): ovality in :data:`REAL_OVALITY` with its major
    axis at a random angle, bark relief in :data:`REAL_BARK_ROUGHNESS_M` (its pattern seeded by
    ``seed``), and for a broadleaf over :data:`REAL_BUTTRESS_MIN_DBH_M` DBH 3-6 buttress lobes of
    amplitude :data:`REAL_BUTTRESS_AMPLITUDE`. ``dbh_m`` (the tape diameter) and every other field
    stay."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, _stable_hash(preset), 4999, int(tree.id) & 0xFFFFFFFF])
    ovality = float(rng.uniform(*REAL_OVALITY))
    azimuth = float(rng.uniform(0.0, 360.0))
    rough = float(rng.uniform(*REAL_BARK_ROUGHNESS_M))
    lobes = int(rng.integers(3, 7))
    amplitude = float(rng.uniform(*REAL_BUTTRESS_AMPLITUDE))
    big_broadleaf = tree.shape == BROADLEAF and tree.dbh_m > REAL_BUTTRESS_MIN_DBH_M
    return dataclasses.replace(
        tree,
        ovality=ovality,
        ovality_azimuth_deg=azimuth,
        bark_roughness_m=rough,
        bark_seed=int(seed),
        buttress_lobes=lobes if big_broadleaf else 0,
        buttress_amplitude=amplitude if big_broadleaf else 0.0,
    )


def _real_stems(trees: Sequence[Tree], seed: int, preset: str) -> list[Tree]:
    return [real_stem_shape(t, seed, preset) for t in trees]


def with_stem_shapes(scene: ForestScene) -> ForestScene:
    """``scene`` with real stem shapes (:func:`real_stem_shape`, drawn from the scene's seed and
    preset and each tree's id) on every tree; nothing else changes (``meta["stem_shapes"]`` is
    "real")."""
    trees = _real_stems(scene.trees, scene.seed, scene.preset)
    return dataclasses.replace(scene, trees=tuple(trees), meta={**dict(scene.meta), "stem_shapes": "real"})


def given_or_made_scene(
    scene: Optional[ForestScene], preset: str, seed: int, size_m: float, overrides: dict[str, Any]
) -> ForestScene:
    """``scene`` when given, else :func:`make_scene` ``(preset, seed, size_m, **overrides)``.

    Raises
    ------
    ParameterError
        Both a scene and overrides are given, or as :func:`make_scene`.
    """
    if scene is None:
        return make_scene(preset, seed=seed, size_m=size_m, **overrides)
    if overrides:
        raise ParameterError("give either a scene or scene overrides, not both")
    return scene


def _stable_hash(text: str) -> int:
    h = 0
    for ch in text.encode("utf-8"):
        h = (h * 131 + ch) % 2_147_483_647
    return h


def _sample_dbh(cfg: PresetConfig, n: int, rng: np.random.Generator) -> np.ndarray:
    lo, hi = cfg.dbh_m
    u = rng.uniform(size=n)
    p = cfg.dbh_power
    if lo <= 0 or hi <= lo or p == 0.0:
        return lo + (hi - lo) * u
    if abs(p - 1.0) < 1e-9:
        return lo * (hi / lo) ** u
    a = 1.0 - p  # inverse CDF of d^-p on [lo, hi]
    return (lo**a + u * (hi**a - lo**a)) ** (1.0 / a)


def _positions(
    cfg: PresetConfig, extent: tuple[float, ...], radii: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Random or clustered stem positions: no two stems closer than r_i + r_j + 0.3 m.

    Returns the accepted positions (n', 2) and their radii (a stem that finds no room in 200
    tries is dropped, so n' <= n).
    """
    xmin, xmax, ymin, ymax = extent
    n = len(radii)
    margin = 0.3
    accepted: list[np.ndarray] = []
    acc_r: list[float] = []
    pts = np.zeros((0, 2))
    rr = np.zeros(0)

    def ok(p: np.ndarray, r: float) -> bool:
        if len(pts) == 0:
            return True
        d = np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1])
        return bool((d >= rr + r + margin).all())

    n_cluster = int(round(cfg.cluster_fraction * n)) if cfg.layout == "clustered" else 0
    parents = None
    if n_cluster:
        n_par = max(1, int(round(n_cluster / max(cfg.cluster_size, 1.0))))
        parents = rng.uniform([xmin, ymin], [xmax, ymax], size=(n_par, 2))
    for k in range(n):
        r = float(radii[k])
        for _attempt in range(200):
            if parents is not None and k < n_cluster:
                c = parents[rng.integers(len(parents))]
                p = c + rng.normal(0.0, cfg.cluster_radius_m, size=2)
                if not (xmin <= p[0] <= xmax and ymin <= p[1] <= ymax):
                    continue
            else:
                p = rng.uniform([xmin, ymin], [xmax, ymax])
            if ok(p, r):
                accepted.append(p)
                acc_r.append(r)
                pts = np.vstack([pts, p[None, :]])
                rr = np.append(rr, r)
                break
    return np.asarray(accepted).reshape(-1, 2), np.asarray(acc_r)


def _make_trees(cfg: PresetConfig, extent: tuple[float, ...], terrain: Terrain, rng: np.random.Generator) -> list[Tree]:
    if cfg.layout == "none":
        return []
    xmin, xmax, ymin, ymax = extent
    area_ha = (xmax - xmin) * (ymax - ymin) / 1.0e4
    if cfg.layout == "grid":
        sp = cfg.grid_spacing_m
        # the rows of a plantation are seldom aligned with the plot
        rot = math.radians(rng.uniform(0.0, 90.0))
        c, s = math.cos(rot), math.sin(rot)
        big = np.arange(-(xmax - xmin), (xmax - xmin) + sp, sp)
        gx, gy = np.meshgrid(big, big)
        g = np.column_stack([gx.ravel(), gy.ravel()])
        pos = g @ np.array([[c, s], [-s, c]])
        inside = (
            (pos[:, 0] > xmin + 0.3) & (pos[:, 0] < xmax - 0.3) & (pos[:, 1] > ymin + 0.3) & (pos[:, 1] < ymax - 0.3)
        )
        pos = pos[inside]
        ang = rng.uniform(0.0, 2 * math.pi, size=len(pos))
        dist = rng.uniform(*cfg.grid_jitter_m, size=len(pos))
        pos = pos + np.column_stack([np.cos(ang), np.sin(ang)]) * dist[:, None]
        keep = rng.uniform(size=len(pos)) >= cfg.missing_fraction
        pos = pos[keep]
        pos = pos[(pos[:, 0] > xmin) & (pos[:, 0] < xmax) & (pos[:, 1] > ymin) & (pos[:, 1] < ymax)]
        dbh = _sample_dbh(cfg, len(pos), rng)
    elif cfg.layout == "rows":
        pos = _row_positions(cfg, extent, rng)
        dbh = _sample_dbh(cfg, len(pos), rng)
    else:
        n = int(round(cfg.stems_per_ha * area_ha))
        dbh = _sample_dbh(cfg, n, rng)
        # place the big stems first so they find room
        order = np.argsort(-dbh)
        dbh = dbh[order]
        pos, radii = _positions(cfg, extent, dbh / 2.0 * 1.2, rng)
        dbh = radii * 2.0 / 1.2
        perm = rng.permutation(len(pos))
        pos, dbh = pos[perm], dbh[perm]
    return _trees_at(cfg, pos, dbh, terrain, rng)


def _row_positions(cfg: PresetConfig, extent: tuple[float, ...], rng: np.random.Generator) -> np.ndarray:
    """Planted rows: trees every ``grid_spacing_m`` along rows ``row_spacing_m`` apart (the grid
    turned at random, centred on the plot centre), each moved by a random direction and a distance
    in ``grid_jitter_m``, ``missing_fraction`` of them left out."""
    xmin, xmax, ymin, ymax = extent
    along = cfg.grid_spacing_m
    across = cfg.row_spacing_m if cfg.row_spacing_m > 0 else along
    rot = math.radians(rng.uniform(0.0, 180.0))
    c, s = math.cos(rot), math.sin(rot)
    reach = math.hypot(xmax - xmin, ymax - ymin) / 2.0
    ka = np.arange(-math.ceil(reach / along), math.ceil(reach / along) + 1)
    kc = np.arange(-math.ceil(reach / across), math.ceil(reach / across) + 1)
    ga, gc = np.meshgrid(ka * along, kc * across)
    u = np.column_stack([ga.ravel(), gc.ravel()])
    pos = u @ np.array([[c, s], [-s, c]])
    ang = rng.uniform(0.0, 2 * math.pi, size=len(pos))
    dist = rng.uniform(*cfg.grid_jitter_m, size=len(pos))
    pos = pos + np.column_stack([np.cos(ang), np.sin(ang)]) * dist[:, None]
    keep = rng.uniform(size=len(pos)) >= cfg.missing_fraction
    pos = pos[keep]
    inside = (pos[:, 0] > xmin + 0.3) & (pos[:, 0] < xmax - 0.3) & (pos[:, 1] > ymin + 0.3) & (pos[:, 1] < ymax - 0.3)
    return pos[inside]


def _trees_at(
    cfg: PresetConfig, pos: np.ndarray, dbh: np.ndarray, terrain: Terrain, rng: np.random.Generator
) -> list[Tree]:
    """Trees of ``cfg``'s stand at ``pos`` (n, 2) with diameters ``dbh``: heights, crowns, lean and
    branches drawn from ``rng``."""
    n = len(pos)
    lo, hi = cfg.dbh_m
    frac = np.clip((dbh - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    hlo, hhi = cfg.height_m
    height = hlo + (hhi - hlo) * np.sqrt(frac) * rng.uniform(0.85, 1.1, size=n)
    height = np.clip(height, hlo, hhi)
    conifer = rng.uniform(size=n) < cfg.conifer_fraction
    cb = rng.uniform(*cfg.crown_base_fraction, size=n) * height
    a, b = cfg.crown_radius_ab
    crown_r = (a + b * dbh) * rng.uniform(*cfg.crown_radius_jitter, size=n)
    crown_r = np.where(conifer, crown_r * 0.8, crown_r)
    lean = cfg.lean_max_deg * rng.uniform(size=n) ** 2
    lean_az = rng.uniform(0.0, 360.0, size=n)
    nb = rng.integers(cfg.branches_per_tree[0], cfg.branches_per_tree[1] + 1, size=n)
    top_frac = np.where(conifer, 0.05, rng.uniform(0.25, 0.4, size=n))
    stem_frac = np.where(conifer, 1.0, rng.uniform(0.7, 0.85, size=n))
    lad = cfg.leaf_area_density * rng.uniform(0.8, 1.2, size=n)
    if cfg.height_scatter > 0:  # drawn last: the other draws stay those of the preset
        factor = np.exp(rng.normal(0.0, cfg.height_scatter, size=n))
        height, cb = height * factor, cb * factor
    z = terrain.z(pos[:, 0], pos[:, 1]) if n else np.zeros(0)
    trees = []
    for i in range(n):
        trees.append(
            Tree(
                id=i + 1,
                x=float(pos[i, 0]),
                y=float(pos[i, 1]),
                z=float(z[i]),
                dbh_m=float(round(dbh[i], 4)),
                height_m=float(height[i]),
                lean_deg=float(lean[i]),
                lean_azimuth_deg=float(lean_az[i]),
                crown_base_m=float(cb[i]),
                crown_radius_m=float(crown_r[i]),
                shape=CONIFER if conifer[i] else BROADLEAF,
                top_radius_fraction=float(top_frac[i]),
                stem_height_fraction=float(stem_frac[i]),
                n_branches=int(nb[i]),
                leaf_area_density=float(lad[i]),
            )
        )
    if cfg.suppressed_clearance_m > 0:
        trees = _suppress_under_crowns(trees, cfg.suppressed_clearance_m)
    return trees


def crown_floor(tree: Tree, x: float, y: float) -> float:
    """z (scene frame) of the lower surface of ``tree``'s crown volume above (x, y): the flat
    base of a conifer's cone, the lower half of a broadleaf's ellipsoid; inf outside the crown's
    reach."""
    length = max(tree.height_m - tree.crown_base_m, 0.0)
    r = tree.crown_radius_m
    if tree.shape == BROADLEAF:
        c = tree.point_at_height(
            min(tree.stem_height_fraction * tree.height_m, (tree.crown_base_m + tree.height_m) / 2.0)
        )
        rho = math.hypot(x - c[0], y - c[1])
        if rho >= r:
            return math.inf
        return tree.z + (tree.crown_base_m + tree.height_m) / 2.0 - 0.5 * length * math.sqrt(1.0 - (rho / r) ** 2)
    apex = tree.point_at_height(tree.height_m)
    return tree.z + tree.crown_base_m if math.hypot(x - apex[0], y - apex[1]) < r else math.inf


def _suppress_under_crowns(trees: list[Tree], clearance_m: float) -> list[Tree]:
    """Subordinate trees (at most 85 % of a neighbour's height) whose top would stand inside
    that neighbour's crown volume, lowered to ``clearance_m`` below the crown's lower surface
    (their crown base scaled with the height). A tree that would lose more than 40 % of its
    height keeps it (co-dominant crowns that meet are left as drawn)."""
    out = list(trees)
    for i, t in enumerate(trees):
        over = [o for o in trees if o.id != t.id and t.height_m <= 0.85 * o.height_m]
        new_h = t.height_m
        for _ in range(5):  # a leaning stem's apex moves as it is lowered: until it is clear
            apex = t.point_at_height(new_h)
            floors = [crown_floor(o, float(apex[0]), float(apex[1])) - clearance_m - t.z for o in over]
            lowest = min([f for f in floors if f < new_h], default=None)
            if lowest is None:
                break
            new_h = lowest
        apex = t.point_at_height(new_h)
        clear = all(crown_floor(o, float(apex[0]), float(apex[1])) - clearance_m - t.z >= new_h - 1e-9 for o in over)
        if clear and 0.6 * t.height_m <= new_h < t.height_m:
            out[i] = dataclasses.replace(
                t, height_m=float(new_h), crown_base_m=float(t.crown_base_m * new_h / t.height_m)
            )
    return out


def _stem_xy(trees: Sequence[Tree]) -> tuple[np.ndarray, np.ndarray]:
    if not trees:
        return np.zeros((0, 2)), np.zeros(0)
    xy = np.array([[t.x, t.y] for t in trees])
    # the flare only: shrubs, lianas and targets stand where they would beside round stems
    r = np.array([t.dbh_m / 2.0 * (1.0 + t.flare) for t in trees])
    return xy, r


def _make_shrubs(
    cfg: PresetConfig,
    extent: tuple[float, ...],
    terrain: Terrain,
    trees: Sequence[Tree],
    boxes: Sequence[Box],
    rng: np.random.Generator,
) -> list[Shrub]:
    xmin, xmax, ymin, ymax = extent
    area_ha = (xmax - xmin) * (ymax - ymin) / 1.0e4
    n = int(rng.poisson(cfg.shrubs_per_ha * area_ha)) if cfg.shrubs_per_ha > 0 else 0
    xy, r = _stem_xy(trees)
    out = []
    for k in range(n):
        for _ in range(20):
            p = rng.uniform([xmin, ymin], [xmax, ymax])
            rad = float(rng.uniform(*cfg.shrub_radius_m))
            if len(xy) and (np.hypot(xy[:, 0] - p[0], xy[:, 1] - p[1]) < r + 0.3).any():
                continue
            if any(
                abs(p[0] - b.x) < b.size[0] / 2 + rad and abs(p[1] - b.y) < b.size[1] / 2 + rad
                for b in boxes
                if b.kind == "building"
            ):
                continue
            out.append(
                Shrub(
                    id=k + 1,
                    x=float(p[0]),
                    y=float(p[1]),
                    z=float(terrain.z(p[0], p[1])),
                    radius_m=rad,
                    height_m=float(rng.uniform(*cfg.shrub_height_m)),
                    leaf_area_density=float(cfg.shrub_leaf_area_density * rng.uniform(0.8, 1.2)),
                )
            )
            break
    return out


def _make_lianas(
    cfg: PresetConfig, extent: tuple[float, ...], terrain: Terrain, trees: Sequence[Tree], rng: np.random.Generator
) -> list[Liana]:
    xmin, xmax, ymin, ymax = extent
    area_ha = (xmax - xmin) * (ymax - ymin) / 1.0e4
    n = int(rng.poisson(cfg.lianas_per_ha * area_ha)) if cfg.lianas_per_ha > 0 and trees else 0
    xy, r = _stem_xy(trees)
    out = []
    for k in range(n):
        host = trees[int(rng.integers(len(trees)))]
        # a liana climbing from the ground, drifting away from and back to a host crown,
        # or hanging free between crowns
        for _ in range(20):
            p0 = np.array([host.x, host.y]) + rng.normal(0.0, 2.0, size=2)
            if not (xmin < p0[0] < xmax and ymin < p0[1] < ymax):
                continue
            if (np.hypot(xy[:, 0] - p0[0], xy[:, 1] - p0[1]) < r + 0.1).any():
                continue
            break
        else:
            continue
        top = host.point_at_height(max(host.crown_base_m, 3.0))
        n_ctrl = 6
        pts = []
        z0 = float(terrain.z(p0[0], p0[1]))
        for i in range(n_ctrl):
            f = i / (n_ctrl - 1)
            q = np.array([p0[0], p0[1], z0]) * (1 - f) + top * f
            q[:2] += rng.normal(0.0, 0.3, size=2) * math.sin(math.pi * f)
            pts.append(tuple(float(v) for v in q))
        pts[0] = (pts[0][0], pts[0][1], z0 - 0.1)
        out.append(Liana(id=k + 1, points=tuple(pts), radius_m=float(rng.uniform(0.01, 0.04))))
    return out


def _make_targets(
    cfg: PresetConfig,
    size_m: float,
    terrain: Terrain,
    trees: Sequence[Tree],
    shrubs: Sequence[Shrub],
    boxes: Sequence[Box],
    rng: np.random.Generator,
) -> list[Target]:
    n = int(rng.integers(cfg.n_targets[0], cfg.n_targets[1] + 1))
    r_max = max(0.30 * size_m, 4.0)
    r_min = 3.0
    xy, rad = _stem_xy(trees)
    out: list[Target] = []
    sep = 4.0
    attempts = 0
    while len(out) < n and attempts < 5000:
        attempts += 1
        if attempts > 2000:
            sep = 2.0
        # spread over the central disc: an evenly spaced azimuth per target plus noise
        az = 2 * math.pi * (len(out) + rng.uniform(-0.35, 0.35)) / n
        rr = math.sqrt(rng.uniform(r_min**2, r_max**2))
        p = np.array([rr * math.cos(az), rr * math.sin(az)])
        if len(xy) and (np.hypot(xy[:, 0] - p[0], xy[:, 1] - p[1]) < rad + 0.6).any():
            continue
        if any(math.hypot(p[0] - s.x, p[1] - s.y) < s.radius_m + 0.3 for s in shrubs):
            continue
        if any(abs(p[0] - b.x) < b.size[0] / 2 + 1.0 and abs(p[1] - b.y) < b.size[1] / 2 + 1.0 for b in boxes):
            continue
        if any(math.hypot(p[0] - t.x, p[1] - t.y) < sep for t in out):
            continue
        gz = float(terrain.z(p[0], p[1]))
        h = float(rng.uniform(*cfg.target_height_m))
        out.append(Target(id=len(out) + 1, x=float(p[0]), y=float(p[1]), z=gz + h, ground_z=gz))
    return out


def _make_boxes(cfg: PresetConfig, extent: tuple[float, ...], terrain: Terrain, rng: np.random.Generator) -> list[Box]:
    xmin, xmax, ymin, ymax = extent
    half = min(xmax - xmin, ymax - ymin) / 2.0
    out: list[Box] = []
    # a building off-centre
    ang = rng.uniform(0, 2 * math.pi)
    d = 0.55 * half
    bx, by = d * math.cos(ang), d * math.sin(ang)
    yaw = float(rng.uniform(0.0, 180.0))
    size = (8.0, 6.0, 4.0)
    corners_z = [terrain.z(bx + sx * size[0] / 2, by + sy * size[1] / 2) for sx in (-1, 1) for sy in (-1, 1)]
    out.append(
        Box(
            id=1,
            x=bx,
            y=by,
            z=float(min(corners_z)) - 0.2,
            size=(size[0], size[1], size[2] + 0.2),
            yaw_deg=yaw,
            kind="building",
        )
    )
    # a straight fence across the plot on the other side: posts every 2.5 m and two rails
    fang = ang + math.pi + rng.uniform(-0.5, 0.5)
    fd = 0.6 * half
    cx, cy = fd * math.cos(fang), fd * math.sin(fang)
    fyaw = math.degrees(fang) + 90.0 + rng.uniform(-20, 20)
    u = np.array([math.cos(math.radians(fyaw)), math.sin(math.radians(fyaw))])
    length = 1.2 * half
    n_posts = int(length / 2.5) + 1
    k = 2
    for i in range(n_posts):
        p = np.array([cx, cy]) + u * (-length / 2 + i * 2.5)
        if not (xmin < p[0] < xmax and ymin < p[1] < ymax):
            continue
        z = float(terrain.z(p[0], p[1]))
        out.append(
            Box(id=k, x=float(p[0]), y=float(p[1]), z=z - 0.1, size=(0.1, 0.1, 1.3), yaw_deg=fyaw, kind="fence_post")
        )
        k += 1
    for rail_h in (0.5, 1.1):
        for i in range(n_posts - 1):
            p = np.array([cx, cy]) + u * (-length / 2 + (i + 0.5) * 2.5)
            if not (xmin < p[0] < xmax and ymin < p[1] < ymax):
                continue
            z = float(terrain.z(p[0], p[1]))
            out.append(
                Box(
                    id=k,
                    x=float(p[0]),
                    y=float(p[1]),
                    z=z + rail_h,
                    size=(2.5, 0.03, 0.1),
                    yaw_deg=fyaw,
                    kind="fence_rail",
                )
            )
            k += 1
    return out
