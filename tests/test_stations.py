"""Scanner stations of a merged terrestrial cloud and their upward limit (engine/tls/stations.py),
against simulated plots with known stations and field of view, and real clouds."""

import math

import numpy as np
import pytest

from forestreg.engine.io import read_scan
from forestreg.engine.simulate import simulate_plot
from forestreg.engine.tls.stations import StationParams, Stations, beyond_view, scanner_stations

STATIONS = [(-5.0, -5.0), (5.0, -5.0), (0.0, 5.0)]


def _merged(elevation_max_deg: float) -> np.ndarray:
    plot = simulate_plot(
        "mixed_temperate",
        STATIONS,
        seed=3,
        size_m=24.0,
        angular_step_deg=0.5,
        scanner_options={"elevation_max_deg": elevation_max_deg},
    )
    return np.vstack([s.world_points() for s in plot.scans])


def _nearest(found: np.ndarray) -> np.ndarray:
    return np.array([np.hypot(*(found[:, :2] - s).T).min() for s in STATIONS])


@pytest.mark.parametrize("limit", [45.0, 60.0])
def test_stations_and_limit_of_a_merged_plot(limit):
    stations = scanner_stations(_merged(limit))
    assert len(stations.positions) == 3
    assert _nearest(stations.positions).max() < 0.25  # 0.03-0.13 m on these scans
    assert np.all(np.abs(stations.positions[:, 2] - 1.5) < 0.3)  # 1.5 m over flat ground at z 0
    assert stations.limited and abs(stations.upward_limit_deg - limit) <= 2.0
    assert stations.step_ratio < 0.6


def test_full_dome_shows_no_limit():
    stations = scanner_stations(_merged(90.0))
    assert len(stations.positions) == 3 and _nearest(stations.positions).max() < 0.25
    assert not stations.limited and stations.upward_limit_deg == 90.0
    assert "full dome" in stations.describe()


def test_limit_as_set_and_switched_off():
    points = _merged(90.0)
    set_60 = scanner_stations(points, StationParams(upward_limit_deg=60.0))
    assert set_60.limited and set_60.upward_limit_deg == 60.0 and set_60.limit_from == "set"
    off = scanner_stations(points, StationParams(upward_limit_deg=90.0))
    assert not off.limited and len(off.positions) == 0


def test_beyond_view_needs_every_station():
    stations = Stations(np.array([[0.0, 0.0, 1.5], [10.0, 0.0, 1.5]]), 60.0)
    # 20 m over a point 5 m from each station: 73 deg above both
    assert beyond_view(np.array([5.0, 0.0, 20.0]), stations, 0.5)
    # 12 m out from the second station it lies at 58 deg: seen from there
    assert not beyond_view(np.array([-2.0, 0.0, 20.0]), stations, 0.5)
    # one station: 7.81 m over it at 5 m out is 57.4 deg, below the limit less the 1 deg margin;
    # the clearance lifts the tested point to 59.3 deg, within it
    one = Stations(stations.positions[:1], 60.0)
    assert not beyond_view(np.array([5.0, 0.0, 9.31]), one, 0.0)
    assert beyond_view(np.array([5.0, 0.0, 9.31]), one, 0.6)
    assert not beyond_view(np.array([5.0, 0.0, 20.0]), Stations(stations.positions, 90.0), 0.5)


@pytest.mark.realdata
def test_real_clouds(shared_data):
    scan = read_scan(shared_data / "TLS_scan_scanner_at_origin.laz")
    points = np.asarray(scan.points, dtype=np.float64)
    one = scanner_stations(points)
    assert len(one.positions) == 1
    origin = -np.asarray(scan.origin_shift, dtype=np.float64)  # the file's origin in the local frame
    # its own blind circle: the cone of its lowest beam places it (0.10 m off)
    assert math.hypot(*(one.positions[0, :2] - origin[:2])) < 0.2
    # a RIEGL VZ-400i sees up to +60 deg (its points reach 61 deg from the origin): 61 deg found
    assert one.limited and 59.0 <= one.upward_limit_deg <= 62.0
    # airborne and mobile clouds leave no blind circles
    for name in ("lidR_MixedConifer.laz", "spanner_MLS_Clip.laz", "SERC_trunk_mls.laz"):
        cloud = np.asarray(read_scan(shared_data / name).points, dtype=np.float64)
        assert len(scanner_stations(cloud).positions) == 0, name


def test_a_ring_that_is_no_ring_is_refused():
    """A ring whose inner radius is not below its outer one, or a blind circle reaching into the
    ring, is a parameter error (one line, exit 2 at the command line), not an empty search."""
    from forestreg.engine.core.errors import ParameterError

    with pytest.raises(ParameterError, match="ring_m"):
        StationParams(ring_m=(3.0, 1.0))
    with pytest.raises(ParameterError, match="hole_m"):
        StationParams(hole_m=2.0)
