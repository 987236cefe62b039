"""Benchmark: exact branch-and-bound VOP matcher vs the paper's literal enumeration.

Run ``python benchmarks/coarse_matcher.py`` (about 1-2 minutes on 2 cores). For each size n, a
realistic pair of VOP sets (n per side over a 22 m radius disc: 60 % shared trees, 10 % trees seen
from one side only, 30 % false VOPs, 2 cm noise) is matched with :func:`match_vops` (median of
several runs) and with the literal enumeration. When the literal enumeration is too long
(m*n > ``literal_full_max_pairs``) it is timed on a random sample of anchor pairs -- every angle k
and every moving point l, the same code path as :func:`match_vops_literal` -- and extrapolated
linearly to all m*n anchor pairs (``literal_extrapolated: True``).

``python benchmarks/coarse_matcher.py --packed`` times the worst case instead: 80 VOPs per scan
packed in a disc of 2 m radius (70 % shared, 2 cm noise), where many VOPs lie within ``D_t`` of each
other and the bounds are loose. It runs the compiled bounds (numba, the default) and the numpy
bounds (the code before the numba kernels) alternately and checks that both give the same result.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from forestreg.engine.tls import coarse


def _spread(rng: np.random.Generator, count: int, radius: float, min_sep: float) -> np.ndarray:
    pts: list[np.ndarray] = []
    while len(pts) < count:
        p = rng.uniform(-radius, radius, 2)
        if np.hypot(*p) <= radius and all(np.hypot(*(p - q)) >= min_sep for q in pts):
            pts.append(p)
    return np.array(pts).reshape(-1, 2)


def realistic_pair(n: int, seed: int = 0, radius: float = 22.0) -> tuple[np.ndarray, np.ndarray, float]:
    """(reference, moving, true rotation deg): n VOPs per side, metres, horizontal XY."""
    rng = np.random.default_rng(seed)
    shared, false = int(round(0.6 * n)), int(round(0.3 * n))
    unique = n - shared - false
    trees = _spread(rng, shared + 2 * unique, radius, 1.0)
    ref = np.vstack([trees[: shared + unique], _spread(rng, false, radius, 0.5)])
    world = np.vstack([trees[:shared], trees[shared + unique :], _spread(rng, false, radius, 0.5)])
    theta = float(rng.uniform(0.0, 360.0))
    c, s = np.cos(np.deg2rad(theta)), np.sin(np.deg2rad(theta))
    moving = (world - rng.uniform(-10.0, 10.0, 2)) @ np.array([[c, -s], [s, c]])
    moving += rng.normal(0.0, 0.02, moving.shape)
    return rng.permutation(ref), rng.permutation(moving), theta


def packed_pair(n: int = 80, seed: int = 0, radius: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(reference, moving): n VOPs per side uniform in a disc of ``radius`` metres (worst case).

    70 % of the moving VOPs are reference VOPs (rotated, shifted, 2 cm noise), the rest random.
    """
    rng = np.random.default_rng(seed)

    def disc(count: int) -> np.ndarray:
        a = rng.uniform(0.0, 2.0 * np.pi, count)
        d = radius * np.sqrt(rng.uniform(0.0, 1.0, count))
        return np.column_stack([d * np.cos(a), d * np.sin(a)])

    reference = disc(n)
    shared = int(round(0.7 * n))
    world = np.vstack([reference[rng.permutation(n)[:shared]], disc(n - shared)])
    theta = np.deg2rad(rng.uniform(0.0, 360.0))
    c, s = np.cos(theta), np.sin(theta)
    moving = (world - rng.uniform(-1.0, 1.0, 2)) @ np.array([[c, -s], [s, c]])
    moving += rng.normal(0.0, 0.02, moving.shape)
    return reference, rng.permutation(moving)


def run_packed(n: int = 80, repeats: int = 2, angle_step_deg: float = 0.1) -> list[dict]:
    """Worst case: wall time (s) of the compiled and the numpy bounds, alternately, same results."""
    reference, moving = packed_pair(n)
    kernels = coarse._compiled_kernels()
    times: dict[str, list[float]] = {"numba": [], "numpy": []}
    results = {}
    try:
        for _ in range(repeats):
            for name in ("numba", "numpy"):
                if name == "numba" and kernels is None:
                    continue
                coarse._kernels = kernels if name == "numba" else None
                t0 = time.perf_counter()
                res = coarse.match_vops(reference, moving, angle_step_deg=angle_step_deg)
                times[name].append(time.perf_counter() - t0)
                results[name] = res
    finally:
        coarse._kernels = kernels
    keys = {k: (r.anchor, r.angle_index, r.score, r.second_score, r.second_rotation_deg) for k, r in results.items()}
    if len(set(keys.values())) != 1:
        raise AssertionError(f"packed case: the bound paths disagree: {keys}")
    return [
        {"path": k, "median_s": statistics.median(v), "runs_s": v, "evaluated": results[k].evaluated}
        for k, v in times.items()
        if v
    ]


def _time_literal(
    reference: np.ndarray, moving: np.ndarray, angle_step_deg: float, sample_pairs: int, seed: int
) -> tuple[float, int]:
    """Seconds of the literal enumeration over ``sample_pairs`` random anchor pairs (all k, all l)."""
    k_count = coarse._angle_count(angle_step_deg)
    m, n = len(reference), len(moving)
    rng = np.random.default_rng(seed)
    flat = rng.choice(m * n, size=min(sample_pairs, m * n), replace=False)
    anchors = np.column_stack([flat // n, flat % n])
    t0 = time.perf_counter()
    scorer = coarse._Scorer(reference, moving, k_count, angle_step_deg, 0.2)
    coarse._literal_scores(scorer, k_count, anchors)
    return time.perf_counter() - t0, anchors.shape[0]


def run(
    sizes: tuple[int, ...] = (20, 40, 80),
    angle_step_deg: float = 0.1,
    *,
    repeats: int = 15,
    literal_full_max_pairs: int = 400,
    literal_sample_pairs: int = 48,
    seed: int = 0,
) -> list[dict]:
    """One row per size: fast and literal wall time (s), their ratio, exact scores computed.
    ``repeats`` runs of the fast matcher (their median) and ``literal_sample_pairs`` sampled
    anchor pairs of the enumeration: with 5 and 12 the ratio at 80 VOPs ranged over
    8,700-12,500x in three runs on one machine within minutes (a 16 ms median, 12 anchors)."""
    rows = []
    for n in sizes:
        reference, moving, theta = realistic_pair(n, seed)
        coarse.match_vops(reference, moving, angle_step_deg=angle_step_deg)  # warm-up
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fast = coarse.match_vops(reference, moving, angle_step_deg=angle_step_deg)
            times.append(time.perf_counter() - t0)
        fast_s = statistics.median(times)
        pairs = len(reference) * len(moving)
        if pairs <= literal_full_max_pairs:
            t0 = time.perf_counter()
            literal = coarse.match_vops_literal(reference, moving, angle_step_deg=angle_step_deg)
            literal_s = time.perf_counter() - t0
            extrapolated = False
            if (literal.anchor, literal.angle_index, literal.score) != (fast.anchor, fast.angle_index, fast.score):
                raise AssertionError(f"n={n}: fast matcher disagrees with the literal enumeration")
        else:
            sample_s, sampled = _time_literal(reference, moving, angle_step_deg, literal_sample_pairs, seed)
            literal_s = sample_s * pairs / sampled
            extrapolated = True
        rows.append(
            {
                "size": n,
                "angle_step_deg": angle_step_deg,
                "fast_s": fast_s,
                "fast_min_s": min(times),
                "literal_s": literal_s,
                "ratio": literal_s / fast_s,
                "literal_extrapolated": extrapolated,
                "evaluated": fast.evaluated,
                "literal_evaluated": pairs * coarse._angle_count(angle_step_deg),
                "matched": fast.matched,
                "second_matched": fast.second_matched,
                "rotation_error_deg": abs((fast.rotation_deg - theta + 180.0) % 360.0 - 180.0),
            }
        )
    return rows


def _format(rows: list[dict]) -> str:
    head = (
        f"{'VOPs':>5} {'fast s':>8} {'(min)':>7} {'literal s':>10} {'extrap.':>7} {'ratio':>9} "
        f"{'evaluated':>9} {'of':>9} {'matched':>7} {'2nd':>4} {'rot err':>7}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['size']:>5} {r['fast_s']:>8.3f} {r['fast_min_s']:>7.3f} {r['literal_s']:>10.1f} "
            f"{'yes' if r['literal_extrapolated'] else 'no':>7} {r['ratio']:>9.0f} {r['evaluated']:>9} "
            f"{r['literal_evaluated']:>9} {r['matched']:>7} {r['second_matched']:>4} {r['rotation_error_deg']:>7.3f}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--packed", action="store_true", help="time the packed worst case (numba vs numpy bounds)")
    parser.add_argument("--repeats", type=int, default=2, help="alternations of the packed case")
    args = parser.parse_args()
    if args.packed:
        for row in run_packed(repeats=args.repeats):
            runs = ", ".join(f"{t:.1f}" for t in row["runs_s"])
            print(
                f"packed 80 VOPs, {row['path']:>5} bounds: {row['median_s']:.1f} s (runs: {runs}), "
                f"{row['evaluated']} exact scores"
            )
    else:
        print(_format(run()))
