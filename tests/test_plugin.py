"""The plugin hosts (thin clients of the job service): the host-free
adapter run for real on a simulated pair through the service (started on first use, in a
temporary state folder), the QGIS provider headless (where ``qgis.core`` imports), and
CloudCompare's ``-APPLY_TRANS`` on our ``transform.txt`` (where the ``CloudCompare`` binary is
installed)."""

from __future__ import annotations

import csv
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest

from forestreg.plugin import adapter

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "forestreg.cli"]


def _csv_rows(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module", autouse=True)
def service_state(tmp_path_factory):
    """The service the adapter starts lives in a temporary state folder and is stopped after."""
    from forestreg.client import read_server_info

    state = tmp_path_factory.mktemp("plugin_service")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FORESTREG_SERVICE_DIR", str(state))
        yield state
    info = read_server_info(state)
    if info:
        os.kill(info["pid"], signal.SIGTERM)
        deadline = time.monotonic() + 30
        while read_server_info(state) and time.monotonic() < deadline:
            time.sleep(0.1)


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """A tiny simulated pair: ``scan_01.laz`` (reference) and ``scan_02.laz`` 9.8 m away."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    out = tmp_path_factory.mktemp("plugin_scans")
    write_simulated_plot(
        simulate_plot("planted_conifer", [(0, 0), (9, 4)], seed=1, angular_step_deg=0.3, size_m=40), out
    )
    return out


@pytest.fixture(scope="module")
def pair_run(scans, tmp_path_factory):
    """``adapter.register_pair`` run for real (CLI in a subprocess), with what it reported."""
    out = tmp_path_factory.mktemp("plugin_pair") / "registration"
    seen: dict = {"progress": [], "log": []}
    job = adapter.PairJob(scans / "scan_01.laz", scans / "scan_02.laz", out)
    outputs = adapter.register_pair(
        job, CLI, progress=lambda f, m: seen["progress"].append((f, m)), log=seen["log"].append
    )
    return outputs, out, seen


# ----------------------------------------------------------------------------- command lines


def test_pair_and_plot_command_lines():
    job = adapter.PairJob(
        "ref.laz", "mov.laz", "out", vop_radius_m=15, scanner_positions=[(1, 2, 3), (4.5, 5, 6)], units="cm"
    )
    cmd = adapter.build_pair_command(job, ["forestreg"])
    assert cmd == [
        "forestreg",
        "register",
        "ref.laz",
        "mov.laz",
        "--out",
        "out",
        "--dr",
        "15.0",
        "--scanner-position",
        "1.0,2.0,3.0",
        "--scanner-position",
        "4.5,5.0,6.0",
        "--units",
        "cm",
    ]
    assert cmd[1:] == adapter.build_pair_args(job)  # the job's arguments, without the program
    plot = adapter.build_plot_command(
        adapter.PlotJob(["a.laz", "b.laz", "c.laz"], "o", centre="b.laz", vop_radius_m=20), ["forestreg"]
    )
    assert plot == ["forestreg", "plot", "a.laz", "b.laz", "c.laz", "--out", "o", "--centre", "b.laz", "--dr", "20.0"]
    with pytest.raises(adapter.AdapterError):
        adapter.build_plot_command(adapter.PlotJob([], "o"))


def test_cli_command_resolution(monkeypatch, tmp_path):
    assert adapter.cli_command(["py", "-m", "forestreg.cli"]) == ["py", "-m", "forestreg.cli"]
    assert adapter.cli_command("python3 -m forestreg.cli") == ["python3", "-m", "forestreg.cli"]
    spaced = tmp_path / "my tools" / "forestreg"
    spaced.parent.mkdir()
    spaced.write_text("")
    assert adapter.cli_command(str(spaced)) == [str(spaced)]  # an existing path is one word
    monkeypatch.setenv(adapter.CLI_ENV, "/opt/fr/bin/forestreg --verbose")
    assert adapter.cli_command() == ["/opt/fr/bin/forestreg", "--verbose"]
    monkeypatch.delenv(adapter.CLI_ENV)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert adapter.cli_command()[1:] == ["-m", "forestreg.cli"]


def test_refused_arguments_are_a_bad_input_error(tmp_path):
    with pytest.raises(adapter.BadInputError, match="--units: invalid choice") as info:
        adapter.run_job(["register", "a.laz", "b.laz", "--out", str(tmp_path), "--units", "parsec"], cli=CLI)
    assert info.value.returncode == 2


def test_adapter_shows_job_events_and_cancels(scans, tmp_path, service_state):
    from forestreg.client import connect

    seen = []
    with pytest.raises(adapter.CancelledError):
        adapter.run_job(
            ["register", str(scans / "scan_01.laz"), str(scans / "scan_02.laz"), "--out", str(tmp_path / "c")],
            progress=lambda f, m: seen.append((f, m)),
            cancelled=lambda: bool(seen),
            cli=CLI,
        )
    assert seen and 0.0 <= seen[0][0] < 1.0
    job = connect(start=False).jobs()[0]  # the newest job of the service the adapter started
    assert job["status"] == "cancelled" and job["args"][0] == "register"
    assert not (tmp_path / "c" / "transform.txt").exists()


def test_bad_input_through_the_real_cli(tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_text("not a las file")
    with pytest.raises(adapter.BadInputError, match="bad.laz"):
        adapter.register_pair(adapter.PairJob(bad, bad, tmp_path / "out"), CLI)


def test_a_missing_output_file_is_named(tmp_path):
    with pytest.raises(adapter.AdapterError, match="result.json is missing"):
        adapter.read_pair_outputs(tmp_path)
    with pytest.raises(adapter.AdapterError, match="poses.json is missing"):
        adapter.read_plot_outputs(tmp_path)
    (tmp_path / "result.json").write_text(
        json.dumps({"status": "ok", "matrix": np.eye(4).tolist(), "reference": "a", "moving": "b"})
    )
    with pytest.raises(adapter.AdapterError, match="reference_vops.csv is missing"):
        adapter.read_pair_outputs(tmp_path)


def test_a_failed_pair_leaves_the_moving_scan_unregistered(tmp_path):
    (tmp_path / "result.json").write_text(
        json.dumps(
            {
                "status": "failed",
                "reason": "fewer than 4 VOPs in the moving scan",
                "matrix": None,
                "reference": "a",
                "moving": "b",
            }
        )
    )
    out = adapter.read_pair_outputs(tmp_path)
    assert out.status == "failed" and out.matrix is None and out.vops == []
    assert out.reason.startswith("fewer than 4 VOPs")
    assert [s["registered"] for s in out.scanners] == [True, False]


# ----------------------------------------------------------------------------- a real pair


def test_real_pair_records_match_result_json(pair_run):
    outputs, out, seen = pair_run
    result = json.loads((out / "result.json").read_text())
    assert outputs.status == result["status"] == "ok"
    matrix = np.array(result["matrix"])
    np.testing.assert_allclose(np.array(outputs.matrix), matrix)
    np.testing.assert_allclose(adapter.read_transform_txt(out / "transform.txt"), matrix, atol=1e-9)

    # progress came from the job's events, in order, up to the end
    fractions = [f for f, _ in seen["progress"]]
    assert len(fractions) >= 5 and fractions == sorted(fractions) and fractions[-1] >= 0.9
    assert any("occlusion" in m for _, m in seen["progress"])
    assert any(line.startswith("ok: ") for line in seen["log"])  # the command's output lines reach the log

    # scanner positions in the reference frame
    ref, mov = outputs.scanners
    assert (ref["name"], ref["role"], ref["x"], ref["y"], ref["z"]) == (result["reference"], "reference", 0.0, 0.0, 0.0)
    assert mov["name"] == result["moving"] and mov["registered"]
    np.testing.assert_allclose([mov["x"], mov["y"], mov["z"]], matrix[:3, 3])
    assert abs(np.hypot(mov["x"], mov["y"]) - np.hypot(9, 4)) < 0.1  # the simulated scanners stand 9.85 m apart

    # one record per VOP row, with the matched flags of the CSVs and of result.json
    ref_rows, mov_rows = _csv_rows(out / "reference_vops.csv"), _csv_rows(out / "moving_vops.csv")
    assert len(ref_rows) == result["reference_vops"] and len(mov_rows) == result["moving_vops"]
    assert len(outputs.vops) == len(ref_rows) + len(mov_rows)
    by_scan = {name: [v for v in outputs.vops if v["scan"] == name] for name in (ref["name"], mov["name"])}
    for name, rows in ((ref["name"], ref_rows), (mov["name"], mov_rows)):
        recs = by_scan[name]
        assert [r["id"] for r in recs] == [int(row["id"]) for row in rows]
        assert [r["matched"] for r in recs] == [bool(row["matched_with"]) for row in rows]
        assert sum(r["matched"] for r in recs) == result["matched"]
        np.testing.assert_allclose(
            [[r["x_file"], r["y_file"], r["z_file"]] for r in recs], [[float(row[k]) for k in "xyz"] for row in rows]
        )
    # reference VOPs stay put, moving VOPs are mapped by the matrix and meet their partners
    refs = {r["id"]: r for r in by_scan[ref["name"]]}
    for r in by_scan[ref["name"]]:
        assert (r["x"], r["y"], r["z"]) == (r["x_file"], r["y_file"], r["z_file"])
    gaps = []
    for m in by_scan[mov["name"]]:
        np.testing.assert_allclose(
            [m["x"], m["y"], m["z"]],
            matrix[:3, :3] @ [m["x_file"], m["y_file"], m["z_file"]] + matrix[:3, 3],
            atol=1e-9,
        )
        if m["matched"]:
            partner = refs[m["matched_with"]]
            assert partner["matched_with"] == m["id"]
            gaps.append(np.hypot(m["x"] - partner["x"], m["y"] - partner["y"]))
    assert np.median(gaps) < 0.1 and max(gaps) < 0.5


def test_real_pair_layer_files(pair_run):
    outputs, out, _ = pair_run
    scanners = _csv_rows(out / "layer_scanners.csv")
    vops = _csv_rows(out / "layer_vops.csv")
    assert [s["name"] for s in scanners] == [s["name"] for s in outputs.scanners]
    assert len(vops) == len(outputs.vops)
    assert sum(int(v["matched"]) for v in vops) == 2 * outputs.matched
    uri = adapter.delimited_text_uri(out / "layer_vops.csv", "EPSG:25832")
    assert uri.startswith("file:///") and "xField=x" in uri and "yField=y" in uri and uri.endswith("crs=EPSG:25832")


def test_real_plot_poses(scans, pair_run, tmp_path):
    pair_outputs, _, _ = pair_run
    seen = []
    job = adapter.PlotJob([scans / "scan_01.laz", scans / "scan_02.laz"], tmp_path / "plot")
    outputs = adapter.register_plot(job, CLI, progress=lambda f, m: seen.append(f))
    poses = json.loads((tmp_path / "plot" / "poses.json").read_text())
    assert outputs.status == "ok" and outputs.frame == poses["frame"] == "scan_01.laz"
    assert [s["name"] for s in outputs.scanners] == list(poses["scans"])
    centre, other = outputs.scanners
    assert centre["role"] == "centre" and (centre["x"], centre["y"], centre["z"]) == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(
        [other["x"], other["y"], other["z"]], np.array(poses["scans"]["scan_02.laz"]["matrix"])[:3, 3]
    )
    # the same registration as the pair run
    np.testing.assert_allclose(
        [other["x"], other["y"], other["z"]], [pair_outputs.scanners[1][k] for k in "xyz"], atol=0.01
    )
    assert seen and max(seen) >= 0.9
    assert len(_csv_rows(tmp_path / "plot" / "layer_scanners.csv")) == 2


# ----------------------------------------------------------------------------- CloudCompare


def test_cloudcompare_module_imports_without_pycc():
    code = "import sys, forestreg.plugin.cloudcompare as m; print(m.ACTION_NAME); sys.exit(1 if 'pycc' in sys.modules else 0)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_cloudcompare_plugin_class_is_built_lazily(monkeypatch):
    import forestreg.plugin.cloudcompare as ccplugin

    fake = types.ModuleType("pycc")

    class PythonPluginInterface:
        def __init__(self):
            pass

    class Action:
        def __init__(self, name, target, icon=None):
            self.name, self.target = name, target

    fake.PythonPluginInterface, fake.Action = PythonPluginInterface, Action
    monkeypatch.setitem(sys.modules, "pycc", fake)
    monkeypatch.setattr(ccplugin, "_plugin_class", None)
    cls = ccplugin.ForestregCC  # what the runtime's entry_point.load() resolves
    assert issubclass(cls, PythonPluginInterface)
    from importlib.metadata import EntryPoint

    assert EntryPoint("forestreg", "forestreg.plugin.cloudcompare:ForestregCC", "cloudcompare.plugins").load() is cls
    action, trees_action = cls().getActions()
    assert action.name == ccplugin.ACTION_NAME and action.target is ccplugin.register_selected
    from forestreg.plugin.cloudcompare import trees as cctrees

    assert trees_action.name == cctrees.LOAD_TREES_ACTION_NAME and trees_action.target is cctrees.load_trees_folder
    with pytest.raises(AttributeError):
        ccplugin.NoSuchThing


def test_pyproject_declares_the_cloudcompare_entry_point():
    try:
        import tomllib
    except ImportError:  # Python < 3.11
        import tomli as tomllib
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert meta["project"]["entry-points"]["cloudcompare.plugins"] == {
        "forestreg": "forestreg.plugin.cloudcompare:ForestregCC"
    }


def test_cloudcompare_entry_point_if_installed():
    from importlib.metadata import entry_points

    eps = [ep for ep in entry_points(group="cloudcompare.plugins") if ep.value.startswith("forestreg.")]
    if not eps:
        pytest.skip(
            "no forestreg entry point in group 'cloudcompare.plugins' in this environment (pyproject.toml declares it; reinstall the package to register it)"
        )
    assert eps[0].value == "forestreg.plugin.cloudcompare:ForestregCC"


def test_cloudcompare_ply_and_shifted_matrix(tmp_path):
    import forestreg
    from forestreg.plugin.cloudcompare import local_matrix, write_ply

    pts = np.random.default_rng(0).uniform(-20, 20, (500, 3)) + [600000.0, 5300000.0, 400.0]
    scan = forestreg.read_scan(write_ply(tmp_path / "c.ply", pts))
    np.testing.assert_allclose(scan.file_points, pts, atol=1e-6)

    a = np.radians(33.0)
    m = np.array([[np.cos(a), -np.sin(a), 0, 4.0], [np.sin(a), np.cos(a), 0, -2.0], [0, 0, 1, 0.3], [0, 0, 0, 1]])
    s_ref, s_mov = np.array([-600000.0, -5300000.0, 0.0]), np.array([-1000.0, 20.0, -5.0])
    glob = pts[:5]
    local = local_matrix(m.tolist(), s_ref, s_mov)
    got = (glob + s_mov) @ np.array(local)[:3, :3].T + np.array(local)[:3, 3]  # moving local -> reference local
    np.testing.assert_allclose(got, glob @ m[:3, :3].T + m[:3, 3] + s_ref, atol=1e-6)


def _cloudcompare_binary():
    for name in ("CloudCompare", "cloudcompare"):
        found = shutil.which(name)
        if found:
            return found
    return None


def test_transform_txt_is_accepted_by_cloudcompare_apply_trans(pair_run, tmp_path):
    binary = _cloudcompare_binary()
    if binary is None:
        pytest.skip("the CloudCompare binary is not installed (Debian: apt-get install cloudcompare)")
    runner = [] if os.environ.get("DISPLAY") else ["xvfb-run", "-a"]
    if runner and shutil.which("xvfb-run") is None:
        pytest.skip("CloudCompare needs a display: no DISPLAY and no xvfb-run")
    _, out, _ = pair_run
    transform = out / "transform.txt"  # written by `forestreg register`
    matrix = np.array(adapter.read_transform_txt(transform))
    pts = np.random.default_rng(1).uniform(-25, 25, (200, 3))
    cloud = tmp_path / "cloud.xyz"
    np.savetxt(cloud, pts, fmt="%.6f")
    saved = tmp_path / "moved.xyz"
    cmd = runner + [
        binary,
        "-SILENT",
        "-AUTO_SAVE",
        "OFF",
        "-O",
        str(cloud),
        "-APPLY_TRANS",
        str(transform),
        "-C_EXPORT_FMT",
        "ASC",
        "-PREC",
        "9",
        "-SAVE_CLOUDS",
        "FILE",
        str(saved),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert run.returncode == 0 and saved.is_file(), run.stdout[-2000:] + run.stderr[-2000:]
    moved = np.loadtxt(saved, ndmin=2)[:, :3]
    np.testing.assert_allclose(moved, pts @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-4)  # CloudCompare stores float32


# ----------------------------------------------------------------------------- QGIS


def _python_with_qgis():
    """An interpreter where ``qgis.core`` imports: this one, else Debian's /usr/bin/python3."""
    for exe in dict.fromkeys([sys.executable, "/usr/bin/python3"]):
        if Path(exe).exists():
            ok = subprocess.run(
                [exe, "-c", "import qgis.core"], capture_output=True, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"}
            )
            if ok.returncode == 0:
                return exe
    return None


def _qgis_or_skip() -> str:
    """:func:`_python_with_qgis`, or skip the test."""
    exe = _python_with_qgis()
    if exe is None:
        pytest.skip("qgis.core does not import here (Debian: apt-get install python3-qgis, for /usr/bin/python3)")
    return exe


def _repository_as_plugin(tmp_path: Path) -> Path:
    """A plugins folder in which QGIS's Python sees the repository as the package ``forestreg``,
    as from its plugins folder."""
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    (plugins / "forestreg").symlink_to(ROOT, target_is_directory=True)
    return plugins


def _qgis_report(exe: str, script: str, plugins: Path, tmp_path: Path, *args: str, timeout: float = 300) -> dict:
    """Run ``script`` in QGIS's Python with ``plugins`` on its path; the JSON it printed after
    ``REPORT`` (the run must succeed)."""
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": str(plugins), "HOME": str(tmp_path)}
    run = subprocess.run(
        [exe, "-c", script, *args], capture_output=True, text=True, timeout=timeout, env=env, cwd=tmp_path
    )
    lines = [l for l in run.stdout.splitlines() if l.startswith("REPORT")]
    assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
    return json.loads(lines[-1][len("REPORT") :])


QGIS_SCRIPT = r"""
import json, sys
sys.path.insert(0, "/usr/share/qgis/python/plugins")
from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingFeedback, QgsProject
app = QgsApplication([], False)
app.initQgis()
report = {}
import forestreg
report["loaded_by_import_forestreg"] = [m for m in sys.modules if m.startswith(("PySide6", "forestreg.plugin.qgis.", "forestreg.engine"))]
from forestreg.plugin.qgis.provider import ForestregProvider
registry = QgsApplication.processingRegistry()
provider = ForestregProvider()
registry.addProvider(provider)
report["algorithms"] = {a.id(): a.displayName() for a in provider.algorithms()}
plot = registry.algorithmById("forestreg:register_plot")
report["plot_parameters"] = [p.name() for p in plot.parameterDefinitions()]
alg = registry.createAlgorithmById("forestreg:register_pair")
report["pair_parameters"] = [p.name() for p in alg.parameterDefinitions()]

class Feedback(QgsProcessingFeedback):
    texts = []
    def setProgressText(self, text):
        self.texts.append(text)

context = QgsProcessingContext()
context.setProject(QgsProject.instance())
feedback = Feedback()
params = json.loads(sys.argv[1])
results, ok = alg.run(params, context, feedback)
report["ok"] = ok
report["results"] = {k: v for k, v in results.items()}
report["progress"] = feedback.progress()
report["progress_texts"] = feedback.texts
layers = {}
for key in ("SCANNERS", "VOPS"):
    layer = context.temporaryLayerStore().mapLayer(results[key])
    layers[key] = {"valid": layer.isValid(), "count": layer.featureCount(), "fields": [f.name() for f in layer.fields()],
                   "points": [[f.geometry().constGet().x(), f.geometry().constGet().y(), f.geometry().constGet().z()] for f in layer.getFeatures()]}
report["layers"] = layers
report["to_load"] = sorted(context.layersToLoadOnCompletion().keys())
registry.removeProvider(provider)

menu = []
class Iface:
    def mainWindow(self): return None
    def addPluginToMenu(self, name, action): menu.append([name, action.text()])
    def removePluginMenu(self, name, action): menu.append(["removed", name])
plugin = forestreg.classFactory(Iface())
plugin.initGui()
report["provider_registered"] = registry.providerById("forestreg") is not None
plugin.unload()
report["provider_after_unload"] = registry.providerById("forestreg") is not None
report["menu"] = menu
report["pyside6"] = [m for m in sys.modules if m.startswith("PySide6")]
print("REPORT" + json.dumps(report))
app.exitQgis()
"""


def test_qgis_provider_headless(pair_run, scans, tmp_path):
    exe = _qgis_or_skip()
    params = {
        "REFERENCE": str(scans / "scan_01.laz"),
        "MOVING": str(scans / "scan_02.laz"),
        "OUTPUT": str(tmp_path / "out"),
        "CLI": shlex.join(CLI),
    }
    report = _qgis_report(exe, QGIS_SCRIPT, _repository_as_plugin(tmp_path), tmp_path, json.dumps(params), timeout=600)
    assert report["loaded_by_import_forestreg"] == [] and report["pyside6"] == []
    assert report["algorithms"] == {
        "forestreg:register_pair": "Register TLS pair (trunk shadows)",
        "forestreg:register_plot": "Register plot",
        "forestreg:coregister": "Co-register ground onto UAV (canopy keypoints)",
        "forestreg:fuse": "Fuse ground and UAV clouds",
        "forestreg:trees": "Measure trees",
        "forestreg:evaluate": "Evaluate trees against field records",
        "forestreg:change": "Re-survey change (persisting, removed, new trees)",
    }
    assert {"SCANS", "OUTPUT", "MERGED", "DR"} <= set(report["plot_parameters"])
    assert {"REFERENCE", "MOVING", "OUTPUT", "DR"} <= set(report["pair_parameters"])
    assert {"SCANS", "OUTPUT", "DR"} <= set(report["plot_parameters"])
    assert report["ok"] is True and report["results"]["STATUS"] == "ok"

    # same registration as the adapter's own run, loaded as point layers
    pair_outputs, _, _ = pair_run
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert report["results"]["MATCHED"] == result["matched"]
    assert report["progress"] == 100 and any("occlusion" in t for t in report["progress_texts"])
    scanners, vops = report["layers"]["SCANNERS"], report["layers"]["VOPS"]
    assert scanners["valid"] and scanners["count"] == 2
    np.testing.assert_allclose(scanners["points"][1], np.array(result["matrix"])[:3, 3], atol=1e-6)
    np.testing.assert_allclose(scanners["points"][1], [pair_outputs.scanners[1][k] for k in "xyz"], atol=0.01)
    assert vops["valid"] and vops["count"] == result["reference_vops"] + result["moving_vops"]
    assert {"scan", "id", "matched", "matched_with", "radius_m"} <= set(vops["fields"])
    assert sorted(report["to_load"]) == sorted([report["results"]["SCANNERS"], report["results"]["VOPS"]])

    assert report["menu"] == [["&forestreg", "forestreg: register scans…"], ["removed", "&forestreg"]]
    assert report["provider_registered"] and not report["provider_after_unload"]


# ----------------------------------------------------------------------------- a missing engine


def test_engine_problem_names_the_missing_modules_and_how_to_install(monkeypatch, tmp_path):
    command = [sys.executable, "-m", "forestreg.cli"]
    assert adapter.engine_problem(command) is None  # this Python has the engine
    monkeypatch.setattr(adapter, "ENGINE_MODULES", adapter.ENGINE_MODULES + ("forestreg_no_such_module",))
    problem = adapter.engine_problem(command)
    assert problem is not None and "lacks forestreg_no_such_module" in problem
    assert "pip install" in problem and "forestreg-env" in problem and adapter.CLI_ENV in problem
    script = tmp_path / "forestreg"  # a forestreg command of its own environment: trusted
    script.write_text("#!/bin/sh\n")
    assert adapter.engine_problem(str(script)) is None
    # no service runs for this state folder: the job stops with the same message before any start
    with pytest.raises(adapter.AdapterError, match="forestreg_no_such_module"):
        adapter.service_client(command, state_dir=tmp_path / "state")
    assert not (tmp_path / "state" / "server.json").exists()


QGIS_MISSING_SCRIPT = r"""
import json, os, sys
from qgis.core import QgsApplication
app = QgsApplication([], False)
app.initQgis()
import forestreg
from forestreg.plugin import adapter
adapter.ENGINE_MODULES = adapter.ENGINE_MODULES + ("forestreg_no_such_module",)
messages = []
class Bar:
    def pushMessage(self, title, text, level, duration): messages.append([title, text])
class Iface:
    def mainWindow(self): return None
    def messageBar(self): return Bar()
    def addPluginToMenu(self, name, action): pass
    def removePluginMenu(self, name, action): pass
report = {}
os.environ["FORESTREG_CLI"] = sys.executable + " -m forestreg.cli"
plugin = forestreg.classFactory(Iface()); plugin.initGui(); plugin.unload()
report["missing"] = messages[:]
del messages[:]
os.environ["FORESTREG_CLI"] = sys.argv[1]
plugin = forestreg.classFactory(Iface()); plugin.initGui(); plugin.unload()
report["installed"] = messages[:]
print("REPORT" + json.dumps(report))
app.exitQgis()
"""


def test_qgis_plugin_says_when_the_engine_is_missing(tmp_path):
    exe = _qgis_or_skip()
    plugins = _repository_as_plugin(tmp_path)
    command = tmp_path / "forestreg"
    command.write_text("#!/bin/sh\n")
    report = _qgis_report(exe, QGIS_MISSING_SCRIPT, plugins, tmp_path, str(command))
    assert len(report["missing"]) == 1 and report["missing"][0][0] == "forestreg"
    assert "forestreg_no_such_module" in report["missing"][0][1] and "pip install" in report["missing"][0][1]
    assert report["installed"] == []


QGIS_ZIP_SCRIPT = r"""
import json, sys
from qgis.core import QgsApplication
app = QgsApplication([], False)
app.initQgis()
import forestreg
class Iface:
    def mainWindow(self): return None
    def messageBar(self): return None
    def addPluginToMenu(self, name, action): pass
    def removePluginMenu(self, name, action): pass
plugin = forestreg.classFactory(Iface())
plugin.initProcessing()
provider = QgsApplication.processingRegistry().providerById("forestreg")
print("REPORT" + json.dumps({"file": forestreg.__file__, "version": forestreg.__version__,
                             "algorithms": sorted(a.id() for a in provider.algorithms())}))
plugin.unload()
app.exitQgis()
"""


def test_qgis_loads_the_packaged_zip(tmp_path):
    """The zip of scripts/package_qgis.py, unpacked into a plugins folder as QGIS's plugin
    manager does, loads in QGIS with its Processing provider."""
    import zipfile

    exe = _qgis_or_skip()
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "package_qgis.py"), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    plugins = tmp_path / "plugins"
    zipfile.ZipFile(next(tmp_path.glob("forestreg-qgis-*.zip"))).extractall(plugins)
    report = _qgis_report(exe, QGIS_ZIP_SCRIPT, plugins, tmp_path)
    assert Path(report["file"]).resolve().is_relative_to(plugins.resolve())
    assert report["algorithms"] == sorted(
        f"forestreg:{n}"
        for n in ("register_pair", "register_plot", "coregister", "fuse", "trees", "evaluate", "change")
    )
