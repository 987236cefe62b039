"""Field registration in the desktop window: *File > Watch folder...* runs the folder watcher while
scans are copied into the folder one after another; each placed scan appears in the project tree,
its link in the links table, a scan of another plot is listed with the watcher's reason, and Cancel
leaves a whole plot folder. The plan's suggestions and the position where a scan that did not
link should be taken again are marked on the top view and stay through its redraws."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QSettings  # noqa: E402

from forestreg.engine.io import write_scan  # noqa: E402

NAMES = ("scan_01.laz", "scan_02.laz")
OTHER = "zz_other_plot.laz"


@pytest.fixture(scope="module")
def scans(tmp_path_factory, sim_plot) -> dict:
    """Two scans of a small simulated plot and one scan of another plot, as LAZ files."""
    folder = tmp_path_factory.mktemp("watch_scans")
    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (8.0, 2.0), (-7.0, 5.0), (2.0, -9.0)), seed=31, step=0.4, size=30.0)
    other = sim_plot("mixed_temperate", ((0.0, 0.0), (5.0, 0.0)), seed=33, step=0.4, size=30.0).scans[1].scan
    paths = {}
    for name, scan in zip(NAMES, plot.scans):
        write_scan(scan.scan, folder / name)
        paths[name] = folder / name
    write_scan(other, folder / OTHER)
    paths[OTHER] = folder / OTHER
    return paths


@pytest.fixture
def window(qtbot, tmp_path: Path):
    from forestreg.ui.main_window import MainWindow

    w = MainWindow(settings=QSettings(str(tmp_path / "settings.ini"), QSettings.Format.IniFormat), interactive=False)
    qtbot.addWidget(w)
    w.show()
    yield w
    w.cancel_run()
    qtbot.waitUntil(lambda: not w.busy, timeout=60_000)


def _status(window, name: str):
    return next((e.status for e in reversed(window.watch_events) if e.name == name), None)


def _map_texts(window) -> list[str]:
    """The texts drawn on the top view's map now (labels, annotations)."""
    axes = window.top_view.figure.axes
    return [t.get_text() for t in axes[0].texts] if axes else []


def _redrawn(qtbot, window) -> None:
    """The top view recomputed and drawn again, as after an edit or a run."""
    with qtbot.waitSignal(window.topViewReady, timeout=60_000):
        window.refresh_top_view()


def test_watch_folder_places_scans_as_they_arrive_and_cancel_leaves_the_folder_whole(
    qtbot, window, scans, tmp_path
) -> None:
    from forestreg.engine.core.atomic import TMP_PREFIX
    from forestreg.ui.watch_actions import WATCH_COLUMNS

    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    assert window.act_watch.isEnabled() and window.act_watch in window.menuBar().actions()[0].menu().actions()
    assert window.watch_folder(folder, out, poll_s=0.1)
    assert window.running and not window.act_watch.isEnabled()

    shutil.copyfile(scans[NAMES[0]], folder / NAMES[0])
    qtbot.waitUntil(lambda: _status(window, NAMES[0]) == "centre", timeout=60_000)
    qtbot.waitUntil(lambda: window.model.index_of_scan(NAMES[0]).isValid(), timeout=10_000)

    shutil.copyfile(scans[NAMES[1]], folder / NAMES[1])
    qtbot.waitUntil(lambda: _status(window, NAMES[1]) == "linked", timeout=60_000)
    qtbot.waitUntil(lambda: window.model.index_of_scan(NAMES[1]).isValid(), timeout=10_000)
    table = window.link_table
    assert table.rowCount() == 1
    assert (table.text(0, "Moving"), table.text(0, "Reference"), table.text(0, "Status")) == (NAMES[1], NAMES[0], "ok")

    shutil.copyfile(scans[OTHER], folder / OTHER)
    qtbot.waitUntil(lambda: _status(window, OTHER) == "refused", timeout=60_000)
    watch = window.watch_table
    assert watch.text(OTHER, "Status") == "refused"
    reason = watch.text(OTHER, "Reason / what to do")
    assert "shares no trunk shadows" in reason and "another plot" in reason
    assert watch.text(NAMES[1], "Linked to") == NAMES[0]
    assert watch.columnCount() == len(WATCH_COLUMNS)
    assert not window.model.index_of_scan(OTHER).isValid()  # set aside: not in the plot

    window.cancel_run()
    qtbot.waitUntil(lambda: not window.running, timeout=60_000)
    assert window.watch_run is not None and window.watch_run.stopped
    assert window.watch_run.placed == NAMES and OTHER in window.watch_run.aside
    poses = json.loads((out / "poses.json").read_text())["scans"]
    assert sorted(poses) == list(NAMES)
    state = json.loads((out / "watch.json").read_text())["files"]
    assert {n: f["status"] for n, f in state.items()} == {NAMES[0]: "centre", NAMES[1]: "linked", OTHER: "refused"}
    assert (out / "project.json").is_file() and not list(out.glob(TMP_PREFIX + "*"))
    assert [s.name for s in window.project.scans] == list(NAMES)
    assert window.act_watch.isEnabled()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)  # the views drawn for the last update

    # Plan next scan: app/plan.py's suggestions as markers on the map
    assert window.act_plan.isEnabled()
    assert window.plan_next_scan()
    qtbot.waitUntil(lambda: getattr(window, "last_plan", None) is not None, timeout=60_000)
    plan = window.last_plan
    assert plan.suggestions and window.top_view.plan_markers == len(plan.suggestions)
    assert window.status_label.text().startswith("Next scan")
    labels = [f"next {k}: links to {s.links_to}" for k, s in enumerate(plan.suggestions, 1)]
    o = window.top_view.view.origin[:2]
    for label, s in zip(labels, plan.suggestions):
        assert window.top_view.mark_labels[label] == pytest.approx((s.x - o[0], s.y - o[1]))

    # the marks are the top view's state: a re-render and the plot folder read again keep them
    _redrawn(qtbot, window)
    assert window.top_view.plan_markers == len(plan.suggestions) and set(labels) <= set(_map_texts(window))
    from forestreg.app.plot import Project

    window.set_project(Project.load(out / "project.json"))
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    assert set(labels) <= set(_map_texts(window)) and window.top_view.plan_markers == len(plan.suggestions)
    window.grab().save(str(tmp_path / "watch.png"))
    window.top_view.grab().save(str(tmp_path / "plan_map.png"))
    # another project: the plan is gone with it
    window.set_project(Project(name="other"))
    assert window.top_view.plan_markers == 0 and not window.top_view.has_marks


def test_a_scan_that_does_not_link_shows_the_reason_and_where_to_stand(qtbot, window, scans, tmp_path) -> None:
    """With an ICP fitness no pair reaches, the second scan shares trunk shadows with the centre
    scan but does not link: the Watch tab gives the watcher's reason and the position that links."""
    from forestreg.engine.tls.params import RegistrationParams

    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    shutil.copyfile(scans[NAMES[0]], folder / NAMES[0])
    window.params_panel.set_params(RegistrationParams(icp_min_fitness=0.99))
    assert window.watch_folder(folder, out, poll_s=0.1)
    qtbot.waitUntil(lambda: _status(window, NAMES[0]) == "centre", timeout=60_000)
    shutil.copyfile(scans[NAMES[1]], folder / NAMES[1])
    qtbot.waitUntil(lambda: _status(window, NAMES[1]) == "not linked", timeout=60_000)
    event = window.watch_events[-1]
    watch = window.watch_table
    reason = watch.text(NAMES[1], "Reason / what to do")
    assert reason.startswith(event.reason) and "ICP fitness" in reason
    assert reason.endswith(f"stand between them, near ({event.advice[0]:.1f}, {event.advice[1]:.1f})")
    assert watch.text(NAMES[1], "Suggested position (x, y m)") == f"{event.advice[0]:.1f}, {event.advice[1]:.1f}"
    qtbot.waitUntil(lambda: window.model.index_of_scan(NAMES[0]).isValid(), timeout=10_000)
    assert not window.model.index_of_scan(NAMES[1]).isValid()

    # the map marks where to scan again, labelled with the scan's name, over the centre scan
    label = f"{NAMES[1]}: not linked, scan again here"
    qtbot.waitUntil(lambda: label in _map_texts(window), timeout=60_000)
    o = window.top_view.view.origin[:2]
    assert window.top_view.mark_labels[label] == pytest.approx((event.advice[0] - o[0], event.advice[1] - o[1]))
    assert NAMES[0] in _map_texts(window), "drawn over the placed centre scan"
    window.cancel_run()
    qtbot.waitUntil(lambda: not window.running, timeout=60_000)
    assert json.loads((out / "watch.json").read_text())["files"][NAMES[1]]["status"] == "not linked"
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    _redrawn(qtbot, window)  # still there after the map is drawn again
    assert label in _map_texts(window) and label in window.top_view.mark_labels
    window.top_view.grab().save(str(tmp_path / "advice_map.png"))
