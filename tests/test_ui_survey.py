"""Survey quality in the desktop window: the pose uncertainty, terrain agreement,
ambiguity and dropped links that the survey registration computes, in the results tables and on
the 2D top view, checked cell by cell against the engine's values.

A small simulated plot of three scans is registered as a survey (all pairs); the extra link
between the two outer scans is then spoilt (6 deg and 1 m off, a plausible wrong answer) so the
adjustment has a link to drop.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")

from matplotlib.colors import to_hex  # noqa: E402
from PySide6.QtCore import QSettings  # noqa: E402

from forestreg.app.plot import PoseSigma  # noqa: E402
from forestreg.engine.core.transform import matrix_from_yaw  # noqa: E402
from forestreg.engine.geometry.icp import IcpParams  # noqa: E402
from forestreg.engine.tls.params import RegistrationParams  # noqa: E402
from forestreg.engine.tls.plot import ScanCache, pose_uncertainty  # noqa: E402
from forestreg.engine.tls.project import Project  # noqa: E402
from forestreg.engine.tls.survey import SurveyParams, register_survey  # noqa: E402


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory) -> Project:
    """A survey of three simulated scans with one spoilt (then dropped) extra link, saved."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    folder = tmp_path_factory.mktemp("ui_survey")
    write_simulated_plot(
        simulate_plot("mixed_temperate", [(0, 0), (10, 2), (-8, 6)], seed=3, angular_step_deg=0.4, size_m=40), folder
    )
    project = Project(
        name="survey plot", params=RegistrationParams(angular_step_deg=0.4, icp=IcpParams(voxel_m=0.1, iterations=30))
    )
    for f in sorted(folder.glob("scan_*.laz")):
        project.add_scan(f)
    scans = ScanCache(project)
    register_survey(project, SurveyParams(pairs="all"), scans=scans)
    poses = project.poses()
    extra = next(link for link in project.links if link.extra)
    own = project.link_of(extra.moving)
    at = scans(extra.reference).scanner_position_file
    about = np.eye(4)
    about[:3, 3] = -at
    true = np.linalg.inv(poses[extra.reference]) @ poses[extra.moving]
    spoilt = matrix_from_yaw(6.0, at + np.array([1.0, 0.0, 0.0])) @ about @ true
    extra.result = dict(
        copy.deepcopy(own.result),
        reference=extra.reference,
        matrix=spoilt.tolist(),
        uncertainty={"translation_m": 0.05, "rotation_deg": 0.3},
    )
    register_survey(project, SurveyParams(pairs="centre"), scans=scans)
    assert [(d["moving"], d["reference"]) for d in project.adjustment["dropped"]] == [(extra.moving, extra.reference)]
    project.save(folder / "survey.json")
    return project


@pytest.fixture
def window(qtbot, tmp_path: Path):
    from forestreg.ui.main_window import MainWindow

    w = MainWindow(settings=QSettings(str(tmp_path / "settings.ini"), QSettings.Format.IniFormat), interactive=False)
    qtbot.addWidget(w)
    w.show()
    yield w
    w.cancel_run()
    qtbot.waitUntil(lambda: not w.busy, timeout=60_000)


def test_survey_quality_in_the_tables_and_on_the_map(qtbot, window, surveyed: Project) -> None:
    from forestreg.ui.results_tables import LINK_TIPS
    from forestreg.ui.top_view import DROPPED_COLOUR, uncertainty_scale

    with qtbot.waitSignal(window.topViewReady, timeout=120_000):
        assert window.open_project(surveyed.path)
    qtbot.waitUntil(lambda: not window.busy and window.top_view.view is not None, timeout=120_000)
    project = window.project
    dropped = {(d["moving"], d["reference"]): d["reason"] for d in project.adjustment["dropped"]}
    quality = project.adjustment["quality"]

    # links table: each link's own figures and the dropped one
    table = window.link_table
    assert table.rowCount() == 3
    for name in ("Pose uncertainty (cm / deg)", "Terrain agreement (cm)", "Ambiguity", "Dropped"):
        c = table.column(name)
        assert not table.isColumnHidden(c)
        assert table.horizontalHeaderItem(c).toolTip() == LINK_TIPS[name] != ""
    for row, link in enumerate(project.links):
        u = link.result["uncertainty"]
        assert table.value(row, "Pose uncertainty (cm / deg)") == pytest.approx((u["translation_m"], u["rotation_deg"]))
        assert (
            table.text(row, "Pose uncertainty (cm / deg)")
            == f"{100 * u['translation_m']:.2f} / {u['rotation_deg']:.3f}"
        )
        q = link.result["quality"]
        assert table.value(row, "Terrain agreement (cm)") == pytest.approx(q["terrain_median_m"])
        assert q["terrain_median_m"] < 0.05  # the simulated scans agree on the ground within centimetres
        assert table.value(row, "Ambiguity") == pytest.approx(q["ambiguity"])
        key = (link.moving, link.reference)
        item = table.item(row, table.column("Dropped"))
        if key in dropped:
            assert item.text() == "dropped" and item.toolTip() == dropped[key]
            assert to_hex(item.foreground().color().name()) == DROPPED_COLOUR
        else:
            assert item.text() == "" and table.value(row, "Dropped") is None

    # scans table: the propagated pose uncertainty and the per-scan quality
    engine_u = pose_uncertainty(project)
    scans = window.scan_table
    for row, s in enumerate(project.scans):
        u = engine_u[s.name]
        assert scans.value(row, "Pose uncertainty (cm / deg)") == pytest.approx((u["translation_m"], u["rotation_deg"]))
        q = quality[s.name]
        assert scans.value(row, "Dropped") == q["dropped_links"]
        assert scans.value(row, "Ambiguity") == pytest.approx(q["max_ambiguity"])
        assert scans.value(row, "Terrain agreement (cm)") == pytest.approx(q["terrain_median_m"])
        assert scans.value(row, "Loop residual (cm)") == pytest.approx(q["max_residual_m"])
    centre = [r for r, s in enumerate(project.scans) if s.name == project.centre][0]
    assert scans.value(centre, "Pose uncertainty (cm / deg)") == (0.0, 0.0)
    # the two scans of the dropped link each count it; the centre scan does not
    assert sorted(scans.value(r, "Dropped") for r in range(3)) == [0, 1, 1]

    # the project tree says which link was dropped
    links_group = window.model.index(1, 0)
    texts = [window.model.index(r, 1, links_group).data() for r in range(window.model.rowCount(links_group))]
    assert sum(t.endswith(", dropped") for t in texts) == 1

    # the map: a label per scanner with the engine's figures, the dropped link red and dashed
    top = window.top_view
    assert top.overlay is not None and top.overlay.dropped == dropped
    for name, u in engine_u.items():
        if name == project.centre:
            assert top.uncertainty_labels[name] == "frame scan"
        else:
            assert (
                top.uncertainty_labels[name]
                == f"\u00b1{100 * u['translation_m']:.1f} cm, {u['rotation_deg']:.2f}\u00b0"
            )
    assert top.uncertainty_factor == uncertainty_scale({n: PoseSigma.of(u) for n, u in engine_u.items()}) > 1
    ax = top.figure.axes[0]
    o = top.view.origin[:2]
    ((moving, reference),) = dropped
    red = [line for line in ax.lines if to_hex(line.get_color()) == DROPPED_COLOUR]
    assert len(red) == 1 and red[0].get_linestyle() == "--"
    xy = np.column_stack(red[0].get_data())
    expected = np.array([top.view.scans[moving].scanner[:2], top.view.scans[reference].scanner[:2]]) - o
    assert np.allclose(xy, expected)
    # uncertainty circles: drawn at the scanners, radius = 1 sigma x the stated factor
    circles = {tuple(np.round(p.center, 6)): p.radius for p in ax.patches if hasattr(p, "radius") and p.get_fill()}
    for name, u in engine_u.items():
        if name == project.centre:
            continue
        c = tuple(np.round(top.view.scans[name].scanner[:2] - o, 6))
        assert circles[c] == pytest.approx(u["translation_m"] * top.uncertainty_factor)
    legend = [t.get_text() for t in top.figure.legends[0].get_texts()]
    assert any("dropped link" in t for t in legend) and any("pose uncertainty" in t for t in legend)


def test_link_table_names_the_weak_motion_and_the_alternative(qtbot, surveyed: Project, tmp_path: Path) -> None:
    """A link whose uncertainty counted a weak motion and a distinct solution shows both, short in
    the cell and whole in its tooltip."""
    from forestreg.engine.core.uncertainty import Alternative, WeakDirection
    from forestreg.ui.results_tables import LinkResultsTable

    project = copy.deepcopy(surveyed)
    link = next(link for link in project.links if link.result is not None and link.result.get("status") == "ok")
    weak = WeakDirection("translation", (0.0, 1.0, 0.0), 0.004, 90.0)
    alternative = Alternative(
        weight=0.05,
        offset_m=3.45,
        offset_deg=0.02,
        support=7,
        chosen_support=9,
        direction_deg=97.0,
        pattern="5 of the 9 matched trunks repeat themselves 3.45 m along 97 deg: regular rows (posts, columns, a planted grid)",
    )
    excluded = Alternative(
        weight=0.0,
        offset_m=16.2,
        offset_deg=180.0,
        support=4,
        chosen_support=9,
        status="excluded: it fails its checks (ICP fitness 0.05 is below 0.10)",
    )
    link.result = dict(
        link.result,
        uncertainty=dict(
            link.result["uncertainty"],
            weak_directions=[weak.to_dict()],
            alternatives=[alternative.to_dict(), excluded.to_dict()],
        ),
    )
    table = LinkResultsTable()
    qtbot.addWidget(table)
    table.show_project(project)
    row = project.links.index(link)
    text = table.text(row, "Weak motion / alternative")
    assert text == (
        "free translation along 90 deg; alternative 3.45 m along 97 deg, 0.02 deg (counted); "
        "alternative 16.20 m, 180.00 deg (excluded)"
    )
    tip = table.item(row, table.column("Weak motion / alternative")).toolTip()
    assert "walls, a row or a fence along it" in tip and "regular rows" in tip and "ICP fitness 0.05" in tip
    table.resize(1800, 200)
    table.grab().save(str(tmp_path / "links.png"))
