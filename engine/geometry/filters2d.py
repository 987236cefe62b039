"""Filters of 2D grids (rasters of cells, any unit): a moving minimum, a 3x3 median, the nearest
measured cell of every cell and a Gaussian smoothing -- each giving, to the last bit, what
``scipy.ndimage`` gives for the same call (``minimum_filter(mode="nearest")``,
``median_filter(size=3, mode="nearest")``, ``distance_transform_edt(return_indices=True)`` and
``gaussian_filter(mode="constant")``), ties included, without importing it. The tests compare
each with SciPy on random grids.

Why these and not ``scipy.ndimage``: ``python -m benchmarks.icp_open3d --only filters`` times both
(median of 7 calls) on random grids of 120 x 127 and 400 x 407 cells (60 m and 200 m of ground at
the ground grid's 0.5 m cells):

==============  =====================  =====================
filter          120 x 127: here/SciPy  400 x 407: here/SciPy
==============  =====================  =====================
minimum 7 x 7   0.23 / 0.33 ms         1.3 / 7.8 ms
median 3 x 3    1.3 / 2.2 ms           17 / 37 ms
nearest cell    0.66 / 1.04 ms         13.9 / 15.0 ms
Gaussian, s=2   0.29 / 0.38 ms         5.9 / 5.7 ms
==============  =====================  =====================

(one run), every result equal to SciPy's to the last bit. Over four runs on the shared 2-core
machine the time ratios ranged 0.16-1.5 (the nearest cell on the larger grid 0.7-1.5, the Gaussian
on it 0.5-1.2, every other 0.16-1.08): at most a few milliseconds either way, while importing
``scipy.ndimage`` costs a fresh process 0.28 s of CPU (median of 7, whole processes with and
without the import), which a small pair's run does without (``tests/test_pair_imports.py``).
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["gaussian_smooth", "median3_nearest", "minimum_filter_nearest", "nearest_cell_indices"]


def minimum_filter_nearest(values: np.ndarray, size: int) -> np.ndarray:
    """The minimum of each cell's ``size`` x ``size`` window (``size`` odd), the grid extended by
    repeating its edge cells (``scipy.ndimage.minimum_filter(values, size, mode="nearest")``;
    values without NaN)."""
    a = np.asarray(values, dtype=np.float64)
    if size < 1 or size % 2 == 0:
        raise ValueError(f"size must be a positive odd number, got {size}")
    half = size // 2
    for axis in range(a.ndim):
        padded = np.pad(a, [(half, half) if k == axis else (0, 0) for k in range(a.ndim)], mode="edge")
        n = a.shape[axis]

        def window(start: int, padded=padded, n=n, axis=axis) -> np.ndarray:
            return padded[tuple(slice(start, start + n) if k == axis else slice(None) for k in range(padded.ndim))]

        out = window(0).copy()
        for s in range(1, size):
            np.minimum(out, window(s), out=out)
        a = out
    return a


def median3_nearest(values: np.ndarray) -> np.ndarray:
    """The median of each cell's 3 x 3 window of a 2D grid, the grid extended by repeating its edge
    cells (``scipy.ndimage.median_filter(values, size=3, mode="nearest")``; values without NaN):
    the fifth smallest of the nine values."""
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"a 2D grid is needed, got shape {a.shape}")
    nx, ny = a.shape
    p = np.pad(a, 1, mode="edge")
    stack = np.stack([p[i : i + nx, j : j + ny] for i in range(3) for j in range(3)])
    return np.partition(stack, 4, axis=0)[4]


def nearest_cell_indices(missing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every cell of a 2D grid, the (row, column) of the nearest cell that is not ``missing``
    (Euclidean distance in cells), ties decided as ``scipy.ndimage.distance_transform_edt(missing,
    return_indices=True)`` decides them: the exact linear-time feature transform of Maurer, Qi and
    Raghavan (IEEE PAMI 25, 2003), one pass along each axis. Needs at least one cell not missing."""
    m = np.ascontiguousarray(np.asarray(missing, dtype=bool))
    if m.ndim != 2:
        raise ValueError(f"a 2D grid is needed, got shape {m.shape}")
    if m.all():
        raise ValueError("every cell is missing: no nearest cell")
    rows = np.empty(m.shape, dtype=np.int64)
    cols = np.empty(m.shape, dtype=np.int64)
    _feature_transform(m, rows, cols)
    return rows, cols


@kernel
def _feature_transform(missing, rows, cols):  # pragma: no cover - compiled
    """:func:`nearest_cell_indices` into ``rows`` and ``cols`` (both the grid's shape, int64)."""
    nx, ny = missing.shape
    n = max(nx, ny)
    f0 = np.empty(n, dtype=np.float64)  # a line's current features (row, column of a cell)
    f1 = np.empty(n, dtype=np.float64)
    valid = np.empty(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    # along axis 0: in every column, each cell's nearest measured cell of that column
    for j in range(ny):
        for i in range(nx):
            valid[i] = not missing[i, j]
            f0[i] = i
            f1[i] = j
        _voronoi_line(f0, f1, valid, nx, 0, float(j), stack)
        for i in range(nx):
            if valid[i]:
                rows[i, j] = np.int64(f0[i])
                cols[i, j] = np.int64(f1[i])
            else:
                rows[i, j] = -1
                cols[i, j] = j
    # along axis 1: in every row, the nearest of the columns' answers
    for i in range(nx):
        for j in range(ny):
            valid[j] = rows[i, j] >= 0
            f0[j] = rows[i, j]
            f1[j] = cols[i, j]
        _voronoi_line(f0, f1, valid, ny, 1, float(i), stack)
        for j in range(ny):
            rows[i, j] = np.int64(f0[j])
            cols[i, j] = np.int64(f1[j])


@kernel
def _voronoi_line(f0, f1, valid, length, axis, other, stack):  # pragma: no cover - compiled
    """One line of the feature transform, in place: ``f0``/``f1`` (the line's ``length`` cells) hold
    each cell's feature (row, column; ``valid[k]`` False: none yet); ``axis`` is the line's axis,
    ``other`` its fixed coordinate on the other axis. Each cell gets the feature nearest to it among
    the line's features (the earlier one of two at equal distance); a line without any stays as
    it is. The features kept are those whose Voronoi cell meets the line, found with a stack (the
    integer-valued float64 arithmetic and comparisons of the published algorithm)."""
    top = -1
    for k in range(length):
        if not valid[k]:
            continue
        fd = f0[k] if axis == 0 else f1[k]
        w = (f1[k] - other) if axis == 0 else (f0[k] - other)
        w_r = w * w
        while top >= 1:
            last = stack[top]
            before = stack[top - 1]
            f_last = f0[last] if axis == 0 else f1[last]
            a = f_last - (f0[before] if axis == 0 else f1[before])
            b = fd - f_last
            c = a + b
            tu = (f1[before] - other) if axis == 0 else (f0[before] - other)
            tv = (f1[last] - other) if axis == 0 else (f0[last] - other)
            u_r = tu * tu
            v_r = tv * tv
            if c * v_r - b * u_r - a * w_r - a * b * c <= 0.0:
                break
            top -= 1
        top += 1
        stack[top] = k
    if top < 0:
        return
    # the stack's features in order along the line: each cell takes the first nearest of them
    out0 = np.empty(length, dtype=np.float64)
    out1 = np.empty(length, dtype=np.float64)
    s = 0
    for k in range(length):
        g = stack[s]
        t0 = (f0[g] - k) if axis == 0 else (f0[g] - other)
        t1 = (f1[g] - other) if axis == 0 else (f1[g] - k)
        d1 = t0 * t0 + t1 * t1
        while s < top:
            h = stack[s + 1]
            t0 = (f0[h] - k) if axis == 0 else (f0[h] - other)
            t1 = (f1[h] - other) if axis == 0 else (f1[h] - k)
            d2 = t0 * t0 + t1 * t1
            if d1 <= d2:
                break
            d1 = d2
            s += 1
        g = stack[s]
        out0[k] = f0[g]
        out1[k] = f1[g]
    for k in range(length):
        f0[k] = out0[k]
        f1[k] = out1[k]
        valid[k] = True


def gaussian_smooth(values: np.ndarray, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """A 2D grid smoothed by a Gaussian of ``sigma`` cells along each axis in turn (axis 0, then 1),
    zero beyond the grid (``scipy.ndimage.gaussian_filter(values, sigma, mode="constant",
    truncate=truncate)``: the same normalised weights over ``int(truncate * sigma + 0.5)`` cells
    each side, and each output the centre's product plus the sums of the mirrored pairs times their
    weight, outermost pair first)."""
    out = np.asarray(values, dtype=np.float64)
    if out.ndim != 2:
        raise ValueError(f"a 2D grid is needed, got shape {out.shape}")
    sd = float(sigma)
    radius = int(truncate * sd + 0.5)
    x = np.arange(-radius, radius + 1)
    weights = np.exp(-0.5 / (sd * sd) * x**2)
    weights = weights / weights.sum()
    # along axis 0, then along axis 1 as axis 0 of the transposed grid (rows read whole)
    return _smooth_rows(_smooth_rows(out, weights, radius).T, weights, radius).T


def _smooth_rows(values: np.ndarray, weights: np.ndarray, radius: int) -> np.ndarray:
    """:func:`gaussian_smooth` along axis 0 only."""
    n = values.shape[0]
    padded = np.zeros((n + 2 * radius,) + values.shape[1:])
    padded[radius : radius + n] = values
    acc = padded[radius : radius + n] * weights[radius]
    pair = np.empty_like(acc)
    for j in range(radius, 0, -1):
        np.add(padded[radius - j : radius - j + n], padded[radius + j : radius + j + n], out=pair)
        pair *= weights[radius - j]
        acc += pair
    return acc
