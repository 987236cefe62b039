"""Compiled (numba) bounds of the exact coarse VOP matcher; see :mod:`.coarse` for the maths.

Frames and units are those of :mod:`.coarse`: radii in metres (pair radii of VOPs in their own scan's
horizontal plane), directions in radians, angles as integer indices ``a`` of the angle step, offset
by ``3K`` inside a window so that they stay positive (``a mod K`` is the angle index, ``a = 0`` is
``k = K``).

Level 1 (:func:`coarse_bounds`) joins the pair radii as the numpy path does -- each moving pair
j < l against one contiguous run of the sorted reference pair radii -- but adds every tuple's bounds
to both twins' cells at once instead of storing the tuple. Level 2 (:func:`fine_bounds`) rebuilds
the tuples of one anchor (i, j) when needed, from a merge of reference row ``i``'s and moving row
``j``'s pair radii, each sorted beforehand. Nothing is stored per tuple, so the memory stays
O(m*n*bins) however packed the VOPs are. The per-(tuple, angle-set) value is the numpy path's
formula; the angular window is bounded without ``acos`` (a series of ``asin`` with a bounded tail),
a window at least as wide as the numpy path's and wider by < 1e-6 rad, so every bound stays >= the
true improvement (module docstring of :mod:`.coarse`) and prunes as much as the numpy path's.

Both levels take the search's ``grid``: ``(k_count, bin_size, n_bins, step_rad, d_win,
wide_limit)`` -- the K angles of the full turn, the angles per bin, the bins, the angle step (rad),
the distance window (m), and the window width (angles) from which a tuple's bound is taken as
constant over the angles.

The exact scores are never computed here: they stay with the nearest-VOP scorer both matchers
share (:class:`~forestreg.engine.geometry.nearest.PlaneNearest`).
Importing this module needs numba; :mod:`.coarse` falls back to its numpy path without it.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

#: numpy's float semantics (a division by zero gives inf, not an exception), as the numpy path
_compiled = kernel(error_model="numpy")


@_compiled
def _window_value(peak: float, lo: int, hi: int, half_step: float, dr2: float, prod4: float, d_win: float) -> float:
    """Bound of ``max(0, D_t - distance)`` over angle indices ``lo..hi`` (metres; ``d_win = D_t + slack``).

    The distance is smallest at the angle nearest the peak; ``sin(x) >= x - x^3/6`` (x = half the
    angle from the peak, < pi/4 here) bounds it from below.
    """
    c = peak
    if c < lo:
        c = lo
    elif c > hi:
        c = hi
    x = abs(c - peak) * half_step
    s = x * (1.0 - x * x * (1.0 / 6.0))
    v = d_win - np.sqrt(dr2 + prod4 * (s * s))
    return v if v > 0.0 else 0.0


@_compiled
def _half_window(y2: float) -> float:
    """Upper bound (rad) of ``2 asin(sqrt(y2)) = acos(1 - 2 y2)`` for ``0 <= y2 <= 1/2``.

    The series of asin has decreasing positive coefficients, so its tail from y^7 on is at most
    ``(5/112) y^7 / (1 - y^2)``: the bound exceeds the true half-window by < 1e-6 rad here (the
    windows are the numpy path's ``acos`` windows), and the factor 1 + 1e-12 covers rounding.
    """
    return (
        2.0
        * np.sqrt(y2)
        * (1.0 + y2 * (1.0 / 6.0 + y2 * (3.0 / 40.0 + y2 * (5.0 / 112.0) / (1.0 - y2))))
        * (1.0 + 1e-12)
    )


@_compiled
def _anchor_tuples(
    i: int,
    j: int,
    ref_r: np.ndarray,
    ref_psi: np.ndarray,
    mov_r: np.ndarray,
    mov_phi: np.ndarray,
    mov_idx: np.ndarray,
    inv_step: float,
    offset: float,
    d_win: float,
    wide_limit: int,
    peak: np.ndarray,
    a_lo: np.ndarray,
    a_hi: np.ndarray,
    dr2: np.ndarray,
    prod4: np.ndarray,
) -> tuple[int, float]:
    """Radius-compatible tuples (q, l) of anchor (i, j), in the first ``count`` slots of the outputs.

    Returns ``(count, const)``: ``const`` (metres) sums the angle-independent bounds of the anchor's
    pairs with a zero radius or a window round the circle or wider than ``wide_limit`` angles;
    those tuples, and the ones whose window holds no angle, get an empty window (a_lo > a_hi).
    The moving anchor itself (l = j) is not included (``coarse._build_bounds`` adds it).
    """
    rr = ref_r[i]
    m = rr.shape[0]
    mr = mov_r[j]
    dw2 = d_win * d_win
    # Merge of the two sorted rows: radius-compatible candidates (the peak direction goes to
    # ``peak``, the moving radius to ``dr2``, the reference radius to ``prod4`` for now).
    count = 0
    first = 0
    for e in range(mr.shape[0]):
        if mov_idx[j, e] == j:
            continue
        rl = mr[e]
        while first < m and rr[first] < rl - d_win:
            first += 1
        phi = mov_phi[j, e]
        f = first
        while f < m and rr[f] <= rl + d_win:
            peak[count] = ref_psi[i, f] - phi
            dr2[count] = rl
            prod4[count] = rr[f]
            count += 1
            f += 1
    # Windows, without branches (vectorised); the numpy path's classification.
    const = 0.0
    for t in range(count):
        rl = dr2[t]
        rq = prod4[t]
        diff = rl - rq
        gap = dw2 - diff * diff
        prod = rl * rq
        y2 = gap / (4.0 * prod)  # sin^2 of half the window; NaN/inf for a zero radius
        yc = min(max(y2, 0.0), 0.5)
        hw = (_half_window(yc) + 1e-9) * inv_step  # widened by 1e-9 rad, as the numpy path
        pk = peak[t] * inv_step + offset
        # floor(x) + 1 instead of ceil(x): an angle exactly on the widened edge has f = 0.
        lo = np.int64(pk - hw) + 1
        hi = np.int64(pk + hw)
        good = gap >= 0.0  # else |rl - rq| is d_win within rounding: f is 0 everywhere
        # A zero radius, a window of 90 deg or more, or one wider than wide_limit: constant.
        windowed = good & (y2 <= 0.5) & (hi - lo < wide_limit)
        const += (d_win - abs(diff)) if (good and not windowed) else 0.0
        peak[t] = pk
        a_lo[t] = lo if windowed else 1
        a_hi[t] = hi if windowed else 0  # an empty window
        dr2[t] = diff * diff
        prod4[t] = 4.0 * prod
    return count, const


@_compiled
def coarse_bounds(
    sorted_r: np.ndarray,
    sorted_i: np.ndarray,
    sorted_q: np.ndarray,
    sorted_psi: np.ndarray,
    mov_r: np.ndarray,
    mov_phi: np.ndarray,
    own: np.ndarray,
    grid: tuple[int, int, int, float, float, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Level-1 bounds (metres) of every cell, the anchors' constant parts and maxima, the lowest cell.

    ``sorted_r`` are all m*m reference pair radii ``|R[q] - R[i]|`` in increasing order,
    ``sorted_i``, ``sorted_q`` and ``sorted_psi`` the pair's points and direction (rad); ``mov_r``
    and ``mov_phi`` (n, n) the moving pair radii and directions ``M[l] - M[j]``; ``own`` (m,) the
    bound of the moving anchor itself. Each moving pair j < l is joined with one contiguous run of
    the sorted reference radii, and every tuple (i, q, j, l) adds its bounds to both twins' anchors
    ``j*m + i`` and ``l*m + q``. The windows and the first two bins' values are computed first for
    the whole run without branches (the compiler vectorises that loop), then added to the cells.
    Returns ``cell_bound`` (m*n*n_bins,), cell = ``(j*m + i) * n_bins + bin``, ``anchor_const``
    and ``anchor_max`` (m*n,), and the smallest cell bound.
    """
    k_count, bin_size, n_bins, step_rad, d_win, wide_limit = grid
    m, n = own.shape[0], mov_r.shape[0]
    inv_step = 1.0 / step_rad
    half_step = 0.5 * step_rad
    offset = 3.0 * k_count
    dw2 = d_win * d_win
    inv_bin = 1.0 / bin_size
    inv_nb = 1.0 / n_bins
    cell_bound = np.zeros(m * n * n_bins)
    cap = sorted_r.shape[0]
    b_const = np.empty(cap)
    b_v0 = np.empty(cap)
    b_v1 = np.empty(cap)
    b_c0 = np.empty(cap, dtype=np.int64)
    b_c1 = np.empty(cap, dtype=np.int64)
    b_more = np.empty(cap, dtype=np.bool_)
    b_lo = np.empty(cap, dtype=np.int64)
    b_hi = np.empty(cap, dtype=np.int64)
    b_pk = np.empty(cap)
    anchor_const = np.zeros(m * n)
    anchor_max = np.empty(m * n)
    for j in range(n):
        anchor_const[j * m : j * m + m] = own
    for j in range(n):
        block = j * m
        for l in range(j + 1, n):
            block_b = l * m
            rl = mov_r[j, l]
            phi = mov_phi[j, l]
            first = np.searchsorted(sorted_r, rl - d_win, side="left")
            last = np.searchsorted(sorted_r, rl + d_win, side="right")
            cnt = last - first
            # Phase 1, branch-free (vectorisable): windows and the first two bins' values.
            for u in range(cnt):
                t = first + u
                rq = sorted_r[t]
                diff = rl - rq
                gap = dw2 - diff * diff
                prod = rl * rq
                y2 = gap / (4.0 * prod)
                yc = min(max(y2, 0.0), 0.5)
                hw = (_half_window(yc) + 1e-9) * inv_step
                pk = (sorted_psi[t] - phi) * inv_step + offset
                lo = np.int64(pk - hw) + 1
                hi = np.int64(pk + hw)
                ob = np.int64((lo + 0.5) * inv_bin)
                start = ob * bin_size
                x0 = abs(min(max(pk, lo), min(hi, start + bin_size - 1)) - pk) * half_step
                s0 = x0 * (1.0 - x0 * x0 * (1.0 / 6.0))
                v0 = d_win - np.sqrt(diff * diff + 4.0 * prod * (s0 * s0))
                start += bin_size
                x1 = abs(min(max(pk, start), min(hi, start + bin_size - 1)) - pk) * half_step
                s1 = x1 * (1.0 - x1 * x1 * (1.0 / 6.0))
                v1 = d_win - np.sqrt(diff * diff + 4.0 * prod * (s1 * s1))
                good = gap >= 0.0
                windowed = good & (y2 <= 0.5) & (hi - lo < wide_limit)
                b_const[u] = (d_win - abs(diff)) if (good and not windowed) else 0.0
                windowed = windowed & (hi >= lo)
                b_v0[u] = max(v0, 0.0) if windowed else 0.0
                b_v1[u] = max(v1, 0.0) if (windowed and hi >= start) else 0.0
                wrapped = ob - n_bins * np.int64((ob + 0.5) * inv_nb)
                b_c0[u] = wrapped
                b_c1[u] = 0 if wrapped == n_bins - 1 else wrapped + 1
                b_more[u] = windowed and (hi >= start + bin_size)
                b_lo[u] = lo
                b_hi[u] = hi
                b_pk[u] = pk
            # Phase 2: add to the anchors' cells.
            for u in range(cnt):
                t = first + u
                anchor = block + sorted_i[t]
                anchor_b = block_b + sorted_q[t]
                if b_const[u] != 0.0:  # rare: predicted
                    anchor_const[anchor] += b_const[u]
                    anchor_const[anchor_b] += b_const[u]
                base = anchor * n_bins
                base_b = anchor_b * n_bins
                cell_bound[base + b_c0[u]] += b_v0[u]
                cell_bound[base + b_c1[u]] += b_v1[u]
                cell_bound[base_b + b_c0[u]] += b_v0[u]
                cell_bound[base_b + b_c1[u]] += b_v1[u]
                if b_more[u]:  # windows over more than two bins (rare)
                    pk, lo, hi = b_pk[u], b_lo[u], b_hi[u]
                    diff = rl - sorted_r[t]
                    d2 = diff * diff
                    p4 = 4.0 * rl * sorted_r[t]
                    for ob in range(np.int64((lo + 0.5) * inv_bin) + 2, np.int64((hi + 0.5) * inv_bin) + 1):
                        start = ob * bin_size
                        v = _window_value(pk, start, min(hi, start + bin_size - 1), half_step, d2, p4, d_win)
                        cell_bound[base + ob - n_bins * np.int64((ob + 0.5) * inv_nb)] += v
                        cell_bound[base_b + ob - n_bins * np.int64((ob + 0.5) * inv_nb)] += v
    lowest = np.inf
    for j in range(n):
        block = j * m
        for i in range(m):
            anchor = block + i
            const = anchor_const[anchor]
            base = anchor * n_bins
            best = -np.inf
            for b in range(n_bins):
                v = cell_bound[base + b] + const
                cell_bound[base + b] = v
                best = max(best, v)
                lowest = min(lowest, v)
            anchor_max[anchor] = best
    return cell_bound, anchor_const, anchor_max, lowest


@_compiled
def fine_bounds(
    cells: np.ndarray,
    ref_r: np.ndarray,
    ref_psi: np.ndarray,
    mov_r: np.ndarray,
    mov_phi: np.ndarray,
    mov_idx: np.ndarray,
    anchor_const: np.ndarray,
    grid: tuple[int, int, int, float, float, int],
) -> np.ndarray:
    """Level-2 bound (metres) of every angle of ``cells``, shape (len(cells), bin_size).

    Row r, column s bounds angle ``(cells[r] % n_bins) * bin_size + s`` of anchor
    ``cells[r] // n_bins`` (anchor ``j*m + i``). Each anchor's tuples are built once per call.
    """
    k_count, bin_size, n_bins, step_rad, d_win, wide_limit = grid
    m = ref_r.shape[0]
    n = mov_r.shape[0]
    inv_step = 1.0 / step_rad
    half_step = 0.5 * step_rad
    offset = 3.0 * k_count
    span = n_bins * bin_size  # = K
    inv_span = 1.0 / span
    cap = m * n
    peak = np.empty(cap)
    a_lo = np.empty(cap, dtype=np.int64)
    a_hi = np.empty(cap, dtype=np.int64)
    dr2 = np.empty(cap)
    prod4 = np.empty(cap)
    out = np.zeros((cells.shape[0], bin_size))
    order = np.argsort(cells)
    current = -1
    count = 0
    for o in range(order.shape[0]):
        r = order[o]
        anchor = cells[r] // n_bins
        b = cells[r] - anchor * n_bins
        if anchor != current:
            current = anchor
            j = anchor // m
            i = anchor - j * m
            count, _ = _anchor_tuples(
                i,
                j,
                ref_r,
                ref_psi,
                mov_r,
                mov_phi,
                mov_idx,
                inv_step,
                offset,
                d_win,
                wide_limit,
                peak,
                a_lo,
                a_hi,
                dr2,
                prod4,
            )
        for t in range(count):
            lo_t, hi_t = a_lo[t], a_hi[t]
            # The window (offset angles, narrower than K/2) meets this bin in at most one copy:
            # the first copy b*B + u*K whose last angle is >= lo_t.
            # (the numerator is > 0; floor by a float product, exact here, not an integer division)
            first = b * bin_size + np.int64((lo_t - b * bin_size - bin_size + span + 0.5) * inv_span) * span
            lo = max(lo_t, first)
            hi = min(hi_t, first + bin_size - 1)
            for a in range(lo, hi + 1):
                out[r, a - first] += _window_value(peak[t], a, a, half_step, dr2[t], prod4[t], d_win)
        const = anchor_const[anchor]
        for s in range(bin_size):
            out[r, s] += const
    return out
