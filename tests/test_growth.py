"""Diameter growth on real stem shapes (oval, rough), and the DBH's stated uncertainty on them.

Ground truth: sections of known ellipses (the shape of a stem both surveys share, with the
growth added and the later survey shifted), simulated scans of oval stems with their tape
(girth-equivalent) DBH, and a simulated re-survey of a stand with oval, rough stems.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from forestreg.engine.change import detect_change, epoch_from_cloud
from forestreg.engine.change.growth import GrowthParams, ShiftPrior, sector_growth, shift_prior, stem_sections
from forestreg.engine.simulate import ForestScene, Material, ScannerSetup, simulate_tls_scan
from forestreg.engine.simulate.resurvey import simulate_resurvey
from forestreg.engine.simulate.scene import Tree, make_terrain
from forestreg.engine.trees.stems import dbh_sigma, fit_stem_circle

PARAMS = GrowthParams()


def _section(rng, a: float, b: float, phi: float, arcs, bark, *, shift=(0.0, 0.0), grow=0.0, n=250) -> np.ndarray:
    """(k, 3) points (x, y, height above the ground) of an elliptic stem (semi-axes a, b, major
    axis at ``phi``) on the angular ``arcs`` between 1.0 and 1.8 m, bark relief ``bark(theta)``
    (the same in both surveys), ``grow`` added to the radius, shifted by ``shift``, 2 mm noise."""
    th = np.concatenate([rng.uniform(s, e, n) for s, e in arcs])
    t = th - phi
    r = a * b / np.sqrt((b * np.cos(t)) ** 2 + (a * np.sin(t)) ** 2) + grow + bark(th)
    p = np.column_stack([r * np.cos(th), r * np.sin(th)]) + shift + rng.normal(0.0, 0.002, (len(th), 2))
    return np.column_stack([p, rng.uniform(1.0, 1.8, len(th))])


def _stem(rng):
    d = rng.uniform(0.15, 0.5)
    ovality = rng.uniform(0.0, 0.10)
    a = d / 2.0
    k = int(rng.integers(5, 12))
    amp, phase = rng.uniform(0.001, 0.003), rng.uniform(0.0, 2 * math.pi, k)

    def bark(th):
        return amp * 1.4 * np.mean([np.sin((j + 6) * th + phase[j]) for j in range(k)], axis=0)

    return a, a * (1.0 - ovality), rng.uniform(0.0, math.pi), bark


def test_sector_growth_on_oval_rough_stems_seen_from_different_sides():
    """Two surveys see overlapping arcs of oval, rough stems from different sides; the later one
    is shifted a few mm (the registration's residual). The growth is within the stated sigma."""
    rng = np.random.default_rng(5)
    errors, z, circle_errors = [], [], []
    for _ in range(150):
        a, b, phi, bark = _stem(rng)
        grow = rng.uniform(0.005, 0.02)
        s0 = rng.uniform(0.0, 2 * math.pi)
        s1 = s0 + math.radians(rng.uniform(-100.0, 100.0))
        w0, w1 = math.radians(rng.uniform(150, 260)), math.radians(rng.uniform(150, 260))
        shift = rng.normal(0.0, 0.003, 2)
        before = _section(rng, a, b, phi, [(s0, s0 + w0)], bark)
        after = _section(rng, a, b, phi, [(s1, s1 + w1)], bark, shift=shift, grow=grow)
        sec = stem_sections(before, after, np.zeros(2), np.array([0.0, 0.0, 1.0]), a, PARAMS)
        fit = sector_growth(sec, ShiftPrior((0.0, 0.0), 0.003), PARAMS)
        if not fit.stated:
            continue
        errors.append(fit.dbh_change_m - 2 * grow)
        z.append(abs(errors[-1]) / fit.dbh_change_sigma_m)
        # what a difference of two circles gives on the same points
        cb = fit_stem_circle(before[:, :2], min_arc_coverage=0.0, max_residual_m=1.0)
        ca = fit_stem_circle(after[:, :2], min_arc_coverage=0.0, max_residual_m=1.0)
        circle_errors.append(2 * (ca.radius_m - cb.radius_m) - 2 * grow)
    errors, z = np.array(errors), np.array(z)
    assert len(errors) >= 130
    rmse = math.sqrt(float(np.mean(errors**2)))
    assert rmse < 0.003
    assert np.mean(z < 2.0) >= 0.9
    # the circles' difference is what the sectors avoid: several times the error
    assert math.sqrt(float(np.mean(np.square(circle_errors)))) > 3.0 * rmse


def test_no_growth_from_a_stem_seen_from_one_side_then_the_other():
    rng = np.random.default_rng(8)
    a, b, phi, bark = _stem(rng)
    before = _section(rng, a, b, phi, [(0.0, math.radians(150))], bark)
    after = _section(rng, a, b, phi, [(math.radians(180), math.radians(330))], bark, grow=0.01)
    fit = sector_growth(
        stem_sections(before, after, np.zeros(2), np.array([0.0, 0.0, 1.0]), a, PARAMS), ShiftPrior(), PARAMS
    )
    assert not fit.stated and math.isnan(fit.dbh_change_m)
    assert "in common" in fit.reason and "at least 60" in fit.reason


def test_shift_prior_follows_the_registration_field():
    """Stems whose arcs fix their shift reveal a turn of 0.05 deg about the plot: the prior of
    each stem is the field at its place, within a millimetre."""
    rng = np.random.default_rng(3)
    turn = math.radians(0.05)
    positions = rng.uniform(-12.0, 12.0, (20, 2))
    fits = []
    for p in positions:
        shift = turn * np.array([-p[1], p[0]]) + [0.002, -0.001]
        a, b, phi, bark = _stem(rng)
        before = _section(rng, a, b, phi, [(0.0, 2 * math.pi)], bark)
        after = _section(rng, a, b, phi, [(0.0, 2 * math.pi)], bark, shift=shift, grow=0.01)
        fits.append(
            sector_growth(
                stem_sections(before, after, np.zeros(2), np.array([0.0, 0.0, 1.0]), a, PARAMS),
                ShiftPrior((0.0, 0.0), PARAMS.max_shift_m),
                PARAMS,
            )
        )
    priors = shift_prior(positions, fits, 0.01, PARAMS)
    for p, prior in zip(positions, priors):
        truth = turn * np.array([-p[1], p[0]]) + [0.002, -0.001]
        assert math.hypot(*(np.array(prior.mean) - truth)) < 0.001
        assert prior.sigma_m < 0.003


def _one_tree_scene(tree: Tree) -> ForestScene:
    extent = (-12.0, 12.0, -12.0, 12.0)
    terrain = make_terrain(
        extent,
        slope_deg=0.0,
        slope_azimuth_deg=0.0,
        roughness_m=0.0,
        roughness_length_m=5.0,
        cell_m=0.5,
        rng=np.random.default_rng(0),
    )
    return ForestScene(preset="test", seed=0, extent=extent, terrain=terrain, trees=(tree,))


@pytest.mark.parametrize("views", [1, 2])
def test_dbh_of_oval_stems_seen_from_one_or_two_sides(views):
    """Oval stems (0-10 %, bark relief 1-3 mm), each scanned from one side or from two places
    70-125 deg apart: a plain circle's DBH misses the tape DBH by several per cent; the section
    fitted with its oval part (the inventory's DBH) comes closer, and the stated sigma covers
    both. Measured (24 stems): one side 3.5 % -> 2.3 %, two sides 2.0 % -> 0.4 % rRMSE."""
    rng = np.random.default_rng(11)
    errors, z, oval_errors, oval_z = [], [], [], []
    for k in range(24):
        tree = Tree(
            1,
            0.0,
            0.0,
            0.0,
            dbh_m=float(rng.uniform(0.15, 0.5)),
            height_m=12.0,
            crown_base_m=11.0,
            crown_radius_m=0.5,
            n_branches=0,
            leaf_area_density=0.0,
            ovality=float(rng.uniform(0.0, 0.10)),
            ovality_azimuth_deg=float(rng.uniform(0.0, 180.0)),
            bark_roughness_m=float(rng.uniform(0.001, 0.003)),
            bark_seed=k,
        )
        heading = rng.uniform(0.0, 2 * math.pi)
        pts = []
        for v in range(views):
            dist = rng.uniform(4.0, 9.0)
            towards = heading + v * rng.uniform(1.2, 2.2)
            setup = ScannerSetup(
                dist * math.cos(towards),
                dist * math.sin(towards),
                angular_step_deg=0.1,
                elevation_min_deg=-8.0,
                elevation_max_deg=2.0,
                range_noise_m=0.002,
                name=f"side {v}",
            )
            sim = simulate_tls_scan(_one_tree_scene(tree), setup, seed=10 * k + v)
            w = sim.world_points()
            on = (sim.labels == Material.TRUNK) & (np.abs(w[:, 2] - 1.3) < 0.05)
            pts.append(w[on, :2])
        for typical, errs, zs in ((None, errors, z), (0.06, oval_errors, oval_z)):
            fit = fit_stem_circle(np.vstack(pts), min_arc_coverage=0.0, typical_ovality=typical)
            d = 2.0 * fit.radius_m
            err = d - tree.girth_diameter_m()
            errs.append(err / tree.girth_diameter_m())
            zs.append(abs(err) / dbh_sigma(d, fit, "medium"))
    errors, z, oval_errors, oval_z = map(np.array, (errors, z, oval_errors, oval_z))
    rrmse, oval_rrmse = (float(np.sqrt(np.mean(e**2))) for e in (errors, oval_errors))
    assert rrmse > (0.03 if views == 1 else 0.012)  # a plain circle takes the seen arc's curvature
    assert oval_rrmse < (0.8 * rrmse if views == 1 else 0.5 * rrmse)
    assert oval_rrmse < (0.035 if views == 1 else 0.01)
    assert np.mean(z < 2.0) >= 0.9
    assert np.mean(oval_z < 2.0) >= 0.9


@pytest.mark.slow
def test_resurvey_growth_on_oval_rough_stems():
    """A mixed stand with oval, rough stems, three scans per survey from different places, six
    years later (a seed the rules were not chosen on): registration, statuses, and a growth for
    most stems within its stated sigma."""
    case = simulate_resurvey("mixed_temperate", seed=21, angular_step_deg=0.4, stem_shapes="real", scans_per_survey=3)
    before = epoch_from_cloud(case.before, name="BEFORE")
    after = epoch_from_cloud(case.after, name="AFTER")
    result = detect_change(before, after)
    assert result.ok
    e = np.linalg.inv(case.matrix) @ result.local_matrix
    assert math.degrees(math.acos(min(1.0, (np.trace(e[:3, :3]) - 1.0) / 2.0))) < 0.05
    # the trees of the earlier survey, as the later one saw them, moved back by the result
    trees_after = np.column_stack([before.breast_points(), np.ones(len(before))]) @ np.linalg.inv(case.matrix).T
    moved = trees_after @ result.local_matrix.T
    assert np.max(np.linalg.norm(moved[:, :3] - before.breast_points(), axis=1)) < 0.03
    fates = case.fates()
    txy = np.array([[f["x"], f["y"]] for f in fates])
    right = false_new = eligible = given = 0
    errors, z = [], []
    for t in result.trees:
        d = np.hypot(*(txy - [t.x, t.y]).T)
        f = fates[int(np.argmin(d))] if d.min() < 0.5 else None
        right += f is not None and f["status"] == t.status
        false_new += t.status == "new" and (f is None or f["status"] != "new")
        if f is None or not (t.status == f["status"] == "persisting"):
            continue
        if math.hypot(f["x"], f["y"]) <= 12.0 and f["dbh_before_m"] >= 0.10:
            eligible += 1
            given += math.isfinite(t.dbh_change_m)
        if math.isfinite(t.dbh_change_m):
            errors.append(t.dbh_change_m - (f["dbh_after_m"] - f["dbh_before_m"]))
            z.append(abs(errors[-1]) / t.dbh_change_sigma_m)
    assert right / len(result.trees) >= 0.95
    assert false_new == 0
    assert eligible >= 15 and given / eligible >= 0.75
    assert math.sqrt(float(np.mean(np.square(errors)))) <= 0.005
    assert np.mean(np.array(z) < 2.0) >= 0.9


@pytest.mark.slow
def test_resurvey_of_a_real_plot_without_ground_registers_and_finds_no_growth(shared_data):
    """Real ``LPine1_demo.laz`` (a pine plot without ground points) surveyed twice: two
    different 70 % samples, the later one turned 117 deg and shifted. The cloud's grounds (its
    lowest points) differ between the samples by up to 1.4 m under a stem, and its pines lean
    alike: stems compared at each survey's own breast height would be off by the lean times that
    difference. Truth: no growth, and the registration known."""
    from forestreg.engine.io import read_scan
    from forestreg.engine.simulate.resurvey import frame_matrix

    p = np.array(read_scan(shared_data / "LPine1_demo.laz").points, dtype=float)
    p = p - np.floor(p.mean(axis=0))
    rng = np.random.default_rng(4)
    before_pts = p[rng.random(len(p)) < 0.7]
    m = frame_matrix(117.0, (412.7, -238.4, 35.2))
    after_pts = (p[rng.random(len(p)) < 0.7] - m[:3, 3]) @ m[:3, :3]
    before, after = epoch_from_cloud(before_pts, name="BEFORE"), epoch_from_cloud(after_pts, name="AFTER")
    result = detect_change(before, after)
    assert result.ok and result.counts()["persisting"] >= 14 and result.counts()["new"] == 0
    truth_after = np.column_stack([before.breast_points(), np.ones(len(before))]) @ np.linalg.inv(m).T
    moved = truth_after @ result.local_matrix.T
    error = np.hypot(*(moved[:, :2] - before.xy).T)
    assert error.max() < 0.015  # the stems' own breast-height points, back where they were
    growth = np.array(
        [
            (t.dbh_change_m, t.dbh_change_sigma_m)
            for t in result.trees
            if t.status == "persisting" and math.isfinite(t.dbh_change_m)
        ]
    )
    assert len(growth) >= 0.8 * result.counts()["persisting"]
    assert math.sqrt(float(np.mean(growth[:, 0] ** 2))) < 0.002  # no growth: RMSE under 2 mm
    assert np.mean(np.abs(growth[:, 0]) < 2.0 * growth[:, 1]) >= 0.9
