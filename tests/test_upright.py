"""A cloud whose z axis is not up (a scan in a tilted scanner's own frame, a cloud exported on its
side) is refused before trees are measured across its stems; level clouds of every kind pass."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.io import read_scan, write_points
from forestreg.engine.tls.level import stem_axis


def _tilted(points: np.ndarray, deg: float, about: str = "x") -> np.ndarray:
    t = np.radians(deg)
    c, s = np.cos(t), np.sin(t)
    r = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) if about == "x" else np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return points @ r.T


@pytest.fixture(scope="module")
def pine(shared_data):
    return read_scan(shared_data / "pine_plot.laz").points


@pytest.mark.parametrize("deg, about", [(40.0, "x"), (90.0, "y")])
def test_the_stems_axis_is_read_over_the_whole_hemisphere(pine, deg, about):
    axis = stem_axis(_tilted(pine, deg, about))
    assert abs(axis.tilt_deg - deg) < 2.0 and not axis.upright


def test_level_clouds_stand_upright(pine, shared_data, sim_plot):
    level = stem_axis(pine)
    assert level.upright and level.tilt_deg < 4.0 and level.normals >= 2000
    # a real shrubby scan with few clean trunks: its best direction is a scan pattern, not trunks
    shrubs = stem_axis(read_scan(shared_data / "TLS_scan_scanner_at_origin.laz").points)
    assert shrubs.upright and shrubs.support < 0.02
    for name in ("mls", "lpine"):
        path = shared_data / ("spanner_MLS_Clip.laz" if name == "mls" else "LPine1_demo.laz")
        assert stem_axis(read_scan(path).points).upright
    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (8.0, 3.0)), seed=5, step=0.4, size=30.0)
    merged = np.vstack([s.world_points() for s in plot.scans])
    axis = stem_axis(merged)
    assert axis.upright and axis.tilt_deg < 2.0
    tilted = stem_axis(_tilted(merged, 25.0))
    assert not tilted.upright and abs(tilted.tilt_deg - 25.0) < 1.5


def test_trees_refuse_a_cloud_on_its_side(pine, tmp_path, capsys):
    path = tmp_path / "pine_on_its_side.laz"
    write_points(path, _tilted(pine, 90.0))
    assert main(["trees", str(path), "--out", str(tmp_path / "out"), "--no-cylinders", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "z axis is not up" in err and "deg off it" in err
    assert not (tmp_path / "out").exists()
