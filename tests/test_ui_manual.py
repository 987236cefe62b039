"""Manual mode of the desktop window (pytest-qt, Qt's offscreen platform as in test_ui.py):
targets picked programmatically through the 3D view's pick handler, manual registration through
the window, targets CSV round trip, reflector detection, and the auto-vs-manual comparison view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")


from forestreg.engine.geometry.icp import IcpParams  # noqa: E402
from forestreg.engine.tls.params import RegistrationParams  # noqa: E402
from forestreg.engine.tls.project import Project  # noqa: E402

RUN_TIMEOUT_MS = 180_000


@pytest.fixture(scope="module")
def plot(tmp_path_factory):
    """Three simulated scans of a planted conifer plot with targets; the truth is known."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    folder = tmp_path_factory.mktemp("manual_plot")
    sim = write_simulated_plot(
        simulate_plot("planted_conifer", [(0, 0), (9, 3), (-7, 7)], seed=61, angular_step_deg=0.3, size_m=45), folder
    )
    return sim, folder


def picked_targets(sim, index: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The targets a user could pick in scan ``index``: those hit by a beam, true centre + 5 mm."""
    rng = np.random.default_rng(seed + index)
    return {
        f"T{t['id']}": np.array([t["x"], t["y"], t["z"]]) + rng.normal(0, 0.005, 3)
        for t in sim.truth["scans"][index]["targets_socs"]
        if t["n_points"] >= 1
    }


@pytest.fixture
def project_file(plot, scans_project) -> Path:
    return scans_project(
        plot[1], "manual plot", RegistrationParams(angular_step_deg=0.3, icp=IcpParams(voxel_m=0.2, iterations=20))
    )


def _pick_all(window, sim) -> dict[str, dict[str, np.ndarray]]:
    picked = {}
    for i, scan in enumerate(window.project.scans):
        picked[scan.name] = picked_targets(sim, i)
        for tid, xyz in picked[scan.name].items():
            assert window.add_picked_target(scan.name, tid, xyz) == tid
    return picked


def test_picked_targets_and_manual_registration(qtbot, window, open_project, plot, project_file: Path) -> None:
    from forestreg.engine.core.transform import rigid_errors

    sim, _ = plot
    open_project(project_file)
    names = [s.name for s in window.project.scans]
    picked = _pick_all(window, sim)
    panel = window.targets_panel
    # the table shows the scan picked last, in file coordinates
    assert panel.scan == names[-1] and panel.table.rowCount() == len(picked[names[-1]])
    row = panel.row_of(next(iter(picked[names[-1]])))
    assert panel.value(row, "x (m)") == pytest.approx(next(iter(picked[names[-1]].values()))[0])
    assert window.dirty
    # a click in the 3D view (pick mode, before-view) maps back to the scan's file coordinates
    window.set_pick_mode(True)
    assert window.scene_view.pick_mode and window.scene_mode == "before"
    qtbot.waitUntil(
        lambda: window.scene_view.scene is not None and window.scene_view.scene.mode == "before" and not window.busy,
        timeout=60_000,
    )
    cloud = window.scene_view.scene.clouds[1]
    scan_name, xyz = window.scan_at(cloud.points[100])
    assert scan_name == cloud.name
    assert np.isclose(xyz, window.scans(cloud.name).file_points, atol=1e-3).all(axis=1).any()
    # and through the rendered image: a click where a point is drawn places the target typed in
    view = window.scene_view
    view.render_now()
    label, pl = view.image_label, view.plotter
    ren = pl.renderer
    ren.SetWorldPoint(*map(float, cloud.points[100]), 1.0)
    ren.WorldToDisplay()
    dx, dy, _ = ren.GetDisplayPoint()
    ww, wh = pl.window_size
    pix = label.pixmap()
    pw, ph = pix.width() / pix.devicePixelRatio(), pix.height() / pix.devicePixelRatio()
    x = (label.width() - pw) / 2 + dx / ww * pw
    y = (label.height() - ph) / 2 + (wh - 1 - dy) / wh * ph
    panel.id_edit.setText("P1")
    with qtbot.waitSignal(window.targetsChanged, timeout=5000) as changed:
        view.pick_in_image(int(round(x)), int(round(y)), label.width(), label.height())
    assert "P1" in window.targets_of(changed.args[0])
    window.set_targets(changed.args[0], {k: v for k, v in window.targets_of(changed.args[0]).items() if k != "P1"})
    window.set_pick_mode(False)
    # every link manual, then register through the window
    panel.manual_all_button.click()
    assert [link.method for link in window.project.links] == ["manual", "manual"]
    assert [window.link_table.value(r, "Method") for r in range(2)] == ["manual", "manual"]
    with qtbot.waitSignal(window.runFinished, timeout=RUN_TIMEOUT_MS):
        assert window.run_manual()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    table = window.link_table
    poses = window.project.poses()
    for row, link in enumerate(window.project.links):
        assert table.value(row, "Method") == "manual" and table.value(row, "Status") == "ok", link.result
        k = names.index(link.moving)
        rot, trans = rigid_errors(poses[link.moving], sim.relative_pose(0, k))
        assert rot < 0.05 and trans < 0.02, (link.moving, rot, trans)
    # the targets are saved with the project
    assert window.save_project()
    again = Project.load(project_file)
    assert set(again.scan(names[1]).targets) == set(picked[names[1]])
    assert again.links[0].method == "manual"
    # switching a link back to auto forgets its result
    window.set_link_method(names[1], "auto")
    assert window.project.link_of(names[1]).method == "auto" and window.project.link_of(names[1]).result is None


def test_targets_table_csv_round_trip_and_reflectors(
    qtbot, window, open_project, plot, project_file: Path, tmp_path: Path
) -> None:
    from forestreg.engine.io.results import write_targets_csv
    from forestreg.engine.tls.manual import read_targets_csv

    sim, _ = plot
    open_project(project_file)
    names = [s.name for s in window.project.scans]
    wanted = {n: picked_targets(sim, i) for i, n in enumerate(names)}
    source = tmp_path / "in.csv"
    write_targets_csv(source, wanted)
    assert window.import_targets_csv(source) == sum(len(v) for v in wanted.values())
    for n in names:
        got = window.targets_of(n)
        assert set(got) == set(wanted[n]) and all(np.allclose(got[k], wanted[n][k]) for k in got)
    out = tmp_path / "out.csv"
    assert window.export_targets_csv(out)
    back = read_targets_csv(out)
    assert set(back) == set(names)
    for n in names:
        assert all(np.array_equal(back[n][k], wanted[n][k]) for k in wanted[n])
    # edit in the table: rename a target, delete one, add one
    panel = window.targets_panel
    panel.select_scan(names[0])
    first = panel.value(0, "Target")
    with qtbot.waitSignal(window.targetsChanged, timeout=5000):
        panel.table.item(0, 0).setText("renamed")
    assert "renamed" in window.targets_of(names[0]) and first not in window.targets_of(names[0])
    before = window.targets_of(names[0])
    with qtbot.waitSignal(panel.editRejected, timeout=5000):
        panel.table.item(0, 1).setText("not a number")
    qtbot.waitUntil(lambda: panel.table.item(0, 1).text() != "not a number", timeout=5000)
    assert window.last_error[0] == "Cannot change the target" and "not a number" in window.last_error[1]
    assert all(np.array_equal(before[k], v) for k, v in window.targets_of(names[0]).items())
    panel.table.selectRow(panel.row_of("renamed"))
    panel.delete_button.click()
    assert "renamed" not in window.targets_of(names[0])
    panel.add_button.click()
    assert len(window.targets_of(names[0])) == len(wanted[names[0]])
    # detected reflectors are named after the scan's targets
    truth = {
        f"T{t['id']}": np.array([t["x"], t["y"], t["z"]])
        for t in sim.truth["scans"][0]["targets_socs"]
        if t["n_points"] >= 5
    }
    rough = {k: v + np.array([0.05, -0.04, 0.02]) for k, v in truth.items()}
    window.set_targets(names[0], rough)
    with qtbot.waitSignal(window.reflectorsDetected, timeout=60_000) as detected:
        assert window.detect_reflectors(names[0])
    assert detected.args[1] >= 3
    got = window.targets_of(names[0])
    moved = [k for k in truth if np.linalg.norm(got[k] - truth[k]) < np.linalg.norm(rough[k] - truth[k])]
    assert len(moved) >= 3
    # a scan without targets gets R1, R2...
    window.set_targets(names[1], {})
    with qtbot.waitSignal(window.reflectorsDetected, timeout=60_000):
        assert window.detect_reflectors(names[1])
    assert "R1" in window.targets_of(names[1])


def test_compare_auto_and_manual(qtbot, window, open_project, plot, project_file: Path, tmp_path: Path) -> None:
    sim, _ = plot
    open_project(project_file)
    names = [s.name for s in window.project.scans]
    for i, n in enumerate(names):
        window.set_targets(n, picked_targets(sim, i))
    # to manual and back: an auto link without a result again
    window.set_link_method(names[2], "manual")
    assert window.project.link_of(names[2]).method == "manual"
    window.set_link_method(names[2], "auto")
    before = [(link.moving, link.method, link.result) for link in window.project.links]
    with qtbot.waitSignal(window.comparisonReady, timeout=RUN_TIMEOUT_MS) as ready:
        assert window.compare_auto_manual()
        assert not window.act_compare.isEnabled()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    comparison = ready.args[0]
    assert window.last_comparison is comparison and window.last_error is None
    # the window's auto links not run before keep the automatic results
    assert all(result is None for _, _, result in before)
    by_moving = {p["moving"]: p for p in comparison["pairs"]}
    for row, link in enumerate(window.project.links):
        assert link.method == "auto" and link.result["status"] == "ok"
        assert link.result["icp"]["std_m"] == pytest.approx(by_moving[link.moving]["auto"]["icp_std_m"])
        assert window.link_table.value(row, "Status") == "ok"
    view = window.comparison_view
    assert window.bottom_tabs.currentWidget() is window.comparison_tab and window.comparison_tab.widget() is view
    pairs = comparison["pairs"]
    assert view.pairs_table.rowCount() == len(pairs) == 2
    for row, pair in enumerate(pairs):
        assert pair["auto"]["status"] == "ok" and pair["manual"]["status"] == "ok", pair
        assert view.pairs_table.value(row, "ICP std auto (cm)") == pytest.approx(pair["auto"]["icp_std_m"])
        assert view.pairs_table.value(row, "ICP std manual (cm)") == pytest.approx(pair["manual"]["icp_std_m"])
        assert view.pairs_table.text(row, "ICP std auto (cm)") == f"{100 * pair['auto']['icp_std_m']:.2f}"
        assert view.pairs_table.text(row, "ICP std manual (cm)") == f"{100 * pair['manual']['icp_std_m']:.2f}"
        assert view.pairs_table.value(row, "Matched VOPs") == pair["auto"]["matched"]
        assert view.pairs_table.value(row, "Targets") == pair["manual"]["targets"] >= 3
        assert pair["rotation_difference_deg"] < 0.05 and pair["translation_difference_m"] < 0.02
    assert view.residual_table.value(0, "Auto (cm)") == pytest.approx(comparison["auto_target_residual_m"])
    assert view.residual_table.value(0, "Manual (cm)") == pytest.approx(comparison["manual_target_residual_m"])
    html = view.browser.toHtml()
    assert "tables 4 and 5" in html and html.count("forestreg-figure://") >= 2
    # a screenshot of the comparison view for the README
    window.resize(1500, 940)
    from PySide6.QtCore import Qt

    window.resizeDocks([window.results_dock], [520], Qt.Orientation.Vertical)
    qtbot.wait(300)
    window.scene_view.render_now()
    qtbot.wait(200)
    shot = tmp_path / "gui_compare.png"  # tests never write into docs/images
    assert window.grab().save(str(shot), "PNG", 0)  # 0: smallest file
    assert 20_000 < shot.stat().st_size < 500_000


def test_tie_points_side_by_side(qtbot, window, open_project, plot, project_file: Path) -> None:
    """The reference and the moving scan in two 3D views next to each other; a
    pick in either view is a target of that scan, the id waits for the other scan, the same id is
    highlighted in both, and the manual registration from those picks is within tolerance."""
    from scipy.spatial import cKDTree

    from forestreg.engine.core.transform import rigid_errors

    sim, _ = plot
    open_project(project_file)
    names = [s.name for s in window.project.scans]
    window.bottom_tabs.setCurrentWidget(window.targets_tab)
    tie = window.tie_view
    assert tie.pair == (names[0], names[1])  # the first moving scan and its link's reference
    for side, name in (("reference", names[0]), ("moving", names[1])):
        scene = tie.views[side].scene
        assert scene is not None and [c.name for c in scene.clouds] == [name]
        # drawn centred on its scanner: the drawn points are the file points minus the scanner
        scanner = window.scans(name).scanner_position_file
        pts = scene.clouds[0].points[:50].astype(float) + scanner
        d, _ = cKDTree(window.scans(name).file_points).query(pts)
        assert d.max() < 1e-3
    window.set_pick_mode(True)
    assert all(v.pick_mode for v in tie.views.values())
    panel = window.targets_panel
    for link_scans in ((names[0], names[1]), (names[0], names[2])):
        if link_scans[1] != tie.pair[1]:
            tie.combos["moving"].setCurrentText(link_scans[1])  # the user chooses the next pair
        assert tie.pair == link_scans
        ref_targets = picked_targets(sim, names.index(link_scans[0]))
        mov_targets = picked_targets(sim, names.index(link_scans[1]))
        for tid in sorted(set(ref_targets) & set(mov_targets)):
            panel.id_edit.setText(tid)
            for side, scan, targets in (
                ("reference", link_scans[0], ref_targets),
                ("moving", link_scans[1], mov_targets),
            ):
                display = targets[tid] - tie.scanners[side]  # what the view's point picker reports
                with qtbot.waitSignal(window.targetsChanged, timeout=5000) as changed:
                    tie.views[side].pointPicked.emit(display)
                assert changed.args[0] == scan
                assert window.targets_of(scan)[tid] == pytest.approx(targets[tid])
                # the id waits for the other scan, and is highlighted in both views
                assert panel.id_edit.text() == tid or side == "moving"
                assert tie.highlighted == tid and tid in tie.targets[side]
                assert tie.captions[side].text().endswith(f"target {tid} placed")
            # the targets table lists the scan picked last, with the picked coordinates
            assert panel.scan == link_scans[1]
            row = panel.row_of(tid)
            assert panel.value(row, "x (m)") == pytest.approx(mov_targets[tid][0])
    window.set_pick_mode(False)
    assert set(window.targets_of(names[1])) & set(window.targets_of(names[0]))
    panel.manual_all_button.click()
    with qtbot.waitSignal(window.runFinished, timeout=RUN_TIMEOUT_MS):
        assert window.run_manual()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    poses = window.project.poses()
    for row, link in enumerate(window.project.links):
        assert window.link_table.value(row, "Method") == "manual" and window.link_table.value(row, "Status") == "ok", (
            link.result
        )
        rot, trans = rigid_errors(poses[link.moving], sim.relative_pose(0, names.index(link.moving)))
        assert rot < 0.05 and trans < 0.02, (link.moving, rot, trans)
