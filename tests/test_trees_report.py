"""The trees report: plot map, table and per-tree figures (points and cylinder models)."""

from __future__ import annotations

import math
import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from forestreg.engine.core.errors import ScanDataError
from forestreg.engine.report.trees_report import (
    FLAG_COLOUR,
    ORDER_COLOURS,
    WOOD_COLOUR,
    cylinder_polygons,
    write_trees_report,
)


def _rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0


def _share_of_colour(png_path, hex_colour: str, tol: float = 0.08) -> float:
    img = mpimg.imread(png_path)[..., :3]
    return float((np.abs(img - _rgb(hex_colour)).max(axis=2) < tol).mean())


def _fake_plot():
    """Three trees (stem cylinder + crown ball) and ground; tree 2 without a cylinder model,
    tree 3 flagged."""
    rng = np.random.default_rng(0)
    pts, ids, wood, rows, cyls = [], [], [], [], {}
    for tid, (x, y, r, h) in enumerate([(2.0, 3.0, 0.15, 12.0), (8.0, 2.0, 0.2, 15.0), (5.0, 8.0, 0.1, 9.0)], start=1):
        z = rng.uniform(0, h * 0.6, 3000)
        a = rng.uniform(0, 2 * math.pi, 3000)
        stem = np.c_[x + r * np.cos(a), y + r * np.sin(a), z]
        crown = rng.normal(0, 1.0, (4000, 3)) * [1.5, 1.5, 1.2] + [x, y, h * 0.75]
        pts += [stem, crown]
        ids += [np.full(len(stem), tid), np.full(len(crown), tid)]
        wood += [np.full(len(stem), 0.9), np.full(len(crown), 0.1)]
        rows.append(
            {
                "tree_id": tid,
                "x": x,
                "y": y,
                "dbh_m": 2 * r,
                "height_m": h,
                "crown_base_m": h * 0.5,
                "crown_area_m2": 7.0,
                "crown_volume_m3": 20.0,
                "volume_m3": 0.3 * tid,
                "flag": "leaning, check the stem" if tid == 3 else "",
            }
        )
        if tid != 2:
            n = 6
            seg = h / n
            table = {
                "start_x": np.r_[np.full(n, x), x, x],
                "start_y": np.r_[np.full(n, y), y, y],
                "start_z": np.r_[np.arange(n) * seg, 5.0, 6.0],
                "axis_x": np.r_[np.zeros(n), 0.8, -0.6],
                "axis_y": np.r_[np.zeros(n), 0.0, 0.0],
                "axis_z": np.r_[np.ones(n), 0.6, 0.8],
                "length_m": np.r_[np.full(n, seg), 2.0, 1.5],
                "radius_m": np.r_[np.linspace(r, r / 3, n), 0.05, 0.03],
                "branch_order": np.r_[np.zeros(n), 1, 2],
                "parent": np.r_[-1, np.arange(n - 1), 1, 2],
            }
            cyls[tid] = table
    ground = np.c_[rng.uniform(0, 10, (5000, 2)), rng.normal(0, 0.02, 5000)]
    pts.append(ground)
    ids.append(np.zeros(len(ground), int))
    wood.append(np.zeros(len(ground)))
    return rows, np.vstack(pts), np.concatenate(ids), np.concatenate(wood), cyls


def test_report_files_and_contents(tmp_path):
    rows, pts, ids, wood, cyls = _fake_plot()
    path = write_trees_report(tmp_path / "trees", rows, pts, ids, wood, cyls, title="Plot 4 trees")
    assert path == tmp_path / "trees" / "report.html" and path.is_file()
    html = path.read_text()
    assert "Plot 4 trees" in html
    for tid in (1, 2, 3):
        assert f'id="row-{tid}"' in html and f'id="tree-{tid}"' in html
        png = tmp_path / "trees" / "figures" / f"tree_{tid}.png"
        assert png.is_file()
        img = mpimg.imread(png)[..., :3]
        assert img.std() > 0.05  # not blank
        assert _share_of_colour(png, WOOD_COLOUR) > 0.001  # wood points drawn
    assert "leaning, check the stem" in html
    assert html.count("data:image/png;base64,") == 4  # map + 3 trees
    assert len(html) < 20e6
    # cylinder models: stem colour in trees 1 and 3, none in tree 2 (no model)
    figs = tmp_path / "trees" / "figures"
    assert _share_of_colour(figs / "tree_1.png", ORDER_COLOURS[0]) > 0.002
    assert _share_of_colour(figs / "tree_1.png", ORDER_COLOURS[1]) > 0.0002
    assert _share_of_colour(figs / "tree_2.png", ORDER_COLOURS[0]) < 0.0005
    # the map: non-blank, and the flagged tree in red
    assert mpimg.imread(figs / "map.png")[..., :3].std() > 0.05
    assert _share_of_colour(figs / "map.png", FLAG_COLOUR) > 0.0002
    # the total wood volume 0.3 + 0.6 + 0.9
    assert "1.800" in html


def test_figure_cap_and_missing_values(tmp_path):
    rows, pts, ids, wood, cyls = _fake_plot()
    rows[1]["dbh_m"] = None
    rows[1]["volume_m3"] = float("nan")
    path = write_trees_report(tmp_path, rows, pts, ids, None, cyls, max_tree_figures=2)
    html = path.read_text()
    assert html.count("data:image/png;base64,") == 3  # map + 2 trees
    assert re.search(r"No figure .* for trees: 3", html)
    assert 'id="row-3"' in html  # still in the table
    assert not (tmp_path / "figures" / "tree_3.png").exists()


def test_cylinder_polygons():
    vertical = {
        "start_x": np.array([1.0]),
        "start_y": np.array([0.0]),
        "start_z": np.array([0.5]),
        "axis_x": np.array([0.0]),
        "axis_y": np.array([0.0]),
        "axis_z": np.array([2.0]),  # not unit: normalised
        "length_m": np.array([2.0]),
        "radius_m": np.array([0.1]),
    }
    poly = cylinder_polygons(vertical)[0]
    np.testing.assert_allclose(sorted(set(np.round(poly[:, 0], 9))), [0.9, 1.1])
    np.testing.assert_allclose(sorted(set(np.round(poly[:, 1], 9))), [0.5, 2.5])
    towards_viewer = dict(vertical, axis_y=np.array([1.0]), axis_z=np.array([0.0]))
    poly = cylinder_polygons(towards_viewer)[0]  # seen end-on: a square of side 2r
    assert np.ptp(poly[:, 0]) == pytest.approx(0.2) and np.ptp(poly[:, 1]) == pytest.approx(0.2)


def test_bad_inputs(tmp_path):
    rows, pts, ids, wood, cyls = _fake_plot()
    with pytest.raises(ScanDataError):
        write_trees_report(tmp_path, rows, pts[:, :2], ids, wood, cyls)
    with pytest.raises(ScanDataError):
        write_trees_report(tmp_path, rows, pts, ids[:-1], wood, cyls)
    with pytest.raises(ScanDataError):
        write_trees_report(tmp_path, rows, pts, ids, wood[:5], cyls)
    bad = {1: dict(cyls[1], radius_m=np.zeros(2))}
    with pytest.raises(ScanDataError, match="differ in length"):
        write_trees_report(tmp_path, rows, pts, ids, wood, bad)


def test_report_draws_heights_against_the_height_diameter_curve(tmp_path):
    """With the plot's curve, a figure of the heights coloured by their trust: the flagged tree's
    height (low) drawn in the flag colour, the curve's description in the caption."""
    from forestreg.engine.trees.allometry import HeightCurve

    rows, pts, ids, wood, cyls = _fake_plot()
    trusts = ("high", "medium", "low")
    rows = [{**r, "height_quality": f"highest tree point; {q}"} for r, q in zip(rows, trusts)]
    curve = HeightCurve(a=1.2, b=0.19, n_trees=12, n_inliers=11, scatter=0.05)
    path = write_trees_report(tmp_path, rows, pts, ids, wood, cyls, height_curve=curve)
    html = path.read_text()
    assert "height-diameter curve" in html and "from 12 trees (11 kept)" in html and "20 % below" in html
    png = tmp_path / "figures" / "height_curve.png"
    assert png.is_file()
    assert _share_of_colour(png, FLAG_COLOUR) > 0.0002  # the low height's cross
    # without a curve, no such figure
    write_trees_report(tmp_path / "none", rows, pts, ids, wood, cyls)
    assert not (tmp_path / "none" / "figures" / "height_curve.png").exists()


def test_report_draws_the_scanner_stations(tmp_path):
    """With the stations found in the cloud, the map draws them (blue triangles) and its caption
    names them and their upward limit; without, neither."""
    from forestreg.engine.tls.stations import Stations

    rows, pts, ids, wood, cyls = _fake_plot()
    stations = Stations(np.array([[1.0, 1.0, 1.5], [9.0, 9.0, 1.5]]), 60.0, step_ratio=0.3, direction_share=1.0)
    html = write_trees_report(tmp_path / "with", rows, pts, ids, wood, cyls, stations=stations).read_text()
    assert "scanner stations (blue triangles): 2 scanner stations, upward limit 60 deg" in html
    plain = write_trees_report(tmp_path / "plain", rows, pts, ids, wood, cyls).read_text()
    assert "scanner station" not in plain
    blue = "#1f77b4"
    assert (
        _share_of_colour(tmp_path / "with" / "figures" / "map.png", blue)
        > _share_of_colour(tmp_path / "plain" / "figures" / "map.png", blue) + 0.0001
    )  # two triangles; none of the tree colours is this blue


def test_report_marks_heights_from_the_curve(tmp_path):
    """A height from the plot's height-diameter curve is marked in the table (a superscript c,
    explained under it) and drawn as a blue square with its points' top; the others are not."""
    from forestreg.engine.trees.allometry import HeightCurve

    rows, pts, ids, wood, cyls = _fake_plot()
    rows = [
        {**r, "height_quality": "highest tree point; high", "height_source": "points", "height_points_m": r["height_m"]}
        for r in rows
    ]
    rows[1].update(
        height_source="curve",
        height_points_m=0.6 * rows[1]["height_m"],
        height_quality="from the plot's height-diameter curve at the DBH: the points' top not taken; medium",
    )
    curve = HeightCurve(a=1.2, b=0.19, n_trees=12, n_inliers=11, scatter=0.05)
    html = write_trees_report(tmp_path, rows, pts, ids, wood, cyls, height_curve=curve).read_text()
    assert html.count("<sup>c</sup>") == 2  # the one height and the note under the table
    assert _share_of_colour(tmp_path / "figures" / "height_curve.png", "#1f77b4") > 0.0002
    plain = write_trees_report(
        tmp_path / "plain", [{**r, "height_source": "points"} for r in rows], pts, ids, wood, cyls, height_curve=curve
    ).read_text()
    assert plain.count("<sup>c</sup>") == 1


def test_trees_without_cylinder_models_get_the_points_panel_alone(tmp_path):
    rows, pts, ids, wood, cyls = _fake_plot()
    both = write_trees_report(tmp_path / "with", rows, pts, ids, wood, cyls).read_text()
    alone = write_trees_report(tmp_path / "without", rows, pts, ids, None, {}).read_text()
    wide = mpimg.imread(tmp_path / "with" / "figures" / "tree_1.png")
    narrow = mpimg.imread(tmp_path / "without" / "figures" / "tree_1.png")
    assert narrow.shape[0] == wide.shape[0] and narrow.shape[1] < 0.75 * wide.shape[1]
    assert narrow[..., :3].std() > 0.05  # the points drawn
    assert "Right: its cylinder model" in both and "Right:" not in alone
    assert "grey (wood and leaves not told apart); no cylinder models" in alone
