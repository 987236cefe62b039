"""The Co-registration tab: a run in a worker (progress, Cancel), the evidence shown against the
simulator's truth, accept, fusion with the counts per source, and a result folder."""

from __future__ import annotations

import functools

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvista")
pytest.importorskip("pytestqt")


TIMEOUT_MS = 400_000


@functools.lru_cache(maxsize=None)
def _case():
    from forestreg.engine.simulate.platforms import simulate_coregistration_case

    return simulate_coregistration_case(
        "planted_conifer",
        seed=0,
        size_m=28.0,
        ground_platform="backpack",
        heading_deg=120.0,
        offset_m=(5.0, -5.0, 1.0),
        uav_density_scale=0.3,
        backpack_density_scale=0.1,
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from forestreg.engine.io import write_scan

    case = _case()
    folder = tmp_path_factory.mktemp("ui_coreg")
    write_scan(case.ground, folder / "ground.laz")
    write_scan(case.uav, folder / "uav.laz")
    return case, folder / "ground.laz", folder / "uav.laz"


def test_cancel_stops_the_run(qtbot, window, files):
    _, ground, uav = files
    view = window.coreg_view
    window.show_tab("Co-registration")
    view.run(str(ground), str(uav))
    assert view.cancel_button.isVisible() and not view.run_button.isEnabled()
    view.cancel()
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.shown is None and "cancelled" in view.headline.text()
    assert view.run_button.isEnabled() and not view.cancel_button.isVisible()


@pytest.mark.slow
def test_run_accept_and_fuse(qtbot, window, files, tmp_path):
    from forestreg.engine.core.transform import rigid_errors
    from forestreg.engine.io import read_scan

    case, ground, uav = files
    view = window.coreg_view
    window.show_tab("Co-registration")
    seen: list[str] = []
    view.progress.valueChanged.connect(lambda v: seen.append(view.progress.format()))
    view.run(str(ground), str(uav))
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    assert view.shown is not None and view.shown.ok, view.headline.text()
    assert len(seen) > 3
    s = view.shown.summary
    rot, trans = rigid_errors(view.shown.matrix, case.matrix)
    assert rot < 0.1 and trans < 0.05
    assert view.value("Matched keypoints") == s.matched >= 3
    assert view.value("Canopy surface correlation") == pytest.approx(s.surface_correlation)
    assert view.value("Margin over the alternative") == pytest.approx(s.surface_correlation - s.alternative_correlation)
    assert view.value("Margin over the alternative") > 0.2
    assert view.picture.pixmap() is not None and not view.picture.pixmap().isNull()
    assert not view.fuse_button.isEnabled()  # only an accepted transform is fused
    view.decide("accepted")
    assert view.fuse_button.isEnabled()
    out = tmp_path / "fused.laz"
    view.fuse(str(out))
    qtbot.waitUntil(lambda: view.worker is None, timeout=TIMEOUT_MS)
    counts = view.fusion_counts
    assert counts is not None, view.headline.text()
    assert len(read_scan(out)) == counts["total"].kept == counts["ground"].kept + counts["uav"].kept
    for source, n in (("ground", len(case.ground)), ("uav", len(case.uav))):
        c = counts[source]
        assert c.input == n and c.kept == n - c.redundant - c.noise
        assert f"{c.kept:,} kept" in view.fusion_label.text()
