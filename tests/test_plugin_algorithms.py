"""The seven Processing algorithms of the QGIS provider, headless against a stand-in for
``qgis.core`` (:mod:`qgis_fakes`): what each declares (ids, parameters with the CLI's defaults,
outputs that chain), the job request each builds (checked against the CLI's own parser), how the
job's progress, log lines and cancel reach the Processing feedback, what loads on completion
(``layers.gpkg`` styled, point clouds where QGIS has them) and the model file. The same
algorithms in real QGIS (``qgis_process``, PyQGIS): :mod:`test_qgis_real`."""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import qgis_fakes  # noqa: E402

from forestreg.plugin import adapter  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "plugin" / "models" / "plot_trees_change.model3"

IDS = ["register_pair", "register_plot", "coregister", "fuse", "trees", "evaluate", "change"]


@pytest.fixture
def provider():
    with qgis_fakes.installed() as module:
        yield module


def _algorithm(provider, name):
    p = provider.ForestregProvider()
    p.loadAlgorithms()
    return next(a for a in p.algorithms() if a.name() == name)


def _cli_parser(command):
    from forestreg.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return parser, sub.choices[command]


class _Jobs:
    """``adapter.run_job`` replaced: records each job's arguments, sends two progress events and
    a log line, asks whether the run was cancelled, and leaves ``files`` in the output folder."""

    def __init__(self, exit_code=0, message="ok: done", files=None):
        self.calls, self.exit_code, self.message, self.files = [], exit_code, message, files or (lambda args: None)

    def __call__(self, args, progress=None, log=None, cancelled=None, cli=None, **kw):
        self.calls.append({"args": list(args), "cli": cli})
        progress(0.25, "[1/2] reading")
        log("a line of the command")
        if cancelled():
            raise adapter.CancelledError("cancelled: the forestreg job was stopped")
        progress(0.8, "[2/2] measuring")
        self.files(args)
        return adapter.JobRun("job1", list(args), self.exit_code, self.message)


# ----------------------------------------------------------------------------- definitions


def test_the_provider_has_seven_algorithms_with_their_parameters_and_outputs(provider):
    p = provider.ForestregProvider()
    p.loadAlgorithms()
    algorithms = {a.name(): a for a in p.algorithms()}
    assert list(algorithms) == IDS
    assert [a.id() for a in algorithms.values()] == [f"forestreg:{n}" for n in IDS]
    assert provider.TREES_ALGORITHM == "forestreg:trees" and provider.CHANGE_ALGORITHM == "forestreg:change"
    for a in algorithms.values():
        assert a.displayName() and a.shortHelpString() and a.groupId() in ("registration", "trees")
        assert a.createInstance().name() == a.name()
    expected = {
        "coregister": (
            [
                "GROUND",
                "UAV",
                "OUTPUT",
                "MIN_CLUSTER_SIZE",
                "VOXEL",
                "DISTANCE_THRESHOLD",
                "CRS",
                "UNITS",
                "PARAMS",
                "CLI",
            ],
            ["TRANSFORM", "RESULT", "LAYERS", "STATUS", "REASON"],
        ),
        "fuse": (
            ["GROUND", "UAV", "TRANSFORM", "OUTPUT", "EPSILON", "CUBE", "CRS", "UNITS", "PARAMS", "CLI"],
            ["POINT_CLOUD", "STATUS", "REASON"],
        ),
        "trees": (
            [
                "CLOUD",
                "OUTPUT",
                "TRANSFORM",
                "FIELD",
                "CYLINDERS",
                "SINGLE_TREE",
                "REPORT",
                "CRS",
                "UNITS",
                "PARAMS",
                "CLI",
            ],
            ["TREES", "LAYERS", "STATUS", "REASON"],
        ),
        "evaluate": (
            ["TREES", "FIELD", "OUTPUT", "RUN_NAME", "ALSO", "BY", "MAX_DISTANCE", "CLI"],
            ["EVALUATION", "STATUS", "REASON"],
        ),
        "change": (
            ["BEFORE", "AFTER", "OUTPUT", "REPORT", "CRS", "UNITS", "PARAMS", "UNITS_BEFORE", "UNITS_AFTER", "CLI"],
            ["CHANGES", "RESULT", "LAYERS", "STATUS", "REASON"],
        ),
        "register_plot": (
            ["SCANS", "CENTRE", "OUTPUT", "MERGED", "DR", "CRS", "CLI"],
            ["SCANNERS", "STATUS", "REASON", "LAYERS", "POINT_CLOUD"],
        ),
        "register_pair": (
            ["REFERENCE", "MOVING", "OUTPUT", "WRITE_REGISTERED", "DR", "CRS", "CLI"],
            ["SCANNERS", "STATUS", "REASON", "VOPS", "MATCHED", "TRANSFORM", "POINT_CLOUD"],
        ),
    }
    for name, (parameters, outputs) in expected.items():
        a = algorithms[name]
        assert [d.name() for d in a.parameterDefinitions()] == parameters, name
        assert [o.name() for o in a.outputDefinitions()] == outputs, name
        kinds = {d.name(): d.kind for d in a.parameterDefinitions()}
        # the output (a folder, or the fused cloud) is a destination: an output of the model step
        assert kinds["OUTPUT"] == (
            "QgsProcessingParameterFileDestination" if name == "fuse" else "QgsProcessingParameterFolderDestination"
        )
        for d in a.parameterDefinitions():
            if d.name() in ("CLI", "PARAMS", "CRS", "UNITS_BEFORE", "UNITS_AFTER"):
                assert d.advanced(), (name, d.name())


def test_outputs_chain_plot_trees_change(provider):
    """The merged cloud of a plot is a file (-> the trees' cloud), the trees' trees.csv a file
    (-> a survey of change), coregister's transform.txt a file (-> fuse and trees)."""
    kinds = {(n, o.name()): o.kind for n in IDS for o in _algorithm(provider, n).outputDefinitions()}
    params = {(n, d.name()): d.kind for n in IDS for d in _algorithm(provider, n).parameterDefinitions()}
    assert params[("register_plot", "MERGED")] == "QgsProcessingParameterFileDestination"
    assert (
        params[("trees", "CLOUD")]
        == params[("change", "BEFORE")]
        == params[("change", "AFTER")]
        == "QgsProcessingParameterFile"
    )
    assert kinds[("trees", "TREES")] == kinds[("coregister", "TRANSFORM")] == "QgsProcessingOutputFile"
    assert params[("fuse", "TRANSFORM")] == params[("trees", "TRANSFORM")] == "QgsProcessingParameterFile"


def test_defaults_are_the_cli_defaults(provider):
    _, trees = _cli_parser("trees")
    d = trees.parse_args(["c.laz", "--out", "o"])
    alg = _algorithm(provider, "trees")
    p = {x.name(): x for x in alg.parameterDefinitions()}
    assert p["CYLINDERS"].defaultValue() is (not d.no_cylinders) is True
    assert p["REPORT"].defaultValue() is (not d.no_report) is True
    assert (
        d.single_tree is None
        and p["SINGLE_TREE"].options()[p["SINGLE_TREE"].defaultValue()] == "decided from the cloud"
    )
    assert p["SINGLE_TREE"].options()[1:] == list(next(a for a in trees._actions if a.dest == "single_tree").choices)
    units = next(a for a in trees._actions if a.dest == "units")
    assert (
        p["UNITS"].options() == sorted(units.choices)
        and p["UNITS"].options()[p["UNITS"].defaultValue()] == units.default == "m"
    )

    _, evaluate = _cli_parser("evaluate")
    d = evaluate.parse_args(["t.csv", "f.csv", "--out", "o"])
    p = {x.name(): x for x in _algorithm(provider, "evaluate").parameterDefinitions()}
    assert p["BY"].options()[p["BY"].defaultValue()] == d.by == "position"
    assert p["BY"].options() == list(next(a for a in evaluate._actions if a.dest == "by").choices)
    assert p["MAX_DISTANCE"].defaultValue() == d.max_distance == 1.0

    for command, names in (
        ("coregister", ("min_cluster_size", "voxel", "distance_threshold")),
        ("fuse", ("epsilon", "cube")),
    ):
        _, sub = _cli_parser(command)
        d = sub.parse_args(["g.laz", "u.laz", "--out", "o.laz" if command == "fuse" else "o"])
        assert all(getattr(d, n) is None for n in names)  # no default: the parameters' own (optional, empty)
        for x in _algorithm(provider, command).parameterDefinitions():
            if x.kind == "QgsProcessingParameterNumber":
                assert x.optional() and x.defaultValue() is None, (command, x.name())

    _, change = _cli_parser("change")
    d = change.parse_args(["a", "b", "--out", "o"])
    p = {x.name(): x for x in _algorithm(provider, "change").parameterDefinitions()}
    assert d.units_before is None and p["UNITS_BEFORE"].options()[p["UNITS_BEFORE"].defaultValue()] == "as Units"
    assert p["REPORT"].defaultValue() is (not d.no_report)


# ----------------------------------------------------------------------------- job requests


CASES = [
    (
        "coregister",
        {"GROUND": "g.laz", "UAV": "u.laz", "OUTPUT": "co"},
        ["coregister", "g.laz", "u.laz", "--out", "co"],
    ),
    (
        "coregister",
        {
            "GROUND": "g.laz",
            "UAV": "u.laz",
            "OUTPUT": "co",
            "MIN_CLUSTER_SIZE": 12,
            "VOXEL": 0.25,
            "DISTANCE_THRESHOLD": 2,
            "CRS": "EPSG:32618",
            "UNITS": 0,
            "PARAMS": "p.toml",
        },
        [
            "coregister",
            "g.laz",
            "u.laz",
            "--out",
            "co",
            "--min-cluster-size",
            "12",
            "--voxel",
            "0.25",
            "--distance-threshold",
            "2.0",
            "--crs",
            "EPSG:32618",
            "--units",
            "cm",
            "--params",
            "p.toml",
        ],
    ),
    (
        "fuse",
        {"GROUND": "g.laz", "UAV": "u.laz", "OUTPUT": "fused.laz"},
        ["fuse", "g.laz", "u.laz", "--out", "fused.laz"],
    ),
    (
        "fuse",
        {
            "GROUND": "g.laz",
            "UAV": "u.laz",
            "OUTPUT": "fused.laz",
            "TRANSFORM": "co/transform.txt",
            "EPSILON": 0.02,
            "CUBE": 5,
            "UNITS": 3,
        },
        [
            "fuse",
            "g.laz",
            "u.laz",
            "--out",
            "fused.laz",
            "--transform",
            "co/transform.txt",
            "--epsilon",
            "0.02",
            "--cube",
            "5.0",
            "--units",
            "mm",
        ],
    ),
    ("trees", {"CLOUD": "plot.laz", "OUTPUT": "trees"}, ["trees", "plot.laz", "--out", "trees"]),
    (
        "trees",
        {
            "CLOUD": "plot.laz",
            "OUTPUT": "trees",
            "TRANSFORM": "t.txt",
            "FIELD": "field.csv",
            "CYLINDERS": False,
            "SINGLE_TREE": 2,
            "REPORT": False,
            "CRS": "EPSG:25832",
            "UNITS": 2,
        },
        [
            "trees",
            "plot.laz",
            "--out",
            "trees",
            "--transform",
            "t.txt",
            "--field",
            "field.csv",
            "--no-cylinders",
            "--single-tree",
            "yes",
            "--no-report",
            "--crs",
            "EPSG:25832",
        ],
    ),
    (
        "evaluate",
        {"TREES": "trees/trees.csv", "FIELD": "field.csv", "OUTPUT": "ev"},
        ["evaluate", "trees/trees.csv", "field.csv", "--out", "ev", "--by", "position", "--max-distance", "1.0"],
    ),
    (
        "evaluate",
        {
            "TREES": "a/trees.csv",
            "FIELD": "field.csv",
            "OUTPUT": "ev",
            "RUN_NAME": "tls",
            "ALSO": "fused=b/trees.csv; c/trees.csv",
            "BY": 1,
            "MAX_DISTANCE": 0.5,
        },
        [
            "evaluate",
            "a/trees.csv",
            "field.csv",
            "--out",
            "ev",
            "--name",
            "tls",
            "--also",
            "fused=b/trees.csv",
            "--also",
            "c/trees.csv",
            "--by",
            "id",
            "--max-distance",
            "0.5",
        ],
    ),
    (
        "change",
        {"BEFORE": "2019/trees.csv", "AFTER": "2024.laz", "OUTPUT": "ch"},
        ["change", "2019/trees.csv", "2024.laz", "--out", "ch"],
    ),
    (
        "change",
        {
            "BEFORE": "a.laz",
            "AFTER": "b.laz",
            "OUTPUT": "ch",
            "REPORT": False,
            "UNITS": 0,
            "UNITS_BEFORE": 0,
            "UNITS_AFTER": 4,
        },
        ["change", "a.laz", "b.laz", "--out", "ch", "--no-report", "--units", "cm", "--units-after", "mm"],
    ),
    (
        "register_pair",
        {"REFERENCE": "a.laz", "MOVING": "b.laz", "OUTPUT": "pair", "DR": 15},
        ["register", "a.laz", "b.laz", "--out", "pair", "--dr", "15.0"],
    ),
    (
        "register_pair",
        {"REFERENCE": "a.laz", "MOVING": "b.laz", "OUTPUT": "pair", "WRITE_REGISTERED": True, "CRS": "EPSG:26912"},
        ["register", "a.laz", "b.laz", "--out", "pair", "--write-registered", "--crs", "EPSG:26912"],
    ),
    (
        "register_plot",
        {"SCANS": ["a.laz", "b.laz"], "OUTPUT": "plot", "MERGED": "plot/merged.copc.laz", "CENTRE": "b.laz"},
        ["plot", "a.laz", "b.laz", "--out", "plot", "--centre", "b.laz", "--merged", "plot/merged.copc.laz"],
    ),
    (
        "register_plot",
        {"SCANS": ["a.laz", "b.laz"], "OUTPUT": "plot", "CRS": "EPSG:32618"},
        ["plot", "a.laz", "b.laz", "--out", "plot", "--crs", "EPSG:32618"],
    ),
]


@pytest.mark.parametrize("name, parameters, expected", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_each_algorithm_builds_the_job_request(provider, monkeypatch, tmp_path, name, parameters, expected):
    monkeypatch.chdir(tmp_path)
    jobs = _Jobs()
    monkeypatch.setattr(adapter, "run_job", jobs)
    if name.startswith("register"):  # the registration reads what the job wrote: stand in for it
        outputs = _plot_outputs(tmp_path)
        if name == "register_pair":
            outputs = adapter.HostOutputs(
                "pair",
                tmp_path,
                "ok",
                "a",
                {},
                [],
                [],
                "",
                adapter.SavedResult.from_dict(
                    {"status": "ok", "matrix": np.eye(4).tolist(), "reference": "a", "moving": "b", "matched": 7}
                ),
            )
        monkeypatch.setattr(
            adapter, name, lambda job, cli, p, l, c: (jobs(adapter.build_args(job), p, l, c, cli), outputs)[1]
        )
        monkeypatch.setattr(
            adapter, "write_layer_files", lambda o: adapter.LayerFiles(tmp_path / "s.csv", tmp_path / "v.csv")
        )
    parameters = {**parameters, "CLI": "/opt/forestreg/bin/forestreg"}
    feedback = qgis_fakes.Feedback()
    results = _algorithm(provider, name).processAlgorithm(parameters, qgis_fakes.QgsProcessingContext(), feedback)
    (call,) = jobs.calls
    assert call["args"] == expected
    assert call["cli"] == "/opt/forestreg/bin/forestreg"
    assert feedback.info[0] == "job: forestreg " + " ".join(expected)
    assert results["STATUS"] == "ok" and results["REASON"] == ""
    # the CLI's own parser (which the service checks jobs with) accepts the request
    from forestreg.cli import build_parser

    build_parser().parse_args(expected)


def _plot_outputs(out):
    return adapter.HostOutputs("plot", Path(out), "ok", "a.laz", {}, [], [], "")


def test_a_failed_command_is_status_failed_with_its_reason(provider, monkeypatch, tmp_path):
    monkeypatch.setattr(adapter, "run_job", _Jobs(exit_code=1, message="failed: fewer than 3 keypoints matched"))
    feedback = qgis_fakes.Feedback()
    results = _algorithm(provider, "coregister").processAlgorithm(
        {"GROUND": "g.laz", "UAV": "u.laz", "OUTPUT": str(tmp_path / "co")}, qgis_fakes.QgsProcessingContext(), feedback
    )
    assert results["STATUS"] == "failed" and results["REASON"] == "fewer than 3 keypoints matched"
    assert results["TRANSFORM"] == "" and any("fewer than 3 keypoints" in e for e in feedback.errors)


def test_an_unknown_choice_is_refused_before_the_job():
    with pytest.raises(adapter.AdapterError, match="single tree"):
        adapter.build_trees_args(adapter.TreesJob("c.laz", "o", single_tree="maybe"))
    with pytest.raises(adapter.AdapterError, match="match by"):
        adapter.build_evaluate_args(adapter.EvaluateJob("t.csv", "f.csv", "o", by="name"))
    with pytest.raises(adapter.AdapterError, match="not a forestreg job"):
        adapter.build_args(object())


# ----------------------------------------------------------------------------- progress and cancel


@pytest.mark.parametrize("name", ["coregister", "fuse", "trees", "evaluate", "change"])
def test_job_progress_log_and_cancel_reach_the_feedback(provider, monkeypatch, tmp_path, name):
    params = {
        "coregister": {"GROUND": "g", "UAV": "u"},
        "fuse": {"GROUND": "g", "UAV": "u"},
        "trees": {"CLOUD": "c"},
        "evaluate": {"TREES": "t", "FIELD": "f"},
        "change": {"BEFORE": "a", "AFTER": "b"},
    }[name]
    params = {**params, "OUTPUT": str(tmp_path / ("out.laz" if name == "fuse" else "out"))}
    monkeypatch.setattr(adapter, "run_job", _Jobs())
    feedback = qgis_fakes.Feedback()
    _algorithm(provider, name).processAlgorithm(params, qgis_fakes.QgsProcessingContext(), feedback)
    assert feedback.progress == [25.0, 80.0, 100.0]  # fractions as percent, then 100 when the job ended
    assert feedback.texts == ["[1/2] reading", "[2/2] measuring"]
    assert feedback.console == ["a line of the command"]

    cancelling = qgis_fakes.Feedback(cancel_after=1)  # Cancel pressed after the first event
    with pytest.raises(qgis_fakes.QgsProcessingException, match="cancelled"):
        _algorithm(provider, name).processAlgorithm(params, qgis_fakes.QgsProcessingContext(), cancelling)
    assert cancelling.progress == [25.0]


def test_service_errors_become_processing_exceptions(provider, monkeypatch):
    def refuse(args, **kw):
        raise adapter.BadInputError("forestreg: bad input: c.laz: no such file", 2, "c.laz: no such file")

    monkeypatch.setattr(adapter, "run_job", refuse)
    feedback = qgis_fakes.Feedback()
    with pytest.raises(qgis_fakes.QgsProcessingException, match="bad input"):
        _algorithm(provider, "trees").processAlgorithm(
            {"CLOUD": "c.laz", "OUTPUT": "o"}, qgis_fakes.QgsProcessingContext(), feedback
        )
    assert feedback.errors == ["c.laz: no such file"]


# ----------------------------------------------------------------------------- what loads on completion


def _write_layers(folder, names=("trees", "crowns", "plot_outline")):
    from forestreg.engine.io.gpkg import Layer, write_geopackage

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ring = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    layers = []
    for n in names:
        if n == "trees":
            layers.append(
                Layer(
                    n,
                    "POINT",
                    ("tree_id",),
                    [{"tree_id": 1}],
                    [np.array([1.0, 2.0, 1.3])],
                    z=True,
                    style="<qgis>trees</qgis>",
                )
            )
        else:
            layers.append(
                Layer(
                    n,
                    "POLYGON",
                    ("name",),
                    [{"name": n}],
                    [ring],
                    style="" if n == "plot_outline" else f"<qgis>{n}</qgis>",
                )
            )
    write_geopackage(folder / "layers.gpkg", layers)
    (folder / "trees.csv").write_text("tree_id,x,y\n1,1,2\n")


def test_adapter_lists_the_layers_of_a_geopackage_with_their_styles(tmp_path):
    _write_layers(tmp_path)
    layers = adapter.gpkg_layers(tmp_path / "layers.gpkg")
    assert [(l.name, l.style) for l in layers] == [
        ("trees", "<qgis>trees</qgis>"),
        ("crowns", "<qgis>crowns</qgis>"),
        ("plot_outline", ""),
    ]
    assert layers[0].uri == f"{(tmp_path / 'layers.gpkg').resolve()}|layername=trees"
    assert adapter.gpkg_layers(tmp_path / "none.gpkg") == []
    (tmp_path / "bad.gpkg").write_text("not a database")
    with pytest.raises(adapter.AdapterError, match="not a GeoPackage"):
        adapter.gpkg_layers(tmp_path / "bad.gpkg")


def test_trees_loads_the_styled_layers_of_its_output_folder(provider, monkeypatch, tmp_path):
    out = tmp_path / "trees"
    monkeypatch.setattr(adapter, "run_job", _Jobs(files=lambda args: _write_layers(args[args.index("--out") + 1])))
    context = qgis_fakes.QgsProcessingContext()
    results = _algorithm(provider, "trees").processAlgorithm(
        {"CLOUD": str(tmp_path / "plot.laz"), "OUTPUT": str(out)}, context, qgis_fakes.Feedback()
    )
    assert results["OUTPUT"] == str(out) and results["TREES"] == str(out / "trees.csv")
    layers = [context.store.mapLayer(i) for i in results["LAYERS"]]
    assert [(l.name(), l.provider) for l in layers] == [
        ("trees (plot)", "ogr"),
        ("crowns (plot)", "ogr"),
        ("plot_outline (plot)", "ogr"),
    ]
    assert layers[0].source.endswith("layers.gpkg|layername=trees")
    assert [l.styles for l in layers] == [["<qgis>trees</qgis>"], ["<qgis>crowns</qgis>"], []]
    assert list(context.to_load) == results["LAYERS"] and {d.output for d in context.to_load.values()} == {"LAYERS"}


def test_change_and_coregister_load_their_layers_a_run_without_them_loads_none(provider, monkeypatch, tmp_path):
    monkeypatch.setattr(
        adapter, "run_job", _Jobs(files=lambda args: _write_layers(args[args.index("--out") + 1], ("tree_changes",)))
    )
    context = qgis_fakes.QgsProcessingContext()
    results = _algorithm(provider, "change").processAlgorithm(
        {"BEFORE": "2019.csv", "AFTER": "2024.csv", "OUTPUT": str(tmp_path / "ch")}, context, qgis_fakes.Feedback()
    )
    assert [context.store.mapLayer(i).name() for i in results["LAYERS"]] == ["tree_changes (2024 since 2019)"]
    monkeypatch.setattr(adapter, "run_job", _Jobs())
    results = _algorithm(provider, "coregister").processAlgorithm(
        {"GROUND": "g", "UAV": "u", "OUTPUT": str(tmp_path / "co")},
        qgis_fakes.QgsProcessingContext(),
        qgis_fakes.Feedback(),
    )
    assert results["LAYERS"] == []


def _fuse(provider, monkeypatch, tmp_path, feedback):
    out = tmp_path / "fused.laz"
    monkeypatch.setattr(adapter, "run_job", _Jobs(files=lambda args: out.write_bytes(b"LASF")))
    context = qgis_fakes.QgsProcessingContext()
    results = _algorithm(provider, "fuse").processAlgorithm(
        {"GROUND": "g.laz", "UAV": "u.laz", "OUTPUT": str(out)}, context, feedback
    )
    return results, context


def test_a_fused_cloud_loads_as_a_point_cloud_layer(provider, monkeypatch, tmp_path):
    results, context = _fuse(provider, monkeypatch, tmp_path, qgis_fakes.Feedback())
    layer = context.store.mapLayer(results["POINT_CLOUD"])
    assert (layer.name(), layer.provider, layer.source) == ("fused.laz", "pdal", str(tmp_path / "fused.laz"))
    assert type(layer).__name__ == "QgsPointCloudLayer" and results["POINT_CLOUD"] in context.to_load


@pytest.mark.parametrize(
    "version, point_clouds, pdal", [(31600, True, True), (33400, False, True), (32216, True, False)]
)
def test_no_point_cloud_layer_where_qgis_has_none(monkeypatch, tmp_path, version, point_clouds, pdal):
    with qgis_fakes.installed(version, point_clouds, pdal) as provider:
        feedback = qgis_fakes.Feedback()
        results, context = _fuse(provider, monkeypatch, tmp_path, feedback)
        kinds = {o.name(): o.kind for o in _algorithm(provider, "fuse").outputDefinitions()}
    assert results["POINT_CLOUD"] is None and not context.to_load and results["STATUS"] == "ok"
    assert any("point cloud" in line or "PDAL" in line for line in feedback.info) and feedback.errors == []
    if not point_clouds:  # the output is declared as a string where QGIS has no point cloud outputs
        assert kinds["POINT_CLOUD"] == "QgsProcessingOutputString"


def test_a_plot_loads_its_layers_and_its_merged_cloud(provider, monkeypatch, tmp_path):
    out, merged = tmp_path / "plot", tmp_path / "plot" / "merged.copc.laz"

    def register_plot(job, cli, progress, log, cancelled):
        _write_layers(out, ("scanners", "links", "plot_outline"))
        merged.write_bytes(b"LASF")
        return _plot_outputs(out)

    monkeypatch.setattr(adapter, "register_plot", register_plot)
    monkeypatch.setattr(adapter, "write_layer_files", lambda outputs: adapter.LayerFiles(out / "layer_scanners.csv"))
    (out).mkdir()
    (out / "layer_scanners.csv").write_text("name,x,y,z\n")
    context = qgis_fakes.QgsProcessingContext()
    results = _algorithm(provider, "register_plot").processAlgorithm(
        {"SCANS": ["a.laz", "b.laz"], "OUTPUT": str(out), "MERGED": str(merged)}, context, qgis_fakes.Feedback()
    )
    assert results["MERGED"] == str(merged)
    assert [context.store.mapLayer(i).name() for i in results["LAYERS"]] == [
        "scanners (plot)",
        "links (plot)",
        "plot_outline (plot)",
    ]
    # one scanners layer: the styled one of layers.gpkg is the scanner positions output
    assert results["SCANNERS"] == results["LAYERS"][0] and len(context.store.layers) == 4
    assert context.store.mapLayer(results["POINT_CLOUD"]).provider == "pdal"


def test_a_pair_loads_its_registered_scan_when_asked(provider, monkeypatch, tmp_path):
    out = tmp_path / "pair"
    out.mkdir()
    result = adapter.SavedResult.from_dict(
        {"status": "ok", "matrix": np.eye(4).tolist(), "reference": "a", "moving": "b", "matched": 7}
    )

    def register_pair(job, cli, progress, log, cancelled):
        assert job.write_registered
        (out / "b_registered.laz").write_bytes(b"LASF")
        return adapter.HostOutputs("pair", out, "ok", "a", {}, [], [], "", result)

    monkeypatch.setattr(adapter, "register_pair", register_pair)
    for name in ("layer_scanners.csv", "layer_vops.csv"):
        (out / name).write_text("name,x,y,z\n")
    monkeypatch.setattr(
        adapter, "write_layer_files", lambda o: adapter.LayerFiles(out / "layer_scanners.csv", out / "layer_vops.csv")
    )
    context = qgis_fakes.QgsProcessingContext()
    results = _algorithm(provider, "register_pair").processAlgorithm(
        {"REFERENCE": "a.laz", "MOVING": "b.laz", "OUTPUT": str(out), "WRITE_REGISTERED": True},
        context,
        qgis_fakes.Feedback(),
    )
    layer = context.store.mapLayer(results["POINT_CLOUD"])
    assert (layer.name(), layer.provider, layer.source) == (
        "registered (b onto a)",
        "pdal",
        str(out / "b_registered.laz"),
    )
    assert results["MATCHED"] == 7 and results["TRANSFORM"] == str(out / "transform.txt")


@pytest.mark.parametrize(
    "parameter, crs, uri_crs, set_crs",
    [
        (
            None,
            {"epsg": "EPSG:26912", "wkt": "PROJCRS[...]"},
            "EPSG:26912",
            None,
        ),  # the scans' own CRS, from result.json
        ("EPSG:32618", {"epsg": "EPSG:26912"}, "EPSG:32618", None),  # the CRS parameter wins
        (
            None,
            {"epsg": None, "wkt": 'PROJCRS["a local grid"]'},
            None,
            'PROJCRS["a local grid"]',
        ),  # no EPSG id: set from the WKT
        (None, {"epsg": None, "wkt": None}, None, None),  # local coordinates
    ],
)
def test_a_pairs_point_layers_take_the_runs_crs(provider, monkeypatch, tmp_path, parameter, crs, uri_crs, set_crs):
    out = tmp_path / "pair"
    out.mkdir()
    summary = {"status": "ok", "matrix": np.eye(4).tolist(), "reference": "a", "moving": "b", "matched": 7, "crs": crs}
    outputs = adapter.HostOutputs("pair", out, "ok", "a", summary, [], [], "", adapter.SavedResult.from_dict(summary))
    monkeypatch.setattr(adapter, "register_pair", lambda job, cli, progress, log, cancelled: outputs)
    for name in ("layer_scanners.csv", "layer_vops.csv"):
        (out / name).write_text("name,x,y,z\n")
    monkeypatch.setattr(
        adapter, "write_layer_files", lambda o: adapter.LayerFiles(out / "layer_scanners.csv", out / "layer_vops.csv")
    )
    context = qgis_fakes.QgsProcessingContext()
    parameters = {
        "REFERENCE": "a.laz",
        "MOVING": "b.laz",
        "OUTPUT": str(out),
        **({"CRS": parameter} if parameter else {}),
    }
    results = _algorithm(provider, "register_pair").processAlgorithm(parameters, context, qgis_fakes.Feedback())
    for key in ("SCANNERS", "VOPS"):
        layer = context.store.mapLayer(results[key])
        assert layer.source.endswith(f"&crs={uri_crs}") if uri_crs else "&crs=" not in layer.source
        assert (getattr(layer, "crs", None).text if hasattr(layer, "crs") else None) == set_crs


# ----------------------------------------------------------------------------- the model


def _options(element):
    """A QGIS ``<Option>`` tree as Python values (maps, lists, strings)."""
    kind = element.get("type")
    if kind == "Map":
        return {child.get("name"): _options(child) for child in element}
    if kind == "List":
        return [_options(child) for child in element]
    return element.get("value")


def test_the_model_chains_register_plot_trees_and_change(provider):
    root = ET.parse(MODEL).getroot()
    assert root.tag == "Option" and root.get("type") == "Map"
    model = _options(root)
    children = model["children"]
    algorithms = {child["id"]: child["alg_id"] for child in children.values()}
    assert sorted(algorithms.values()) == sorted(["forestreg:register_plot", "forestreg:trees", "forestreg:change"])
    by_alg = {child["alg_id"]: child for child in children.values()}
    ids = {a: c["id"] for a, c in by_alg.items()}

    def source(alg, parameter):
        (s,) = by_alg[alg]["params"][parameter]
        return s

    # the plot's merged cloud is the trees' cloud; the trees' trees.csv is the later survey of change
    assert source("forestreg:trees", "CLOUD") == {
        "child_id": ids["forestreg:register_plot"],
        "output_name": "MERGED",
        "source": "1",
    }
    assert source("forestreg:change", "AFTER") == {
        "child_id": ids["forestreg:trees"],
        "output_name": "TREES",
        "source": "1",
    }
    assert source("forestreg:change", "BEFORE")["source"] == "0"  # a model input: the earlier survey
    # every parameter the model feeds exists in its algorithm, every model input is defined
    for alg, child in by_alg.items():
        names = {d.name() for d in _algorithm(provider, alg.split(":")[1]).parameterDefinitions()}
        assert set(child["params"]) <= names, alg
        for sources in child["params"].values():
            for s in sources:
                if s["source"] == "0":
                    assert s["parameter_name"] in model["parameterDefinitions"]
                elif s["source"] == "1":
                    outputs = {
                        o.name()
                        for o in _algorithm(provider, algorithms[s["child_id"]].split(":")[1]).outputDefinitions()
                    }
                    outputs |= {
                        d.name()
                        for d in _algorithm(provider, algorithms[s["child_id"]].split(":")[1]).parameterDefinitions()
                        if d.kind.endswith("Destination")
                    }
                    assert s["output_name"] in outputs
    assert model["model_name"] and model["model_group"] == "forestreg"
    # the scans are files (QGIS's TypeFile, 4): a layer type would make QGIS open each scan as a map layer, and refuse it
    assert model["parameterDefinitions"]["scans"]["layer_type"] == str(qgis_fakes.QgsProcessing.TypeFile) == "4"


# ----------------------------------------------------------------------------- real QGIS


def test_metadata_declares_the_processing_provider_for_qgis_process():
    import configparser

    meta = configparser.ConfigParser(interpolation=None)
    meta.read(ROOT / "metadata.txt", encoding="utf-8")
    assert meta["general"]["hasProcessingProvider"] == "yes"  # qgis_process loads only such plugins


def test_the_guide_names_every_algorithm_and_the_model():
    guide = (ROOT / "docs" / "guide" / "qgis.md").read_text(encoding="utf-8")
    for name in IDS:
        assert f"`forestreg:{name}`" in guide
    assert MODEL.relative_to(ROOT).as_posix() in guide
