"""UAV LiDAR and backpack simulators and the ground/UAV co-registration case (System B test bed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestreg.engine.core.errors import ParameterError
from forestreg.engine.simulate import (
    BackpackSetup,
    Material,
    SimulatedCloud,
    UavSetup,
    backpack_path,
    canopy_point_density,
    make_scene,
    simulate_backpack_scan,
    simulate_coregistration_case,
    simulate_uav_scan,
    uav_flight_lines,
)
from forestreg.engine.simulate.platforms import backpack_waypoints

SIZE_M = 20.0


@pytest.fixture(scope="module")
def scene():
    return make_scene("planted_conifer", seed=0, size_m=SIZE_M)


@pytest.fixture(scope="module")
def uav(scene):
    """A full-density flight (the paper's density) over the small plot."""
    return simulate_uav_scan(scene, UavSetup(), seed=1)


@pytest.fixture(scope="module")
def walk(scene):
    """A short backpack loop at a tenth of the default density."""
    setup = BackpackSetup(
        waypoints=((-6.0, -6.0), (6.0, -6.0), (6.0, 6.0), (-6.0, 6.0), (-6.0, -5.0)), density_scale=0.025
    )
    return setup, simulate_backpack_scan(scene, setup, seed=2)


# --------------------------------------------------------------------------------------------
# UAV
# --------------------------------------------------------------------------------------------


def test_uav_canopy_density_is_the_papers(uav, scene):
    # paper table 1: 250-300 points/m2; nominal: 16 ch * 10 Hz * 450 firings / (50 m * 5 m/s)
    assert UavSetup().nominal_density_per_m2 == pytest.approx(288.0)
    canopy = canopy_point_density(uav.points, scene)
    assert 200.0 <= canopy <= 350.0, canopy
    assert uav.meta["canopy_density_per_m2"] == pytest.approx(canopy)
    # a patch in the middle of the plot gives the same figure
    patch = canopy_point_density(uav.points, scene, extent=(-5.0, 5.0, -5.0, 5.0))
    assert 200.0 <= patch <= 350.0, patch
    # a density scale thins the cloud proportionally
    thin = simulate_uav_scan(scene, UavSetup(density_scale=0.1), seed=1)
    assert len(thin) / len(uav) == pytest.approx(0.1, rel=0.15)


def test_uav_sees_few_points_under_the_crowns(uav, scene):
    pts = uav.points
    height = pts[:, 2] - scene.ground_z(pts[:, 0], pts[:, 1])
    tops = np.array([t.point_at_height(t.height_m)[:2] for t in scene.trees])
    radius = np.array([t.crown_radius_m for t in scene.trees])
    crown_base = np.array([t.crown_base_m for t in scene.trees])
    dist, k = cKDTree(tops).query(pts[:, :2])
    core = dist < 0.3 * radius[k]  # under the middle of a crown
    under = int((core & (height < 2.0)).sum())
    in_crown = int((core & (height > crown_base[k])).sum())
    assert in_crown > 1000
    assert under / in_crown < 0.45, (under, in_crown)
    # the ground is sampled far more densely in the gaps than under the crowns' middle
    ground = uav.labels == Material.GROUND
    open_ground = ground & (dist > 1.2 * radius[k])
    assert open_ground.sum() > 0


def test_uav_flight_geometry(uav, scene):
    setup = UavSetup()
    lines = uav_flight_lines(scene, setup)
    # serpentine lines 50 m apart along x, alternating direction, at 86 m over the plot centre
    ys = lines[:, 0, 1]
    assert np.allclose(np.diff(ys), 50.0)
    assert 0.0 in ys
    assert np.all(np.sign(lines[:, 1, 0] - lines[:, 0, 0]) == [(-1) ** i for i in range(len(lines))])
    z_flight = scene.ground_z(0.0, 0.0) + 86.0
    assert np.allclose(uav.trajectory[:, 2], z_flight)
    step = np.linalg.norm(np.diff(uav.trajectory[:40], axis=0), axis=1)
    assert np.allclose(step, setup.speed_m_s / setup.rotation_hz)
    # every return within 45 deg of nadir across track of some line, and within 100 m
    pts = uav.points
    across = np.abs(pts[:, 1, None] - ys[None, :])
    angle = np.degrees(np.arctan2(across, z_flight - pts[:, 2, None])).min(axis=1)
    assert angle.max() <= 45.0 + 0.1
    rng, _ = cKDTree(uav.trajectory).query(pts)
    assert rng.max() <= 100.0 + 0.2
    # range noise ~3 cm: ground points scatter about the exact terrain by sigma * cos(angle)
    ground = uav.labels == Material.GROUND
    dz = pts[ground, 2] - scene.ground_z(pts[ground, 0], pts[ground, 1])
    assert 0.02 < dz.std() < 0.032, dz.std()
    assert abs(dz.mean()) < 0.003


def test_uav_rejects_a_flight_through_the_canopy(scene):
    with pytest.raises(ParameterError, match="canopy"):
        simulate_uav_scan(scene, UavSetup(altitude_m=12.0), seed=0)
    with pytest.raises(ParameterError, match="altitude_m"):
        UavSetup(altitude_m=-5.0)


# --------------------------------------------------------------------------------------------
# backpack
# --------------------------------------------------------------------------------------------


def test_backpack_trajectory_length_and_speed(walk, scene):
    setup, cloud = walk
    traj = cloud.trajectory
    planned = 12.0 * 3 + 11.0  # the loop's legs
    horizontal = np.hypot(*np.diff(traj[:, :2], axis=0).T)
    length = float(horizontal.sum())
    assert length == pytest.approx(planned, rel=0.03)
    duration = (len(traj) - 1) / (setup.rotation_hz * setup.sectors_per_rotation)
    assert length / duration == pytest.approx(setup.speed_m_s, rel=0.01)
    assert cloud.meta["speed_m_s"] == pytest.approx(setup.speed_m_s, rel=0.01)
    assert cloud.meta["duration_s"] == pytest.approx(planned / setup.speed_m_s, rel=0.03)
    assert np.allclose(traj[:, 2], scene.ground_z(traj[:, 0], traj[:, 1]) + setup.height_m)
    # the path keeps clear of every stem (surface + clearance) at walking heights
    for tree in scene.trees:
        r = tree.dbh_m / 2.0 * (1.0 + tree.flare)
        for h in (0.0, 1.0, 1.5):
            c = tree.point_at_height(h)[:2]
            assert np.hypot(*(traj[:, :2] - c).T).min() >= r + setup.clearance_m - 1e-6


def test_backpack_samples_the_stems(walk, scene):
    setup, cloud = walk
    pts = cloud.points
    rng, _ = cKDTree(cloud.trajectory).query(pts)
    assert rng.min() >= setup.min_range_m - 0.15 and rng.max() <= setup.max_range_m + 0.15
    trunk = cloud.labels == Material.TRUNK
    assert trunk.mean() > 0.15, trunk.mean()
    # stems within 4 m of the path have bark points at breast height (+-0.25 m), even at a
    # tenth of the default density (a few stand behind others or by the path's corners)
    counts = []
    for tree in scene.trees:
        bh = tree.point_at_height(1.3)
        if np.hypot(*(cloud.trajectory[:, :2] - bh[:2]).T).min() > 4.0:
            continue
        counts.append(int((trunk & (cloud.object_ids == tree.id) & (np.abs(pts[:, 2] - bh[2]) < 0.25)).sum()))
    counts = np.asarray(counts)
    assert len(counts) >= 20
    assert np.median(counts) >= 100, counts
    assert (counts >= 20).mean() >= 0.8, counts
    # stems are sampled far more densely than from the air (per tree, at 0.5-3 m)
    height = pts[:, 2] - scene.ground_z(pts[:, 0], pts[:, 1])
    low_trunk = trunk & (height > 0.5) & (height < 3.0)
    assert low_trunk.sum() > 20 * len(scene.trees)


def test_backpack_default_serpentine(scene):
    setup = BackpackSetup()
    wp = backpack_waypoints(scene, setup)
    half = SIZE_M / 2.0 - setup.edge_margin_m
    assert np.allclose(np.abs(wp).max(axis=0), half)
    assert len(np.unique(wp[:, 1])) == round(2 * half / setup.line_spacing_m) + 1
    path = backpack_path(scene, BackpackSetup(extent_m=6.0, centre=(1.0, -1.0)))
    assert np.abs(path[:, 0] - 1.0).max() <= 3.0 + 1.0 and np.abs(path[:, 1] + 1.0).max() <= 3.0 + 1.0
    with pytest.raises(ParameterError, match="outside the plot"):
        backpack_path(scene, BackpackSetup(waypoints=((0.0, 0.0), (30.0, 0.0))))
    with pytest.raises(ParameterError, match="waypoints"):
        BackpackSetup(waypoints=((0.0, 0.0),))


def test_backpack_path_goes_around_stems_and_buildings(scene):
    tree = min(scene.trees, key=lambda t: math.hypot(t.x, t.y))
    setup = BackpackSetup(waypoints=((tree.x - 3.0, tree.y), (tree.x + 3.0, tree.y)))
    path = backpack_path(scene, setup)  # straight through the stem's axis
    r = tree.dbh_m / 2.0 * (1.0 + tree.flare)
    assert np.hypot(path[:, 0] - tree.x, path[:, 1] - tree.y).min() >= r + setup.clearance_m - 1e-6
    steps = np.hypot(*np.diff(path[:, :2], axis=0).T)
    ds = setup.speed_m_s / (setup.rotation_hz * setup.sectors_per_rotation)
    assert steps.max() < 1.5 * ds  # a continuous detour round the stem, at walking speed
    # half-way round this stem, and the path also skirts a neighbour near its end
    keep_out = r + setup.clearance_m
    assert 6.0 + 0.5 * (math.pi - 2.0) * keep_out < steps.sum() < 6.0 + 2.0 * math.pi * keep_out
    field = make_scene("open_field", seed=0, size_m=30.0)
    house = next(b for b in field.boxes if b.kind == "building")
    path = backpack_path(field, BackpackSetup(waypoints=((house.x - 9.0, house.y), (house.x + 9.0, house.y))))
    a = math.radians(house.yaw_deg)
    rel = path[:, :2] - (house.x, house.y)
    u = rel[:, 0] * math.cos(a) + rel[:, 1] * math.sin(a)
    w = -rel[:, 0] * math.sin(a) + rel[:, 1] * math.cos(a)
    to_wall = np.hypot(
        np.maximum(np.abs(u) - house.size[0] / 2.0, 0.0), np.maximum(np.abs(w) - house.size[1] / 2.0, 0.0)
    )
    assert to_wall.min() >= 0.5 - 1e-6
    assert np.hypot(*np.diff(path[:, :2], axis=0).T).max() < 1.5 * ds


def test_simulated_cloud_subset_and_scan(walk):
    _, cloud = walk
    mask = cloud.labels == Material.TRUNK
    sub = cloud.subset(mask)
    assert isinstance(sub, SimulatedCloud) and len(sub) == int(mask.sum())
    assert np.all(sub.labels == Material.TRUNK)
    m = np.eye(4)
    m[:3, 3] = (100.0, -50.0, 3.0)
    scan = sub.to_scan("trunks", matrix=m)
    assert scan.name == "trunks" and len(scan) == len(sub)
    assert np.abs(scan.file_points - (sub.points + m[:3, 3])).max() < 1e-12


# --------------------------------------------------------------------------------------------
# co-registration case
# --------------------------------------------------------------------------------------------


def _mapped(case) -> np.ndarray:
    g = case.ground.file_points
    return g @ case.matrix[:3, :3].T + case.matrix[:3, 3]


@pytest.mark.parametrize("platform", ["backpack", "tls"])
def test_coregistration_matrix_is_exact(scene, platform):
    case = simulate_coregistration_case(
        scene=scene,
        seed=4,
        ground_platform=platform,
        ground_extent_m=12.0,
        heading_deg=180.0,
        offset_m=(10.0, -10.0, 10.0),
        uav_density_scale=0.1,
        backpack_density_scale=0.01,
        tls_step_deg=0.8,
    )
    # p_uav = matrix @ p_ground, exactly, for every ground point
    assert np.abs(_mapped(case) - case.ground_cloud.points).max() < 1e-9
    assert np.allclose(case.matrix[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-15)
    assert np.allclose(case.matrix[:3, 3], (10.0, -10.0, 10.0))
    # the ground frame really is displaced: heading 180 and 10 m offsets
    centre_ground = case.ground.file_points[:, :2].mean(axis=0)
    centre_world = case.ground_cloud.points[:, :2].mean(axis=0)
    assert np.allclose(centre_ground, -(centre_world - (10.0, -10.0)), atol=1e-6)
    # ground data only over the central 12 m, the UAV over the whole plot
    assert np.abs(case.ground_cloud.points[:, :2]).max() <= 6.0
    assert np.abs(case.uav.file_points[:, :2]).max() > 9.0
    assert len(case.ground_cloud.labels) == len(case.ground) and len(case.uav_cloud.labels) == len(case.uav)
    assert (case.ground_cloud.labels == Material.TRUNK).sum() > 500
    assert case.uav_cloud.object_ids.shape == case.uav_cloud.labels.shape


def test_coregistration_with_utm_like_coordinates(scene):
    offset = np.array([500000.0, 5000000.0, 200.0])
    case = simulate_coregistration_case(
        scene=scene,
        seed=5,
        ground_extent_m=10.0,
        heading_deg=-35.0,
        offset_m=(2.0, 3.0, -1.0),
        uav_density_scale=0.1,
        backpack_density_scale=0.01,
        world_offset=offset,
    )
    uav = case.uav
    # the UAV scan keeps a local frame near the data: float64 keeps sub-micrometre steps
    assert np.all(np.abs(uav.origin_shift - offset) < 200.0)
    assert np.abs(uav.points).max() < 300.0
    assert np.abs(uav.points - (case.uav_cloud.points + offset - uav.origin_shift)).max() < 1e-9
    assert np.all(case.ground.origin_shift == 0.0)
    expected = case.ground_cloud.points + offset
    assert np.abs(_mapped(case) - expected).max() < 2e-9  # float64 ulp at 5e6 m is 1e-9
    assert np.allclose(case.matrix[:3, 3], offset + (2.0, 3.0, -1.0))


def test_coregistration_is_deterministic_per_seed():
    kw = dict(size_m=15.0, ground_extent_m=8.0, uav_density_scale=0.05, backpack_density_scale=0.01, heading_deg=10.0)
    a = simulate_coregistration_case("planted_conifer", seed=7, **kw)
    b = simulate_coregistration_case("planted_conifer", seed=7, **kw)
    c = simulate_coregistration_case("planted_conifer", seed=8, **kw)
    assert np.array_equal(a.ground.points, b.ground.points)
    assert np.array_equal(a.uav.points, b.uav.points)
    assert np.array_equal(a.ground_cloud.labels, b.ground_cloud.labels)
    assert len(a.ground) != len(c.ground) or not np.array_equal(a.ground.points, c.ground.points)
    with pytest.raises(ParameterError, match="ground_platform"):
        simulate_coregistration_case("planted_conifer", ground_platform="drone")
    with pytest.raises(ParameterError, match="ground_extent_m"):
        simulate_coregistration_case("planted_conifer", size_m=15.0, ground_extent_m=30.0)


def test_progress_is_reported(scene):
    seen: list[float] = []
    simulate_uav_scan(scene, UavSetup(density_scale=0.02), seed=0, progress=lambda f, m: seen.append(f))
    assert seen[0] == 0.0 and seen[-1] == 1.0
    assert all(b >= a for a, b in zip(seen, seen[1:]))
    assert math.isfinite(sum(seen))


def test_backpack_slam_tilt_and_drift(scene):
    """A SLAM map error: a constant 1.5 deg tilt (down towards azimuth 30 deg) and a drift growing
    over the walk. The tilt alone is rigid (the fitted map -> world rotation is 1.5 deg, nothing
    left over); the drift leaves a non-rigid residual that grows with it."""
    from forestreg.engine.core.transform import rotation_angle_deg

    wp = ((-6.0, -6.0), (6.0, -6.0), (6.0, 6.0), (-6.0, 6.0))
    tilted = BackpackSetup(waypoints=wp, density_scale=0.01, slam_tilt_deg=1.5, slam_tilt_azimuth_deg=30.0)
    cloud = simulate_backpack_scan(scene, tilted, seed=2)
    fit = np.asarray(cloud.meta["slam_fit_matrix"])
    assert abs(rotation_angle_deg(fit[:3, :3]) - 1.5) < 1e-6
    assert cloud.meta["slam_residual_rms_m"] < 1e-6
    # the map sinks towards azimuth 30 deg: a plane through the ground points dips that way
    g = cloud.points[cloud.labels == Material.GROUND]
    a, b, _ = np.linalg.lstsq(np.column_stack([g[:, 0], g[:, 1], np.ones(len(g))]), g[:, 2], rcond=None)[0]
    truth_g = g @ fit[:3, :3].T + fit[:3, 3]
    a0, b0, _ = np.linalg.lstsq(
        np.column_stack([truth_g[:, 0], truth_g[:, 1], np.ones(len(g))]), truth_g[:, 2], rcond=None
    )[0]
    slope = np.array([a - a0, b - b0])
    assert abs(np.degrees(np.arctan(np.hypot(*slope))) - 1.5) < 0.05
    assert abs(np.degrees(np.arctan2(-slope[1], -slope[0])) - 30.0) < 2.0

    drifted = BackpackSetup(waypoints=wp, density_scale=0.01, slam_drift_deg=2.0, slam_drift_m=(0.3, 0.0, 0.1))
    cloud = simulate_backpack_scan(scene, drifted, seed=2)
    assert 0.02 < cloud.meta["slam_residual_rms_m"] < 0.5
    with pytest.raises(ParameterError):
        BackpackSetup(slam_drift_m=(0.0, float("nan"), 0.0))
    with pytest.raises(ParameterError):
        BackpackSetup(slam_tilt_deg=-1.0)
