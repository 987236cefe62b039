"""Real clouds from ../shared/data: VOPs on a real RIEGL scan, and registration of scans simulated
from real merged plots (paper sec. 4.3) against their known poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import read_scan
from forestreg.engine.simulate import simulate_scan_from_cloud
from forestreg.engine.tls.pair import register
from forestreg.engine.tls.params import RegistrationParams
from forestreg.engine.tls.prepare import extract_vops, prepare_scan, slice_layers


def test_real_riegl_scan_yields_vops_on_vertical_stems(shared_data):
    scan = read_scan(shared_data / "TLS_scan_scanner_at_origin.laz")
    params = RegistrationParams()
    prepared = prepare_scan(scan.points, scan.scanner_position, params)
    assert not prepared.levelled, "a level RIEGL scan must not be re-levelled"
    assert 1.0 < prepared.scanner_height_m < 2.0
    vops = extract_vops(slice_layers(prepared, params), params, 10.0)
    assert len(vops) >= 10
    # A VOP stands on a stem: around it, points rise continuously from the ground to above the
    # slice (a leaf cluster does not). Count 0.4 m height bins from 0.4 to 2.4 m above ground.
    pts = prepared.points[~prepared.ground_mask]
    above = pts[:, 2] - prepared.ground.height_at(pts[:, :2])
    tree = cKDTree(pts[:, :2])
    upright = 0
    for xy, r in zip(vops.xy, vops.radius):
        near = np.array(tree.query_ball_point(xy, r + 0.08), dtype=np.int64)
        bins = np.unique(np.floor((above[near] - 0.4) / 0.4).astype(int)) if len(near) else []
        upright += int(np.sum((np.asarray(bins) >= 0) & (np.asarray(bins) < 5)) >= 4)
    assert upright >= 0.6 * len(vops), f"only {upright} of {len(vops)} VOPs stand on a vertical structure"


@pytest.mark.parametrize(
    "name, first, second, step",
    [
        # ground mostly removed: the scanner height is given (1.4 m above the stems' base level)
        ("LPine1_demo.laz", (4.0, 3.0, 1.4), (11.0, 5.0, 1.4), 0.3),
        ("pine_plot.laz", (3.0, 3.0), (7.0, 6.0), 0.3),
    ],
)
def test_scans_simulated_from_real_plots_register(shared_data, name, first, second, step):
    cloud = read_scan(shared_data / name)
    a = simulate_scan_from_cloud(cloud, first, angular_step_deg=step, yaw_deg=0.0, name="a")
    b = simulate_scan_from_cloud(cloud, second, angular_step_deg=step, yaw_deg=70.0, name="b")
    truth = np.linalg.inv(a.pose) @ b.pose
    result = register(a.scan, b.scan)
    assert result.ok, result.reason
    rot, trans = rigid_errors(result.matrix, truth)
    assert rot < 0.05 and trans < 0.02, f"{rot:.4f} deg, {100 * trans:.2f} cm"
    crot, ctrans = rigid_errors(result.coarse_matrix, truth)
    assert crot < 0.5 and ctrans < 0.25, f"coarse {crot:.3f} deg, {ctrans:.3f} m"
    assert result.matched >= 6


def test_real_riegl_scan_origin_is_confirmed_quickly_and_a_moved_origin_is_not(shared_data):
    """The scanner-position shortcut on a real RIEGL scan: the file origin (the scanner) is the
    density peak; 20 m away it is not, and the full estimate runs instead."""
    from forestreg.engine.tls.scanner_position import estimate_scanner_position, origin_is_density_peak

    scan = read_scan(shared_data / "TLS_scan_scanner_at_origin.laz")
    assert origin_is_density_peak(scan.points, scan.scanner_position)
    assert np.hypot(*estimate_scanner_position(scan.points).position[:2]) < 0.5, "the full estimate agrees"
    assert not origin_is_density_peak(scan.points, scan.scanner_position + np.array([20.0, 5.0, 0.0]))


def test_real_riegl_scan_registers_onto_a_copy_whose_scanner_is_found_from_the_data(shared_data):
    """A scan exported in project coordinates (no scanner position) against one whose position is
    given: the found position stands ~0.2 m too high (the default instrument height), so its trunk
    slices lie 0.2 m higher in the world than the other scan's. The free-space check compares the
    points at the same heights and must not refuse the correct pose (it did: 15 %, allowed 15 %)."""
    from forestreg.engine.core.scan import Scan

    scan = read_scan(shared_data / "TLS_scan_scanner_at_origin.laz")
    turn = np.radians(23.0)
    to_copy = np.eye(4)
    to_copy[:2, :2] = [[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]
    to_copy[:3, 3] = (-2.7, 3.9, -0.3)  # the scanner stands 4.7 m from the copy's origin
    copy = Scan.from_points(scan.points @ to_copy[:3, :3].T + to_copy[:3, 3], name="moved copy")
    result = register(scan, copy)
    assert copy.meta["scanner_position"] == "file origin"
    moving = result.details.moving
    assert result.ok, result.reason
    rot, trans = rigid_errors(result.matrix, np.linalg.inv(to_copy))
    assert rot < 0.01 and trans < 0.005, (rot, trans)
    assert result.free_space_violation < 0.05
    # the copy's scanner was found from the data (not given), and higher than it stood
    assert moving.scanner_height_m > result.details.reference.scanner_height_m + 0.1
