"""Compiled (numba) kernels of the coarse VOP matcher's bounds; see :mod:`.coarse` for the maths.

Frames and units are those of :mod:`.coarse`: radii in metres (pair radii of VOPs in their own scan's
horizontal plane), directions in radians, angles as integer indices ``a`` of the angle step (offset
by ``3K`` so that they stay positive; ``a mod K`` is the angle index, ``a = 0`` is ``k = K``).

Every kernel computes the same bounds as the numpy path of :mod:`.coarse` (the same formulas per
tuple and angle); only the summation order of a bound differs, which the bound's slack covers. The
exact scores are never computed here (they stay with the k-d tree scorer both matchers share).

Importing this module needs numba; :mod:`.coarse` falls back to its numpy path without it.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _window_value(peak: float, lo: int, hi: int, half_step: float, dr2: float, prod4: float, d_win: float) -> float:
    """Bound of ``max(0, D_t - distance)`` over angle indices ``lo..hi`` (metres; ``d_win = D_t + slack``)."""
    c = peak
    if c < lo:
        c = lo
    elif c > hi:
        c = hi
    x = abs(c - peak) * half_step
    s = x * (1.0 - x * x * (1.0 / 6.0))
    d = np.sqrt(dr2 + prod4 * (s * s))
    v = d_win - d
    return v if v > 0.0 else 0.0


@njit(cache=True, nogil=True)
def build_bounds(
    sorted_r: np.ndarray,
    order: np.ndarray,
    psi: np.ndarray,
    rm: np.ndarray,
    ph: np.ndarray,
    jj: np.ndarray,
    ll: np.ndarray,
    m: int,
    k_count: int,
    bin_size: int,
    n_bins: int,
    step_rad: float,
    d_win: float,
    wide_limit: int,
    cell_bound: np.ndarray,
    anchor_const: np.ndarray,
):
    """Join the pair radii into tuples and accumulate the level-1 bounds (see ``coarse._build_bounds``).

    ``sorted_r`` are the m*m reference pair radii (m) in increasing order, ``order`` their flat index
    ``i*m + q`` and ``psi`` (by flat index) their directions (rad); ``rm``, ``ph`` are the radii and
    directions of the moving pairs ``(jj, ll)`` with ``jj < ll``. Adds every tuple's bound to
    ``cell_bound`` (anchor ``j*m + i`` times ``n_bins`` plus bin) and angle-independent bounds to
    ``anchor_const``, in place. Returns the kept tuples: peak, a_lo, a_hi, (rho_l - rho_q)^2,
    4 rho_l rho_q, and the two twins' anchors.
    """
    inv_step = 1.0 / step_rad
    half_step = 0.5 * step_rad
    dw2 = d_win * d_win
    offset = 3.0 * k_count
    n_ref = sorted_r.shape[0]
    cap = 1024
    peak_o = np.empty(cap)
    lo_o = np.empty(cap, dtype=np.int32)
    hi_o = np.empty(cap, dtype=np.int32)
    dr2_o = np.empty(cap)
    prod4_o = np.empty(cap)
    anc_a_o = np.empty(cap, dtype=np.int32)
    anc_b_o = np.empty(cap, dtype=np.int32)
    count = 0
    for p in range(rm.shape[0]):
        rl = rm[p]
        first = np.searchsorted(sorted_r, rl - d_win, side="left")
        last = np.searchsorted(sorted_r, rl + d_win, side="right")
        base_a = jj[p] * m
        base_b = ll[p] * m
        phi = ph[p]
        for t in range(first, min(last, n_ref)):
            rp = order[t]
            rq = sorted_r[t]
            i = rp // m
            q = rp - i * m
            anchor_a = base_a + i
            anchor_b = base_b + q
            prod = 2.0 * rl * rq
            const = prod == 0.0
            if not const:
                c = (rl * rl + rq * rq - dw2) / prod
                if not (c > -1.0):
                    const = True
                else:
                    hw = (np.arccos(min(c, 1.0)) + 1e-9) * inv_step
                    peak = (psi[rp] - phi) * inv_step + offset
                    # floor(x) + 1 instead of ceil(x): an angle exactly on the widened edge has f = 0.
                    a_lo = np.int64(peak - hw) + 1
                    a_hi = np.int64(peak + hw)
                    if a_hi - a_lo >= wide_limit:
                        const = True
            if const:
                v = d_win - abs(rl - rq)
                if v > 0.0:
                    anchor_const[anchor_a] += v
                    anchor_const[anchor_b] += v
                continue
            if a_hi < a_lo:
                continue
            dr2 = (rl - rq) * (rl - rq)
            prod4 = 4.0 * rl * rq
            if count == cap:
                cap *= 2
                peak_o = _grow(peak_o, cap)
                lo_o = _grow(lo_o, cap)
                hi_o = _grow(hi_o, cap)
                dr2_o = _grow(dr2_o, cap)
                prod4_o = _grow(prod4_o, cap)
                anc_a_o = _grow(anc_a_o, cap)
                anc_b_o = _grow(anc_b_o, cap)
            peak_o[count] = peak
            lo_o[count] = a_lo
            hi_o[count] = a_hi
            dr2_o[count] = dr2
            prod4_o[count] = prod4
            anc_a_o[count] = anchor_a
            anc_b_o[count] = anchor_b
            count += 1
            row_a = anchor_a * n_bins
            row_b = anchor_b * n_bins
            for ob in range(a_lo // bin_size, a_hi // bin_size + 1):
                start = ob * bin_size
                v = _window_value(
                    peak, max(a_lo, start), min(a_hi, start + bin_size - 1), half_step, dr2, prod4, d_win
                )
                if v > 0.0:
                    b = ob % n_bins
                    cell_bound[row_a + b] += v
                    cell_bound[row_b + b] += v
    return (
        peak_o[:count].copy(),
        lo_o[:count].copy(),
        hi_o[:count].copy(),
        dr2_o[:count].copy(),
        prod4_o[:count].copy(),
        anc_a_o[:count].copy(),
        anc_b_o[:count].copy(),
    )


@njit(cache=True, nogil=True)
def _grow(arr: np.ndarray, cap: int) -> np.ndarray:
    out = np.empty(cap, dtype=arr.dtype)
    out[: arr.shape[0]] = arr
    return out


@njit(cache=True, nogil=True)
def anchor_lists(anc_a: np.ndarray, anc_b: np.ndarray, anchors: int) -> tuple[np.ndarray, np.ndarray]:
    """Tuples of every anchor (either twin): CSR ``start`` (anchors + 1,) and tuple ids, by anchor."""
    start = np.zeros(anchors + 1, dtype=np.int64)
    for t in range(anc_a.shape[0]):
        start[anc_a[t] + 1] += 1
        start[anc_b[t] + 1] += 1
    for a in range(anchors):
        start[a + 1] += start[a]
    fill = start[:-1].copy()
    ids = np.empty(2 * anc_a.shape[0], dtype=np.int32)
    for t in range(anc_a.shape[0]):
        ids[fill[anc_a[t]]] = t
        fill[anc_a[t]] += 1
        ids[fill[anc_b[t]]] = t
        fill[anc_b[t]] += 1
    return start, ids


@njit(cache=True, nogil=True)
def fine_bounds(
    cells: np.ndarray,
    bin_size: int,
    n_bins: int,
    step_rad: float,
    d_win: float,
    start: np.ndarray,
    ids: np.ndarray,
    peak: np.ndarray,
    a_lo: np.ndarray,
    a_hi: np.ndarray,
    dr2: np.ndarray,
    prod4: np.ndarray,
    anchor_const: np.ndarray,
) -> np.ndarray:
    """Level-2 bound (metres) of every angle of ``cells``, shape (len(cells), bin_size).

    Row r, column s bounds angle ``(cells[r] % n_bins) * bin_size + s`` of anchor
    ``cells[r] // n_bins``; ``start``/``ids`` list each anchor's tuples (:func:`anchor_lists`).
    """
    half_step = 0.5 * step_rad
    out = np.empty((cells.shape[0], bin_size))
    span = n_bins * bin_size  # = K
    for r in range(cells.shape[0]):
        anchor = cells[r] // n_bins
        b = cells[r] - anchor * n_bins
        const = anchor_const[anchor]
        for s in range(bin_size):
            out[r, s] = 0.0
        for e in range(start[anchor], start[anchor + 1]):
            t = ids[e]
            lo_t, hi_t, p = a_lo[t], a_hi[t], peak[t]
            # The window (offset angles, inside [K/2, 5.5K]) meets this bin in at most one copy.
            first = b * bin_size + ((lo_t - b * bin_size - bin_size + 1 + span - 1) // span) * span
            lo = max(lo_t, first)
            hi = min(hi_t, first + bin_size - 1)
            for a in range(lo, hi + 1):
                out[r, a - first] += _window_value(p, a, a, half_step, dr2[t], prod4[t], d_win)
        for s in range(bin_size):
            out[r, s] += const
    return out
