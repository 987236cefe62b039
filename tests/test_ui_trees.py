"""The Trees tab (map, table, selected tree in 3D, stem curve) and its correction loop, driven as a
user would (pytest-qt); every value shown is checked against the engine's own results."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QSettings, Qt  # noqa: E402

from forestreg.engine.trees.inventory import TreeParams, measure_trees  # noqa: E402

TIMEOUT_MS = 180_000
PARAMS = TreeParams(cylinder_models=False)


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    """A small simulated conifer plot (one scan) as a LAZ file, and its truth."""
    from forestreg.engine.io import read_scan, write_points
    from forestreg.engine.simulate import simulate_plot

    folder = tmp_path_factory.mktemp("ui_trees")
    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.4, size_m=14.0)
    path = folder / "plot.laz"
    write_points(path, np.vstack([s.world_points() for s in plot.scans]))
    return plot, path, read_scan(path)


@pytest.fixture(scope="module")
def trees_dir(cloud, tmp_path_factory):
    """What 'forestreg trees --out DIR' writes (the engine's writer, cylinder models included)."""
    _, _, scan = cloud
    inv = measure_trees(scan.points, TreeParams(), origin_shift=scan.origin_shift)
    folder = tmp_path_factory.mktemp("trees_out")
    inv.write(folder)
    return folder, inv


@pytest.fixture
def window(window):
    """The shared main window (conftest), at a desktop size."""
    window.resize(1280, 800)
    return window


def test_trees_folder_map_table_and_3d(qtbot, window, cloud, trees_dir):
    folder, inv = trees_dir
    _, path, _ = cloud
    assert window.open_trees(folder, path)
    view = window.trees_view
    assert window.central_tabs.currentWidget() is view and not window.results_dock.isVisible()
    table = view.table
    rows = {r["tree_id"]: r for r in inv.rows()}
    assert table.rowCount() == len(inv.trees) >= 10
    for row in range(table.rowCount()):
        tid = table.value(row, "tree_id")
        assert table.value(row, "dbh_m") == pytest.approx(rows[tid]["dbh_m"], abs=1e-4, nan_ok=True)
        assert table.value(row, "height_m") == pytest.approx(rows[tid]["height_m"], abs=1e-4, nan_ok=True)
        assert table.value(row, "flag") == rows[tid]["flag"]
        if math.isfinite(rows[tid]["dbh_m"]):
            assert (
                table.text(row, "dbh_m") == f"{100 * table.value(row, 'dbh_m'):.1f}"
            )  # cm, as written (4 decimals of m)
        assert table.text(row, "tree_id").startswith("\u26a0") == bool(rows[tid]["flag"])
    # sorting by DBH puts the thinnest measured tree first
    table.sortItems(table.column("dbh_m"), Qt.SortOrder.AscendingOrder)
    dbh = [r["dbh_m"] for r in rows.values() if math.isfinite(r["dbh_m"])]
    assert table.value(0, "dbh_m") == pytest.approx(min(dbh), abs=1e-4)
    # selecting a row shows that tree: cylinders, stem circles, its points, its stem curve
    target = max(inv.trees, key=lambda r: len(r.cylinders) if r.cylinders is not None else 0)
    table.selectRow(table.row_of(target.tree_id))
    assert view.selected == target.tree_id
    actors = view.scene3d.plotter.actors
    assert "stem" in actors and "tree-points" in actors and "ring0" in actors
    n_pts = actors["tree-points"].mapper.dataset.n_points
    assert 0.5 * target.n_points < n_pts < 3 * target.n_points
    ax = view.curve.figure.axes[0]
    assert f"tree {target.tree_id}" in ax.get_title()
    # the map: one marker per tree, flagged ones as crosses
    assert (
        view.map.figure.axes[0]
        .get_title()
        .startswith(f"{len(inv.trees)} trees, {sum(bool(r.flags) for r in inv.trees)} flagged")
    )
    # a bad folder: one clear message, nothing replaced
    assert not window.open_trees(folder / "nope")
    assert "not a trees result folder" in window.last_error[1]
    assert view.table.rowCount() == len(inv.trees)


def test_correction_loop_edits_undo_and_save(qtbot, window, cloud, tmp_path):
    from forestreg.engine.io.results import read_trees_dir
    from forestreg.engine.trees import edit as E

    plot, path, scan = cloud
    view = window.trees_view
    view.params = PARAMS
    window.show_tab("Trees")
    assert view.measure(str(path))
    qtbot.waitUntil(lambda: view.worker is None and view.inventory is not None, timeout=TIMEOUT_MS)
    engine = measure_trees(scan.points, PARAMS, origin_shift=scan.origin_shift)
    assert view.table.rowCount() == len(engine.trees)
    n = len(engine.trees)
    shift = scan.origin_shift

    def near(x, y):
        return min(engine.trees, key=lambda r: math.hypot(r.stem.x - x, r.stem.y - y))

    a, b = near(1.93 - shift[0], 0.08 - shift[1]), near(2.69 - shift[0], 3.41 - shift[1])
    # merge two trees: one row less, the merged tree's points are both trees'
    view.select_tree(a.tree_id)
    assert view.merge_selected_with(b.tree_id)
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.table.rowCount() == n - 1
    row = view.table.row_of(a.tree_id)
    assert view.table.value(row, "n_points") == a.n_points + b.n_points
    assert "\u270e" in view.table.text(row, "tree_id")
    # undo restores the engine's trees
    assert view.undo()
    assert view.table.rowCount() == n and view.table.value(view.table.row_of(b.tree_id), "dbh_m") == pytest.approx(
        b.dbh_m, abs=1e-4
    )
    # DBH at 2 m: the value shown is the engine's for that edit
    view.select_tree(a.tree_id)
    assert view.dbh_height_selected(2.0)
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    want = next(r for r in E.dbh_at_height(scan.points, engine, a.tree_id, 2.0, PARAMS).trees if r.tree_id == a.tree_id)
    assert view.table.value(view.table.row_of(a.tree_id), "dbh_m") == pytest.approx(want.dbh_m, abs=1e-6)
    # delete, then add the stem back by a click beside it (file coordinates)
    view.select_tree(b.tree_id)
    assert view.delete_selected()
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.table.row_of(b.tree_id) == -1
    assert view.add_stem_at(b.stem.x + shift[0] + 0.2, b.stem.y + shift[1] - 0.2)
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.table.rowCount() == n and view.selected not in {r.tree_id for r in engine.trees}
    new = view.table.row_of(view.selected)
    assert view.table.value(new, "dbh_m") == pytest.approx(b.dbh_m, abs=0.005)
    # a click on nothing: an honest message, nothing changed
    assert view.add_stem_at(-5.5 + shift[0], -3.0 + shift[1])
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.last_error is not None and ("no stem" in view.last_error or "too few points" in view.last_error)
    assert view.table.rowCount() == n
    # saved: trees.csv marks the edited trees, edits.json replays to the same trees
    view.save_edits(str(tmp_path / "edited"))
    out = read_trees_dir(tmp_path / "edited")
    assert {t.tree_id for t in out.trees if t.edited} == {a.tree_id, view.selected}
    replayed = E.apply_edits(scan.points, engine, E.read_edits(tmp_path / "edited" / "edits.json"), PARAMS)
    assert sorted(r.tree_id for r in replayed.trees) == sorted(t.tree_id for t in out.trees)


def test_a_height_from_the_curve_is_marked_in_the_table(window, cloud, trees_dir, tmp_path):
    """A height predicted from the plot's height-diameter curve (``height_source`` "curve") shows
    as "(curve)" beside its value, the reason in its tip; the others show the bare value."""
    import csv
    import shutil

    folder, inv = trees_dir
    copy = tmp_path / "curve"
    shutil.copytree(folder, copy)
    with (copy / "trees.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    rows[0].update(
        height_source="curve",
        height_m="21.5",
        height_quality="from the plot's height-diameter curve at the DBH: the points' top (14.2 m) not taken; medium",
    )
    with (copy / "trees.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    assert window.open_trees(copy, cloud[1])
    table = window.trees_view.table
    first = table.row_of(int(rows[0]["tree_id"]))
    assert table.text(first, "height_m") == "21.5 (curve)" and table.value(first, "height_m") == 21.5
    assert "not taken" in table.item(first, table.column("height_m")).toolTip()
    other = table.row_of(int(rows[1]["tree_id"]))
    assert not table.text(other, "height_m").endswith("(curve)")


def test_offscreen_screenshot_of_a_trees_folder(trees_dir, cloud, tmp_path):
    """``forestreg gui --offscreen --trees DIR --screenshot OUT.png`` with no display at all."""
    import os
    import subprocess
    import sys

    from PySide6.QtGui import QImage

    folder, inv = trees_dir
    out = tmp_path / "trees.png"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.ui.app",
            "--offscreen",
            "--trees",
            str(folder),
            "--cloud",
            str(cloud[1]),
            "--size",
            "1280x800",
            "--screenshot",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    img = QImage(str(out))
    assert (img.width(), img.height()) == (1280, 800)  # nothing widens the window beyond the screen
    x, y, w, h = (
        int(v) for v in next(l for l in proc.stdout.splitlines() if l.startswith("3d view:")).split(":")[1].split()
    )
    colours = {img.pixel(x + i * w // 40, y + j * h // 40) for i in range(1, 40) for j in range(1, 40)}
    assert len(colours) > 20  # the tree is drawn, not an empty background
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.ui.app",
            "--offscreen",
            "--trees",
            str(tmp_path / "none"),
            "--screenshot",
            str(tmp_path / "x.png"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert bad.returncode == 2 and "not a trees result folder" in bad.stderr and "Traceback" not in bad.stderr


def test_field_data_evaluation_side_by_side(window, cloud, trees_dir, tmp_path):
    from forestreg.engine.trees.evaluate import evaluate

    plot, _, scan = cloud
    folder, inv = trees_dir
    field = tmp_path / "field.csv"
    lines = ["tree_id,x,y,dbh_m,height_m"] + [
        f"T{t.id},{t.x:.3f},{t.y:.3f},{t.dbh_m:.4f},{t.height_m:.3f}"
        for t in plot.scene.trees
        if abs(t.x) < 6.5 and abs(t.y) < 6.5
    ]
    field.write_text("\n".join(lines) + "\n")
    assert window.evaluate_field(field, {"one": folder, "again": folder / "trees.csv"})
    view = window.evaluation_view
    want = evaluate(folder / "trees.csv", field)
    for run in ("one", "again"):
        for p in ("dbh_m", "height_m"):
            s = want.stats[p]
            assert view.value(run, p, "n") == s.n > 5
            assert view.value(run, p, "RMSE") == pytest.approx(s.rmse)
            assert view.value(run, p, "rRMSE (%)") == pytest.approx(s.rrmse_percent)
    assert view.value("one", "dbh_m", "rRMSE (%)") < 10.0
    assert len(view.figure.axes) == 2
    assert not window.evaluate_field(tmp_path / "missing.csv", {"one": folder})


def test_the_project_keeps_system_b_results(qtbot, window, trees_dir, tmp_path):
    """Opened results go into the project (paths relative to it, atomic save) and come back."""
    import json

    from forestreg.engine.tls.project import Project
    from forestreg.ui.main_window import MainWindow

    folder, inv = trees_dir
    assert window.open_trees(folder)
    target = tmp_path / "sub" / "plot.json"
    target.parent.mkdir()
    window.project.save(target)
    stored = json.loads(target.read_text())["forest"]
    assert not Path(stored["trees"][folder.name]).is_absolute()
    loaded = Project.load(target)
    assert loaded.forest.trees[folder.name] == folder.resolve()
    other = MainWindow(settings=QSettings(str(tmp_path / "o.ini"), QSettings.Format.IniFormat), interactive=False)
    qtbot.addWidget(other)
    assert other.open_project(target)
    qtbot.waitUntil(lambda: not other.busy, timeout=TIMEOUT_MS)
    assert other.trees_view.table.rowCount() == len(inv.trees)
