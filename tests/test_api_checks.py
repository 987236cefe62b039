"""The Python API under a hostile caller, clouds in the wrong unit, a plot
taken as a single tree, and a merged cloud inside the plot's output folder.

- every public function checks what it is given as the command line does and raises the
  product's errors (a cloud in mm used to end the interpreter with ``std::bad_alloc``; an array
  given to ``register`` a raw ``AttributeError``), run in a subprocess so that a crash fails the
  test instead of killing pytest;
- a cloud in cm or mm is refused in seconds, with the likely unit, by every command that reads
  clouds and by the API (one check, :func:`forestreg.app.common.check_units`); no real cloud of
  ``../shared/data`` nor the simulator's outputs in metres is refused;
- ``--single-tree yes`` on a plot flags the tree and warns; a real single tree is not flagged;
- ``plot --merged OUT/all.copc.laz`` works on a fresh run.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import main

CLI = [sys.executable, "-m", "forestreg.cli"]

REAL_CLOUDS = (
    "LPine1_demo.laz",
    "pine_plot.laz",
    "pine.laz",
    "spruce.laz",
    "TLS_scan_scanner_at_origin.laz",
    "cloud.txt",
    "spanner_MLS_Clip.laz",
    "spanner_ALS_Clip.laz",
    "lidR_MixedConifer.laz",
    "AdTree_tree1.xyz",
    "AdTree_tree7.xyz",
    "AdTree_Lille_2.xyz",
    "aRchi_Tree_2_point_cloud.las",
    "SERC_transect_als.laz",
    "SERC_transect_drone.laz",
    "SERC_transect_drone_leafoff.laz",
    "SERC_trunk_tls.laz",
    "SERC_trunk_mls.laz",
    "SERC_trunk_drone.laz",
    "SERC_trunk_drone_leafoff.laz",
)


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p] + [env.get("PYTHONPATH", "")])
    return env


def _run(*args, timeout: float = 120) -> tuple[subprocess.CompletedProcess, float]:
    """The CLI in its own process, and how long it took (s)."""
    t0 = time.perf_counter()
    done = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, env=_env(), timeout=timeout)
    return done, time.perf_counter() - t0


def _python(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``code`` in a Python process of its own (a crash there is a failed test, not a dead pytest)."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=_env(), timeout=timeout
    )


def _write_scaled(path: Path, points: np.ndarray, factor: float) -> Path:
    """``points`` (file coordinates, metres) times ``factor`` as a LAS/LAZ file: a cloud in cm or
    mm as a user's exporter writes it (laspy, not forestreg's writer, which refuses such extents)."""
    import laspy

    p = np.asarray(points, dtype=np.float64) * factor
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = [0.001 * factor] * 3
    header.offsets = np.floor(p.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def scans(tmp_path_factory, sim_plot):
    """Two tiny simulated TLS scans (30 m plot, 0.5 deg steps) as files in m, cm and mm:
    ``{unit: (path1, path2)}``, and the plot."""
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (6.0, 2.0), (-5.0, 4.0)), seed=3, step=0.5, size=30.0)
    folder = tmp_path_factory.mktemp("api_scans")
    files = {}
    for unit, factor in (("m", 1.0), ("cm", 100.0), ("mm", 1000.0)):
        files[unit] = tuple(
            _write_scaled(folder / f"{s.scan.name}_{unit}.laz", s.scan.file_points, factor) for s in plot.scans[:2]
        )
    return files, plot


@pytest.fixture(scope="module")
def pine_plot_units(shared_data, tmp_path_factory):
    """pine_plot.laz in cm and in mm: ``{unit: path}``."""
    from forestreg.engine.io import read_scan

    points = read_scan(shared_data / "pine_plot.laz", with_intensity=False).file_points
    folder = tmp_path_factory.mktemp("api_pine_plot")
    return {
        unit: _write_scaled(folder / f"pine_plot_{unit}.laz", points, factor)
        for unit, factor in (("cm", 100.0), ("mm", 1000.0))
    }


# ----------------------------------------------------------------------------- 2, 13: the Python API


def test_measure_trees_of_a_cloud_in_mm_raises_the_products_error_not_a_crash(shared_data):
    """A pine_plot crop times 1000 (float, int64) and times 100 ended the interpreter with
    std::bad_alloc (signal 6) or ran for minutes; now each raises a ForestregError at once."""
    done = _python(f"""
        import json, time, numpy as np, forestreg
        from forestreg.engine.io import read_scan
        points = read_scan({str(shared_data / "pine_plot.laz")!r}).points
        out = []
        for factor, dtype in ((1000, np.float64), (1000, np.int64), (100, np.float64), (100, np.int64)):
            t0 = time.perf_counter()
            try:
                forestreg.measure_trees((points * factor).astype(dtype))
                out.append(["returned", "", 0.0])
            except forestreg.ForestregError as exc:
                out.append([type(exc).__name__, str(exc), time.perf_counter() - t0])
        print(json.dumps(out))
    """)
    assert done.returncode == 0, f"the interpreter ended with {done.returncode}: {done.stderr[-500:]}"
    results = json.loads(done.stdout.strip().splitlines()[-1])
    assert [r[0] for r in results] == ["ScanDataError", "ScanDataError", "UnitError", "UnitError"]
    assert all(seconds < 20 for _, _, seconds in results)
    assert "millimetres" in results[0][1] and "centimetres" in results[2][1] and "--units cm" in results[2][1]


#: (a call of the public API, the error class expected, words its message must hold)
HOSTILE_CALLS = (
    ("forestreg.register(object(), object())", "InvalidArgumentError", "Scan"),
    ("forestreg.register(np.zeros((50, 2)), np.zeros((50, 2)))", "ScanDataError", "(N, 3)"),
    ("forestreg.register(P, P)", "UsageError", "same scan"),
    ("forestreg.register(P * 100, P2 * 100)", "UnitError", "centimetres"),
    ("forestreg.register(P, P2, params=forestreg.TreeParams())", "ParameterError", "RegistrationParams"),
    ("forestreg.measure_trees(object())", "InvalidArgumentError", "(N, 3) array"),
    ("forestreg.measure_trees('missing.laz')", "ScanReadError", "missing.laz"),
    ("forestreg.measure_trees(np.full((100, 3), np.nan))", "ScanDataError", "NaN"),
    ("forestreg.measure_trees(np.zeros((100, 2)))", "ScanDataError", "(N, 3)"),
    ("forestreg.measure_trees(P, forestreg.RegistrationParams())", "ParameterError", "TreeParams"),
    ("forestreg.coregister(object(), P)", "InvalidArgumentError", "Scan"),
    ("forestreg.coregister(P * 100, P2 * 100)", "UnitError", "centimetres"),
    ("forestreg.fuse_scans(P, P2, np.eye(3))", "TransformError", "4x4"),
    ("forestreg.fuse_scans(P * 100, P2 * 100, np.eye(4))", "UnitError", "centimetres"),
    ("forestreg.fuse(P * 100, np.zeros((0, 3)))", "UnitError", "centimetres"),
    ("forestreg.fuse_files('a.laz', 'b.laz', np.eye(4))", "ScanReadError", "a.laz"),
    ("forestreg.fuse_files(1, 2, np.eye(4))", "InvalidArgumentError", "path"),
    ("forestreg.evaluate(np.zeros((3, 3)), np.zeros((3, 3)))", "InvalidArgumentError", "TreeTable"),
    ("forestreg.evaluate(ROWS, ROWS, by='name')", "ParameterError", "position"),
    ("forestreg.evaluate(ROWS, ROWS, max_distance_m=-1)", "ParameterError", "positive"),
    ("forestreg.evaluate(ROWS, ROWS, parameters='dbh_m')", "ParameterError", "list"),
    ("forestreg.terrain_model(np.zeros((10, 2)))", "ScanDataError", "(N, 3)"),
    ("forestreg.terrain_model(P * 100)", "UnitError", "centimetres"),
    ("forestreg.locate_scanner(np.zeros(3))", "ScanDataError", "(N, 3)"),
    ("forestreg.register_manual(object(), P, {}, {})", "InvalidArgumentError", "Scan"),
    ("forestreg.register_project(np.zeros(3))", "InvalidArgumentError", "Project"),
    ("forestreg.register_survey(np.zeros(3))", "InvalidArgumentError", "Project"),
    ("forestreg.compare_auto_manual(np.zeros(3))", "InvalidArgumentError", "Project"),
    ("forestreg.read_scan(123)", "InvalidArgumentError", "path"),
    ("forestreg.read_scan(CM_FILE)", "UnitError", "unit_scale=0.01"),
    ("forestreg.write_scan(object(), 'x.laz')", "InvalidArgumentError", "Scan"),
)


def test_every_public_function_raises_the_products_errors_naming_what_it_expects(scans, tmp_path):
    """Wrong types, shapes, units and parameters, given to each function of the public API in a
    process of its own: a ForestregError naming what was expected, never a raw AttributeError or
    TypeError, never a crash."""
    files, plot = scans
    calls = json.dumps([c for c, _, _ in HOSTILE_CALLS])
    done = _python(
        f"""
        import json, os, numpy as np, forestreg
        os.chdir({str(tmp_path)!r})
        P = forestreg.read_scan({str(files["m"][0])!r}).points
        P2 = forestreg.read_scan({str(files["m"][1])!r}).points
        CM_FILE = {str(files["cm"][0])!r}
        ROWS = [{{"tree_id": 1, "x": 0.0, "y": 0.0, "dbh_m": 0.3}}]
        out = []
        for call in json.loads({calls!r}):
            try:
                eval(call)
                out.append(["returned", ""])
            except forestreg.ForestregError as exc:
                out.append([type(exc).__name__, str(exc)])
            except Exception as exc:
                out.append(["raw " + type(exc).__name__, str(exc)])
        print(json.dumps(out))
    """,
        timeout=300,
    )
    assert done.returncode == 0, f"the interpreter ended with {done.returncode}: {done.stderr[-800:]}"
    results = json.loads(done.stdout.strip().splitlines()[-1])
    wrong = [
        f"{call}: {got} {text[:160]!r} (expected {cls} naming {words!r})"
        for (call, cls, words), (got, text) in zip(HOSTILE_CALLS, results)
        if got != cls or words not in text
    ]
    assert wrong == []


def test_register_takes_arrays_and_measure_trees_takes_a_scan(scans, shared_data):
    """register(ndarray, ndarray) gave AttributeError ('numpy.ndarray' object has no attribute
    'meta') and measure_trees(Scan) a TypeError: both are taken, and give what the scans give."""
    import forestreg
    from forestreg.engine.core.transform import rigid_errors

    files, plot = scans
    a, b = (forestreg.read_scan(p) for p in files["m"])
    by_arrays = forestreg.register(a.points, b.points)
    assert by_arrays.ok, by_arrays.reason
    rot, trans = rigid_errors(by_arrays.matrix, plot.relative_pose(0, 1))
    assert rot < 0.05 and trans < 0.02

    params = forestreg.TreeParams().replace(cylinder_models=False)
    scan = forestreg.read_scan(shared_data / "AdTree_tree1.xyz")
    by_scan = forestreg.measure_trees(scan, params)
    by_points = forestreg.measure_trees(scan.points, params)
    by_path = forestreg.measure_trees(shared_data / "AdTree_tree1.xyz", params)
    assert len(by_scan.trees) == len(by_points.trees) == len(by_path.trees) == 1
    assert by_scan.rows()[0]["height_m"] == pytest.approx(by_points.rows()[0]["height_m"])
    assert by_scan.rows()[0]["dbh_m"] == pytest.approx(by_path.rows()[0]["dbh_m"])


# ----------------------------------------------------------------------------- 3: clouds in the wrong unit


@pytest.mark.parametrize("unit", ["cm", "mm"])
def test_pine_plot_in_cm_or_mm_is_refused_by_trees_in_seconds(pine_plot_units, tmp_path, unit):
    """``forestreg trees crop_cm.laz`` ran for minutes at 1.7 GB: now exit 2 in seconds, with the
    likely unit and the option that gives it; nothing written."""
    done, seconds = _run("trees", pine_plot_units[unit], "--out", tmp_path / "trees", timeout=60)
    assert done.returncode == 2, done.stderr
    assert seconds < 60
    assert "--units" in done.stderr and ("centimetres" if unit == "cm" else "millimetres") in done.stderr
    assert not (tmp_path / "trees").exists()


def test_pine_plot_in_cm_is_measured_with_its_unit(pine_plot_units, tmp_path):
    """The same cloud with ``--units cm`` passes the check (and is measured)."""
    from forestreg.app.common import check_units
    from forestreg.engine.io import read_scan

    check_units(read_scan(pine_plot_units["cm"], unit_scale=0.01).points, "cm", "pine_plot_cm")
    assert (
        main(
            [
                "trees",
                str(pine_plot_units["cm"]),
                "--out",
                str(tmp_path / "t"),
                "--units",
                "cm",
                "--no-cylinders",
                "--no-report",
                "-q",
            ]
        )
        == 0
    )


@pytest.mark.parametrize("unit", ["cm", "mm"])
@pytest.mark.parametrize("command", ["register", "plot", "coregister", "fuse", "trees"])
def test_every_command_refuses_simulated_scans_in_cm_or_mm(scans, tmp_path, command, unit):
    """Every command that reads clouds refuses the simulated scans in cm or mm: exit 2 within 60 s,
    naming the unit, before anything is written."""
    files, _ = scans
    a, b = files[unit]
    out = tmp_path / "out"
    args = {
        "register": (a, b, "--out", out),
        "plot": (a, b, "--out", out),
        "coregister": (a, b, "--out", out),
        "fuse": (a, b, "--out", tmp_path / "fused.laz"),
        "trees": (a, "--out", out),
    }[command]
    done, seconds = _run(command, *args, timeout=60)
    assert done.returncode == 2, done.stderr
    assert seconds < 60
    assert ("centimetres" if unit == "cm" else "millimetres") in done.stderr
    assert not out.exists() and not (tmp_path / "fused.laz").exists()


def test_the_api_refuses_simulated_scans_in_cm_and_takes_them_in_metres(scans):
    """The API's functions refuse the simulated points in cm with the product's error naming the
    unit, and take them in metres (the same check as the command line)."""
    import forestreg
    from forestreg.app.common import UnitError

    files, plot = scans
    points = plot.scans[0].scan.points
    for call in (
        lambda p: forestreg.measure_trees(p),
        lambda p: forestreg.terrain_model(p),
        lambda p: forestreg.fuse(p, np.zeros((0, 3))),
        lambda p: forestreg.locate_scanner(p),
    ):
        with pytest.raises(UnitError, match="centimetres"):
            call(points * 100.0)
    with pytest.raises(UnitError, match="looks like metres"):
        forestreg.read_scan(files["m"][0], unit_scale=0.01)
    assert len(forestreg.terrain_model(points).ground) == len(points)
    assert len(forestreg.read_scan(files["cm"][0], unit_scale=0.01).points) == len(points)


def test_no_real_cloud_in_metres_is_refused(shared_data):
    """Every real cloud of ../shared/data, in metres: not refused (TLS, MLS, ALS, drone, single trees,
    trunk sections, UTM); each checked in well under a second."""
    from forestreg.app.common import check_units
    from forestreg.engine.io import read_scan

    slow = []
    for name in REAL_CLOUDS:
        scan = read_scan(shared_data / name, with_intensity=False)
        t0 = time.perf_counter()
        check_units(scan.points, "m", name)
        if time.perf_counter() - t0 > 2.0:
            slow.append(name)
    assert slow == []


def test_georeferenced_coordinates_stored_as_float32_are_refused(shared_data, tmp_path):
    """pine_plot.laz at UTM coordinates stored as float32 (northing steps of 0.5 m) gave "6 trees
    found from the canopy (no stems)", exit 0. The coarse steps are refused in one line (exit 2),
    before any work; a raster of heights exported as points (one per 0.5 m cell) is not."""
    from forestreg.app.common import UnitError, check_units
    from forestreg.engine.io import read_scan

    p = np.asarray(read_scan(shared_data / "pine_plot.laz").points, dtype=np.float64)
    utm = (p - p.mean(axis=0) + [470_000.0, 5_210_000.0, 250.0]).astype(np.float32).astype(np.float64)
    with pytest.raises(UnitError, match=r"y coordinates take only \d+ values, 0.5 m apart"):
        check_units(utm, "m", "pine_utm")
    path = tmp_path / "pine_utm.xyz"
    np.savetxt(path, utm, fmt="%.3f")
    assert main(["trees", str(path), "--out", str(tmp_path / "t"), "--no-cylinders", "--no-report", "-q"]) == 2
    assert not (tmp_path / "t").exists()
    check_units(p, "m", "pine_plot")  # the same cloud in double precision passes
    x, y = np.meshgrid(np.arange(0.0, 60.0, 0.5), np.arange(0.0, 60.0, 0.5))
    raster = np.c_[x.ravel(), y.ravel(), np.random.default_rng(0).uniform(0, 25, x.size)]
    check_units(raster, "m", "dsm")


def test_real_clouds_in_cm_are_refused_with_centimetres(shared_data):
    """The plots and trees of ../shared/data times 100 are refused as centimetres (trunk sections a
    metre tall are not: nothing in them says so, and they run fast)."""
    from forestreg.app.common import UnitError, check_units
    from forestreg.engine.io import read_scan

    for name in (
        "LPine1_demo.laz",
        "pine_plot.laz",
        "pine.laz",
        "spruce.laz",
        "TLS_scan_scanner_at_origin.laz",
        "spanner_MLS_Clip.laz",
        "spanner_ALS_Clip.laz",
        "AdTree_tree1.xyz",
        "AdTree_Lille_2.xyz",
        "aRchi_Tree_2_point_cloud.las",
        "cloud.txt",
    ):
        points = read_scan(shared_data / name, with_intensity=False).points * 100.0
        with pytest.raises(UnitError, match="looks like centimetres"):
            check_units(points, "m", name)


@pytest.mark.parametrize("preset", ["planted_conifer", "mixed_temperate", "rainforest", "sloped", "park"])
def test_simulated_scans_in_metres_pass_and_in_cm_do_not(sim_plot, preset):
    """The simulator's TLS scans and their merged cloud (metres) pass the check; the same times 100
    are refused."""
    from forestreg.app.common import UnitError, check_units

    plot = sim_plot(preset, ((0.0, 0.0), (8.0, 3.0)), seed=1, step=0.5, size=30.0)
    clouds = [s.scan.points for s in plot.scans] + [np.vstack([s.scan.file_points for s in plot.scans])]
    for points in clouds:
        check_units(points, "m", preset)
    with pytest.raises(UnitError, match="centimetres"):
        check_units(clouds[-1] * 100.0, "m", preset)


@pytest.mark.slow
def test_simulated_ground_and_uav_clouds_pass(tmp_path):
    """The simulator's backpack (MLS) and UAV clouds, in metres, pass the check."""
    from forestreg.app.common import check_units
    from forestreg.engine.simulate import simulate_coregistration_case

    case = simulate_coregistration_case(seed=0, size_m=30.0)
    for scan in (case.ground, case.uav):
        check_units(scan.points, "m", "simulated")


# ----------------------------------------------------------------------------- 8: --single-tree yes on a plot


def test_single_tree_yes_on_a_plot_warns_and_flags_the_tree(shared_data, tmp_path):
    """pine_plot.laz (about 16 stems) with ``--single-tree yes``: one tree as asked, but flagged,
    its values not trusted high, a warning on stderr saying how many stems the cloud holds."""
    done, _ = _run(
        "trees",
        shared_data / "pine_plot.laz",
        "--out",
        tmp_path / "t",
        "--single-tree",
        "yes",
        "--no-cylinders",
        "--no-report",
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    warnings = [line for line in (done.stdout + done.stderr).splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "stems: not a single tree" in warnings[0], done.stderr
    assert int(warnings[0].split("holds ")[1].split()[0]) >= 12  # about 16 stems
    assert "1 flagged" in done.stdout + done.stderr
    with open(tmp_path / "t" / "trees.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert "not a single tree" in row["flag"]
    for column in ("height_quality", "crown_quality"):
        assert row[column].endswith("; low"), row[column]
    assert row["dbh_quality"].endswith(("; low", "; none")), row["dbh_quality"]


@pytest.mark.parametrize("name", ["pine.laz", "AdTree_Lille_2.xyz"])
def test_a_real_single_tree_is_not_flagged_for_stems(shared_data, name):
    """A real single tree taken as one tree: one stem, no flag about stems, its height trusted."""
    import forestreg
    from forestreg.engine.trees.single import separate_stems

    inventory = forestreg.measure_trees(
        shared_data / name, forestreg.TreeParams().replace(cylinder_models=False), single_tree=True
    )
    (tree,) = inventory.trees
    assert not any("stems" in f for f in tree.flags)
    assert tree.quality["height"].endswith("; high")
    assert separate_stems([tree.stem]) == 1


# ----------------------------------------------------------------------------- 12: --merged inside --out


def test_plot_merged_inside_the_output_folder_on_a_fresh_run(scans, tmp_path, monkeypatch):
    """The README's ``plot scans/*.laz --out plot --merged plot/all.copc.laz``: refused on a fresh
    run ("folder plot does not exist"); now the merged cloud lands inside the finished folder, and a
    second run replaces it."""
    files, _ = scans
    monkeypatch.chdir(tmp_path)
    args = ["plot", *map(str, files["m"]), "--out", "plot", "--merged", "plot/all.copc.laz", "-q"]
    assert main(args) == 0
    assert (tmp_path / "plot" / "all.copc.laz").is_file() and (tmp_path / "plot" / "poses.json").is_file()
    assert main(args) == 0
    assert (tmp_path / "plot" / "all.copc.laz").is_file()
    # a wrong suffix inside the folder is still refused before the work
    assert main(["plot", *map(str, files["m"]), "--out", "other", "--merged", "other/all.txt.gz", "-q"]) == 2
    assert not (tmp_path / "other").exists()


def test_the_api_withholds_a_matrix_that_is_not_rigid(monkeypatch):
    """``forestreg.register`` and ``forestreg.coregister`` end with the use cases' last check: an
    "ok" whose matrix is scaled comes back failed, without the matrix, whatever the engine said."""
    import dataclasses
    import importlib

    import forestreg

    coreg_engine = importlib.import_module("forestreg.engine.coreg.coregister")
    pair_engine = importlib.import_module("forestreg.engine.tls.pair")

    @dataclasses.dataclass(frozen=True)
    class Result:
        status: str
        reason: str
        matrix: object

    scaled = np.eye(4)
    scaled[:3, :3] *= 1.01
    monkeypatch.setattr(pair_engine, "register", lambda *a, **k: Result("ok", "", scaled))
    monkeypatch.setattr(coreg_engine, "coregister", lambda *a, **k: Result("ok", "", scaled))
    points = np.random.default_rng(0).uniform(-20, 20, (2000, 3))
    for result in (forestreg.register(points, points + 1.0), forestreg.coregister(points, points + 1.0)):
        assert result.status == "failed" and result.matrix is None and "withheld" in result.reason
    monkeypatch.setattr(pair_engine, "register", lambda *a, **k: Result("ok", "", np.eye(4)))
    assert forestreg.register(points, points + 1.0).status == "ok"
