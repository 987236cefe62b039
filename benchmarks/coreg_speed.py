"""Quick, repeatable timing of System B's co-registration (:func:`forestreg.engine.coreg.coregister`).

The case is :mod:`benchmarks.system_b`'s: a simulated 40 m ``planted_conifer`` plot flown by the
UAV at 86 m (~0.40 M points) and walked with a backpack (~3.4 M points), misaligned by 180 deg
and (8, -6, 1.5) m; ``--tls`` takes the ``mixed_temperate`` TLS case instead. The clouds are
simulated once and cached as LAZ files (with the true matrix) under ``bench_out/coreg_speed/``,
so later runs read them back in a few seconds and time the co-registration alone.

Run from the repository root::

    python -m benchmarks.coreg_speed                 # backpack case, one run
    python -m benchmarks.coreg_speed --repeat 3      # three runs, per-step timings of each
    python -m benchmarks.coreg_speed --tls           # the TLS case
    python -m benchmarks.coreg_speed --profile 40    # cProfile: the 40 costliest functions

Prints the per-step timings (``CoregistrationResult.timings``, seconds) and the errors against
the truth (rotation, deg; translation, m). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
from pathlib import Path

import numpy as np

from forestreg.engine.core.scan import Scan
from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.coreg import coregister
from forestreg.engine.io import read_scan, write_scan

CACHE = Path("bench_out") / "coreg_speed"
#: (preset, ground platform, heading deg, offset m): benchmarks.system_b's cases
CASES = {
    "backpack": ("planted_conifer", "backpack", 180.0, (8.0, -6.0, 1.5)),
    "tls": ("mixed_temperate", "tls", -75.0, (-4.0, 9.0, -1.0)),
}


def load_case(name: str, seed: int = 0) -> tuple[Scan, Scan, np.ndarray]:
    """(ground scan, UAV scan, true 4x4 ground -> UAV matrix) of a case, simulated on first use and
    read back from the LAZ cache afterwards."""
    folder = CACHE / f"{name}_seed{seed}"
    files = folder / "ground.laz", folder / "uav.laz", folder / "truth.json"
    if not all(f.exists() for f in files):
        from forestreg.engine.simulate.platforms import simulate_coregistration_case

        preset, platform, heading, offset = CASES[name]
        t = time.perf_counter()
        case = simulate_coregistration_case(
            preset,
            seed=seed,
            size_m=40.0,
            ground_platform=platform,
            heading_deg=heading,
            offset_m=offset,
            uav_density_scale=1.0,
            backpack_density_scale=0.25,
            tls_step_deg=0.2,
        )
        folder.mkdir(parents=True, exist_ok=True)
        write_scan(case.ground, files[0])
        write_scan(case.uav, files[1])
        files[2].write_text(json.dumps({"matrix": np.asarray(case.matrix).tolist()}))
        print(f"simulated {name} in {time.perf_counter() - t:.0f} s, cached in {folder}")
    truth = np.asarray(json.loads(files[2].read_text())["matrix"], dtype=np.float64)
    return read_scan(files[0]), read_scan(files[1]), truth


def run_once(ground: Scan, uav: Scan, truth: np.ndarray) -> dict[str, float | str]:
    """One co-registration: its timings (s), status and errors against the truth."""
    t = time.perf_counter()
    result = coregister(ground, uav)
    row: dict[str, float | str] = {"wall_s": time.perf_counter() - t, "status": result.status, "reason": result.reason}
    row.update(result.timings)
    if result.ground_keypoints is not None and result.uav_keypoints is not None:
        row["keypoints"] = f"{len(result.ground_keypoints)}/{len(result.uav_keypoints)}, {result.n_matched} matched"
    if result.matrix is not None:
        rot, trans = rigid_errors(result.matrix, truth)
        row.update(rotation_error_deg=rot, translation_error_m=trans)
    return row


def main() -> None:  # pragma: no cover
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tls", action="store_true", help="the TLS case instead of the backpack one")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument(
        "--profile", type=int, default=0, metavar="N", help="cProfile one run, print the N costliest functions"
    )
    args = ap.parse_args()
    ground, uav, truth = load_case("tls" if args.tls else "backpack", args.seed)
    print(f"ground {len(ground):,} points, UAV {len(uav):,} points")
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        row = run_once(ground, uav, truth)
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(args.profile)
        print(row)
        return
    for k in range(args.repeat):
        row = run_once(ground, uav, truth)
        steps = "  ".join(
            f"{key[:-2]} {v:.2f}" for key, v in row.items() if key.endswith("_s") and isinstance(v, float)
        )
        err = (
            f"error {row['rotation_error_deg']:.4f} deg / {1000 * row['translation_error_m']:.1f} mm"
            if "rotation_error_deg" in row
            else f"{row['status']}: {row['reason']}"
        )
        print(f"run {k + 1}: {steps}  |  keypoints {row.get('keypoints', '-')}  |  {err}", flush=True)


if __name__ == "__main__":  # pragma: no cover
    main()
