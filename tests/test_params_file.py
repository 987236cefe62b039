"""Values set in a nested TOML parameter file reach the step that uses them: the automatic VOP
radii, the scanner-position estimate (through a project and its scan cache, and the project file),
the survey's loop-closure floors, the co-registration's stem layer, the stem profile's spacing
and the noisy profile, the ground evidence under a crown and the trees' flags."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError
from forestreg.engine.core.scan import Scan
from forestreg.engine.core.transform import matrix_from_yaw
from forestreg.engine.io import write_scan
from forestreg.engine.params import ProductParams, load_params
from forestreg.engine.tls.pair import vop_radii
from forestreg.engine.tls.plot import ScanCache
from forestreg.engine.tls.project import Link, Project
from forestreg.engine.tls.survey import inconsistent_links

TOML = """
[registration]
auto_vop_radii_m = [12.0, 18.0]

[scanner_position]
default_height_m = 2.5

[survey]
min_closure_m = 0.2
"""


@pytest.fixture()
def params(tmp_path):
    path = tmp_path / "params.toml"
    path.write_text(TOML, encoding="utf-8")
    return load_params(path)


def test_automatic_vop_radii_come_from_the_file(params):
    assert vop_radii(params.registration) == (12.0, 18.0)
    assert vop_radii(params.registration.replace(max_range_m=20.0)) == (12.0,)  # within 3 m of the range
    assert vop_radii(ProductParams().registration) == (10.0, 15.0, 20.0, 25.0)


def test_scanner_position_settings_reach_the_scan_cache_and_the_project_file(params, tmp_path):
    """A scan in project coordinates (its scanner 20 m from the file origin) over flat ground:
    the ground profile gives no instrument height, so the file's default height places it."""
    rng = np.random.default_rng(0)
    r, a = rng.uniform(1.5, 25.0, 200000), rng.uniform(0.0, 2 * np.pi, 200000)
    pts = np.column_stack([20.0 + r * np.cos(a), 5.0 + r * np.sin(a), rng.normal(0.0, 0.01, len(r))])
    path = tmp_path / "ground.laz"
    write_scan(Scan.from_points(pts, name="ground"), path)
    heights = []
    for scanner_params in (None, params.scanner_position):
        project = Project(name="p")
        project.add_scan(path)
        if scanner_params is not None:
            project.scanner_params = scanner_params
        project.save(tmp_path / f"project{len(heights)}.json")
        again = Project.load(tmp_path / f"project{len(heights)}.json")
        assert again.scanner_params == project.scanner_params
        scan = ScanCache(again)("ground.laz")
        assert scan.meta["scanner_position"] == "estimated"
        assert np.hypot(scan.scanner_position_file[0] - 20.0, scan.scanner_position_file[1] - 5.0) < 0.05
        heights.append(float(scan.scanner_position_file[2]))
    assert abs(heights[0] - 1.5) < 0.05 and abs(heights[1] - 2.5) < 0.05


def test_survey_closure_floor_comes_from_the_file(params):
    """Three scans whose loop misses by 10 cm with 1 mm stated sigmas: it fails to close at the
    default 3 cm floor and closes at the file's 20 cm."""
    poses = {
        "a": np.eye(4),
        "b": matrix_from_yaw(30.0, np.array([10.0, 0.0, 0.0])),
        "c": matrix_from_yaw(-20.0, np.array([0.0, 10.0, 0.0])),
    }
    links = []
    for (m, r), off in ((("b", "a"), 0.1), (("c", "b"), 0.0), (("a", "c"), 0.0)):
        truth = np.linalg.inv(poses[r]) @ poses[m]
        truth[0, 3] += off
        link = Link(moving=m, reference=r)
        link.result = {
            "status": "ok",
            "matrix": truth.tolist(),
            "uncertainty": {"translation_m": 0.001, "rotation_deg": 0.001},
        }
        links.append(link)
    scanner = {n: np.zeros(3) for n in poses}
    default = inconsistent_links(links, scanner, 4.0)
    survey = params.survey
    from_file = inconsistent_links(
        links,
        scanner,
        survey.closure_sigmas,
        min_closure_m=survey.min_closure_m,
        min_closure_deg=survey.min_closure_deg,
    )
    assert [row["closes"] for row in default[1] if "closes" in row] == [False] and len(
        default[0]
    ) == 1  # the weakest link goes
    assert [row["closes"] for row in from_file[1]] == [True] and from_file[0] == []
    from forestreg.app.survey import survey_params

    project = Project(name="p")
    assert (
        survey_params("within:30", project, base=survey).min_closure_m == 0.2
    )  # the command line's pairs, the file's floors


def test_bad_values_in_the_new_sections_are_refused(tmp_path):
    for text in (
        '[survey]\npairs = "some"\n',
        "[scanner_position]\ndefault_height_m = 50.0\n",
        "[registration]\nauto_vop_radii_m = []\n",
    ):
        path = tmp_path / "bad.toml"
        path.write_text(text, encoding="utf-8")
        with pytest.raises(ParameterError):
            load_params(path)


def test_the_coregistration_stem_layer_comes_from_the_file(tmp_path):
    """A thinner stem layer from the file: fewer UAV points make the stem evidence, and the
    co-registration still finds the true transform."""
    from forestreg.engine.core.transform import rigid_errors
    from forestreg.engine.coreg.coregister import coregister
    from forestreg.engine.simulate.platforms import simulate_coregistration_case

    path = tmp_path / "coreg.toml"
    path.write_text(
        "[coregistration]\nstem_layer_m = [0.5, 1.5]\n\n[coregistration.low_layer_icp]\nmax_distances_m = [2.0, 0.5, 0.12]\n",
        encoding="utf-8",
    )
    params = load_params(path).coregistration
    assert params.low_layer_icp.max_distances_m == (2.0, 0.5, 0.12)
    case = simulate_coregistration_case(
        "planted_conifer",
        seed=0,
        size_m=40.0,
        ground_platform="tls",
        heading_deg=35.0,
        offset_m=(3.0, -2.0, 0.5),
        uav_density_scale=0.3,
        tls_step_deg=0.3,
    )
    default, thin = coregister(case.ground, case.uav), coregister(case.ground, case.uav, params)
    assert default.ok and thin.ok
    assert 0 < thin.coarse.stem_layer_points < default.coarse.stem_layer_points
    for result in (default, thin):
        rot, trans = rigid_errors(result.matrix, case.matrix)
        assert rot < 0.2 and trans < 0.1


def test_tree_settings_once_module_constants_come_from_the_file(tmp_path):
    """[trees.stems] sparse_spacing_m picks the noisy stem profile first for a dense cloud, and
    [trees.canopy] ground_tolerance / ground_ring_width_m decide the ground evidence under a crown."""
    from scipy.spatial import cKDTree

    from forestreg.engine.trees.canopy import ground_evidence
    from forestreg.engine.trees.stems import detect_stems_adaptive

    path = tmp_path / "trees.toml"
    path.write_text(
        "[trees.stems]\nsparse_spacing_m = 0.001\n\n[trees.canopy]\nground_tolerance = 0.001\nground_ring_width_m = 0.5\n",
        encoding="utf-8",
    )
    trees = load_params(path).trees
    # a densely sampled stem on flat ground: the fine profile at the default, the noisy one first
    # for the file (both find the stem)
    rng = np.random.default_rng(0)
    a, z = rng.uniform(0, 2 * np.pi, 60000), rng.uniform(0.0, 3.0, 60000)
    pts = np.vstack(
        [
            np.column_stack([0.2 * np.cos(a), 0.2 * np.sin(a), z]),
            np.column_stack([rng.uniform(-3, 3, (20000, 2)), np.zeros(20000)]),
        ]
    )
    profiles = [detect_stems_adaptive(pts, pts[:, 2], p) for p in (ProductParams().trees.stems, trees.stems)]
    assert [(len(stems), name) for stems, _, name in profiles] == [(1, "fine"), (1, "noisy")]
    # open ground on a slope around a crown without returns under it, the DEM 0.2 m off the plane
    xy = rng.uniform(-15, 15, (4000, 2))
    xy = xy[np.hypot(xy[:, 0], xy[:, 1]) > 6.0]
    g = np.column_stack([xy, 0.15 * xy[:, 0] + rng.normal(0, 0.03, len(xy))])
    index, top = cKDTree(g[:, :2]), np.array([0.5, 0.0, 20.0])
    default = ground_evidence(g, index, top, 6.0, 0.15 * 0.5 + 0.2, 20.0)
    strict = ground_evidence(g, index, top, 6.0, 0.15 * 0.5 + 0.2, 20.0, trees.canopy)
    assert not default.unsure and strict.unsure
    assert strict.n_ring < default.n_ring  # the narrower ring holds fewer returns


def test_airborne_ratio_and_tilted_partner_radius_come_from_the_file(tmp_path, monkeypatch):
    """[trees] airborne_band_ratio decides whether a cloud counts as airborne, and [registration]
    tilted_partner_vop_radius_m is the D_r of the links that look for a tilted scan's partner."""
    from forestreg.engine.core.progress import Progress
    from forestreg.engine.tls import plot
    from forestreg.engine.trees.inventory import _airborne_like

    path = tmp_path / "p.toml"
    path.write_text(
        "[registration]\ntilted_partner_vop_radius_m = 12.5\n\n[trees]\nairborne_band_ratio = 0.01\n", encoding="utf-8"
    )
    params = load_params(path)
    heights = np.r_[np.full(30, 2.0), np.full(1000, 10.0)]  # 0.03 points low per point high
    assert _airborne_like(heights, ProductParams().trees.airborne_band_ratio) and not _airborne_like(
        heights, params.trees.airborne_band_ratio
    )
    radii = []
    monkeypatch.setattr(plot, "_run_link", lambda project, link, *rest: radii.append(link.vop_radius_m))
    project = Project(name="p", params=params.registration)
    for name in ("level", "tilted"):
        (tmp_path / name).write_bytes(b"")
        project.add_scan(tmp_path / name)
    project.centre = "level"
    project.scan("tilted").tilted = True
    monkeypatch.setattr(Project, "chained_poses", lambda self: {"level": np.eye(4), "tilted": None})
    plot._register_tilted_without_partner(project, project.scan("tilted"), None, Progress(None), None)
    assert radii == [12.5]


def test_tree_flags_edit_search_and_noisy_profile_come_from_the_file(tmp_path):
    """[trees] ground_near_stem_m, shared_top_min_points, max_slenderness and
    stem_search_radius_m, and [trees.noisy_stems], reach the steps that use them: a stem's ground
    evidence, the flag of a top amid a thicker neighbour's crown, the slenderness flag, the search
    around a clicked position, the noisy stem profile."""
    import math

    from forestreg.engine.core.errors import ScanDataError
    from forestreg.engine.geometry.columns import ColumnIndex
    from forestreg.engine.simulate import simulate_plot
    from forestreg.engine.trees import edit as E
    from forestreg.engine.trees.crown import CrownMeasurement
    from forestreg.engine.trees.inventory import _shared_tops, ground_near_stems, measure_trees
    from forestreg.engine.trees.stems import Stem, detect_stems_adaptive

    path = tmp_path / "p.toml"
    path.write_text(
        "[trees]\nground_near_stem_m = 1.5\nshared_top_min_points = 3\nmax_slenderness = 20.0\nstem_search_radius_m = 0.3\n"
        "cylinder_models = false\n\n[trees.noisy_stems]\nmin_slice_points = 40\n",
        encoding="utf-8",
    )
    default, trees = ProductParams().trees.replace(cylinder_models=False), load_params(path).trees

    def stem(i, x, r):
        return Stem(
            id=i,
            base=np.array([x, 0.0, 0.0]),
            axis=np.array([0.0, 0.0, 1.0]),
            radius_m=r,
            point_indices=np.zeros(0, dtype=np.int64),
        )

    # ground 2 m from a stem: near with 3 m, not with 1.5 m
    p = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 5.0]])
    ground = np.array([True, False])
    assert ground_near_stems(p, ground, [stem(1, 0.0, 0.1)], default.ground_near_stem_m) == {1: True}
    assert ground_near_stems(p, ground, [stem(1, 0.0, 0.1)], trees.ground_near_stem_m) == {1: False}
    # four points of a thicker neighbour beside a tree's top: a shared top with 3, not with 6
    nan = math.nan
    crowns = {
        i: CrownMeasurement(
            tree_id=i,
            x=x,
            y=0.0,
            height_m=nan,
            crown_base_m=nan,
            crown_width_ew_m=nan,
            crown_width_ns_m=nan,
            crown_area_m2=nan,
            crown_diameter_m=nan,
            crown_length_m=nan,
            crown_volume_m3=nan,
            n_points=0,
            top=(x, 0.0, 10.0),
            ok=True,
            reasons=(),
        )
        for i, x in ((1, 0.0), (2, 5.0))
    }
    pts = np.array([[0.0, 0.0, 10.0]] + [[0.5, 0.1 * k, 10.0] for k in range(4)])
    labels = np.array([1, 2, 2, 2, 2])
    stems = [stem(1, 0.0, 0.1), stem(2, 5.0, 0.2)]
    assert _shared_tops(pts, labels, stems, crowns, ColumnIndex(pts, 1.0), default.shared_top_min_points) == {}
    assert 1 in _shared_tops(pts, labels, stems, crowns, ColumnIndex(pts, 1.0), trees.shared_top_min_points)
    # a simulated plot: re-measured with the file's slenderness limit, a tree's height is flagged
    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.5, size_m=10.0)
    points = np.vstack([s.world_points() for s in plot.scans])
    inv = measure_trees(points, default)
    rec = max(inv.trees, key=lambda r: r.crown.height_m / r.dbh_m)
    assert not any("slenderness" in f for f in rec.flags)
    idx = np.flatnonzero(inv.labels == rec.tree_id)
    again = E.measure_tree(points, inv, rec.stem, idx, trees)
    assert any("slenderness" in f for f in again.flags) and again.quality["height"].endswith("; low")
    # a click 0.6 m beside a stem finds it within 1 m, not within 0.3 m
    click = (rec.stem.x + 0.6, rec.stem.y)
    assert (
        math.hypot(
            E._stem_near(points, inv, click, default).x - rec.stem.x,
            E._stem_near(points, inv, click, default).y - rec.stem.y,
        )
        < 0.1
    )
    with pytest.raises(ScanDataError):
        E._stem_near(points, inv, click, trees)
    # the noisy profile (tried first when the band is sparser than sparse_spacing_m) takes its
    # slice minimum from [trees.noisy_stems]
    sparse = default.stems.replace(sparse_spacing_m=0.001)
    used = [detect_stems_adaptive(points, inv.heights, sparse, None, t.noisy_stems) for t in (default, trees)]
    assert [(u[2], u[1].min_slice_points) for u in used] == [("noisy", 10), ("noisy", 40)]


def test_change_uncertainties_band_and_ground_decision_come_from_the_file(tmp_path):
    """[change] height_sigma_m and table_dbh_sigma_m give a survey's uncertainties by trust,
    stem_band_m the band kept for the slices, no_ground_fraction whether a cloud has ground."""
    from forestreg.engine.change import epoch_from_cloud, epoch_from_table
    from forestreg.engine.simulate import simulate_plot

    path = tmp_path / "p.toml"
    path.write_text(
        "[change]\nheight_sigma_m = [0.2, 0.9, 2.0]\ntable_dbh_sigma_m = [0.004, 0.02, 0.05]\n"
        "stem_band_m = [0.2, 3.5]\nno_ground_fraction = 0.0\n",
        encoding="utf-8",
    )
    default, change = ProductParams().change, load_params(path).change
    rows = [
        {
            "tree_id": "1",
            "x": "1.0",
            "y": "2.0",
            "z": "0.0",
            "dbh_m": "0.3",
            "height_m": "20.0",
            "dbh_quality": "circle fit; medium",
            "height_quality": "top; low",
        }
    ]
    before, after = epoch_from_table(rows, change=default), epoch_from_table(rows, change=change)
    assert (before.dbh_sigma_m[0], before.height_sigma_m[0]) == (0.012, 1.5)
    assert (after.dbh_sigma_m[0], after.height_sigma_m[0]) == (0.02, 2.0)
    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.5, size_m=10.0)
    points = np.vstack([s.world_points() for s in plot.scans])
    below = points[: len(points) // 1000] - [0.0, 0.0, 2.0]  # 0.1 % of the points 2 m under the ground
    trees = ProductParams().trees.replace(cylinder_models=False)
    a, b = (epoch_from_cloud(np.vstack([points, below]), trees, change=c) for c in (default, change))
    assert a.band_heights.min() >= 0.3 and a.band_heights.max() <= 3.0
    assert b.band_heights.min() < 0.3 and b.band_heights.max() > 3.0 and len(b.band) > len(a.band)
    assert not any("no ground" in f for f in a.flags) and any("no ground" in f for f in b.flags)
    with pytest.raises(ParameterError):
        default.replace(stem_band_m=(0.6, 3.0))  # does not hold the slices at 0.5 m


def test_uncertainty_floors_and_target_limits_come_from_the_file(tmp_path):
    """[registration] min_uncertainty_m / min_uncertainty_deg floor a pair's stated uncertainty;
    manual_max_target_rmse_m and manual_min_target_spread_m decide which target fits are refused
    and which targets are suspects."""
    from types import SimpleNamespace

    from forestreg.engine.core.errors import TargetError
    from forestreg.engine.tls.manual import fit_to_targets, register_manual, suspect_targets
    from forestreg.engine.tls.pair import _pair_uncertainty

    path = tmp_path / "p.toml"
    path.write_text(
        "[registration]\nmin_uncertainty_m = 0.05\nmin_uncertainty_deg = 0.2\n"
        "manual_max_target_rmse_m = 0.02\nmanual_min_target_spread_m = 0.5\n",
        encoding="utf-8",
    )
    default, reg = ProductParams().registration, load_params(path).registration
    # twenty trunks that coincide within 1 mm after ICP: the floors decide what is stated
    rng = np.random.default_rng(3)
    ref = rng.uniform(-12, 12, (20, 2))
    vops = lambda xy: SimpleNamespace(xy=xy)  # noqa: E731
    attempt = SimpleNamespace(
        match=SimpleNamespace(matched_pairs=np.column_stack([np.arange(20), np.arange(20)])),
        reference_vops=vops(ref),
        moving_vops=vops(ref + rng.normal(0, 0.001, ref.shape)),
    )
    fine = SimpleNamespace(matrix=np.eye(4), std_m=0.001)
    low, floored = (_pair_uncertainty(attempt, fine, p) for p in (default, reg))
    assert low["translation_m"] < 0.05 and low["rotation_deg"] < 0.2
    assert (
        floored["vertical_m"] == 0.05
        and floored["translation_m"] == pytest.approx(0.05, abs=1e-4)
        and floored["rotation_deg"] == 0.2
    )
    # five targets, one 5 cm off: a suspect at 2 cm, not at 10 cm
    ref_t = {f"T{k}": np.array(v) for k, v in enumerate([[0, 0, 1], [10, 0, 1.5], [0, 10, 2], [10, 10, 1], [5, 3, 3]])}
    mov_t = {k: v + ([0.05, 0, 0] if k == "T4" else 0.0) for k, v in ref_t.items()}
    assert (
        suspect_targets(
            ref_t, mov_t, inlier_m=default.manual_max_target_rmse_m, min_spread_m=default.manual_min_target_spread_m
        )
        == []
    )
    assert suspect_targets(
        ref_t, mov_t, inlier_m=reg.manual_max_target_rmse_m, min_spread_m=reg.manual_min_target_spread_m
    ) == ["T4"]
    # T4 8 cm off: a target fit within the default limit (10 cm RMS), refused at 2 cm
    mov_t = {k: v + ([0.08, 0, 0] if k == "T4" else 0.0) for k, v in ref_t.items()}
    assert reg.manual_max_target_rmse_m < fit_to_targets(ref_t, mov_t).rmse_m < default.manual_max_target_rmse_m
    scan = Scan.from_points(rng.uniform(-5, 5, (1000, 3)), name="s")
    result = register_manual(scan, scan, ref_t, mov_t, reg)
    assert not result.ok and "limit 0.02 m" in result.reason and result.suspects == ["T4"]
    # three targets 0.2 m (RMS) off one straight line: enough at 2 cm, refused at 0.5 m
    line = {"A": np.array([0.0, 0.0, 0.0]), "B": np.array([5.0, 0.0, 0.0]), "C": np.array([10.0, 0.6, 0.0])}
    assert fit_to_targets(line, line, min_spread_m=default.manual_min_target_spread_m).rmse_m < 1e-9
    with pytest.raises(TargetError, match="one straight line"):
        fit_to_targets(line, line, min_spread_m=reg.manual_min_target_spread_m)


def test_levelling_sample_comes_from_the_file(tmp_path):
    """[registration] level_voxel_m and level_radius_m make the sample whose normals estimate a
    scan's vertical: the points within the radius, one a voxel."""
    from forestreg.engine.tls.prepare import centre_scan

    path = tmp_path / "p.toml"
    path.write_text("[registration]\nlevel_voxel_m = 0.3\nlevel_radius_m = 6.0\n", encoding="utf-8")
    default, reg = ProductParams().registration, load_params(path).registration
    rng = np.random.default_rng(0)
    r, a = rng.uniform(1.0, 25.0, 100000), rng.uniform(0.0, 2 * np.pi, 100000)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1.5, 1.0, len(r))])
    near = [np.linalg.norm(centre_scan(pts, np.zeros(3), p).near, axis=1) for p in (default, reg)]
    assert near[0].max() > 14.0 and near[1].max() <= 6.0
    assert 0 < len(near[1]) < 0.6 * (near[0] <= 6.0).sum()  # 0.3 m voxels hold fewer points than 0.1 m ones


def test_cylinder_model_limits_and_breast_height_come_from_the_file(tmp_path):
    """[trees.qsm] min_points refuses a tree with too few points, max_fit_points caps the points a
    cylinder is fitted to, breast_height_m is where the model's DBH is read (a tapering stem)."""
    from forestreg.engine.core.errors import ScanDataError
    from forestreg.engine.trees.qsm import fit_qsm

    path = tmp_path / "p.toml"
    path.write_text("[trees.qsm]\nbreast_height_m = 3.0\nmax_fit_points = 20\n", encoding="utf-8")
    default, qsm = ProductParams().trees.qsm, load_params(path).trees.qsm
    rng = np.random.default_rng(0)
    z, a = rng.uniform(0.0, 4.0, 6000), rng.uniform(0.0, 2 * np.pi, 6000)
    r = 0.2 - 0.03 * z  # DBH 0.322 m at 1.3 m, 0.22 m at 3 m
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), z]) + rng.normal(0.0, 0.002, (len(z), 3))
    model, again = fit_qsm(pts, default), fit_qsm(pts, qsm.replace(max_fit_points=default.max_fit_points))
    assert abs(model.dbh_from_cylinders_m - 0.322) < 0.015 and abs(again.dbh_from_cylinders_m - 0.22) < 0.015
    capped = fit_qsm(pts, qsm)
    assert not np.allclose(capped.radius_m, model.radius_m)  # fitted to 20 points a cylinder, not 1500
    with pytest.raises(ScanDataError, match="at least 10000 points"):
        fit_qsm(pts, default.replace(min_points=10000))


def test_icp_settings_are_one_nested_set_and_old_flat_names_still_read(tmp_path, caplog):
    """Each product's ICP is an ``IcpParams`` table ([registration.icp], [coregistration.icp],
    [coregistration.coarse_icp], [coregistration.low_layer_icp], [change.stem_icp]) with the
    product's own defaults; a file written with the former flat names is read into them, with one
    warning line per name."""
    from forestreg.engine.geometry.icp import IcpParams
    from forestreg.engine.params import params_toml

    p = ProductParams()
    assert p.registration.icp == IcpParams()
    assert (p.coregistration.icp.voxel_m, p.coregistration.coarse_icp.voxel_m, p.change.stem_icp.voxel_m) == (
        0.1,
        0.3,
        0.02,
    )
    assert "[coregistration.coarse_icp]\nvoxel_m = 0.3" in params_toml()
    path = tmp_path / "old.toml"
    path.write_text(
        "[registration]\nicp_voxel_m = 0.1\nicp_iterations = 30\n\n[coregistration]\ncoarse_voxel_m = 0.4\n"
        "\n[change]\nicp_max_distances_m = [0.3, 0.1]\n",
        encoding="utf-8",
    )
    with caplog.at_level("WARNING"):
        old = load_params(path)
    assert old.registration.icp == IcpParams(voxel_m=0.1, iterations=30)
    assert old.coregistration.coarse_icp == p.coregistration.coarse_icp.replace(voxel_m=0.4)
    assert old.change.stem_icp == p.change.stem_icp.replace(max_distances_m=(0.3, 0.1))
    assert sum("is now [registration.icp] voxel_m" in r.getMessage() for r in caplog.records) == 1
    with pytest.raises(ParameterError, match="max_distances_m: needs at least one value"):
        IcpParams(max_distances_m=())


def test_icp_normal_neighbours_and_coarse_tolerance_come_from_the_file(tmp_path):
    """[registration.icp] normal_neighbours sets how many neighbours give a reference normal (the
    normals, and so the fit, change); [coregistration.coarse_icp] final_tolerance_m/_deg stop the
    candidates' coarse ICP (a looser tolerance, fewer iterations)."""
    from forestreg.engine.core.transform import matrix_from_yaw
    from forestreg.engine.geometry.icp import IcpReference, icp

    path = tmp_path / "p.toml"
    path.write_text(
        "[registration.icp]\nnormal_neighbours = 40\n\n[coregistration.coarse_icp]\nfinal_tolerance_m = 0.01\n"
        "final_tolerance_deg = 0.5\n",
        encoding="utf-8",
    )
    default, loaded = ProductParams(), load_params(path)
    assert loaded.registration.icp.normal_neighbours == 40
    rng = np.random.default_rng(5)
    xy = rng.uniform(-5, 5, (20000, 2))
    ref = np.column_stack([xy, 0.3 * np.sin(xy[:, 0]) + 0.2 * np.cos(1.3 * xy[:, 1])])  # a wavy ground
    reference = IcpReference(ref)
    index = np.arange(0, len(reference.level(0.1)[0]), 7)
    twelve, forty = (
        reference.normals(0.1, index, p.icp.normal_neighbours) for p in (default.registration, loaded.registration)
    )
    turned = np.degrees(np.arccos(np.clip(np.abs(np.sum(twelve * forty, axis=1)), 0.0, 1.0)))
    assert turned.mean() > 0.2  # wider neighbourhoods smooth the normals of the wavy ground
    start = matrix_from_yaw(3.0, np.array([0.3, -0.2, 0.1]))
    runs = [
        icp(ref, ref[::3], start, statistics=False, **p.coarse_icp.keywords())
        for p in (default.coregistration, loaded.coregistration)
    ]
    assert runs[1].iterations < runs[0].iterations
    assert np.abs(runs[0].matrix - np.eye(4)).max() < 0.01  # the default converges


def test_crown_reach_settings_come_from_the_file(tmp_path):
    """[trees.segmentation] axis_dominance_dbh and dominance_ratio, and [trees] crown_reach_dbh,
    reach the steps that use them: which stems' axes climb into the crowns, and the flag of a
    stem within a thicker one's crown reach."""
    from forestreg.engine.trees.inventory import _within_crown_reach
    from forestreg.engine.trees.segmentation import axis_stems
    from forestreg.engine.trees.stems import Stem

    path = tmp_path / "p.toml"
    path.write_text(
        "[trees]\ncrown_reach_dbh = 12.0\n\n[trees.segmentation]\naxis_dominance_dbh = 2.0\ndominance_ratio = 1.1\n",
        encoding="utf-8",
    )
    default, trees = ProductParams().trees, load_params(path).trees

    def stem(i, x, dbh):
        return Stem(
            id=i,
            base=np.array([x, 0.0, 0.0]),
            axis=np.array([0.0, 0.0, 1.0]),
            radius_m=dbh / 2,
            point_indices=np.zeros(0, dtype=np.int64),
        )

    # a 20 cm stem 2 m from a 40 cm one (6 DBH: 2.4 m), a 23 cm stem 5 m from it
    stems = [stem(1, 0.0, 0.4), stem(2, 2.0, 0.2), stem(3, -5.0, 0.23)]
    seg = default.segmentation
    assert [s.id for s in axis_stems(stems, seg.axis_dominance_dbh, seg.dominance_ratio)] == [1, 3]
    seg = trees.segmentation
    assert [s.id for s in axis_stems(stems, seg.axis_dominance_dbh, seg.dominance_ratio)] == [1, 2, 3]
    # by default the 20 cm stem grows without its axis (no flag) and 5 m is beyond 7 DBH (2.8 m); with
    # the file its axis climbs, and 2 m is within 12 DBH (4.8 m): flagged
    assert _within_crown_reach(stems, default) == {}
    assert set(_within_crown_reach(stems, trees)) == {2}
