"""Scanners that see a sector only, and the built scenes (walls, posts in rows, a corridor, a
courtyard, a park) and planted rows of the simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError
from forestreg.engine.simulate import (
    BUILT_PRESETS,
    Material,
    ScannerSetup,
    make_scene,
    preset_names,
    scanner_options,
    simulate_plot,
    simulate_scan_from_cloud,
    simulate_tls_scan,
    stand_positions,
)
from forestreg.engine.simulate.built import local_to_world, post_rows

STEP = 1.0  # coarse beams: these tests check geometry, not density


def _socs_azimuth(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 1], points[:, 0]))


def _offset(az: np.ndarray, centre: float) -> np.ndarray:
    return (az - centre + 180.0) % 360.0 - 180.0


@pytest.fixture(scope="module")
def corridor():
    return make_scene("corridor", seed=3, size_m=40.0, post_rows=2)


def test_forward_looking_scan_sees_only_its_sector_and_clips_its_range(corridor):
    pos = stand_positions(corridor, 3.0, np.random.default_rng(0), n=1)[0]
    setup = ScannerSetup(
        x=float(pos[0]),
        y=float(pos[1]),
        yaw_deg=corridor.meta["axis_deg"],
        angular_step_deg=0.5,
        **scanner_options("robot_forward", azimuth_centre_deg=25.0),
    )
    sim = simulate_tls_scan(corridor, setup, seed=1)
    off = _offset(_socs_azimuth(sim.scan.points), 25.0)
    assert len(off) > 1000
    assert np.abs(off).max() <= 90.0 + 1e-6
    assert np.abs(off).max() > 88.0  # the sector is seen out to its edges
    r = np.linalg.norm(sim.scan.points, axis=1)
    assert r.max() <= 33.0 + 5 * setup.range_noise_m
    assert r.min() >= 0.3 - 5 * setup.range_noise_m
    # the robot's laser stands 0.7 m above the ground and its band is -20..+20 deg
    assert sim.pose[2, 3] - corridor.ground_z(*pos) == pytest.approx(0.7)
    el = np.degrees(np.arcsin(sim.scan.points[:, 2] / r))
    assert el.min() >= -20.0 - 0.1 and el.max() <= 20.0 + 0.1
    assert sim.scan.meta["azimuth_fov_deg"] == 180.0 and sim.scan.meta["azimuth_centre_deg"] == 25.0
    assert np.allclose(sim.scan.scanner_position, 0.0)


def test_a_300_degree_sector_leaves_its_gap_empty_and_a_full_turn_is_unchanged(corridor):
    pos = stand_positions(corridor, 3.0, np.random.default_rng(1), n=1)[0]
    base = dict(x=float(pos[0]), y=float(pos[1]), yaw_deg=10.0, angular_step_deg=STEP)
    sector = simulate_tls_scan(corridor, ScannerSetup(**base, **scanner_options("sector_300")), seed=2)
    full = simulate_tls_scan(corridor, ScannerSetup(**base), seed=2)
    off = _offset(_socs_azimuth(sector.scan.points), 0.0)
    assert np.abs(off).max() <= 150.0 + 1e-6
    gap = np.abs(_offset(_socs_azimuth(full.scan.points), 180.0)) < 30.0
    assert gap.sum() > 100  # the full turn sees what the sector leaves out
    assert 0.75 < len(sector.scan) / len(full.scan) < 0.9
    assert "azimuth_fov_deg" not in full.scan.meta


def test_sixteen_laser_lines():
    scene = make_scene("fence", seed=2, size_m=30.0)
    setup = ScannerSetup(
        x=0.0, y=3.0, yaw_deg=scene.meta["axis_deg"], angular_step_deg=0.5, **scanner_options("robot_lines")
    )
    sim = simulate_tls_scan(scene, setup, seed=0)
    el = np.degrees(np.arcsin(sim.scan.points[:, 2] / np.linalg.norm(sim.scan.points, axis=1)))
    lines = np.unique(np.round(el).astype(int))
    assert set(lines) <= set(range(-15, 16, 2)) and len(lines) >= 8


def test_corridor_scan_hits_walls_and_posts_where_they_stand(corridor):
    positions = stand_positions(corridor, 3.5, np.random.default_rng(2))
    plot = simulate_plot("corridor", positions, scene=corridor, seed=3, angular_step_deg=0.5, yaw_deg=[30.0, 200.0])
    sim = plot.scans[0]
    world = sim.world_points()
    walls = [b for b in corridor.boxes if b.kind == "wall"]
    assert len(walls) == 2
    on = {}
    for b in walls:
        sel = (sim.labels == Material.STRUCTURE) & (sim.object_ids == b.id)
        on[b.id] = int(sel.sum())
        a = math.radians(b.yaw_deg)
        across = -(world[sel, 0] - b.x) * math.sin(a) + (world[sel, 1] - b.y) * math.cos(a)
        assert np.abs(np.abs(across) - b.size[1] / 2.0).max() < 0.03  # on the wall's inner face
    assert all(n > 500 for n in on.values()), on
    hit_posts = 0
    for p in corridor.posts:
        sel = (sim.labels == Material.STRUCTURE) & (sim.object_ids == p.id)
        if sel.sum() < 5:
            continue
        hit_posts += 1
        d = np.hypot(world[sel, 0] - p.x, world[sel, 1] - p.y)
        assert np.abs(d - p.radius_m).max() < 0.02
    assert hit_posts >= 6
    assert (sim.labels == Material.GROUND).sum() > 1000
    assert not corridor.trees and (sim.labels == Material.TRUNK).sum() == 0
    assert len(plot.truth["posts"]) == len(corridor.posts) and len(plot.truth["walls"]) == 2


def test_posts_stand_at_the_stated_spacing_in_straight_rows(corridor):
    spacing = corridor.meta["post_spacing_m"]
    assert 3.0 <= spacing <= 4.0
    assert 6.0 <= corridor.meta["corridor_width_m"] <= 10.0
    rows = post_rows(corridor)
    assert len(rows) == 2
    by_id = {p.id: p for p in corridor.posts}
    for row in rows:
        xy = np.array([[by_id[i].x, by_id[i].y] for i in row["post_ids"]])
        assert len(xy) >= 8
        steps = np.hypot(*np.diff(xy, axis=0).T)
        assert np.abs(steps - spacing).max() < 0.06, steps  # built to a 1 cm tolerance
        ideal = local_to_world(corridor.meta["axis_deg"], np.array(row["u_m"]), np.full(len(xy), row["v_m"]))
        assert np.abs(xy - ideal).max() < 0.05
        assert all(0.1 <= by_id[i].radius_m <= 0.2 for i in row["post_ids"])
    # the two rows face each other across the corridor
    a, b = rows
    assert (
        abs(abs(a["v_m"] - b["v_m"]) - (corridor.meta["corridor_width_m"] - 2 * corridor.meta["post_offset_m"])) < 1e-9
    )


@pytest.mark.parametrize("preset", sorted(BUILT_PRESETS))
def test_built_scenes_are_deterministic_and_walkable(preset):
    a = make_scene(preset, seed=7, size_m=40.0)
    b = make_scene(preset, seed=7, size_m=40.0)
    c = make_scene(preset, seed=8, size_m=40.0)
    assert (a.boxes, a.posts, a.trees) == (b.boxes, b.posts, b.trees)
    assert (a.boxes, a.posts, a.trees) != (c.boxes, c.posts, c.trees)
    assert preset in preset_names()
    pos = stand_positions(a, 4.0, np.random.default_rng(0))
    assert np.hypot(*(pos[1] - pos[0])) == pytest.approx(4.0)
    cleared = a.cleared(pos, 1.0)
    assert [x for x in cleared.boxes if x.kind in ("wall", "block")] == [
        x for x in a.boxes if x.kind in ("wall", "block")
    ]


def test_built_scene_contents():
    court = make_scene("courtyard", seed=1, size_m=40.0)
    assert 3 <= len(court.trees) <= 6 and not court.posts
    assert sum(b.kind == "wall" for b in court.boxes) == 5  # one wall in two pieces either side of the entrance
    assert 26.0 <= court.meta["courtyard_side_m"] <= 32.0
    for name, (lo, hi) in (("park", (4, 7)), ("campus", (2, 4))):
        sc = make_scene(name, seed=2, size_m=50.0)
        assert lo <= len(sc.trees) <= hi, name
        xy = np.array([[t.x, t.y] for t in sc.trees])
        d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
        assert d.min() >= 8.0
        assert any(b.kind == "block" for b in sc.boxes)
    fence = make_scene("fence", seed=1, size_m=40.0)
    assert any(b.kind == "fence_rail" for b in fence.boxes)
    assert all(p.kind == "fence_post" and p.height_m >= 1.8 for p in fence.posts)
    with pytest.raises(ParameterError):
        make_scene("corridor", no_such_option=1)
    narrow = make_scene("corridor", seed=1, size_m=40.0, corridor_width_m=6.0, post_spacing_m=3.5)
    assert narrow.meta["corridor_width_m"] == 6.0 and narrow.meta["post_spacing_m"] == 3.5


def test_plantation_rows_are_an_exact_lattice():
    from scipy.spatial import cKDTree

    sc = make_scene("plantation_rows", seed=4, size_m=50.0)
    xy = np.array([[t.x, t.y] for t in sc.trees])
    nn = cKDTree(xy).query(xy, k=2)[0][:, 1]
    assert np.median(nn) == pytest.approx(3.0, abs=0.1)
    assert np.percentile(nn, 90) < 3.2  # small jitter: every tree's nearest neighbour is about 3 m away
    full = 50.0 * 50.0 / 12.0
    assert 0.9 * full < len(xy) < 1.05 * full


def test_from_cloud_sector():
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 20000)
    rad = rng.uniform(3, 15, 20000)
    cloud = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-1.4, 3.0, 20000)])
    sim = simulate_scan_from_cloud(
        cloud,
        (0.0, 0.0, 0.0),
        angular_step_deg=2.0,
        point_spacing_m=0.0,
        yaw_deg=40.0,
        azimuth_fov_deg=120.0,
        azimuth_centre_deg=-30.0,
    )
    off = _offset(_socs_azimuth(sim.scan.points), -30.0)
    assert np.abs(off).max() <= 60.0 + 1e-6 and np.abs(off).max() > 55.0
    assert sim.setup.azimuth_fov_deg == 120.0
