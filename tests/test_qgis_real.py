"""The QGIS plugin in real, headless QGIS: ``qgis_process`` runs each of the seven algorithms and
the model ``plugin/models/plot_trees_change.model3`` through the forestreg job service, and QGIS's
own Python (Debian's ``/usr/bin/python3``, which has ``qgis`` but not forestreg's dependencies)
opens the layers of ``layers.gpkg`` as the plugin loads them: valid, in the input's CRS, drawn
with the QML style of the GeoPackage's ``layer_styles``.

Skipped, with the reason, where QGIS (``qgis_process`` and ``python3-qgis``) is not installed.
The plugin folder is the repository under the name ``forestreg`` in a plugins folder given by
``QGIS_PLUGINPATH``, enabled in a QGIS profile of the test's own (``XDG_DATA_HOME``)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from forestreg.plugin import adapter

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "plugin" / "models" / "plot_trees_change.model3"
QGIS_PYTHON = "/usr/bin/python3"
#: the CRS the spanner clips are in (they declare none; NAD83 / UTM zone 12N, Arizona)
SPANNER_CRS = "EPSG:26912"
IDS = ["register_pair", "register_plot", "coregister", "fuse", "trees", "evaluate", "change"]


def qgis_process_command() -> list[str] | None:
    """The ``qgis_process`` to run, or None. Debian's ``/usr/bin/qgis_process`` is a shell wrapper
    that adds ``--noversioncheck`` (an option of the desktop application that ``qgis_process``
    3.22 refuses: "Command --noversioncheck not known!"), so the binary beside it,
    ``qgis_process.bin``, is run where it exists."""
    exe = shutil.which("qgis_process")
    if exe is None:
        return None
    binary = Path(exe).with_name("qgis_process.bin")
    return [str(binary)] if binary.is_file() else [exe]


def _qgis_python_works(env: dict) -> bool:
    if not Path(QGIS_PYTHON).exists():
        return False
    run = subprocess.run([QGIS_PYTHON, "-c", "import qgis.core"], capture_output=True, env=env, timeout=120)
    return run.returncode == 0


class Qgis:
    """One headless QGIS set-up: ``qgis_process`` with the plugin enabled in a profile of its own,
    the forestreg service of the tests (``FORESTREG_SERVICE_DIR``), QGIS's Python."""

    def __init__(self, command: list[str], folder: Path) -> None:
        self.command, self.folder = command, folder
        self.plugins = folder / "plugins"
        self.plugins.mkdir()
        (self.plugins / "forestreg").symlink_to(ROOT, target_is_directory=True)
        from forestreg.engine.core.jit import kernel_cache_dir

        self.service = folder / "service"
        self.env = {
            **os.environ,
            "QT_QPA_PLATFORM": "offscreen",
            "QGIS_PLUGINPATH": str(self.plugins),
            # QGIS's profile, settings and caches in the test's folder; the compiled kernels where they are
            "XDG_DATA_HOME": str(folder / "data"),
            "XDG_CONFIG_HOME": str(folder / "config"),
            "XDG_CACHE_HOME": str(folder / "cache"),
            "XDG_RUNTIME_DIR": str(folder / "runtime"),
            "NUMBA_CACHE_DIR": kernel_cache_dir() or "",
            "FORESTREG_SERVICE_DIR": str(self.service),
            adapter.CLI_ENV: f"{sys.executable} -m forestreg.cli",
        }
        (folder / "runtime").mkdir(mode=0o700)
        if not self.env["NUMBA_CACHE_DIR"]:
            del self.env["NUMBA_CACHE_DIR"]

    def process(self, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*self.command, *args], capture_output=True, text=True, env=self.env, timeout=timeout, cwd=self.folder
        )

    def run(self, algorithm: str, timeout: float = 600, **parameters) -> dict:
        """``qgis_process --json run ALGORITHM -- NAME=VALUE ...`` (a list value: the name repeated);
        its JSON answer (``results``, ``log``), the run having succeeded."""
        values = []
        for name, value in parameters.items():
            for v in value if isinstance(value, (list, tuple)) else [value]:
                values.append(f"{name}={v}")
        run = self.process("--json", "run", algorithm, "--", *values, timeout=timeout)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        return json.loads(run.stdout[run.stdout.index("{") :])

    def python(self, script: str, *args: str, timeout: float = 300) -> dict:
        """``script`` in QGIS's Python with the plugins folder on its path; the JSON it printed
        after ``REPORT``."""
        env = {**self.env, "PYTHONPATH": str(self.plugins)}
        run = subprocess.run(
            [QGIS_PYTHON, "-c", script, *args],
            capture_output=True,
            text=True,
            env=env,
            timeout=timeout,
            cwd=self.folder,
        )
        lines = [line for line in run.stdout.splitlines() if line.startswith("REPORT")]
        assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
        return json.loads(lines[-1][len("REPORT") :])

    def stop_service(self) -> None:
        from forestreg.client import read_server_info

        info = read_server_info(self.service)
        if info:
            try:
                os.kill(info["pid"], 15)
            except ProcessLookupError:
                pass


@pytest.fixture(scope="module")
def qgis(tmp_path_factory):
    command = qgis_process_command()
    if command is None:
        pytest.skip(
            "qgis_process is not installed (QGIS is needed for these runs; Debian: apt-get install qgis python3-qgis)"
        )
    folder = tmp_path_factory.mktemp("qgis")
    q = Qgis(command, folder)
    if not _qgis_python_works(q.env):
        pytest.skip(f"qgis.core does not import in {QGIS_PYTHON} (Debian: apt-get install python3-qgis)")
    enabled = q.process("plugins", "enable", "forestreg", timeout=300)
    assert enabled.returncode == 0, enabled.stdout[-2000:] + enabled.stderr[-2000:]
    yield q
    q.stop_service()


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Two simulated TLS scans of a 24 m conifer plot, 10 m apart, with their truth (``forestreg simulate``)."""
    folder = tmp_path_factory.mktemp("scans") / "scans"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "simulate",
            "planted_conifer",
            "--out",
            str(folder),
            "--positions",
            "0,0;10,0",
            "--step",
            "0.4",
            "--size",
            "24",
            "--seed",
            "1",
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    return folder


@pytest.fixture(scope="module")
def mls(shared_data, tmp_path_factory) -> Path:
    """The real MLS clip (spanner, ~20 stems with ground) with its CRS written into the file."""
    import laspy
    import pyproj

    las = laspy.read(shared_data / "spanner_MLS_Clip.laz")
    las.header.add_crs(pyproj.CRS.from_user_input(SPANNER_CRS))
    path = tmp_path_factory.mktemp("mls") / "mls.laz"
    las.write(path)
    return path


@pytest.fixture(scope="module")
def trees_run(qgis, mls, tmp_path_factory):
    out = tmp_path_factory.mktemp("trees") / "trees"
    answer = qgis.run("forestreg:trees", CLOUD=mls, OUTPUT=out, CYLINDERS="false", REPORT="false")
    return answer, out


def _rows(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


# ----------------------------------------------------------------------------- what QGIS shows

LAYERS_SCRIPT = r"""
import json, sys
from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingFeedback, QgsProject, QgsVectorLayer
app = QgsApplication([], False)
app.initQgis()
from forestreg.plugin.qgis import provider

def rules(layer):
    renderer = layer.renderer()
    if renderer.type() != "RuleRenderer":
        return None
    out = []
    for rule in renderer.rootRule().children():
        symbol_layer = rule.symbol().symbolLayer(0)
        size = symbol_layer.size() if hasattr(symbol_layer, "size") else None
        out.append({"label": rule.label(), "filter": rule.filterExpression(), "class": symbol_layer.layerType(),
                    "colour": list(symbol_layer.color().getRgb()), "size": size})
    return out

class Feedback(QgsProcessingFeedback):
    errors = []
    def reportError(self, text, fatalError=False):
        self.errors.append(text)

report = {}
for folder in sys.argv[1:]:
    context = QgsProcessingContext()
    context.setProject(QgsProject.instance())
    feedback = Feedback()
    ids = provider._load_gpkg_layers(folder, "run", context, "LAYERS", feedback)
    layers = {}
    for name, layer_id in ids.items():
        layer = context.temporaryLayerStore().mapLayer(layer_id)
        # the same layer as a user adds it by hand (Layer > Add Vector Layer): QGIS reads its default style itself
        plain = QgsVectorLayer(layer.source(), name, "ogr")
        extent = plain.extent()
        layers[name] = {"valid": layer.isValid(), "plain_valid": plain.isValid(), "crs": layer.crs().authid(),
                        "plain_crs": plain.crs().authid(), "count": layer.featureCount(), "renderer": layer.renderer().type(),
                        "rules": rules(layer), "plain_rules": rules(plain),
                        "extent": [extent.xMinimum(), extent.yMinimum(), extent.xMaximum(), extent.yMaximum()]}
    report[folder] = {"layers": layers, "errors": feedback.errors,
                      "to_load": sorted(d.name for d in context.layersToLoadOnCompletion().values())}
    del layer, plain
    context.temporaryLayerStore().removeAllMapLayers()  # the layers go before QGIS's providers do
    del context
print("REPORT" + json.dumps(report))
app.exitQgis()
"""


PAIR_SCRIPT = r"""
import json, sys
from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingFeedback, QgsProject
app = QgsApplication([], False)
app.initQgis()
from forestreg.plugin.qgis.provider import ForestregProvider
registry = QgsApplication.processingRegistry()
provider = ForestregProvider()
registry.addProvider(provider)
alg = registry.createAlgorithmById("forestreg:register_pair")
context = QgsProcessingContext()
context.setProject(QgsProject.instance())
results, ok = alg.run(json.loads(sys.argv[1]), context, QgsProcessingFeedback())
report = {"ok": ok, "status": results["STATUS"]}
for key in ("SCANNERS", "VOPS"):
    layer = context.temporaryLayerStore().mapLayer(results[key])
    report[key] = {"valid": layer.isValid(), "crs": layer.crs().authid(), "count": layer.featureCount()}
del layer, alg
context.temporaryLayerStore().removeAllMapLayers()
del context
registry.removeProvider(provider)
print("REPORT" + json.dumps(report))
app.exitQgis()
"""


def _qml_rules(gpkg: Path, layer: str) -> list[dict]:
    """The rules of ``layer``'s QML style in ``gpkg``'s ``layer_styles``: label, filter, symbol
    layer class, colour (r, g, b, a) and marker size."""
    import sqlite3

    con = sqlite3.connect(gpkg)
    try:
        (qml,) = con.execute(
            "SELECT styleQML FROM layer_styles WHERE f_table_name = ? AND useAsDefault", (layer,)
        ).fetchone()
    finally:
        con.close()
    root = ET.fromstring(qml.split("\n", 1)[1])
    symbols = {s.get("name"): s.find("layer") for s in root.iter("symbol")}
    out = []
    for rule in root.iter("rule"):
        layer_el = symbols[rule.get("symbol")]
        props = {p.get("k"): p.get("v") for p in layer_el.iter("prop")}
        colour = props.get("color") or props.get("line_color")
        out.append(
            {
                "label": rule.get("label"),
                "filter": rule.get("filter") or "",
                "class": layer_el.get("class"),
                "colour": [int(v) for v in colour.split(",")],
                "size": float(props["size"]) if "size" in props else None,
            }
        )
    return out


def _assert_styled_as_qml(layers: dict, gpkg: Path) -> None:
    for name, layer in layers.items():
        expected = _qml_rules(gpkg, name)
        got = [{**r, "size": r["size"] if r["class"] == "SimpleMarker" else None} for r in layer["rules"]]
        assert layer["renderer"] == "RuleRenderer" and got == expected, name
        assert layer["plain_rules"] == layer["rules"], f"{name}: QGIS does not read the default style of layer_styles"


def _gpkg_srs(gpkg: Path) -> dict:
    import sqlite3

    con = sqlite3.connect(gpkg)
    try:
        return dict(
            con.execute(
                "SELECT c.table_name, s.organization || ':' || s.organization_coordsys_id FROM gpkg_contents c "
                "JOIN gpkg_spatial_ref_sys s ON s.srs_id = c.srs_id WHERE c.data_type = 'features'"
            ).fetchall()
        )
    finally:
        con.close()


# ----------------------------------------------------------------------------- the provider in qgis_process


def test_qgis_process_lists_the_seven_algorithms(qgis):
    run = qgis.process("list")
    assert run.returncode == 0, run.stderr[-2000:]
    listed = [line.split()[0] for line in run.stdout.splitlines() if line.strip().startswith("forestreg:")]
    assert sorted(listed) == sorted(f"forestreg:{n}" for n in IDS)


def test_register_pair_in_qgis_process(qgis, scans, tmp_path):
    out = tmp_path / "pair"
    answer = qgis.run(
        "forestreg:register_pair", REFERENCE=scans / "scan_01.laz", MOVING=scans / "scan_02.laz", OUTPUT=out
    )
    results = answer["results"]
    result = json.loads((out / "result.json").read_text())
    assert results["STATUS"] == "ok" and results["MATCHED"] == result["matched"] >= 5
    assert Path(results["TRANSFORM"]) == out / "transform.txt"
    # the matrix is the simulator's true relative pose within 5 cm and 0.2 deg
    truth = json.loads((scans / "truth.json").read_text())
    poses = {s["file"]: np.array(s["matrix"]) for s in truth["scans"]}
    true = np.linalg.inv(poses["scan_01.laz"]) @ poses["scan_02.laz"]
    found = np.loadtxt(out / "transform.txt")
    assert np.linalg.norm(found[:3, 3] - true[:3, 3]) < 0.05
    angle = np.degrees(np.arccos(np.clip((np.trace(found[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 0.2
    # the scanners and VOPs load as point layers (delimited text of the output folder)
    assert results["SCANNERS"].startswith("scanners") and results["VOPS"].startswith("VOPs")
    assert len(_rows(out / "layer_vops.csv")) == result["reference_vops"] + result["moving_vops"]
    assert any(line.startswith("job: forestreg register") for line in answer["log"]["info"])


def test_a_pairs_point_layers_take_the_scans_crs_in_qgis(qgis, scans, tmp_path):
    """Scans that declare a CRS: the scanner and VOP layers (delimited text) are in it without the
    CRS parameter."""
    import laspy
    import pyproj

    for name in ("scan_01.laz", "scan_02.laz"):
        las = laspy.read(scans / name)
        las.header.add_crs(pyproj.CRS.from_epsg(32618))
        las.write(tmp_path / name)
    out = tmp_path / "pair"
    report = qgis.python(
        PAIR_SCRIPT,
        json.dumps(
            {"REFERENCE": str(tmp_path / "scan_01.laz"), "MOVING": str(tmp_path / "scan_02.laz"), "OUTPUT": str(out)}
        ),
    )
    assert report["ok"] and report["status"] == "ok"
    assert json.loads((out / "result.json").read_text())["crs"]["epsg"] == "EPSG:32618"
    result = json.loads((out / "result.json").read_text())
    assert report["SCANNERS"] == {"valid": True, "crs": "EPSG:32618", "count": 2}
    assert report["VOPS"] == {
        "valid": True,
        "crs": "EPSG:32618",
        "count": result["reference_vops"] + result["moving_vops"],
    }


def test_register_plot_in_qgis_process(qgis, scans, tmp_path):
    out = tmp_path / "plot"
    results = qgis.run(
        "forestreg:register_plot",
        SCANS=[scans / "scan_01.laz", scans / "scan_02.laz"],
        OUTPUT=out,
        MERGED=out / "merged.laz",
        CRS="EPSG:32618",
    )["results"]
    assert (
        results["STATUS"] == "ok"
        and Path(results["MERGED"]) == out / "merged.laz"
        and (out / "merged.laz").stat().st_size > 100_000
    )
    assert [name.split("__")[0] for name in results["LAYERS"]] == ["scanners", "links", "plot_outline"]
    assert results["SCANNERS"] == results["LAYERS"][0]  # one scanners layer, the styled one
    poses = json.loads((out / "poses.json").read_text())["scans"]
    assert sorted(poses) == ["scan_01.laz", "scan_02.laz"] and all(s["status"] == "ok" for s in poses.values())
    assert set(_gpkg_srs(out / "layers.gpkg").values()) == {"EPSG:32618"}  # the CRS parameter reached the command


def test_trees_in_qgis_process_and_its_layers_in_qgis(qgis, trees_run, mls):
    import laspy

    answer, out = trees_run
    results = answer["results"]
    trees = _rows(out / "trees.csv")
    assert results["STATUS"] == "ok" and Path(results["TREES"]) == out / "trees.csv" and len(trees) >= 15
    assert [name.split("__")[0] for name in results["LAYERS"]] == ["trees", "crowns", "plot_outline"]

    report = qgis.python(LAYERS_SCRIPT, str(out))[str(out)]
    layers = report["layers"]
    assert list(layers) == ["trees", "crowns", "plot_outline"] and report["errors"] == []
    input_crs = laspy.read(mls).header.parse_crs().to_epsg()
    for name, layer in layers.items():
        assert layer["valid"] and layer["plain_valid"], name
        assert layer["crs"] == layer["plain_crs"] == f"EPSG:{input_crs}" == SPANNER_CRS, name
    assert layers["trees"]["count"] == layers["crowns"]["count"] == len(trees) and layers["plot_outline"]["count"] == 1
    # the trees lie inside the input cloud's extent, in its coordinates
    header = laspy.read(mls).header
    x0, y0, x1, y1 = layers["trees"]["extent"]
    assert (
        header.mins[0] - 0.01 <= x0 <= x1 <= header.maxs[0] + 0.01
        and header.mins[1] - 0.01 <= y0 <= y1 <= header.maxs[1] + 0.01
    )
    # graduated by DBH (one rule per DBH class), flagged trees ringed on top, as the QML says
    labels = [r["label"] for r in layers["trees"]["rules"]]
    assert sum('"dbh_m"' in r["filter"] for r in layers["trees"]["rules"]) >= 5 and labels[-1].startswith("flagged")
    _assert_styled_as_qml(layers, out / "layers.gpkg")
    assert report["to_load"] == ["crowns (run)", "plot_outline (run)", "trees (run)"]


def test_evaluate_in_qgis_process(qgis, trees_run, tmp_path):
    _, trees_out = trees_run
    trees = [r for r in _rows(trees_out / "trees.csv") if r["dbh_m"] and r["height_m"]]
    field = tmp_path / "field.csv"
    with open(field, "w", newline="", encoding="utf-8") as fh:  # the field crew: DBH 1 cm off, heights 0.5 m off
        w = csv.writer(fh)
        w.writerow(["tree_id", "x", "y", "dbh_cm", "height_m"])
        for i, r in enumerate(trees):
            w.writerow(
                [
                    r["tree_id"],
                    float(r["x"]) + 0.1,
                    float(r["y"]) - 0.1,
                    round(float(r["dbh_m"]) * 100 + (1 if i % 2 else -1), 2),
                    round(float(r["height_m"]) + (0.5 if i % 2 else -0.5), 3),
                ]
            )
    out = tmp_path / "evaluation"
    results = qgis.run("forestreg:evaluate", TREES=trees_out / "trees.csv", FIELD=field, OUTPUT=out)["results"]
    assert results["STATUS"] == "ok" and Path(results["EVALUATION"]) == out / "evaluation.json"
    (run,) = json.loads((out / "evaluation.json").read_text())["runs"].values()
    assert run["detection"]["matched"] == len(trees)
    assert run["parameters"]["dbh_m"]["rmse"] == pytest.approx(0.01, abs=0.0005)
    assert run["parameters"]["height_m"]["rmse"] == pytest.approx(0.5, abs=0.005)


def test_change_in_qgis_process_and_its_layers_in_qgis(qgis, trees_run, tmp_path):
    _, trees_out = trees_run
    later = _rows(trees_out / "trees.csv")
    before = tmp_path / "before.csv"
    with open(
        before, "w", newline="", encoding="utf-8"
    ) as fh:  # the same trees 2 cm thinner and 0.8 m lower, and one cut since
        w = csv.DictWriter(fh, fieldnames=list(later[0]))
        w.writeheader()
        for r in later:
            w.writerow(
                {
                    **r,
                    "dbh_m": f"{float(r['dbh_m']) - 0.02:.4f}" if r["dbh_m"] else "",
                    "height_m": f"{float(r['height_m']) - 0.8:.4f}" if r["height_m"] else "",
                }
            )
        w.writerow(
            {
                **later[0],
                "tree_id": "999",
                "x": f"{float(later[0]['x']) + 6:.4f}",
                "y": f"{float(later[0]['y']) + 6:.4f}",
            }
        )
    out = tmp_path / "change"
    results = qgis.run(
        "forestreg:change", BEFORE=before, AFTER=trees_out / "trees.csv", OUTPUT=out, REPORT="false", CRS=SPANNER_CRS
    )["results"]
    assert results["STATUS"] == "ok" and Path(results["CHANGES"]) == out / "tree_changes.csv"
    changes = _rows(out / "tree_changes.csv")
    persisting = [r for r in changes if r["status"] == "persisting"]
    assert [r["tree_id_before"] for r in changes if r["status"] == "removed"] == ["999"]
    assert len(persisting) >= len(later) - 2
    grown = [
        float(r["dbh_after_m"]) - float(r["dbh_before_m"]) for r in persisting if r["dbh_after_m"] and r["dbh_before_m"]
    ]
    assert grown and np.allclose(grown, 0.02, atol=1e-4)
    assert np.median([float(r["height_change_m"]) for r in persisting if r["height_change_m"]]) == pytest.approx(
        0.8, abs=0.01
    )

    report = qgis.python(LAYERS_SCRIPT, str(out))[str(out)]
    layers = report["layers"]
    assert list(layers) == ["tree_changes", "plot_outline"]
    assert all(layer["valid"] and layer["crs"] == SPANNER_CRS for layer in layers.values())
    assert layers["tree_changes"]["count"] == len(changes)
    assert [r["label"] for r in layers["tree_changes"]["rules"]][:3] == ["persisting", "removed", "new"]
    _assert_styled_as_qml(layers, out / "layers.gpkg")


def test_fuse_in_qgis_process(qgis, shared_data, tmp_path):
    import laspy

    out = tmp_path / "fused.laz"
    ground, uav = shared_data / "spanner_MLS_Clip.laz", shared_data / "spanner_ALS_Clip.laz"
    answer = qgis.run("forestreg:fuse", GROUND=ground, UAV=uav, OUTPUT=out, CRS=SPANNER_CRS)
    results = answer["results"]
    assert results["STATUS"] == "ok" and Path(results["OUTPUT"]) == out
    fused = laspy.read(out)
    n_in = laspy.read(ground).header.point_count + laspy.read(uav).header.point_count
    assert 0.5 * n_in < fused.header.point_count <= n_in  # redundant points and noise removed
    assert fused.header.parse_crs().to_epsg() == 26912
    # a QGIS built without PDAL (Debian 12's 3.22) says so and leaves the cloud in the output folder, no error
    if results["POINT_CLOUD"] is None:
        assert any("PDAL" in line or "point cloud" in line for line in answer["log"]["info"])


@pytest.mark.slow
def test_coregister_in_qgis_process(qgis, shared_data, tmp_path):
    out = tmp_path / "co"
    results = qgis.run(
        "forestreg:coregister",
        GROUND=shared_data / "spanner_MLS_Clip.laz",
        UAV=shared_data / "spanner_ALS_Clip.laz",
        OUTPUT=out,
        CRS=SPANNER_CRS,
        timeout=900,
    )["results"]
    assert results["STATUS"] == "ok" and Path(results["TRANSFORM"]) == out / "transform.txt"
    import laspy

    matrix = np.loadtxt(out / "transform.txt")
    # the clips share one frame; the MLS is tilted about 1.5 deg against the airborne clip: a small
    # rotation that leaves the plot's centre within a metre
    angle = np.degrees(np.arccos(np.clip((np.trace(matrix[:3, :3]) - 1) / 2, -1, 1)))
    header = laspy.read(shared_data / "spanner_MLS_Clip.laz").header
    centre = (np.asarray(header.mins) + np.asarray(header.maxs)) / 2
    assert angle < 3.0 and np.linalg.norm(matrix[:3, :3] @ centre + matrix[:3, 3] - centre) < 1.0
    names = [name.split("__")[0] for name in results["LAYERS"]]
    assert names and len(names) == len(set(names))
    assert set(_gpkg_srs(out / "layers.gpkg").values()) == {SPANNER_CRS}


@pytest.mark.slow
def test_the_model_runs_headless(qgis, scans, tmp_path):
    """register plot -> trees (of the merged cloud) -> change (the earlier survey: the plot's true
    trees 1 cm thinner)."""
    truth = json.loads((scans / "truth.json").read_text())
    earlier = tmp_path / "earlier.csv"
    with open(earlier, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["tree_id", "x", "y", "z", "dbh_m", "height_m"])
        for t in truth["trees"]:
            w.writerow(
                [
                    t["id"],
                    round(t["x"], 3),
                    round(t["y"], 3),
                    round(t["z"], 3),
                    round(t["dbh_m"] - 0.01, 4),
                    round(t["height_m"], 2),
                ]
            )
    folders = {"plot": tmp_path / "plot", "trees": tmp_path / "trees", "change": tmp_path / "change"}
    answer = qgis.run(
        str(MODEL),
        timeout=1200,
        scans=[scans / "scan_01.laz", scans / "scan_02.laz"],
        earlier_survey=earlier,
        **{
            "forestreg:register_plot_1:Plot folder": folders["plot"],
            "forestreg:register_plot_1:Merged cloud": folders["plot"] / "merged.laz",
            "forestreg:trees_1:Trees folder": folders["trees"],
            "forestreg:change_1:Change folder": folders["change"],
        },
    )
    assert Path(answer["results"]["forestreg:change_1:Change folder"]) == folders["change"]
    assert (folders["plot"] / "merged.laz").is_file() and (folders["trees"] / "layers.gpkg").is_file()
    result = json.loads((folders["change"] / "result.json").read_text())
    assert result["status"] == "ok"
    changes = _rows(folders["change"] / "tree_changes.csv")
    persisting = [r for r in changes if r["status"] == "persisting"]
    assert len(persisting) >= 0.7 * len(truth["trees"])
    grown = [
        float(r["dbh_after_m"]) - float(r["dbh_before_m"]) for r in persisting if r["dbh_after_m"] and r["dbh_before_m"]
    ]
    assert len(grown) >= 10 and np.median(grown) == pytest.approx(
        0.01, abs=0.005
    )  # the merged cloud's DBH: the truth's within mm
