"""Tops at the edge of the scanners' view: a planted conifer plot scanned from two stations that
see up to +60 deg (a common terrestrial scanner's limit), each tree's height scattered 12 % about
the stand's relation. Seed 712 was drawn after the rule was chosen (on the benchmark's plots,
``python -m benchmarks.trees_compare --halves``)."""

from __future__ import annotations

import functools
import math

import numpy as np

from forestreg.engine.simulate import make_scene, simulate_plot
from forestreg.engine.tls.stations import StationParams
from forestreg.engine.trees.inventory import TreeParams, measure_trees

STATIONS = [(-5.0, 0.0), (5.0, 0.0)]


@functools.lru_cache(maxsize=None)
def _plot():
    scene = make_scene("planted_conifer", seed=712, size_m=25.0, stem_shapes="real", height_scatter=0.12)
    plot = simulate_plot(
        "planted_conifer",
        STATIONS,
        scene=scene,
        seed=712,
        angular_step_deg=0.35,
        scanner_options={"elevation_max_deg": 60.0},
    )
    return scene, np.vstack([s.world_points() for s in plot.scans])


def _matched(upward_limit_deg: float = 0.0):
    """(inventory, [(record, true tree, true top beyond both stations' view)]) for the trees of
    at least 10 cm within 12 m that were found (a stem within 0.5 m), and how many there are."""
    scene, points = _plot()
    params = TreeParams(cylinder_models=False, stations=StationParams(upward_limit_deg=upward_limit_deg))
    inv = measure_trees(points, params)
    xy = np.array([(r.stem.x, r.stem.y) for r in inv.trees])
    out, n = [], 0
    for t in scene.trees:
        if math.hypot(t.x, t.y) > 12.0 or t.dbh_m < 0.1:
            continue
        n += 1
        d = np.hypot(*(xy - (t.x, t.y)).T)
        if d.min() >= 0.5:
            continue
        el = [math.degrees(math.atan2(t.height_m - 1.5, math.hypot(t.x - sx, t.y - sy))) for sx, sy in STATIONS]
        out.append((inv.trees[int(np.argmin(d))], t, min(el) > 60.0))
    return inv, out, n


def _unflagged(rec) -> bool:
    return not rec.quality["height"].endswith("low")


def test_tops_cut_by_the_view_are_flagged():
    """The two stations are found (within 0.3 m) with their +60 deg limit. No tree whose true top
    lies beyond both stations' view stands unflagged more than 10 % short (6 do with the check
    switched off, 10-20 % short), and the unflagged heights' rRMSE is under 8 % (measured 6.6 %;
    9.7 % without the check); every height 10.3 % (11.2 % without)."""
    inv, pairs, n = _matched()
    assert len(pairs) >= 0.85 * n  # 44 of 49 found (two stations: some stems hidden from both)
    found = inv.stations.positions
    assert len(found) == 2
    assert max(np.hypot(*(found[:, :2] - s).T).min() for s in STATIONS) < 0.3
    assert abs(inv.stations.upward_limit_deg - 60.0) <= 2.0
    cut_short = [
        (r.tree_id, r.height_m / t.height_m - 1)
        for r, t, cut in pairs
        if cut and _unflagged(r) and r.height_m < 0.9 * t.height_m
    ]
    assert not cut_short, cut_short
    flagged = [r for r, _, _ in pairs if any("edge of the scanners' view" in f for f in r.flags)]
    assert len(flagged) >= 5
    unflagged = np.array([r.height_m / t.height_m - 1 for r, t, _ in pairs if _unflagged(r)])
    assert len(unflagged) >= 10 and math.sqrt(float(np.mean(unflagged**2))) < 0.08
    every = np.array([r.height_m / t.height_m - 1 for r, t, _ in pairs])
    assert math.sqrt(float(np.mean(every**2))) < 0.108


def test_without_the_check_cut_tops_stand_unflagged():
    """The same plot with the check switched off (``upward_limit_deg = 90``): tops cut by the
    view stand unflagged 10-20 % short, which the check above removes."""
    inv, pairs, _ = _matched(90.0)
    assert not inv.stations.limited and len(inv.stations.positions) == 0
    assert sum(1 for r, t, cut in pairs if cut and _unflagged(r) and r.height_m < 0.9 * t.height_m) >= 3


def test_the_height_curve_rests_on_tops_in_view(monkeypatch):
    """Tops at the edge of the view are lower bounds: the plot's height-diameter curve is fitted
    without them (``[trees.height_curve] in_view_only``), so tops cut alike do not pull it down.
    Here 12 of the 27 trees the curve would rest on are such tops."""
    import forestreg.engine.trees.inventory as inventory

    fitted = []
    real_fit = inventory.fit_height_curve

    def spy(d, h, params):
        fitted.append(np.asarray(h, dtype=np.float64))
        return real_fit(d, h, params)

    monkeypatch.setattr(inventory, "fit_height_curve", spy)
    inv, _, _ = _matched()
    cut = [r.crown.height_m for r in inv.trees if any("edge of the scanners' view" in f for f in r.flags)]
    assert len(cut) >= 5 and len(fitted[-1]) >= 10
    assert not np.isin(np.round(cut, 6), np.round(fitted[-1], 6)).any()
    params = TreeParams(cylinder_models=False, stations=StationParams(upward_limit_deg=0.0))
    measure_trees(_plot()[1], params.replace(height_curve=params.height_curve.replace(in_view_only=False)))
    assert np.isin(np.round(cut, 6), np.round(fitted[-1], 6)).sum() >= 5  # without the rule they would be in it
