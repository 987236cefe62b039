"""Pair registration against ground truth: simulated plots with known poses, and real clouds."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.tls.pair import register
from forestreg.engine.tls.params import RegistrationParams

FINE_ROTATION_DEG = 0.05
FINE_TRANSLATION_M = 0.02
COARSE_ROTATION_DEG = 0.5
COARSE_TRANSLATION_M = 0.25


def _check_against_truth(result, truth) -> None:
    assert result.ok, result.reason
    rot, trans = rigid_errors(result.matrix, truth)
    assert rot < FINE_ROTATION_DEG, f"rotation error {rot:.4f} deg"
    assert trans < FINE_TRANSLATION_M, f"translation error {100 * trans:.2f} cm"
    crot, ctrans = rigid_errors(result.coarse_matrix, truth)
    assert crot < COARSE_ROTATION_DEG, f"coarse rotation error {crot:.3f} deg"
    assert ctrans < COARSE_TRANSLATION_M, f"coarse translation error {ctrans:.3f} m"
    assert result.matched >= 4
    assert result.matched - (result.second_matched or 0) >= 2
    assert result.icp.std_m < 0.03
    assert set(result.timings) >= {
        "prepare_reference_s",
        "prepare_moving_s",
        "slice_s",
        "vops_s",
        "coarse_s",
        "vertical_s",
        "icp_s",
    }


@pytest.mark.parametrize(
    "preset, offset, seed",
    [
        ("planted_conifer", (9.0, 4.0), 1),
        ("mixed_temperate", (12.0, -3.0), 2),
        ("rainforest", (7.0, 2.0), 3),
        ("sloped", (10.0, 3.0), 4),
    ],
)
def test_presets_register_to_truth(sim_plot, preset, offset, seed):
    plot = sim_plot(preset, ((0.0, 0.0), offset), seed=seed)
    ref, mov = plot.scans
    result = register(ref.scan, mov.scan)
    _check_against_truth(result, plot.relative_pose(0, 1))


def test_pair_twenty_metres_apart(sim_plot):
    plot = sim_plot("mixed_temperate", ((-10.0, 0.0), (10.0, 1.0)), seed=5, size=60.0)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    _check_against_truth(result, plot.relative_pose(0, 1))
    assert result.vop_radius_m >= 20.0


def test_a_densified_pair_is_prepared_at_its_scan_resolution_and_registers_alike(sim_plot):
    """Each scan repeated four times with 2 mm jitter (a finer or densified file of the same
    scene): the preparation thins it back to about one point per angular pixel, and the pair
    registers to the truth, within a hundredth of a degree and 2 mm of the original pair."""
    import dataclasses

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    ref, mov = plot.scans
    rng = np.random.default_rng(3)

    def densified(scan):
        copies = [scan.points] + [scan.points + rng.uniform(-0.002, 0.002, scan.points.shape) for _ in range(3)]
        return dataclasses.replace(scan, points=np.concatenate(copies), intensity=None)

    original = register(ref.scan, mov.scan)
    dense = register(densified(ref.scan), densified(mov.scan))
    _check_against_truth(dense, plot.relative_pose(0, 1))
    rot, trans = rigid_errors(dense.matrix, original.matrix)
    assert rot < 0.01 and trans < 0.002, (rot, trans)
    for a, b in (
        (dense.details.reference, original.details.reference),
        (dense.details.moving, original.details.moving),
    ):
        assert len(b.points) <= len(a.points) < 1.3 * len(b.points)  # a copy jittered across a pixel edge stays


def test_level_scan_to_tilted_scan_at_the_same_spot(sim_plot):
    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (0.3, 0.2)), seed=6, tilted=((1, 30.0),))
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    assert result.moving_tilt_deg == pytest.approx(30.0, abs=3.0)
    assert result.reference_tilt_deg == 0.0
    _check_against_truth(result, plot.relative_pose(0, 1))


def test_a_scene_without_trees_fails_with_a_reason(sim_plot):
    plot = sim_plot("open_field", ((0.0, 0.0), (10.0, 0.0)), seed=7)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    assert result.status == "failed"
    assert result.matrix is None and result.coarse_matrix is None
    assert "visual occlusion points" in result.reason


def test_scans_of_different_plots_fail_rather_than_guess(sim_plot):
    a = sim_plot("mixed_temperate", ((0.0, 0.0), (10.0, 0.0)), seed=8)
    b = sim_plot("mixed_temperate", ((0.0, 0.0), (10.0, 0.0)), seed=9)
    result = register(a.scans[0].scan, b.scans[1].scan)
    assert result.status == "failed", f"registered unrelated plots: {result.matched} matched"
    assert result.matrix is None


def test_inputs_are_not_modified(sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    ref, mov = plot.scans[0].scan, plot.scans[1].scan
    before = ref.points.copy(), mov.points.copy()
    register(ref, mov, RegistrationParams(vop_radius_m=15.0))
    assert np.array_equal(ref.points, before[0]) and np.array_equal(mov.points, before[1])


def test_given_radius_is_used_and_reported(sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    result = register(plot.scans[0].scan, plot.scans[1].scan, RegistrationParams(vop_radius_m=15.0))
    assert result.vop_radius_m == 15.0
    assert [a["vop_radius_m"] for a in result.attempts] == [15.0]
    _check_against_truth(result, plot.relative_pose(0, 1))


def test_a_chance_match_between_unrelated_plots_is_refused(sim_plot):
    """Planted trees and a mixed plot share no trunk, but with three slice layers their VOPs give
    a chance match that survives the VOP evidence; the free-space check refuses it."""
    planted = sim_plot("planted_conifer", ((0.0, 0.0),), seed=49, size=60.0)
    mixed = sim_plot("mixed_temperate", ((3.0, 1.0),), seed=50, size=60.0)
    params = RegistrationParams(slice_offsets_m=(0.0, 0.6, 1.2))
    result = register(planted.scans[0].scan, mixed.scans[0].scan, params)
    assert result.status == "failed" and result.matrix is None
    assert "empty space" in result.reason or "chance" in result.reason or "ambiguous" in result.reason


def test_free_space_violation_is_small_for_a_correct_registration(sim_plot):
    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (12.0, -3.0)), seed=2)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    assert result.ok and result.free_space_violation is not None and result.free_space_violation < 0.1


def test_scans_read_by_the_engine_are_let_go_once_centred(sim_plot, monkeypatch):
    """Scans given as readers: each scan's own points are gone before its levelling and grids
    (only the float32 centred copy is held), and the result is that of the scans given whole."""
    import dataclasses
    import gc
    import threading
    import weakref

    from forestreg.engine.tls import pair as pair_module

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    ref, mov = plot.scans
    raw: list = []  # weak references to the points each reader made

    def reader(scan):
        def read():
            copy = dataclasses.replace(scan.scan, points=scan.scan.points.copy())
            raw.append(weakref.ref(copy.points))
            return copy

        return read

    centring: dict = {}  # thread -> the raw points it centred
    alive: list[bool] = []
    real_centre, real_prepare = pair_module.centre_scan, pair_module.prepare_centred

    def centre(points, *args, **kwargs):
        centring[threading.get_ident()] = next(r for r in raw if r() is points)
        return real_centre(points, *args, **kwargs)

    def prepare(*args, **kwargs):
        gc.collect()
        alive.append(centring[threading.get_ident()]() is not None)
        return real_prepare(*args, **kwargs)

    monkeypatch.setattr(pair_module, "centre_scan", centre)
    monkeypatch.setattr(pair_module, "prepare_centred", prepare)
    read = register(reader(ref), reader(mov))
    monkeypatch.undo()
    whole = register(ref.scan, mov.scan)
    assert len(raw) == 2 and alive == [False, False]
    np.testing.assert_array_equal(read.matrix, whole.matrix)
    _check_against_truth(read, plot.relative_pose(0, 1))


@pytest.mark.parametrize("turn_deg, shift_m", [(8.0, 1.5), (3.0, 0.8), (0.0, 1.0)])
def test_free_space_check_refuses_a_plausible_wrong_pose(sim_plot, turn_deg, shift_m):
    # the same pair, the registration moved by a wrong link's error (turned about the reference
    # scanner, shifted): the moving scan's points at the reference's slice heights stand in the
    # reference scanner's free space far beyond what a correct pose leaves (< 10 %)
    from forestreg.engine.tls.evidence import mutual_free_space_violation

    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (12.0, -3.0)), seed=2)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    d = result.details
    params = RegistrationParams()
    right, _ = mutual_free_space_violation(
        d.reference, d.moving, d.reference_layers, d.moving_layers, d.lsf_matrix, params
    )
    wrong = np.eye(4)
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    wrong[:2, :2] = [[c, -s], [s, c]]
    wrong[:2, 3] = (shift_m * 0.6, shift_m * 0.8)
    violation, tested = mutual_free_space_violation(
        d.reference, d.moving, d.reference_layers, d.moving_layers, wrong @ d.lsf_matrix, params
    )
    assert right < 0.1 and tested >= 100
    assert violation > params.max_free_space_violation, (right, violation)


def test_each_scans_vops_are_found_once_in_the_thread_that_prepared_it(sim_plot, monkeypatch):
    """The slice layers and VOPs of each scan at every radius are made once, in the thread that
    prepared the scan (the first scan's while the second is still read or prepared), and the
    coarse attempts use those: the result is that of the scans found after both were prepared."""
    import threading

    from forestreg.engine.tls import pair as pair_module

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    ref, mov = plot.scans
    made: list = []  # (thread, layers' first point, radius) per extraction
    real_extract = pair_module.extract_vops

    def extract(layers, params, radius):
        made.append((threading.current_thread().name, layers[0].xyz[:1].tobytes(), radius))
        return real_extract(layers, params, radius)

    monkeypatch.setattr(pair_module, "extract_vops", extract)
    result = register(ref.scan, mov.scan)
    monkeypatch.undo()
    radii = pair_module.vop_radii(RegistrationParams())
    assert len(made) == 2 * len(radii) and len({(scan, radius) for _, scan, radius in made}) == 2 * len(radii)
    assert all(name.startswith("forestreg-vops") for name, _, _ in made)
    assert [a.radius_m for a in result.details.attempts] == list(radii)
    _check_against_truth(result, plot.relative_pose(0, 1))


def test_a_pair_on_one_core_runs_no_second_thread_and_gives_the_same_matrix(sim_plot, monkeypatch):
    """With one core allowed (``FORESTREG_THREADS=1``, a batch's ``--threads 1``) the two scans'
    work runs one after the other: one VOP thread (the caller waits for it), no ICP-grid thread
    beside the pair, and the matrices are bit for bit those of the two-thread run."""
    import threading

    from forestreg.engine.tls import pair as pair_module

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    ref, mov = plot.scans
    two = register(ref.scan, mov.scan)
    names: list = []
    real_extract = pair_module.extract_vops

    def extract(layers, params, radius):
        names.append(threading.current_thread().name)
        return real_extract(layers, params, radius)

    monkeypatch.setattr(pair_module, "extract_vops", extract)
    monkeypatch.setenv("FORESTREG_THREADS", "1")
    before = {t.name for t in threading.enumerate()}
    one = register(ref.scan, mov.scan)
    assert names and set(names) <= {"forestreg-vops_0"}, names
    assert not any(t.name.startswith("forestreg-icp-grid") for t in threading.enumerate() if t.name not in before)
    assert np.array_equal(one.matrix, two.matrix) and np.array_equal(one.coarse_matrix, two.coarse_matrix)
    _check_against_truth(one, plot.relative_pose(0, 1))


@pytest.mark.parametrize("threads, started", [("1", False), ("2", True)])
def test_background_imports_only_with_a_second_core(monkeypatch, threads, started):
    """A use case loads its report modules and kernels in a second thread while it reads; a
    process allowed one core (a batch's ``--threads 1``) starts no such thread."""
    import threading

    from forestreg.app.common import import_in_background

    names: list = []
    real_start = threading.Thread.start

    def start(self):
        names.append(self.name)
        return real_start(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    monkeypatch.setenv("FORESTREG_THREADS", threads)
    import_in_background(".engine.report.figures")
    assert ("forestreg-imports" in names) == started, names


@pytest.mark.parametrize("failed, long_name", [(False, False), (True, False), (False, True)])
def test_pair_figure_keeps_each_title_over_its_own_panel(sim_plot, tmp_path, failed, long_name):
    """The pair figure: every title, a long failure reason's or scan name's too (wrapped on two
    lines), lies over its own panel and inside the image; the panels hold what they show (the
    scanner, the VOPs in the scans' colours, the matched pairs in green); the PNG is written at
    its size."""
    import dataclasses

    from PIL import Image

    from forestreg.engine.report import figures
    from forestreg.engine.report.topview import rgb
    from forestreg.engine.report.views import MOVING_COLOUR, REFERENCE_COLOUR

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    if failed:
        reason = "ambiguous: the best solution matches 12 VOPs and a different one 11 (need a margin of 3) - regular planting or too few common trunks"
        result = dataclasses.replace(result, status="failed", reason=reason)
    if long_name:  # a real scan's name (../shared/data): its title takes two lines
        result = dataclasses.replace(result, reference_name="TLS_scan_scanner_at_origin")
    canvas, panels = figures.draw_pair(result)
    width, height = canvas.image.size
    for panel in panels:
        x0, y0, x1, y1 = panel.title_box
        assert panel.left - 30 <= x0 and x1 <= panel.right + 30 and y0 >= 0
        assert 0 <= panel.left < panel.right <= width and 0 <= panel.top < panel.bottom <= height
    assert panels[0].right < panels[1].left and panels[1].right < panels[2].left
    one_line = panels[1].title_box[3] - panels[1].title_box[1]
    assert (
        panels[2].title_box[3] - panels[2].title_box[1]
    ) > 1.5 * one_line  # the reason, or the stated uncertainty, on a second line
    assert ((panels[0].title_box[3] - panels[0].title_box[1]) > 1.5 * one_line) == long_name
    pixels = np.asarray(canvas.image)

    def colours_near(panel, xy, reach=12):
        ((x, y),) = panel.to_px(np.asarray(xy, dtype=float).reshape(1, 2)).astype(int)
        return {tuple(p) for p in pixels[y - reach : y + reach, x - reach : x + reach].reshape(-1, 3)}

    att = result.details.chosen
    assert (0, 0, 0) in colours_near(panels[0], (0.0, 0.0), 4)  # the reference scanner
    assert rgb(REFERENCE_COLOUR) in colours_near(panels[0], att.reference_vops.xy[0])
    assert rgb(MOVING_COLOUR) in colours_near(panels[1], att.moving_vops.xy[0])
    pairs = np.asarray(att.match.matched_pairs).reshape(-1, 2)
    assert rgb("#2ca02c") in colours_near(panels[2], att.reference_vops.xy[pairs[0, 0]])
    figures.pair_figure(result, tmp_path / "pair.png")
    with Image.open(tmp_path / "pair.png") as png:
        assert png.size == (canvas.width, canvas.height) == (1980, 682)
    assert (tmp_path / "pair.png").stat().st_size > 10_000


def test_the_pair_figure_needs_no_matplotlib():
    """``forestreg register`` draws its figure without importing matplotlib (~0.3 s of CPU)."""
    import subprocess
    import sys

    code = "import sys; import forestreg.engine.report.figures; print(any(m.split('.')[0] == 'matplotlib' for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_pair_figure_of_a_result_without_a_finite_matrix(sim_plot, tmp_path):
    """A failed result whose matrix holds NaN still gets its figure (the scans' own panels and the
    reference's in the third), not an error."""
    import dataclasses

    from PIL import Image

    from forestreg.engine.report import figures

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    result = register(plot.scans[0].scan, plot.scans[1].scan)
    details = dataclasses.replace(result.details, lsf_matrix=None, coarse_lsf_matrix=np.full((4, 4), np.nan))
    failed = dataclasses.replace(result, status="failed", reason="the matrix is not finite", details=details)
    figures.pair_figure(failed, tmp_path / "pair.png")
    with Image.open(tmp_path / "pair.png") as png:
        assert png.size == (1980, 682)
