"""The desktop window driven as a user would (pytest-qt), on a small simulated plot.

In-process windows use Qt's offscreen platform (tests/conftest.py), so their 3D view renders
images off screen; the two screenshot tests start ``python -m forestreg.ui.app`` in a separate
process: once with ``--offscreen`` and no display at all, once as a normal window under Xvfb
(pyvistaqt's OpenGL view), and check that the picture shows the points.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")

from PySide6.QtGui import QImage  # noqa: E402

from forestreg.engine.geometry.icp import IcpParams  # noqa: E402
from forestreg.engine.tls.params import RegistrationParams  # noqa: E402
from forestreg.engine.tls.project import Project  # noqa: E402

RUN_TIMEOUT_MS = 180_000
#: A registered copy of the test plot, left by test_run_fills_the_tables for the screenshot tests.
_REGISTERED: dict[str, Path] = {}


@pytest.fixture(scope="module")
def plot_dir(tmp_path_factory) -> Path:
    """Three simulated scans (0.4 deg) of a small mixed forest plot."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    folder = tmp_path_factory.mktemp("ui_plot")
    write_simulated_plot(
        simulate_plot("mixed_temperate", [(0, 0), (10, 2), (-8, 6)], seed=3, angular_step_deg=0.4, size_m=40), folder
    )
    return folder


def _params() -> RegistrationParams:
    return RegistrationParams(angular_step_deg=0.4, icp=IcpParams(voxel_m=0.1, iterations=30))


@pytest.fixture
def project_file(plot_dir: Path, scans_project) -> Path:
    """An unregistered project of the three scans, saved in the test's own folder."""
    return scans_project(plot_dir, "test plot", _params())


def test_run_fills_the_tables(qtbot, window, open_project, project_file: Path, tmp_path: Path) -> None:
    open_project(project_file)
    assert [window.link_table.rowCount(), window.scan_table.rowCount()] == [0, 3]
    assert window.scene_mode == "before" and len(window.scene_view.scene.clouds) == 3
    progress: list[tuple[float, str]] = []
    links_done: list[str] = []
    with qtbot.waitSignal(window.runFinished, timeout=RUN_TIMEOUT_MS) as finished:
        assert window.run()
        assert window.running and not window.act_run.isEnabled() and window.act_cancel.isEnabled()
        window.run_worker.progress.connect(lambda f, m: progress.append((f, m)))
        window.run_worker.link_done.connect(links_done.append)
        # the GUI thread keeps handling events: progress reaches the status bar during the run
        qtbot.waitUntil(
            lambda: window.progress_bar.value() > 0 and window.status_label.text() != "Registering\u2026",
            timeout=60_000,
        )
        window.set_scene_mode("before")
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    outcome = finished.args[0]
    project = window.project
    assert outcome.failed == [] and sorted(links_done) == ["scan_02.laz", "scan_03.laz"]
    assert progress and progress[-1][0] == pytest.approx(1.0)
    # links table = the engine's results
    table = window.link_table
    assert table.rowCount() == len(project.links) == 2
    for row, link in enumerate(project.links):
        assert table.value(row, "Moving") == link.moving
        assert table.value(row, "Status") == "ok" == link.result["status"]
        assert table.value(row, "Matched") == link.result["matched"] >= 4
        assert table.text(row, "Matched") == str(link.result["matched"])
        assert table.value(row, "Fine fit std (cm)") == pytest.approx(link.result["icp"]["std_m"])
        assert table.text(row, "Fine fit std (cm)") == f"{100 * link.result['icp']['std_m']:.2f}"
        assert table.value(row, "Overlap") == pytest.approx(link.result["icp"]["fitness"])
        assert table.value(row, "Search radius (m)") == link.result["vop_radius_m"]
    assert table.isColumnHidden(table.column("Reason"))  # no link has a reason: no empty column
    # scans table = the poses
    poses = project.poses()
    for row, scan in enumerate(project.scans):
        assert window.scan_table.value(row, "Scan") == scan.name
        assert window.scan_table.value(row, "State") in ("centre", "registered")
        assert window.scan_table.value(row, "x (m)") == pytest.approx(poses[scan.name][0, 3])
        assert window.scan_table.value(row, "y (m)") == pytest.approx(poses[scan.name][1, 3])
    # tree, 3D view (now after registration), top view with matched pairs
    states = [window.model.index(r, 1, window.model.index(0, 0)).data() for r in range(3)]
    assert states == ["centre", "registered", "registered"]
    assert window.scene_mode == "after" and window.act_after.isChecked()
    assert len(window.scene_view.scene.clouds) == 3 and window.scene_view.scene.point_count <= 200_000
    assert window.top_view.view is not None and sum(len(lv.pairs) for lv in window.top_view.view.links) >= 8
    # the engine saved the project after each link; the window after the run
    saved = Project.load(project_file)
    assert [link.result["matched"] for link in saved.links] == [link.result["matched"] for link in project.links]
    assert not window.dirty and window.act_export_report.isEnabled()
    # exports
    out = tmp_path / "out"
    out.mkdir()  # the exports run at once: the merged cloud must not wait for the poses to make it
    with qtbot.waitSignal(window.tasks.idle, timeout=60_000):
        window.export_poses(out)
        window.export_merged(out / "merged.laz")
        window.export_report(out / "report.html")
        window.export_e57(out / "registered.e57")
    assert window.last_error is None
    assert (out / "poses.json").is_file() and (out / "scan_02.laz.transform.txt").is_file()
    from forestreg.engine.io import read_scan

    assert len(read_scan(out / "merged.laz")) == sum(len(window.scans(s.name)) for s in project.scans)
    assert "scan_03.laz" in (out / "report.html").read_text()
    assert (out / "registered.e57").stat().st_size > 100_000
    with qtbot.waitSignal(window.tasks.idle, timeout=60_000):
        window.export_scans(out / "scans")
    assert window.last_error is None
    assert sorted(p.name for p in (out / "scans").iterdir()) == [f"scan_0{k}_registered.laz" for k in (1, 2, 3)]
    keep = tmp_path.parent / "registered_ui_plot.json"
    project.save(keep)
    _REGISTERED["project"] = keep


def test_cancel_stops_and_keeps_the_window_usable(qtbot, window, open_project, project_file: Path) -> None:
    open_project(project_file)
    before = project_file.read_text()
    with qtbot.waitSignal(window.runCancelled, timeout=RUN_TIMEOUT_MS):
        assert window.run()
        qtbot.waitUntil(
            lambda: window.progress_bar.isVisible() and "prepar" in window.status_label.text(), timeout=60_000
        )
        window.act_cancel.trigger()
    qtbot.waitUntil(lambda: not window.running, timeout=60_000)
    assert window.last_error is None
    assert all(link.result is None for link in window.project.links)
    assert project_file.read_text() == before
    assert window.act_run.isEnabled() and not window.act_cancel.isEnabled() and not window.cancel_button.isVisible()
    assert "cancelled" in window.status_label.text().lower()
    assert [window.link_table.value(r, "Status") for r in range(window.link_table.rowCount())] == ["not run"] * 2
    # still usable: edit and save
    window.model.set_centre("scan_02.laz")
    assert window.project.centre == "scan_02.laz" and window.dirty
    assert window.save_project()
    assert Project.load(project_file).centre == "scan_02.laz"


def test_an_unreadable_scan_fails_its_link_with_a_readable_reason(
    qtbot, window, open_project, plot_dir: Path, tmp_path: Path
) -> None:
    """A scan file that is gone fails its own link (the engine's rule), not the whole run; the
    reason shows in the links table, whose Reason column appears only now."""
    project = Project(name="broken", params=_params())
    project.add_scan(plot_dir / "scan_01.laz")
    project.add_scan(tmp_path / "gone.laz")
    path = project.save(tmp_path / "broken.json")
    open_project(path)
    assert "gone.laz" in window.scene_view.scene.missing
    table = window.link_table
    with qtbot.waitSignal(window.runFinished, timeout=RUN_TIMEOUT_MS):
        assert window.run()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    result = window.project.link_of("gone.laz").result
    assert result is not None and result["status"] == "failed" and "gone.laz" in result["reason"]
    row = [table.value(r, "Moving") for r in range(table.rowCount())].index("gone.laz")
    assert table.value(row, "Status") == "failed" and table.value(row, "Reason") == result["reason"]
    assert not table.isColumnHidden(table.column("Reason"))
    assert window.act_run.isEnabled()


def test_save_reopen_and_project_edits(qtbot, window, open_project, project_file: Path, tmp_path: Path) -> None:
    open_project(project_file)
    model = window.model
    model.set_tilted("scan_03.laz", True, "scan_02.laz")
    # drag scan_02 onto scan_03: link it there
    data = model.mimeData([model.index_of_scan("scan_02.laz")])
    from PySide6.QtCore import Qt

    assert model.canDropMimeData(data, Qt.DropAction.LinkAction, -1, -1, model.index_of_scan("scan_03.laz"))
    assert not model.canDropMimeData(data, Qt.DropAction.LinkAction, -1, -1, model.index_of_scan("scan_02.laz"))
    model.dropMimeData(data, Qt.DropAction.LinkAction, -1, -1, model.index_of_scan("scan_03.laz"))
    qtbot.waitUntil(lambda: window.project.link_of("scan_02.laz") is not None)
    assert window.project.link_of("scan_02.laz").reference == "scan_03.laz"
    # context menu: make scan_02 the centre
    menu = window.tree_menu(model.index_of_scan("scan_02.laz"))
    texts = [a.text() for a in menu.actions()]
    assert "Mark as centre scan" in texts and "Remove from project" in texts
    next(a for a in menu.actions() if a.text() == "Mark as centre scan").trigger()
    assert window.project.centre == "scan_02.laz" and window.project.link_of("scan_02.laz") is None
    assert model.index_of_scan("scan_02.laz").data().startswith("\u2605")
    window.params_panel.set_value("max_range_m", 25.0)
    assert window.project.params.max_range_m == 25.0 and window.dirty
    out = tmp_path / "copy" / "edited.json"
    out.parent.mkdir()
    assert window.save_project(out)
    assert not window.dirty and window.windowTitle().startswith("forestreg")
    assert window.recent_files()[0] == str(out.resolve())

    again = Project.load(out)
    assert again.centre == "scan_02.laz" and again.params == window.project.params
    assert again.scan("scan_03.laz").tilted and again.scan("scan_03.laz").level_partner == "scan_02.laz"
    assert [s.path for s in again.scans] == [s.path for s in window.project.scans]
    window.new_project()
    assert window.project.scans == []
    with qtbot.waitSignal(window.projectLoaded, timeout=10_000):
        assert window.open_project(out)
    assert window.params_panel.params() == again.params
    # a damaged file is refused, the open project stays
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    assert not window.open_project(bad)
    assert "damaged" in window.last_error[1] and window.project.path == out.resolve()
    assert bad.read_text() == "{ not json"
    # shortcuts, and settings kept for the next start
    assert [
        window.act_run.shortcut().toString(),
        window.act_cancel.shortcut().toString(),
        window.act_save.shortcut().toString(),
    ] == ["Ctrl+R", "Esc", "Ctrl+S"]
    window.resize(1234, 777)
    window.save_settings()
    from forestreg.ui.main_window import MainWindow

    second = MainWindow(settings=window.settings, interactive=False)
    qtbot.addWidget(second)
    assert second.recent_files()[0] == str(out.resolve())
    assert window.settings.value("window/geometry") is not None and window.settings.value("window/state") is not None
    assert [a.text().split(" ", 1)[1] for a in second.recent_menu.actions()][0] == str(out.resolve())


def test_parameter_panel_builds_the_params(qtbot) -> None:
    from forestreg.ui.params_panel import ParameterPanel

    panel = ParameterPanel()
    qtbot.addWidget(panel)
    assert panel.params() == RegistrationParams()
    flat = {row["name"]: row["default"] for row in RegistrationParams.table()}  # the ICP's as icp.voxel_m, ...
    assert set(panel.field_names()) == set(flat) and "icp.normal_neighbours" in flat
    assert "D_c" in panel.editor("max_range_m").toolTip() and panel.editor("max_range_m").suffix() == " m"
    wanted = RegistrationParams(
        max_range_m=25.0,
        slice_offsets_m=(0.0, 0.6),
        fallback_slice_offsets_m=(),
        follow_terrain=False,
        angular_step_deg=0.25,
        vop_radius_m=12.5,
        min_matched=5,
        icp=IcpParams(max_distances_m=(0.4, 0.1), normal_neighbours=20),
    )
    seen = []
    panel.paramsChanged.connect(seen.append)
    for name in flat:
        value: object = wanted
        for part in name.split("."):
            value = getattr(value, part)
        panel.set_value(name, value)
    assert panel.params() == wanted and seen[-1] == wanted
    assert panel.editor("icp.normal_neighbours").value() == 20
    count = len(seen)
    panel.editor("icp.max_distances_m").setText("")  # a nested field the engine refuses: marked, named
    assert not panel.message.isHidden() and "max_distances_m" in panel.message.text() and len(seen) == count
    assert "#fde2e1" in panel.editor("icp.max_distances_m").styleSheet()
    panel.editor("icp.max_distances_m").setText("0.4, 0.1")
    assert panel.message.isHidden() and panel.params() == wanted
    panel.set_value("vop_radius_m", None)
    assert panel.params() == wanted.replace(vop_radius_m=None)
    count = len(seen)
    panel.editor("slice_offsets_m").setText("0, a")
    assert not panel.message.isHidden() and "comma" in panel.message.text() and len(seen) == count
    panel.editor("slice_offsets_m").setText("0, 0.6")
    assert panel.message.isHidden()
    panel.set_params(RegistrationParams(), emit=True)
    assert seen[-1] == RegistrationParams()


def _registered_project(plot_dir: Path, tmp_path: Path) -> Path:
    """The project registered by the run test, or registered here when that test did not run."""
    if "project" in _REGISTERED and _REGISTERED["project"].is_file():
        return _REGISTERED["project"]
    from forestreg.engine.tls.plot import register_project

    project = Project(name="test plot", params=_params())
    for f in sorted(plot_dir.glob("scan_*.laz")):
        project.add_scan(f)
    register_project(project)
    return project.save(tmp_path / "registered.json")


def _check_screenshot(path: Path, view_rect: tuple[int, int, int, int]) -> None:
    img = QImage(str(path)).convertToFormat(QImage.Format.Format_RGB888)
    assert img.width() == 1400 and img.height() == 900
    ptr = img.constBits()
    arr = np.frombuffer(ptr, dtype=np.uint8).reshape(img.height(), img.bytesPerLine())[:, : img.width() * 3]
    arr = arr.reshape(img.height(), img.width(), 3)
    colours = np.unique(arr.reshape(-1, 3)[::7], axis=0)
    assert len(colours) > 300, f"only {len(colours)} distinct colours: the window looks blank"
    x, y, w, h = view_rect
    view = arr[y + 40 : y + h - 40, x + 10 : x + w - 10].reshape(-1, 3).astype(int)
    # the scan colours are saturated; the background gradient is grey-blue
    saturation = view.max(axis=1) - view.min(axis=1)
    assert (saturation > 80).sum() > 5000, "the 3D view shows no points"


def _screenshot(args: list[str], env: dict[str, str], out: Path) -> tuple[int, int, int, int]:
    cmd = [sys.executable, "-m", "forestreg.ui.app", *args, "--screenshot", str(out), "--size", "1400x900"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert out.is_file() and out.stat().st_size > 20_000
    line = next(ln for ln in done.stdout.splitlines() if ln.startswith("3d view:"))
    return tuple(int(v) for v in line.split(":")[1].split())  # type: ignore[return-value]


def test_offscreen_screenshot_without_a_display(plot_dir: Path, tmp_path: Path) -> None:
    project = _registered_project(plot_dir, tmp_path)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    out = tmp_path / "offscreen.png"
    rect = _screenshot(["--offscreen", "--project", str(project), "--run"], env, out)
    _check_screenshot(out, rect)


def test_interactive_window_screenshot_under_xvfb(plot_dir: Path, tmp_path: Path) -> None:
    if not os.environ.get("DISPLAY"):
        pytest.skip("no X display (pytest-xvfb starts one where Xvfb is installed)")
    project = _registered_project(plot_dir, tmp_path)
    env = dict(os.environ, QT_QPA_PLATFORM="xcb")
    env.pop("FORESTREG_3D", None)
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)  # the window's OpenGL view draws on the X display
    out = tmp_path / "window.png"
    rect = _screenshot(["--project", str(project)], env, out)
    _check_screenshot(out, rect)
