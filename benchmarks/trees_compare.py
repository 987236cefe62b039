"""Benchmark: trees side by side with Sylva -- the same clouds in the same run, with truth where there is one.

Commands, each a child process under :func:`benchmarks.peers.run_command` (wall time and peak
memory per command):

* forestreg: ``python -m forestreg.cli trees IN --out DIR --no-report --quiet``;
* Sylva (PyPI ``sylva-rs``): ``sylva ground IN NORM`` then ``sylva trees NORM -o trees.csv``
  (plots; the two commands' seconds added, the larger peak), ``sylva qsm IN OUT`` (single trees).

Cases (small, so the whole runs in a few minutes on a shared machine):

* ``sim plot``: a simulated ``mixed_temperate`` plot, 30 m square, four full-dome TLS scans
  (elevation up to the zenith) merged, suppressed trees 0.5 m below their neighbours' crowns (the
  truth: every tree's position, DBH, height and top seen or not). Figures over the true trees
  within :data:`RADIUS_M` of the centre with DBH >= 0.1 m: found (a stem within 0.5 m), false
  stems (detected within the radius, no true tree within 0.5 m), DBH rRMSE, height rRMSE of every
  matched tree and of forestreg's unflagged heights (Sylva flags none), summed volume.
* ``sim plot, crowns intermixed``: the same kind of plot, 40 m square, crowns growing into each
  other (no gap over a suppressed top): tops hidden or inside a neighbour's crown.
* ``pine_plot.laz``: the real TLS plot, against its 16 stem rings counted by hand.
* ``sim single tree``: one open-grown broadleaf, leaf-off, no ground (the simulator's meshed stem
  and branches are the volume truth): forestreg ``trees`` against ``sylva qsm``.
* real single trees (aRchi, AdTree tree1 and tree7, TreeLS ``pine.laz``, rTwig ``cloud.txt``):
  forestreg ``trees``, ``sylva qsm`` and the TreeQSM port side by side, total and stem volume.
  :data:`TREEQSM` holds the TreeQSM port's figures for them (PyPI ``pytlidar`` 1.1.2, default
  inputs from its ``define_input``; a benchmark reference only, run apart: it pins numba 0.61).

Held-out benchmark (``--halves``; :func:`run_halves`): forestreg and Sylva on the plots of
:data:`HALF_KINDS` (mixed with suppressed trees, broadleaf rainforest, planted conifers, small
trees beside big ones under or inside their crowns, crowns intermixed; 2-5 scans; full dome or
elevation up to +60 deg; oval, rough stems: ``stem_shapes="real"``), each kind drawn once from a
seed of :data:`TUNE_SEEDS` (the rules and thresholds were chosen on these: "tune") and once from
a seed of :data:`HELD_OUT_SEEDS` ("held out"; ``--held-out-seed`` draws others), and once more
from a seed of :data:`LOOSE_SEEDS` with each tree's height scattered about the stand's
height-diameter relation (:data:`LOOSE_HEIGHT_SCATTER`, as in a stand of several species or ages:
"looser"; never used to choose a rule). Per group: trees
found, false stems, DBH rRMSE, height rRMSE over every tree (forestreg and Sylva), the share of
forestreg's heights left unflagged (height trust not low) with their rRMSE and worst error, and
the flags' precision (flagged heights really more than 10 % off) and recall (heights more than
10 % off that are flagged). ``--height-evidence`` (:func:`height_evidence`) runs forestreg
alone, in-process, on the same cached plots and gives every matched tree's height evidence and
verdict beside its truth: the loop for choosing the height rules on the tune half.

Another crown model (``--branched``; :func:`run_branched`): mixed temperate stands whose trees are
grown as branching skeletons with leaves on the twigs (:mod:`forestreg.engine.simulate.branched_stand`),
dominant broadleaves and narrow-crowned trees with suppressed trees under their crowns, four
full-dome scans; the same figures, for the seeds looked at while a rule was chosen
(:data:`BRANCHED_TUNE_SEEDS`) and for seeds held out (:data:`BRANCHED_HELD_OUT_SEEDS`).

The simulated clouds are cached under ``bench_out/trees_compare/``. Run from the repository root:
``python -m benchmarks.trees_compare`` (or through ``benchmarks/run.py --only trees``).
"""

from __future__ import annotations

import csv
import json
import math
import re
import sys
import tempfile
from pathlib import Path
from typing import Any, Optional

import numpy as np

if __package__:
    from .peers import run_command, show_rows, sylva_command
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from peers import run_command, show_rows, sylva_command  # type: ignore[no-redef]

OUT = Path("bench_out") / "trees_compare"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RADIUS_M = 11.0
MATCH_M = 0.5
#: The TreeQSM port (pytlidar 1.1.2, default inputs) on the real single trees: total and stem
#: (trunk) volume (m3), DBH (m, its 1.3 m cylinder), height (m).
TREEQSM = {
    "aRchi_Tree_2_point_cloud.las": {"volume_m3": 0.0366, "stem_volume_m3": 0.0120, "dbh_m": 0.0649, "height_m": 6.20},
    "AdTree_tree1.xyz": {"volume_m3": 0.2011, "stem_volume_m3": 0.0560, "dbh_m": 0.1596, "height_m": 5.71},
    "AdTree_tree7.xyz": {"volume_m3": 0.1010, "stem_volume_m3": 0.0272, "dbh_m": 0.0774, "height_m": 5.24},
    "pine.laz": {"volume_m3": 1.0400, "stem_volume_m3": 0.5941, "dbh_m": 0.3377, "height_m": 20.38},
    "cloud.txt": {"volume_m3": 0.0234, "stem_volume_m3": 0.0108, "dbh_m": 0.0751, "height_m": 3.70},
    "AdTree_Lille_2.xyz": {"volume_m3": 7.5154, "stem_volume_m3": 1.3579, "dbh_m": 0.4973, "height_m": 15.83},
}
#: Stem rings of pine_plot.laz counted by hand (m from the cloud's minimum corner; see
#: tests/test_trees_platforms.py).
PINE_PLOT_RINGS = [
    (0.4, 0.0),
    (0.3, 2.0),
    (0.4, 4.0),
    (0.5, 6.1),
    (0.4, 8.2),
    (3.5, 1.5),
    (3.4, 3.6),
    (3.5, 5.7),
    (3.5, 7.7),
    (6.2, 1.0),
    (6.4, 4.7),
    (8.0, 4.6),
    (9.4, 1.2),
    (9.3, 3.4),
    (9.3, 5.4),
    (9.3, 7.5),
]


#: The simulated plots: (case, file stem, seed, plot size m, suppressed trees' clearance m: 0 =
#: crowns growing into each other).
SIM_PLOTS = (
    ("sim plot", "sim_plot_dome", 3, 30.0, 0.5),
    ("sim plot, crowns intermixed", "sim_plot_intermixed", 6, 40.0, 0.0),
)


def sim_plot(
    out: Path = OUT, stem: str = "sim_plot_dome", seed: int = 3, size_m: float = 30.0, clearance_m: float = 0.5
) -> tuple[Path, list[dict[str, Any]]]:
    """A simulated 4-scan plot (LAZ) and its true trees (see :data:`SIM_PLOTS`); simulated once
    and cached."""
    laz, truth = out / f"{stem}.laz", out / f"{stem}.json"
    if not (laz.exists() and truth.exists()):
        from scipy.spatial import cKDTree

        from forestreg.engine.io import write_points
        from forestreg.engine.simulate import simulate_plot

        plot = simulate_plot(
            "mixed_temperate",
            [(-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0)],
            seed=seed,
            angular_step_deg=0.35,
            size_m=size_m,
            scanner_options={"elevation_max_deg": 90.0},
            suppressed_clearance_m=clearance_m,
        )
        pts = np.vstack([s.world_points() for s in plot.scans])
        ids = np.concatenate([s.object_ids for s in plot.scans])
        trees = []
        for t in plot.scene.trees:
            mine = pts[ids == t.id]
            seen = len(mine) > 0 and float(cKDTree(mine).query(t.point_at_height(t.height_m))[0]) < 0.3
            trees.append(
                {"id": t.id, "x": t.x, "y": t.y, "dbh_m": t.dbh_m, "height_m": t.height_m, "top_seen": bool(seen)}
            )
        out.mkdir(parents=True, exist_ok=True)
        write_points(laz, pts)
        truth.write_text(json.dumps(trees, indent=1))
    return laz, json.loads(truth.read_text())


#: The held-out benchmark's plot kinds: (name, scene: a preset of
#: :func:`~forestreg.engine.simulate.make_scene` or "understory"
#: (:func:`~forestreg.engine.simulate.hard.understory_scene`), scene overrides, scans,
#: elevation_max_deg, plot side m, angular step deg).
HALF_KINDS = (
    ("mixed, suppressed", "mixed_temperate", {"suppressed_clearance_m": 0.5}, 4, 90.0, 30.0, 0.35),
    ("broadleaf rainforest", "rainforest", {}, 3, 60.0, 25.0, 0.3),
    ("planted conifer", "planted_conifer", {}, 2, 60.0, 25.0, 0.35),
    ("small beside big", "understory", {}, 4, 90.0, 30.0, 0.35),
    ("crowns intermixed", "mixed_temperate", {}, 5, 60.0, 30.0, 0.35),
)
#: One seed per kind of :data:`HALF_KINDS`: the plots the rules and thresholds were chosen on.
TUNE_SEEDS = (101, 102, 103, 104, 105)
#: One seed per kind: the plots reported as held out (not looked at while choosing).
HELD_OUT_SEEDS = (201, 202, 203, 204, 205)
#: One seed per kind: plots whose heights scatter about the stand's relation (held out too).
LOOSE_SEEDS = (301, 302, 303, 304, 305)
#: ...by exp(N(0, this)) per tree (:attr:`~forestreg.engine.simulate.scene.PresetConfig.height_scatter`).
LOOSE_HEIGHT_SCATTER = 0.12
#: Scanner positions (m) by the number of scans.
SCAN_LAYOUTS = {
    2: [(-5.0, 0.0), (5.0, 0.0)],
    3: [(-5.0, -3.0), (5.0, -3.0), (0.0, 5.5)],
    4: [(-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0)],
    5: [(-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0), (0.0, 0.0)],
}


def half_plot(kind: int, seed: int, out: Path = OUT, height_scatter: float = 0.0) -> tuple[Path, list[dict[str, Any]]]:
    """The plot of :data:`HALF_KINDS` ``[kind]`` drawn from ``seed`` (LAZ, the scans merged) and its
    true trees (id, x, y, DBH, height, shape, whether an added small tree, whether the truth's own
    points reach within 0.3 m of the top); simulated once and cached. ``height_scatter``: each
    tree's height scattered about the stand's relation by exp(N(0, it))."""
    name, scene_kind, overrides, n_scans, elev, size_m, step = HALF_KINDS[kind]
    stem = f"half_{kind}_{seed}"
    if height_scatter > 0:
        overrides = {**overrides, "height_scatter": height_scatter}
        stem += f"_scatter{round(100 * height_scatter)}"
    laz, truth = out / f"{stem}.laz", out / f"{stem}.json"
    if not (laz.exists() and truth.exists()):
        from scipy.spatial import cKDTree

        from forestreg.engine.io import write_points
        from forestreg.engine.simulate import make_scene, simulate_plot
        from forestreg.engine.simulate.hard import understory_scene

        if scene_kind == "understory":
            scene = understory_scene(seed, size_m, **overrides)
        else:
            scene = make_scene(scene_kind, seed=seed, size_m=size_m, stem_shapes="real", **overrides)
        added = set(scene.meta.get("understory_added", ()))
        plot = simulate_plot(
            scene_kind,
            SCAN_LAYOUTS[n_scans],
            scene=scene,
            seed=seed,
            angular_step_deg=step,
            scanner_options={"elevation_max_deg": elev},
        )
        pts = np.vstack([s.world_points() for s in plot.scans])
        ids = np.concatenate([s.object_ids for s in plot.scans])
        trees = []
        for t in plot.scene.trees:
            mine = pts[ids == t.id]
            seen = len(mine) > 0 and float(cKDTree(mine).query(t.point_at_height(t.height_m))[0]) < 0.3
            trees.append(
                {
                    "id": t.id,
                    "x": t.x,
                    "y": t.y,
                    "dbh_m": t.dbh_m,
                    "height_m": t.height_m,
                    "shape": t.shape,
                    "small_beside_big": t.id in added,
                    "top_seen": bool(seen),
                }
            )
        out.mkdir(parents=True, exist_ok=True)
        write_points(laz, pts)
        truth.write_text(json.dumps(trees, indent=1))
    return laz, json.loads(truth.read_text())


#: Branched stands (:mod:`forestreg.engine.simulate.branched_stand`: crowns grown from branches and
#: leaves, another crown model than the plots'): the seeds a height rule was checked on while it
#: was chosen, and the seeds held out.
BRANCHED_TUNE_SEEDS = (601, 602, 603, 604, 605, 606)
BRANCHED_HELD_OUT_SEEDS = (611, 612, 613, 614, 615, 616)


def branched_plot(seed: int, out: Path = OUT) -> tuple[Path, list[dict[str, Any]]]:
    """A branched stand drawn from ``seed`` (four full-dome scans at 0.3 deg from 5 m off the centre
    along both diagonals, merged; LAZ) and its true trees (id, x, y, DBH, height: the top of the
    tree's own mesh, form, suppressed); simulated once and cached."""
    laz, truth = out / f"branched_{seed}.laz", out / f"branched_{seed}.json"
    if not (laz.exists() and truth.exists()):
        from forestreg.engine.io import write_points
        from forestreg.engine.simulate.branched_stand import branched_stand, scan_branched_stand

        stand = branched_stand(seed)
        pts, _, heights = scan_branched_stand(stand, SCAN_LAYOUTS[4])
        out.mkdir(parents=True, exist_ok=True)
        write_points(laz, pts)
        trees = [
            {
                "id": t.id,
                "x": t.x,
                "y": t.y,
                "dbh_m": t.dbh_m,
                "height_m": heights[t.id],
                "form": t.form,
                "suppressed": t.suppressed,
            }
            for t in stand.trees
        ]
        truth.write_text(json.dumps(trees, indent=1))
    return laz, json.loads(truth.read_text())


def run_branched(workdir: Optional[Path] = None) -> list[dict[str, Any]]:
    """forestreg (``trees --no-cylinders``) and Sylva on the branched stands
    (:data:`BRANCHED_TUNE_SEEDS`, :data:`BRANCHED_HELD_OUT_SEEDS`): rows as :func:`run_halves`'."""
    sylva = sylva_command()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="forestreg-trees-branched-") as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for half, seeds in (("branched, tune", BRANCHED_TUNE_SEEDS), ("branched, held out", BRANCHED_HELD_OUT_SEEDS)):
            for seed in seeds:
                laz, truth = branched_plot(seed)
                case = {"half": half, "kind": "branched stand", "seed": seed, "case": f"branched stand (seed {seed})"}
                rows += _both_tools(case, laz, truth, work, sylva)
    return rows


def sim_single(out: Path = OUT) -> tuple[Path, dict[str, float]]:
    """The simulated single tree without ground (LAZ) and its truth (DBH, height to the cloud's
    top, meshed wood volume); simulated once and cached."""
    laz, truth = out / "sim_single.laz", out / "sim_single.json"
    if not (laz.exists() and truth.exists()):
        from forestreg.engine.io import write_points
        from forestreg.engine.simulate import simulate_plot
        from forestreg.engine.simulate.hard import leaf_off, single_tree_scene
        from forestreg.engine.simulate.mesh import tree_wood_volume

        scene = leaf_off(single_tree_scene(0))
        plot = simulate_plot(
            "single",
            [(-7.0, -3.0), (6.0, -4.0), (1.0, 7.0)],
            scene=scene,
            seed=1,
            angular_step_deg=0.25,
            clearance_m=0.5,
        )
        pts = np.vstack([s.world_points() for s in plot.scans])
        pts = pts[np.concatenate([s.object_ids for s in plot.scans]) == 1]
        tree = scene.trees[0]
        stem, branch = tree_wood_volume(scene, tree)
        out.mkdir(parents=True, exist_ok=True)
        write_points(laz, pts)
        truth.write_text(
            json.dumps({"dbh_m": tree.dbh_m, "height_m": float(pts[:, 2].max() - tree.z), "volume_m3": stem + branch})
        )
    return laz, json.loads(truth.read_text())


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _rrmse(pairs: list[tuple[float, float]]) -> float:
    a = np.array([p for p in pairs if math.isfinite(p[0])], dtype=float).reshape(-1, 2)
    return 100.0 * math.sqrt(float(np.mean((a[:, 0] - a[:, 1]) ** 2))) / float(np.mean(a[:, 1])) if len(a) else math.nan


def _forestreg(cloud: Path, work: Path, extra: tuple[str, ...] = ()) -> tuple[Any, list[dict[str, str]]]:
    out = work / f"fr_{cloud.stem}"
    run = run_command(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "trees",
            str(cloud),
            "--out",
            str(out),
            "--no-report",
            "--quiet",
            *extra,
        ],
        log=work / f"fr_{cloud.stem}.log",
    )
    return run, _rows(out / "trees.csv") if run.status == 0 else []


def _sylva_trees(sylva: str, cloud: Path, work: Path) -> tuple[dict[str, float], list[dict[str, str]]]:
    norm, table = work / f"sy_{cloud.stem}_norm.laz", work / f"sy_{cloud.stem}_trees.csv"
    g = run_command([sylva, "--no-progress", "ground", str(cloud), str(norm)])
    t = run_command([sylva, "--no-progress", "trees", str(norm), "-o", str(table)]) if g.status == 0 else g
    ok = g.status == 0 and t.status == 0
    return (
        {
            "wall_s": g.wall_s + t.wall_s,
            "peak_mb": max(g.peak_mb, t.peak_mb),
            "status": 0 if ok else (t.status or g.status),
        },
        _rows(table) if ok else [],
    )


def _sylva_qsm(sylva: str, cloud: Path, work: Path) -> tuple[dict[str, float], dict[str, float]]:
    log = work / f"sy_{cloud.stem}_qsm.log"
    run = run_command([sylva, "--no-progress", "qsm", str(cloud), str(work / f"sy_{cloud.stem}_qsm.csv")], log=log)
    text = log.read_text(errors="replace") if log.exists() else ""

    def grab(key: str) -> float:
        m = re.search(rf"{key}:\s*([-0-9.eE+]+)", text)
        return float(m.group(1)) if m else math.nan

    return {"wall_s": run.wall_s, "peak_mb": run.peak_mb, "status": run.status}, {
        "volume_m3": grab("total_volume_m3"),
        "stem_volume_m3": grab("stem_volume_m3"),
        "dbh_m": grab("dbh_m"),
    }


def _plot_figures(
    rows: list[dict[str, str]], truth: list[dict[str, Any]], *, dbh_key: str, height_key: str, flagged=None
) -> dict[str, Any]:
    """Found, false stems, DBH and height rRMSE against the simulated truth (see the module docstring)."""
    inside = [t for t in truth if math.hypot(t["x"], t["y"]) < RADIUS_M and t["dbh_m"] >= 0.1]
    txy = np.array([(t["x"], t["y"]) for t in truth])
    pairs, false = [], 0
    for r in rows:
        x, y = _num(r["x"]), _num(r["y"])
        d = np.hypot(txy[:, 0] - x, txy[:, 1] - y)
        k = int(np.argmin(d))
        if d[k] < MATCH_M:
            pairs.append((r, truth[k]))
        elif math.hypot(x, y) < RADIUS_M and math.isfinite(_num(r.get(dbh_key))):
            false += 1
    ids = {t["id"] for t in inside}
    found = [(r, t) for r, t in pairs if t["id"] in ids]
    out = {
        "true": len(inside),
        "found": len({t["id"] for _, t in found}),
        "false_stems": false,
        "dbh_rrmse_pct": _rrmse([(_num(r[dbh_key]), t["dbh_m"]) for r, t in found]),
        "height_rrmse_pct": _rrmse([(_num(r[height_key]), t["height_m"]) for r, t in found]),
    }
    if flagged is not None:
        unflagged = [(r, t) for r, t in found if not flagged(r)]
        errs = [
            abs(_num(r[height_key]) - t["height_m"]) / t["height_m"]
            for r, t in unflagged
            if math.isfinite(_num(r[height_key]))
        ]
        out.update(
            heights_unflagged=len(errs),
            unflagged_height_rrmse_pct=_rrmse([(_num(r[height_key]), t["height_m"]) for r, t in unflagged]),
            unflagged_height_max_pct=100.0 * max(errs) if errs else math.nan,
        )
    return out


def _height_low(r: dict[str, str]) -> bool:
    return r.get("height_quality", "").endswith(("low", "none"))


def _rings_found(rows: list[dict[str, str]], corner: np.ndarray) -> dict[str, Any]:
    xy = np.array([(_num(r["x"]), _num(r["y"])) for r in rows]).reshape(-1, 2) - corner
    rings = np.array(PINE_PLOT_RINGS)
    hit = [bool(len(xy)) and float(np.min(np.hypot(*(xy - ring).T))) < MATCH_M for ring in rings]
    matched = [bool(np.min(np.hypot(*(rings - p).T)) < MATCH_M) for p in xy]
    return {"true": len(rings), "found": int(sum(hit)), "false_stems": int(len(xy) - sum(matched))}


def _plots(sylva: Optional[str], work: Path) -> list[dict[str, Any]]:
    """The simulated plots and the real ``pine_plot.laz``: forestreg ``trees`` beside Sylva."""
    rows: list[dict[str, Any]] = []
    for case, stem, seed, size_m, clearance_m in SIM_PLOTS:
        laz, truth = sim_plot(OUT, stem, seed, size_m, clearance_m)
        run_, fr = _forestreg(laz, work)
        fig = _plot_figures(fr, truth, dbh_key="dbh_m", height_key="height_m", flagged=_height_low)
        fig["volume_m3"] = float(np.nansum([_num(r["volume_m3"]) for r in fr]))
        rows.append(
            {
                "case": case,
                "tool": "forestreg trees",
                "wall_s": run_.wall_s,
                "peak_mb": run_.peak_mb,
                "status": run_.status,
                **fig,
            }
        )
        if sylva:
            res, sy = _sylva_trees(sylva, laz, work)
            rows.append(
                {
                    "case": case,
                    "tool": "sylva ground + trees",
                    **res,
                    **_plot_figures(sy, truth, dbh_key="dbh", height_key="height"),
                }
            )

    real = DATA / "pine_plot.laz"
    if real.exists():
        from forestreg.engine.io import read_scan

        scan = read_scan(real)
        corner = scan.points[:, :2].min(axis=0) + scan.origin_shift[:2]
        run_, fr = _forestreg(real, work)
        flagged = sum(1 for r in fr if r["flag"])
        rows.append(
            {
                "case": "pine_plot.laz (real)",
                "tool": "forestreg trees",
                "wall_s": run_.wall_s,
                "peak_mb": run_.peak_mb,
                "status": run_.status,
                **_rings_found(fr, corner),
                "flagged": flagged,
                "heights_unflagged": sum(1 for r in fr if not _height_low(r)),
                "volume_m3": float(np.nansum([_num(r["volume_m3"]) for r in fr])),
            }
        )
        if sylva:
            res, sy = _sylva_trees(sylva, real, work)
            rows.append(
                {"case": "pine_plot.laz (real)", "tool": "sylva ground + trees", **res, **_rings_found(sy, corner)}
            )
    return rows


def _flag_figures(rows: list[dict[str, str]], truth: list[dict[str, Any]]) -> list[tuple[float, float, bool]]:
    """(reported height m, true height m, flagged) of forestreg's trees matched to the true trees
    within :data:`RADIUS_M` with DBH >= 0.1 m (flagged: the height's trust low or none)."""
    inside = {t["id"]: t for t in truth if math.hypot(t["x"], t["y"]) < RADIUS_M and t["dbh_m"] >= 0.1}
    txy = np.array([(t["x"], t["y"]) for t in truth])
    out = []
    for r in rows:
        d = np.hypot(txy[:, 0] - _num(r["x"]), txy[:, 1] - _num(r["y"]))
        k = int(np.argmin(d))
        if d[k] < MATCH_M and truth[k]["id"] in inside:
            out.append((_num(r["height_m"]), truth[k]["height_m"], _height_low(r)))
    return out


def run_halves(
    workdir: Optional[Path] = None, held_out: Optional[list[int]] = None, tune: bool = True, loose: bool = True
) -> list[dict[str, Any]]:
    """forestreg (``trees --no-cylinders``) and Sylva on every plot of :data:`HALF_KINDS`, for the
    tune seeds (:data:`TUNE_SEEDS`, unless ``tune`` is False), the held-out ones
    (``held_out``, default :data:`HELD_OUT_SEEDS`) and, unless ``loose`` is False, the looser
    ones (:data:`LOOSE_SEEDS`, heights scattered by :data:`LOOSE_HEIGHT_SCATTER`); one row per (plot, tool) with the figures of
    :func:`_plot_figures`, the half, kind and seed, and for forestreg the (height, true height,
    flagged) triples (``heights``)."""
    sylva = sylva_command()
    halves = (
        ([("tune", list(TUNE_SEEDS), 0.0)] if tune else [])
        + [("held out", list(held_out or HELD_OUT_SEEDS), 0.0)]
        + ([("looser", list(LOOSE_SEEDS), LOOSE_HEIGHT_SCATTER)] if loose else [])
    )
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="forestreg-trees-halves-") as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for half, seeds, scatter in halves:
            for kind, seed in enumerate(seeds):
                laz, truth = half_plot(kind, seed, height_scatter=scatter)
                case = {
                    "half": half,
                    "kind": HALF_KINDS[kind][0],
                    "seed": seed,
                    "case": f"{HALF_KINDS[kind][0]} ({HALF_KINDS[kind][3]} scans, up to {HALF_KINDS[kind][4]:.0f} deg, seed {seed})",
                }
                rows += _both_tools(case, laz, truth, work, sylva)
    return rows


def _both_tools(
    case: dict[str, Any], laz: Path, truth: list[dict[str, Any]], work: Path, sylva: Optional[str]
) -> list[dict[str, Any]]:
    """forestreg (``trees --no-cylinders``) and, where installed, Sylva on one simulated plot: a row
    each with ``case`` and the figures of :func:`_plot_figures`; forestreg's with its (height, true
    height, flagged) triples (``heights``), both with their matched pairs."""
    print(f"{case['half']}: {case['case']}", file=sys.stderr, flush=True)
    run_, fr = _forestreg(laz, work, ("--no-cylinders",))
    rows = [
        {
            **case,
            "tool": "forestreg trees",
            "wall_s": run_.wall_s,
            "peak_mb": run_.peak_mb,
            "status": run_.status,
            **_plot_figures(fr, truth, dbh_key="dbh_m", height_key="height_m", flagged=_height_low),
            "heights": _flag_figures(fr, truth),
            "pairs": _pairs(fr, truth, "dbh_m", "height_m"),
        }
    ]
    if sylva:
        res, sy = _sylva_trees(sylva, laz, work)
        rows.append(
            {
                **case,
                "tool": "sylva ground + trees",
                **res,
                **_plot_figures(sy, truth, dbh_key="dbh", height_key="height"),
                "pairs": _pairs(sy, truth, "dbh", "height"),
            }
        )
    return rows


def height_evidence(seeds: Optional[dict[str, list[int]]] = None) -> list[dict[str, Any]]:
    """forestreg's height judgement on the cached plots of the halves, tree by tree (in-process
    ``measure_trees`` without cylinder models, no Sylva: minutes, not the whole benchmark): for
    every true tree of DBH >= 0.1 m within :data:`RADIUS_M` matched to a stem within
    :data:`MATCH_M`, the evidence the judgement sees (the top's offset from the stem axis and its
    top layer's, as fractions of the crown radius; apex seen as a tip, top over the stem, cut
    flat; the departure from the plot's height-diameter curve; the reach among the neighbours'
    tops, :attr:`~forestreg.engine.trees.inventory.TreeParams.min_neighbour_reach`; the point
    count; the quality text naming the hints) beside the verdict (trust, flagged, where the
    height came from) and the truth (errors of the reported height, of the points' top and of the
    curve's height, fractions). ``seeds``: {half: seeds, one per kind}; default both halves."""
    from forestreg.engine.io import read_scan
    from forestreg.engine.trees.crown import CrownParams, apex_tip, top_cut_flat, top_over_stem
    from forestreg.engine.trees.inventory import TreeParams, _neighbour_reach, measure_trees

    params = TreeParams(cylinder_models=False)
    crown_params = CrownParams()
    out: list[dict[str, Any]] = []
    for half, half_seeds in (seeds or {"tune": list(TUNE_SEEDS), "held out": list(HELD_OUT_SEEDS)}).items():
        for kind, seed in enumerate(half_seeds):
            laz, truth = half_plot(kind, seed)
            scan = read_scan(laz)
            pts = np.asarray(scan.points, dtype=np.float64)
            shift = np.floor(pts.mean(axis=0))
            print(f"{half}: {HALF_KINDS[kind][0]}, seed {seed}", file=sys.stderr, flush=True)
            inv = measure_trees(pts - shift, params, single_tree=False)
            reach = _neighbour_reach(
                [r.stem for r in inv.trees], {r.tree_id: r.crown for r in inv.trees}, params.neighbour_radius_m
            )
            curve = inv.height_curve
            inside = [t for t in truth if math.hypot(t["x"], t["y"]) < RADIUS_M and t["dbh_m"] >= 0.1]
            xy = np.array([(r.stem.x + shift[0], r.stem.y + shift[1]) for r in inv.trees]).reshape(-1, 2)
            for t in inside:
                d = np.hypot(xy[:, 0] - t["x"], xy[:, 1] - t["y"])
                if not len(d) or d.min() >= MATCH_M:
                    continue
                r = inv.trees[int(np.argmin(d))]
                c = r.crown
                curve_h = curve.height_m(r.dbh_m) if curve is not None else math.nan
                quality = r.quality["height"]
                out.append(
                    {
                        "half": half,
                        "kind": HALF_KINDS[kind][0],
                        "seed": seed,
                        "tree_id": r.tree_id,
                        "true_height_m": t["height_m"],
                        "height_m": r.height_m,
                        "height_source": r.height_source,
                        "trust": quality.rsplit("; ", 1)[-1],
                        "flagged": quality.endswith(("low", "none")),
                        "error": r.height_m / t["height_m"] - 1.0,
                        "points_error": c.height_m / t["height_m"] - 1.0,
                        "curve_error": curve_h / t["height_m"] - 1.0,
                        "departure": curve.departure(r.dbh_m, c.height_m) if curve is not None else math.nan,
                        "reach": reach.get(r.tree_id, math.nan),
                        "top_offset_ratio": c.top_offset_ratio,
                        "top_layer_offset_ratio": c.top_layer_offset_ratio,
                        "apex_tip": apex_tip(c, crown_params),
                        "top_over_stem": top_over_stem(c, crown_params),
                        "cut_flat": top_cut_flat(c, crown_params),
                        "n_points": r.n_points,
                        "dbh_m": r.dbh_m,
                        "true_dbh_m": t["dbh_m"],
                        "small_beside_big": t.get("small_beside_big", False),
                        "true_top_seen": t.get("top_seen", False),
                        "quality": quality,
                    }
                )
    return out


def evidence_summary(rows: list[dict[str, Any]]) -> str:
    """Per half: trees, unflagged (share, rRMSE, worst) and the flags' precision and recall (a
    height more than 10 % off is wrong) of :func:`height_evidence`'s rows."""
    lines = []
    for half in dict.fromkeys(r["half"] for r in rows):
        e = np.array([r["error"] for r in rows if r["half"] == half])
        flagged = np.array([r["flagged"] for r in rows if r["half"] == half], dtype=bool)
        wrong = np.abs(e) > 0.10
        kept = e[~flagged]
        lines.append(
            f"{half}: {len(e)} trees, every height rRMSE {100 * math.sqrt(np.mean(e**2)):.1f} %; unflagged "
            f"{len(kept)} ({100 * len(kept) / max(len(e), 1):.0f} %), rRMSE "
            f"{100 * math.sqrt(np.mean(kept**2)) if len(kept) else math.nan:.1f} %, worst "
            f"{100 * np.max(np.abs(kept)) if len(kept) else math.nan:.0f} %; flag precision "
            f"{100 * np.mean(wrong[flagged]) if flagged.any() else math.nan:.0f} %, recall "
            f"{100 * np.mean(flagged[wrong]) if wrong.any() else math.nan:.0f} %"
        )
    return "\n".join(lines)


def _pairs(
    rows: list[dict[str, str]], truth: list[dict[str, Any]], dbh_key: str, height_key: str
) -> list[tuple[float, float, float, float]]:
    """(DBH m, true DBH m, height m, true height m) of a tool's trees matched to the true trees
    within :data:`RADIUS_M` with DBH >= 0.1 m (one per true tree: the nearest)."""
    inside = {t["id"] for t in truth if math.hypot(t["x"], t["y"]) < RADIUS_M and t["dbh_m"] >= 0.1}
    txy = np.array([(t["x"], t["y"]) for t in truth])
    best: dict[int, tuple[float, tuple[float, float, float, float]]] = {}
    for r in rows:
        d = np.hypot(txy[:, 0] - _num(r["x"]), txy[:, 1] - _num(r["y"]))
        k = int(np.argmin(d))
        t = truth[k]
        if d[k] < MATCH_M and t["id"] in inside and (t["id"] not in best or d[k] < best[t["id"]][0]):
            best[t["id"]] = (float(d[k]), (_num(r[dbh_key]), t["dbh_m"], _num(r[height_key]), t["height_m"]))
    return [v for _, v in best.values()]


def halves_summary(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The figures of each half, pooled over its plots: trees found (of true), false stems, DBH
    rRMSE and height rRMSE over every tree found (each tool), forestreg's unflagged share, their
    rRMSE and worst error (%), and the flags' precision and recall (a height more than 10 % off
    is wrong)."""
    out: dict[str, dict[str, Any]] = {}
    for half in dict.fromkeys(r["half"] for r in rows):
        mine = [r for r in rows if r["half"] == half]
        fig: dict[str, Any] = {"plots": len({r["seed"] for r in mine}), "seeds": sorted({r["seed"] for r in mine})}
        for tool, key in (("forestreg trees", "fr"), ("sylva ground + trees", "sy")):
            t = [r for r in mine if r["tool"] == tool]
            if not t:
                continue
            pairs = [p for r in t for p in r.get("pairs", [])]
            fig[f"{key}_found"] = sum(r["found"] for r in t)
            fig[f"{key}_true"] = sum(r["true"] for r in t)
            fig[f"{key}_false"] = sum(r["false_stems"] for r in t)
            fig[f"{key}_dbh_rrmse"] = _rrmse([(p[0], p[1]) for p in pairs])
            fig[f"{key}_height_rrmse"] = _rrmse([(p[2], p[3]) for p in pairs])
        h = [x for r in mine if r["tool"] == "forestreg trees" for x in r.get("heights", [])]
        if h:
            off = [abs(a / b - 1.0) > 0.10 if math.isfinite(a) else True for a, b, _ in h]
            flagged = [f for _, _, f in h]
            unflagged = [(a, b) for a, b, f in h if not f]
            tp = sum(o and f for o, f in zip(off, flagged))
            fig.update(
                fr_unflagged=len(unflagged),
                fr_heights=len(h),
                fr_unflagged_rrmse=_rrmse(unflagged),
                fr_unflagged_worst=100.0 * max((abs(a / b - 1.0) for a, b in unflagged), default=math.nan),
                flag_precision=100.0 * tp / sum(flagged) if sum(flagged) else math.nan,
                flag_recall=100.0 * tp / sum(off) if sum(off) else math.nan,
                flagged=sum(flagged),
                wrong=sum(off),
            )
        out[half] = fig
    return out


def halves_table(rows: list[dict[str, Any]]) -> str:
    """The held-out benchmark's table (Markdown): one column per half."""
    s = halves_summary(rows)
    halves = list(s)

    def cell(half: str, fmt) -> str:
        try:
            return fmt(s[half])
        except (KeyError, ValueError, ZeroDivisionError):
            return "-"

    lines = [
        "| | " + " | ".join(f"{h} (seeds {', '.join(map(str, s[h]['seeds']))})" for h in halves) + " |",
        "|---|" + "---:|" * len(halves),
    ]
    spec = [
        ("trees found (forestreg / Sylva)", lambda f: f"{f['fr_found']} / {f['sy_found']} of {f['fr_true']}"),
        ("false stems (forestreg / Sylva)", lambda f: f"{f['fr_false']} / {f['sy_false']}"),
        ("DBH rRMSE (forestreg / Sylva)", lambda f: f"{f['fr_dbh_rrmse']:.1f} % / {f['sy_dbh_rrmse']:.1f} %"),
        (
            "height rRMSE, every tree (forestreg / Sylva)",
            lambda f: f"{f['fr_height_rrmse']:.1f} % / {f['sy_height_rrmse']:.1f} %",
        ),
        (
            "forestreg heights unflagged",
            lambda f: f"{f['fr_unflagged']} of {f['fr_heights']} ({100 * f['fr_unflagged'] / f['fr_heights']:.0f} %)",
        ),
        (
            "unflagged heights: rRMSE, worst",
            lambda f: f"{f['fr_unflagged_rrmse']:.1f} %, {f['fr_unflagged_worst']:.0f} %",
        ),
        (
            "flag precision (flagged heights > 10 % off)",
            lambda f: f"{f['flag_precision']:.0f} % ({f['flagged']} flagged)",
        ),
        ("flag recall (> 10 % off heights flagged)", lambda f: f"{f['flag_recall']:.0f} % ({f['wrong']} > 10 % off)"),
    ]
    for name, fmt in spec:
        lines.append(f"| {name} | " + " | ".join(cell(h, fmt) for h in halves) + " |")
    return "\n".join(lines)


def halves_plot_rows(rows: list[dict[str, Any]]) -> str:
    """Each plot of the held-out benchmark: found, false stems, DBH and height rRMSE of both tools,
    forestreg's unflagged heights (Markdown)."""
    lines = [
        "| half | plot | tool | found | false | DBH rRMSE % | height rRMSE % | unflagged: n, rRMSE %, worst % | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        unf = (
            f"{r['heights_unflagged']}, {_f(r['unflagged_height_rrmse_pct'], '.1f')}, {_f(r['unflagged_height_max_pct'], '.0f')}"
            if "heights_unflagged" in r
            else "-"
        )
        lines.append(
            f"| {r['half']} | {r['case']} | {r['tool']} | {r['found']}/{r['true']} | {r['false_stems']} "
            f"| {_f(r['dbh_rrmse_pct'], '.1f')} | {_f(r['height_rrmse_pct'], '.1f')} | {unf} | {_f(r.get('wall_s'), '.0f')} |"
        )
    return "\n".join(lines)


def run(workdir: Optional[Path] = None, single_trees_only: bool = False) -> list[dict[str, Any]]:
    """Every case (or the single trees only), forestreg and Sylva in turn; one row per (case, tool)."""
    sylva = sylva_command()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="forestreg-trees-compare-") as tmp:
        work = Path(workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        if not single_trees_only:
            rows += _plots(sylva, work)
        laz, t = sim_single()
        singles = [("sim single tree", laz, t)]
        for name, ref in TREEQSM.items():
            if (DATA / name).exists():
                singles.append((f"{name} (real)", DATA / name, {"treeqsm_" + k: v for k, v in ref.items()}))
        for case, cloud, ref in singles:
            run_, fr = _forestreg(cloud, work)
            r = fr[0] if len(fr) == 1 else {}
            rows.append(
                {
                    "case": case,
                    "tool": "forestreg trees",
                    "wall_s": run_.wall_s,
                    "peak_mb": run_.peak_mb,
                    "status": run_.status,
                    "trees": len(fr),
                    "dbh_m": _num(r.get("dbh_m")),
                    "height_m": _num(r.get("height_m")),
                    "volume_m3": _num(r.get("volume_m3")),
                    "stem_volume_m3": _num(r.get("stem_volume_m3")),
                    **{f"true_{k}": v for k, v in ref.items() if not k.startswith("treeqsm")},
                    **{k: v for k, v in ref.items() if k.startswith("treeqsm")},
                }
            )
            if sylva:
                res, q = _sylva_qsm(sylva, cloud, work)
                rows.append({"case": case, "tool": "sylva qsm", **res, "trees": 1, **q})
            if "treeqsm_volume_m3" in ref:
                rows.append(
                    {
                        "case": case,
                        "tool": "TreeQSM port (pytlidar, stored)",
                        "trees": 1,
                        "dbh_m": ref["treeqsm_dbh_m"],
                        "height_m": ref["treeqsm_height_m"],
                        "volume_m3": ref["treeqsm_volume_m3"],
                        "stem_volume_m3": ref["treeqsm_stem_volume_m3"],
                    }
                )
    return rows


def single_tree_table(rows: list[dict[str, Any]]) -> str:
    """The real single trees: total and stem volume of forestreg, ``sylva qsm`` and the TreeQSM
    port side by side, each against the TreeQSM port (a Markdown table)."""
    cases: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if r["case"].endswith("(real)") and ("stem_volume_m3" in r or r["tool"] == "sylva qsm"):
            cases.setdefault(r["case"], {})[r["tool"].split(" (")[0]] = r
    lines = [
        "| tree | forestreg total (stem) m3 | sylva qsm total (stem) m3 | TreeQSM port total (stem) m3 | forestreg / TreeQSM total, stem |",
        "|---|---:|---:|---:|---:|",
    ]
    for case, by in cases.items():
        fr, sy, tq = by.get("forestreg trees", {}), by.get("sylva qsm", {}), by.get("TreeQSM port", {})

        def pair(r: dict[str, Any]) -> str:
            return f"{_f(r.get('volume_m3'), '.3f')} ({_f(r.get('stem_volume_m3'), '.3f')})"

        def pct(a: Any, b: Any) -> str:
            return _f(100.0 * (_num(a) / _num(b) - 1.0) if _num(b) > 0 else math.nan, "+.0f") + " %"

        lines.append(
            f"| {case.replace(' (real)', '')} | {pair(fr)} | {pair(sy)} | {pair(tq)} "
            f"| {pct(fr.get('volume_m3'), tq.get('volume_m3'))}, {pct(fr.get('stem_volume_m3'), tq.get('stem_volume_m3'))} |"
        )
    return "\n".join(lines)


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def format_rows(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the rows."""
    head = (
        "| case | tool | found | false stems | DBH rRMSE % | height rRMSE % (unflagged: n, rRMSE, max) | DBH m | height m | volume m3 "
        "| s | MB |"
    )
    lines = ["Trees side by side with Sylva (one run; seconds and MB of each command)", "", head, "|" + "---|" * 11]
    for r in rows:
        found = f"{r['found']}/{r['true']}" if "found" in r else "-"
        hr = _f(r.get("height_rrmse_pct"), ".1f")
        if "heights_unflagged" in r and "unflagged_height_rrmse_pct" in r:
            hr += f" ({r['heights_unflagged']}, {_f(r['unflagged_height_rrmse_pct'], '.1f')}, {_f(r['unflagged_height_max_pct'], '.0f')})"
        elif "heights_unflagged" in r:
            hr = f"- ({r['heights_unflagged']} unflagged, {r.get('flagged', 0)} trees flagged)"
        truth = ""
        if r.get("stem_volume_m3") is not None and math.isfinite(_num(r.get("stem_volume_m3"))):
            truth = f" (stem {r['stem_volume_m3']:.3f})"
        if "true_volume_m3" in r:
            truth = f" (true {r['true_volume_m3']:.3f})"
        dbh = _f(r.get("dbh_m"), ".3f") + (f" (true {r['true_dbh_m']:.3f})" if "true_dbh_m" in r else "")
        status = "" if r.get("status", 0) == 0 else f" (failed, status {r['status']})"
        lines.append(
            f"| {r['case']} | {r['tool']}{status} | {found} | {r.get('false_stems', '-')} | {_f(r.get('dbh_rrmse_pct'), '.1f')} | {hr} "
            f"| {dbh} | {_f(r.get('height_m'), '.2f')} | {_f(r.get('volume_m3'), '.3f')}{truth} | {_f(r.get('wall_s'), '.0f')} "
            f"| {_f(r.get('peak_mb'), '.0f')} |"
        )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    ap.add_argument("--workdir", type=Path, help="keep the outputs of every command here")
    ap.add_argument("--single-trees", action="store_true", help="only the single trees (simulated and real)")
    ap.add_argument(
        "--halves",
        action="store_true",
        help="only the held-out benchmark: tune, held-out and looser plots, forestreg and Sylva",
    )
    ap.add_argument(
        "--height-evidence",
        action="store_true",
        help="only forestreg's height judgement on the cached plots of the halves, tree by tree (no Sylva); "
        "--json writes the rows",
    )
    ap.add_argument(
        "--held-out-seed",
        type=int,
        help="with --halves: draw the held-out plots from this seed on (one per kind) "
        "instead of the stored held-out seeds",
    )
    ap.add_argument(
        "--branched",
        action="store_true",
        help="only the branched stands (crowns grown from branches and leaves): tune and held-out seeds, "
        "forestreg and Sylva",
    )
    args = ap.parse_args(argv)
    if args.branched:
        rows = run_branched(args.workdir)
        return show_rows(halves_table(rows) + "\n\n" + halves_plot_rows(rows), rows, args.json, indent=1, default=float)
    if args.height_evidence:
        rows = height_evidence()
        return show_rows(evidence_summary(rows), rows, args.json, indent=1, default=float)
    if args.halves:
        held = [args.held_out_seed + k for k in range(len(HALF_KINDS))] if args.held_out_seed is not None else None
        rows = run_halves(args.workdir, held)
        print(
            "seeds: tune "
            + ", ".join(map(str, TUNE_SEEDS))
            + "; held out "
            + ", ".join(map(str, held or HELD_OUT_SEEDS))
            + f"; looser (heights scattered {100 * LOOSE_HEIGHT_SCATTER:.0f} % about the stand's relation) "
            + ", ".join(map(str, LOOSE_SEEDS))
        )
        return show_rows(halves_table(rows) + "\n\n" + halves_plot_rows(rows), rows, args.json, indent=1, default=float)
    rows = run(args.workdir, single_trees_only=args.single_trees)
    return show_rows(format_rows(rows) + "\n\n" + single_tree_table(rows), rows, args.json, indent=1, default=float)


if __name__ == "__main__":
    sys.exit(main())
