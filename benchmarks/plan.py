"""Benchmark: the next-scan planner (``forestreg plan``) against the simulator's truth.

Over ``--plots`` simulated plots (default 20; circles of 20-30 m across, presets in turn, in a
forest going on 5 m beyond the plot's square, coarse angular step), each scanned from the plot's
centre and from a second position 6-9 m away (registered with the plot's own engine path), the
planner suggests the next scanner position within the plot. Then:

* **links**: the scan simulated at the suggested position is registered into the plot
  (:func:`~forestreg.engine.tls.plot.register_project`, onto the centre scan, else the other placed
  scan) and must be "ok" and within 0.1 deg / 5 cm of the truth;
* **area gain**: the stem area it newly sees (truth: bark bins of 10 deg x 0.5 m between 0.3 and
  2.3 m above the base of each stem within the plot hit by the new scan and by neither placed
  scan, each bin's area ``r * 10 deg * 0.5 m``) against the median of ``--random`` placements at the same distance from
  the placed scan the suggestion links to (random direction, within the plot circle, at least
  0.6 m from every stem's bark).

Printed per plot (preset, seed, side, figures) and overall: the link rate, the summed area gain
over the summed random medians, and the median of the per-plot ratios. Pass: links >= 95 % and
area >= 1.2 x random.

Run: ``python -m benchmarks.plan [--plots 20] [--random 7] [--step 0.4] [--seed 0]`` (about 10
minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PRESETS = ("mixed_temperate", "planted_conifer", "sloped", "mixed_temperate", "rainforest")
#: The forest goes on this far beyond the plot (the simulated scene is the plot and this margin), m
MARGIN_M = 5.0
BAND_M = (0.3, 2.3)
AZ_BIN_DEG, H_BIN_M = 10.0, 0.5


def seen_bins(sim, scene, radius: float = np.inf) -> dict:
    """{(tree id, azimuth bin, height bin): bin area m2} of the bark a simulated scan hit (truth),
    of the trees standing within ``radius`` of the plot's centre."""
    from forestreg.engine.simulate import Material

    labels, ids = sim.labels, sim.object_ids
    mask = labels == Material.TRUNK
    if not mask.any():
        return {}
    world = sim.world_points()[mask]
    ids = ids[mask]
    trees = {t.id: t for t in scene.trees if np.hypot(t.x, t.y) <= radius}
    out = {}
    for tid in np.unique(ids):
        t = trees.get(int(tid))
        if t is None:
            continue
        p = world[ids == tid]
        h = p[:, 2] - t.z
        keep = (h >= BAND_M[0]) & (h < BAND_M[1])
        if not keep.any():
            continue
        p, h = p[keep], h[keep]
        axis = np.array([t.point_at_height(float(v)) for v in h])
        az = np.degrees(np.arctan2(p[:, 1] - axis[:, 1], p[:, 0] - axis[:, 0])) % 360.0
        area = (t.dbh_m / 2.0) * np.radians(AZ_BIN_DEG) * H_BIN_M
        for a, b in set(zip((az // AZ_BIN_DEG).astype(int).tolist(), (h // H_BIN_M).astype(int).tolist())):
            out[(int(tid), a, b)] = area
    return out


def new_area(bins: dict, seen: set) -> float:
    return float(sum(a for k, a in bins.items() if k not in seen))


def clear_of_stems(xy, scene, clearance: float = 0.6) -> bool:
    return all(np.hypot(xy[0] - t.x, xy[1] - t.y) - t.dbh_m / 2 >= clearance for t in scene.trees)


def one_plot(k: int, seed: int, step: float, randoms: int, work: Path) -> dict:
    from forestreg.engine.core.errors import ScanDataError
    from forestreg.engine.core.transform import rigid_errors
    from forestreg.engine.io import write_scan
    from forestreg.engine.simulate import ScannerSetup, make_scene, raycaster_for, simulate_tls_scan
    from forestreg.engine.tls.params import PlanParams
    from forestreg.engine.tls.plan import placed_links, placed_views, plan_scans
    from forestreg.engine.tls.plot import ScanCache, register_project
    from forestreg.engine.tls.project import Project

    rng = np.random.default_rng([seed, k])
    preset = PRESETS[k % len(PRESETS)]
    size = float(rng.uniform(20.0, 30.0))
    radius = size / 2
    scene = make_scene(preset, seed=seed * 1000 + k, size_m=size + 2 * MARGIN_M)
    angle = rng.uniform(0, 2 * np.pi)
    second = np.array([np.cos(angle), np.sin(angle)]) * rng.uniform(6.0, 9.0)
    placed_xy = [np.zeros(2), second]
    scene = scene.cleared(placed_xy, 1.0)
    caster = raycaster_for(scene)
    folder = work / f"plot{k:02d}"
    folder.mkdir(parents=True, exist_ok=True)

    def scan_at(xy, name: str, s: int):
        return simulate_tls_scan(
            scene,
            ScannerSetup(x=float(xy[0]), y=float(xy[1]), angular_step_deg=step, name=name),
            seed=s,
            raycaster=caster,
        )

    sims = [scan_at(xy, f"scan_{i + 1:02d}", seed * 100 + k * 10 + i) for i, xy in enumerate(placed_xy)]
    project = Project(name=folder.name)
    for sim in sims:
        write_scan(sim.scan, folder / f"{sim.name}.laz")
        project.add_scan(folder / f"{sim.name}.laz")
    cache = ScanCache(project, with_intensity=False)
    base = register_project(project, scans=cache)
    row = {"k": k, "preset": preset, "seed": seed * 1000 + k, "size_m": round(size, 1)}
    if base.failed:
        row["skipped"] = f"the two placed scans did not link: {base.reason}"
        return row
    t0 = time.perf_counter()
    plan = plan_scans(
        placed_views(project, cache), PlanParams(radius_m=radius), project.params, n=1, links=placed_links(project)
    )
    row["plan_s"] = round(time.perf_counter() - t0, 2)
    if not plan.suggestions:
        row["skipped"] = f"no suggestion: {plan.reason}"
        return row
    s = plan.suggestions[0]
    m0 = sims[0].pose
    world = (m0 @ np.array([s.x, s.y, 0.0, 1.0]))[:2]
    partner = sims[[sim.name + ".laz" for sim in sims].index(s.links_to)].position[:2]
    distance = float(np.hypot(*(world - partner)))
    seen = set()
    for sim in sims:
        seen |= set(seen_bins(sim, scene, radius))
    try:
        suggested = scan_at(world, "scan_03", seed * 100 + k * 10 + 5)
    except ScanDataError as exc:  # the position lies inside an object no placed scan saw
        row.update(
            x=round(float(world[0]), 2),
            y=round(float(world[1]), 2),
            links_to=s.links_to,
            predicted_shared=s.shared_stems,
            distance_m=round(distance, 2),
            linked=False,
            reason=f"the scanner stands inside an object ({exc})",
            suggested_m2=0.0,
        )
        return row
    write_scan(suggested.scan, folder / "scan_03.laz")
    project.add_scan(folder / "scan_03.laz")
    outcome = register_project(project, scans=cache)
    ok = outcome.scans.get("scan_03.laz") == "ok"
    if ok:
        truth = np.linalg.solve(m0, suggested.pose)
        rot, trans = rigid_errors(project.poses()["scan_03.laz"], truth)
        ok = rot < 0.1 and trans < 0.05
    row.update(
        x=round(float(world[0]), 2),
        y=round(float(world[1]), 2),
        links_to=s.links_to,
        predicted_shared=s.shared_stems,
        distance_m=round(distance, 2),
        linked=bool(ok),
        reason="" if ok else outcome.reasons.get("scan_03.laz", "pose off the truth"),
        suggested_m2=round(new_area(seen_bins(suggested, scene, radius), seen), 3),
    )
    randoms_m2 = []
    tries = 0
    while len(randoms_m2) < randoms and tries < 200:
        tries += 1
        a = rng.uniform(0, 2 * np.pi)
        xy = partner + distance * np.array([np.cos(a), np.sin(a)])
        if np.hypot(*xy) > radius or not clear_of_stems(xy, scene):
            continue
        try:
            sim = scan_at(xy, "random", seed * 100 + k * 10 + 6 + len(randoms_m2))
        except ScanDataError:  # inside a shrub or another object: not a place to set up
            continue
        randoms_m2.append(new_area(seen_bins(sim, scene, radius), seen))
    row["random_median_m2"] = round(float(statistics.median(randoms_m2)), 3) if randoms_m2 else None
    row["randoms"] = len(randoms_m2)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plots", type=int, default=20)
    parser.add_argument("--random", type=int, default=7)
    parser.add_argument("--step", type=float, default=0.4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", help="folder for the simulated scans (default: a temporary one)")
    args = parser.parse_args(argv)
    import logging

    logging.getLogger("forestreg").setLevel(logging.ERROR)
    rows = []
    with tempfile.TemporaryDirectory(prefix="forestreg-plan-bench-") as tmp:
        work = Path(args.workdir or tmp)
        for k in range(args.plots):
            t = time.perf_counter()
            row = one_plot(k, args.seed, args.step, args.random, work)
            row["s"] = round(time.perf_counter() - t, 1)
            rows.append(row)
            if "skipped" in row:
                print(
                    f"{k:2d} {row['preset']:16} seed {row['seed']:6d} {row['size_m']:5.1f} m: skipped - {row['skipped']}",
                    flush=True,
                )
                continue
            ratio = row["suggested_m2"] / row["random_median_m2"] if row.get("random_median_m2") else float("nan")
            print(
                f"{k:2d} {row['preset']:16} seed {row['seed']:6d} {row['size_m']:5.1f} m: links {'yes' if row['linked'] else 'NO '} "
                f"(predicted {row['predicted_shared']} shared, {row['distance_m']:.1f} m from {row['links_to']}) "
                f"new stem area {row['suggested_m2']:.2f} m2 vs random median {row['random_median_m2']} m2 ({ratio:.2f}x) "
                f"plan {row['plan_s']} s, {row['s']} s{'' if row['linked'] else ' - ' + row['reason']}",
                flush=True,
            )
    done = [r for r in rows if "skipped" not in r]
    linked = sum(r["linked"] for r in done)
    rate = linked / max(len(done), 1)
    with_random = [r for r in done if r.get("random_median_m2")]
    total = sum(r["suggested_m2"] for r in with_random) / max(sum(r["random_median_m2"] for r in with_random), 1e-9)
    ratios = [r["suggested_m2"] / r["random_median_m2"] for r in with_random]
    print(
        f"\nplots: {len(rows)} ({len(rows) - len(done)} skipped), seed {args.seed}, step {args.step} deg, {args.random} random placements each"
    )
    print(f"suggested scan links: {linked} of {len(done)} ({100 * rate:.0f} %)")
    print(
        f"new stem area, suggested / median random at the same distance: {total:.2f}x summed, "
        f"{statistics.median(ratios) if ratios else float('nan'):.2f}x median of the plots"
    )
    passed = rate >= 0.95 and total >= 1.2
    print("PASS" if passed else "FAIL")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
