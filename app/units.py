"""The files' units: metres per unit of each ``--units`` choice, and the one check that a cloud's
coordinates are in the unit they are said to be in (:func:`unit_problem`, raised by
:func:`forestreg.app.common.check_units`: the one check of every command and every function of the
Python API that takes a cloud).

No heavy import at the top: the command line's parser reads :data:`UNITS` before anything else
loads; numpy is imported where a cloud is checked.

How the unit is judged (a cloud in the wrong unit is refused in well under a second, before any
work, instead of running for minutes on a plot 100 times too large):

* the columns: no tree is taller than about 115 m, so points of the same 10 m x 10 m column of a
  cloud in metres never climb more than :data:`COLUMN_RANGE_MAX_M` (the tallest trees, and the
  terrain's slope across the column). In centimetres the columns are 10 cm wide and a tree's stem
  or crown fills them over thousands of units: when a tenth of the columns climb further, the
  cloud is not in metres;
* the shape: a cloud more than :data:`TALL_MAX_M` tall that is taller than it is wide is not a
  forest in metres (a georeferenced ALS tile with such relief spans kilometres);
* the point spacing and the heights then say which unit it likely is (centimetres, millimetres,
  feet): the unit that makes the points a few mm to cm apart and the cloud a tree's height tall.

Vertical extents are taken from the lowest to the highest point, never absolute elevations (a
georeferenced cloud stands hundreds of metres above sea level), and robustly (a few stray returns
above or below the cloud do not count).
"""

from __future__ import annotations

from typing import Any, Optional

#: Metres per unit of the files' coordinates (the ``--units`` choices).
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "usft": 1200.0 / 3937.0}

#: The units' names, for messages.
UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "ft": "feet", "usft": "US survey feet"}

#: Side (m) of the columns whose vertical ranges are compared with the tallest trees.
COLUMN_M = 10.0
#: The highest vertical range (m) a 10 m column of a forest cloud in metres holds at its 90th
#: percentile: the tallest trees (~115 m) and the terrain's rise across the column.
COLUMN_RANGE_MAX_M = 150.0
#: The percentile of the columns' vertical ranges compared (a tenth of the columns must climb
#: further for a refusal: stray returns in a few columns do not count).
COLUMN_PERCENTILE = 90.0
#: The fewest columns of at least 4 points the column test needs (fewer: no evidence).
MIN_COLUMNS = 20
#: A cloud taller than this (m) and taller than it is wide is not a forest in metres.
TALL_MAX_M = 150.0
#: A cloud said to be in cm, mm or feet that spans less than this (m) is not a forest cloud.
SMALL_MIN_M = 0.5
#: A cloud in metres that spans less than this (m) both across and in height holds no tree: a
#: file in kilometres, or coordinates scaled away.
TINY_MAX_M = 0.1
#: The points the check looks at (a random sample of larger clouds).
SAMPLE_POINTS = 200_000
#: The points the spacing is measured on when a cloud is refused (a random thinning of larger ones).
SPACING_POINTS = 1_000_000
#: Plausible ranges of a forest cloud in metres: its height (m) and its point spacing (m, from
#: dense TLS to sparse ALS); the likely unit is the one whose scaling puts the cloud within them.
PLAUSIBLE_HEIGHT_M = (3.0, 80.0)
PLAUSIBLE_SPACING_M = (0.002, 0.5)


#: A cloud whose x or y coordinates take distinct values at least this far apart (m), each shared
#: by many points, was stored with too little precision for trees (float32 keeps about 7 digits:
#: 0.25-0.5 m at UTM northings).
COARSE_STEP_M = 0.1
#: ... many: at least this many points per distinct value (a small cloud's values are few anyway).
POINTS_PER_VALUE = 20


def precision_problem(points: Any, label: str = "cloud") -> Optional[str]:
    """Why the coordinates of ``points`` (N, 3; metres) are too coarse to measure trees on (one
    line), or None: x or y whose distinct values (in a sample of :data:`SAMPLE_POINTS`) lie at
    least :data:`COARSE_STEP_M` apart, each held by :data:`POINTS_PER_VALUE` points or more on
    average, with several points on each (x, y) position, as float32 storage of georeferenced
    coordinates leaves them (a raster of heights exported as points, one point per cell, is not
    refused)."""
    import numpy as np

    p = _sample(points, SAMPLE_POINTS, 1)
    if len(np.unique(p[:, :2], axis=0)) * 4 > len(p):
        return None
    for k, axis in enumerate("xy"):
        values = np.unique(p[:, k])
        if len(values) < 2 or len(p) < POINTS_PER_VALUE * len(values):
            continue
        step = float(np.min(np.diff(values)))
        if step >= COARSE_STEP_M:
            return (
                f"{label}: its {axis} coordinates take only {len(values)} values, {step:.3g} m apart, for "
                f"{len(p)} points: they were stored with too little precision (float32 keeps about 7 digits, "
                "a fraction of a metre at georeferenced coordinates); export the cloud in double precision "
                "or with a local offset"
            )
    return None


#: Two lengths of unit agree when they differ by at most this fraction (the international foot and
#: the US survey foot, 2 ppm apart, are the same for trees).
UNIT_TOLERANCE = 1e-5


def crs_unit_problem(crs: Any, units: str = "m", label: str = "cloud") -> Optional[str]:
    """Why a cloud whose file declares the coordinate reference system ``crs`` (a
    :class:`~forestreg.engine.io.crs.Crs`, or None) cannot be read in ``units`` (one line), or None:
    a CRS whose axes are in another unit (a State Plane CRS in US survey feet read as metres), a
    geographic CRS (degrees of latitude and longitude), a geocentric one (its z is not up) and a
    compound CRS whose heights are in another unit than its eastings and northings. Without pyproj,
    or for a CRS it cannot read, nothing is said."""
    if crs is None or units not in UNITS:
        return None
    try:
        c = crs.to_pyproj()
        if c is None:
            return None
        parts = list(c.sub_crs_list) if c.is_compound else [c]
        horizontal = parts[0]
        axes = [a for part in parts for a in part.axis_info]
    except Exception:  # noqa: BLE001 - a CRS pyproj cannot read: the points' own check decides
        return None
    name = getattr(crs, "label", None) or str(c.name)
    if horizontal.is_geographic:
        return (
            f"{label}: its CRS {name} is geographic (latitude and longitude in degrees): trees are measured in a "
            "projected CRS in metres or feet; reproject the cloud first (e.g. to its UTM zone)"
        )
    if horizontal.is_geocentric:
        return (
            f"{label}: its CRS {name} is geocentric (Earth-centred x, y, z: z is not up): reproject the cloud to a "
            "projected CRS first (e.g. its UTM zone)"
        )
    factors = [float(a.unit_conversion_factor) for a in axes if a.unit_conversion_factor]
    if not factors:
        return None
    said = UNITS[units]

    def same(a: float, b: float) -> bool:
        return abs(a - b) <= UNIT_TOLERANCE * max(a, b)

    if not all(same(f, factors[0]) for f in factors):
        kinds = ", ".join(f"{a.name.lower()} in {a.unit_name}s" for a in axes)
        return (
            f"{label}: its CRS {name} mixes units ({kinds}): forestreg reads one unit for x, y and z; "
            "convert the heights to the unit of the eastings first"
        )
    if same(factors[0], said):
        return None
    unit = min(UNITS, key=lambda u: abs(UNITS[u] - factors[0]))  # the closer foot of the two
    unit = unit if same(UNITS[unit], factors[0]) else None
    given = f"--units {units}" if units != "m" else "metres (the default)"
    told = UNIT_NAMES[unit] if unit else f"{axes[0].unit_name}s ({factors[0]:g} m)"
    how = f"give --units {unit}" if unit else "convert the cloud to metres first"
    return (
        f"{label}: its CRS {name} gives its coordinates in {told}, but they were to be read in {given}: "
        f"{how} (Python: read_scan(path, unit_scale={factors[0]:g})); if the file's CRS is wrong, correct it first "
        "(e.g. PDAL's writers.las a_srs)"
    )


#: A plot whose trees stand this tall at the median (m) is more likely a file in feet read as
#: metres than a forest (only the tallest old-growth stands reach it).
TALL_STAND_M = 45.0
#: ... over at least this many trees with a height.
TALL_STAND_TREES = 5


def tall_stand_note(heights_m: Any, units: str = "m", label: str = "cloud") -> Optional[str]:
    """A warning (one line) when the trees of a cloud read in metres without a CRS to say so stand
    implausibly tall (median of ``heights_m`` at least :data:`TALL_STAND_M` over at least
    :data:`TALL_STAND_TREES` trees): a file in feet read as metres gives trees 3.28 times too tall
    and thick, and nothing else in the points tells feet from metres (a tree's height over its
    diameter is the same in both). None otherwise."""
    import numpy as np

    h = np.asarray(heights_m, dtype=np.float64)
    h = h[np.isfinite(h)]
    if units != "m" or len(h) < TALL_STAND_TREES:
        return None
    median = float(np.median(h))
    if median < TALL_STAND_M:
        return None
    return (
        f"{label}: its trees stand {median:.0f} m tall at the median ({len(h)} trees), as only the tallest "
        f"old-growth stands do: if the file is in feet, run again with --units ft (or usft); these would be "
        f"{median * UNITS['ft']:.0f} m"
    )


def unit_of_scale(scale: float) -> str:
    """The ``--units`` name of ``scale`` metres per unit ("m" for a scale that is none of them)."""
    return next((name for name, s in UNITS.items() if abs(s - float(scale)) <= 1e-9 * s), "m")


def cloud_unit_figures(points: Any, *, sample: int = SAMPLE_POINTS, seed: int = 0) -> dict:
    """The figures :func:`unit_problem` judges a cloud by (its coordinates taken as metres):
    ``height`` and ``width`` (robust vertical and largest horizontal extent), ``columns`` (columns of
    :data:`COLUMN_M` with at least 4 points) and ``column_range`` (their vertical ranges'
    :data:`COLUMN_PERCENTILE` th percentile; NaN with fewer than :data:`MIN_COLUMNS` columns)."""
    p = _sample(points, sample, seed)
    return _figures(p)


def unit_problem(points: Any, units: str = "m", label: str = "cloud") -> Optional[str]:
    """Why the cloud ``points`` is not in ``units`` (one line naming the likely unit and how to give
    it), or None when the data do not say otherwise. ``points`` (N, 3) are its coordinates already
    scaled to metres by ``units`` (a scan's points, or an array of the Python API). Looks at a
    sample of :data:`SAMPLE_POINTS` points: well under a second on any cloud. Raising is
    :func:`forestreg.app.common.check_units`'s."""
    scale = UNITS[units]
    p = _sample(points, SAMPLE_POINTS, 0)
    if len(p) < 10:
        return None
    figures = _figures(p)
    too_large = _too_large(figures)
    too_small = max(figures["height"], figures["width"]) < (SMALL_MIN_M if units != "m" else TINY_MAX_M)
    if not too_large and not too_small:
        return None
    spacing = _spacing(points)
    said = f"--units {units}" if units != "m" else "metres"
    facts = _facts(figures, spacing, too_large)
    guess = _likely_unit(p, spacing, units, larger=too_small)
    if guess is None:
        return (
            f"{label}: this cloud is not in {UNIT_NAMES[units]}: {facts}; check the file's unit "
            f"(--units {'|'.join(UNITS)}), or convert it to metres first"
        )
    unit, also = guess
    factor = UNITS[unit] / scale
    perhaps = f" (perhaps {UNIT_NAMES[also]})" if also else ""
    return (
        f"{label}: this cloud looks like {UNIT_NAMES[unit]}{perhaps}, not {UNIT_NAMES[units]}: taken in {said}, {facts}; "
        f"give its unit: --units {unit}, or convert it to {UNIT_NAMES[units]} (Python: read_scan(path, unit_scale={UNITS[unit]:g}), "
        f"or the points times {factor:g})"
    )


# ----------------------------------------------------------------------------- figures


def _sample(points: Any, n: int, seed: int):
    """A float64 (M, 3) sample of at most ``n`` of ``points`` (all of a smaller cloud), in their order."""
    import numpy as np

    p = np.asarray(points)
    if len(p) > n:
        idx = np.sort(np.random.default_rng(seed).integers(0, len(p), n))
        p = p[idx[np.r_[True, idx[1:] != idx[:-1]]]]  # each drawn once (np.unique is many times slower)
    return np.asarray(p, dtype=np.float64).reshape(-1, 3)


def _figures(p) -> dict:
    import numpy as np

    if len(p) == 0:
        return {"height": 0.0, "width": 0.0, "columns": 0, "column_range": float("nan")}
    lo = np.percentile(p, 0.5, axis=0)
    hi = np.percentile(p, 99.5, axis=0)
    height = float(hi[2] - lo[2])
    width = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    columns, column_range = _column_ranges(p, COLUMN_M)
    return {"height": height, "width": width, "columns": columns, "column_range": column_range}


def _column_ranges(p, side: float) -> tuple[int, float]:
    """(columns of ``side`` holding at least 4 points, the :data:`COLUMN_PERCENTILE` th percentile
    of their vertical ranges; NaN with fewer than :data:`MIN_COLUMNS`). A column's range leaves its
    lowest and highest point out (one stray return per column does not count)."""
    import numpy as np

    xy = p[:, :2] - p[:, :2].min(axis=0)
    cells = np.floor(xy / side)
    if not np.isfinite(cells).all() or cells.max(initial=0.0) > 1e8:
        return 0, float("nan")
    ij = cells.astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((p[:, 2], key))
    k = key[order]
    z = p[order, 2]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    counts = np.diff(np.r_[starts, len(k)])
    full = counts >= 4
    s, c = starts[full], counts[full]
    if len(s) < MIN_COLUMNS:
        return int(len(s)), float("nan")
    ranges = z[s + c - 2] - z[s + 1]
    return int(len(s)), float(np.percentile(ranges, COLUMN_PERCENTILE))


def _too_large(f: dict) -> bool:
    import math

    if math.isfinite(f["column_range"]) and f["column_range"] > COLUMN_RANGE_MAX_M:
        return True
    return f["height"] > TALL_MAX_M and f["height"] > f["width"]


def _spacing(points) -> float:
    """The median distance of a point to its nearest neighbour (the cloud's units): over the whole
    cloud up to :data:`SPACING_POINTS` points, else over a random thinning of that size, scaled as
    a surface's by the square root of the thinning."""
    import numpy as np
    from scipy.spatial import cKDTree

    n = len(points)
    p = _sample(points, SPACING_POINTS, 2)
    if len(p) < 3:
        return float("nan")
    rng = np.random.default_rng(1)
    query = p[rng.choice(len(p), size=min(5000, len(p)), replace=False)]
    d, _ = cKDTree(p, balanced_tree=False, compact_nodes=False).query(query, k=2)
    nn = d[:, 1][d[:, 1] > 0]
    if not len(nn):
        return float("nan")
    return float(np.median(nn)) * float(np.sqrt(max(n, len(p)) / len(p)))


def _facts(f: dict, spacing: float, too_large: bool) -> str:
    import math

    size = f"the points span {f['width']:,.3g} m across and {f['height']:,.3g} m in height"
    parts = [size]
    if too_large and math.isfinite(f["column_range"]) and f["column_range"] > COLUMN_RANGE_MAX_M:
        parts.append(f"in {COLUMN_M:g} m columns they climb {f['column_range']:,.0f} m (no tree is over ~115 m tall)")
    elif too_large:
        parts.append(f"taller than it is wide and over {TALL_MAX_M:g} m tall (no forest is)")
    else:
        parts.append("smaller than any tree")
    if math.isfinite(spacing):
        parts.append(f"its points stand {spacing:.3g} m apart (median; ground-based scans' are mm to cm apart)")
    return ", ".join(parts)


def _likely_unit(p, spacing: float, said: str, *, larger: bool):
    """The likely unit of the cloud's file (and a second one when it is nearly as plausible), or
    None: among the units whose scaling passes the check, the one that puts the cloud's height and
    spacing within :data:`PLAUSIBLE_HEIGHT_M` and :data:`PLAUSIBLE_SPACING_M` (by the least factor
    outside them; a tie goes to the more common unit: metres, centimetres, millimetres, feet)."""
    import math

    def outside(value: float, bounds: tuple[float, float]) -> float:
        if not math.isfinite(value) or value <= 0:
            return 0.0
        return max(0.0, math.log(bounds[0] / value), math.log(value / bounds[1]))

    scale = UNITS[said]
    scored = []
    for rank, unit in enumerate(("m", "cm", "mm", "ft")):
        factor = UNITS[unit] / scale
        if unit == said or (factor > 1.0) != larger:
            continue
        f = _figures(p * factor)
        if _too_large(f) or max(f["height"], f["width"]) < SMALL_MIN_M:
            continue
        score = outside(f["height"], PLAUSIBLE_HEIGHT_M) + outside(spacing * factor, PLAUSIBLE_SPACING_M)
        scored.append((score, rank, unit))
    if not scored:
        return None
    scored.sort()
    also = scored[1][2] if len(scored) > 1 and scored[1][0] < scored[0][0] + 0.5 else None
    return scored[0][2], also
