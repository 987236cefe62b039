"""Evaluation of tree parameters against field data (paper table 3)."""

from __future__ import annotations

import csv
import json
import math
import time

import numpy as np
import pytest

from forestreg.app.evaluation import write_evaluation
from forestreg.engine.core.errors import ParameterError
from forestreg.engine.trees.evaluate import (
    TreeTableError,
    agreement,
    evaluate,
    match_trees,
    read_tree_table,
    tree_table_from_rows,
)


def _write(path, text):
    path.write_text(text, encoding="utf-8")
    return path


def _rows(ids, xy, **values):
    out = []
    for k, (i, (x, y)) in enumerate(zip(ids, xy)):
        row = {"tree_id": i, "x": x, "y": y}
        row.update({name: v[k] for name, v in values.items()})
        out.append(row)
    return out


# ------------------------------------------------------------------------------------------------
# figures by hand
# ------------------------------------------------------------------------------------------------


def test_agreement_by_hand():
    # DBH: diffs 0.02, -0.02, 0.03; SS_res = 0.0017; field mean 0.3, SS_tot = 0.02
    fig = agreement([0.22, 0.28, 0.43], [0.20, 0.30, 0.40])
    assert fig["n"] == 3
    assert fig["r2"] == pytest.approx(1 - 0.0017 / 0.02)  # 0.915
    assert fig["rmse"] == pytest.approx(math.sqrt(0.0017 / 3))  # 0.0238 m
    assert fig["rrmse_percent"] == pytest.approx(100 * math.sqrt(0.0017 / 3) / 0.3)  # 7.93 %
    assert fig["bias"] == pytest.approx(0.01)
    # heights: diffs 2, -2, 3, 1; SS_res 18, SS_tot 500; a missing pair is skipped
    fig = agreement([12, 18, 33, 41, np.nan], [10, 20, 30, 40, 50])
    assert fig["n"] == 4
    assert fig["r2"] == pytest.approx(1 - 18 / 500)
    assert fig["rmse"] == pytest.approx(math.sqrt(4.5))
    assert fig["rrmse_percent"] == pytest.approx(100 * math.sqrt(4.5) / 25)
    assert fig["bias"] == pytest.approx(1.0)
    # a constant bias lowers R2 (it is not the squared correlation): est = field + 10
    fig = agreement([20, 30, 40], [10, 20, 30])
    assert fig["r2"] == pytest.approx(1 - 300 / 200) and fig["r2"] < 0
    assert math.isnan(agreement([], [])["rmse"]) and math.isnan(agreement([1.0], [2.0])["r2"])


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------


def test_read_table_converts_cm_and_reads_missing(tmp_path):
    p = _write(
        tmp_path / "field.csv",
        "Tree ID;X;Y;DBH_cm;height_m;crown_area_m2\n"
        "A1;1.0;2.0;25,5;18.2;NA\nA2;3.5;4.0;31.0;;12.5\n# a comment\nA3;5;6;40;22.0;20\n",
    )
    t = read_tree_table(p)
    assert list(t.tree_id) == ["A1", "A2", "A3"]
    np.testing.assert_allclose(t.values["dbh_m"], [0.255, 0.31, 0.40])
    assert any("dbh_cm" in n and "metres" in n for n in t.notes)
    assert math.isnan(t.values["height_m"][1]) and math.isnan(t.values["crown_area_m2"][0])
    assert t.parameters == ["dbh_m", "height_m", "crown_area_m2"]
    np.testing.assert_allclose(t.xy, [[1, 2], [3.5, 4], [5, 6]])


#: (what the error says, the table's text): tables a reader must refuse
BAD_TABLES = (
    ("centimetres", "tree_id,x,y,dbh_m\n1,0,0,0.3\n2,1,1,25.3\n"),
    ("metres", "tree_id,x,y,dbh_cm\n1,0,0,0.3\n2,1,1,0.25\n"),
    ("height_m", "tree_id,x,y,height_m\n1,0,0,1850\n"),
    ("no unit", "tree_id,x,y,dbh\n1,0,0,30\n"),
    ("missing column", "tree_id,x,dbh_m\n1,0,0.3\n"),
    ("duplicate", "tree_id,x,y\n1,0,0\n1,1,1\n"),
    ("not a number", "tree_id,x,y,dbh_m\n1,0,0,thick\n"),
    ("negative", "tree_id,x,y,height_m\n1,0,0,-3\n"),
    ("dbh_cm has negative", "tree_id,x,y,dbh_cm\n1,0,0,25\n2,1,1,-12.3\n"),
    ("DBH of 0", "tree_id,x,y,dbh_m\n1,0,0,0.3\n2,1,1,0\n"),
    ("infinite", "tree_id,x,y,dbh_m\n1,0,0,0.3\n2,1,1,inf\n"),
)


@pytest.mark.parametrize("message, text", BAD_TABLES, ids=[m for m, _ in BAD_TABLES])
def test_wrong_units_and_bad_tables_are_errors(tmp_path, message, text):
    with pytest.raises(TreeTableError, match=message):
        read_tree_table(_write(tmp_path / "bad.csv", text))


def test_a_missing_table_and_rows_in_the_wrong_unit_are_errors(tmp_path):
    with pytest.raises(TreeTableError, match="does not exist"):
        read_tree_table(tmp_path / "none.csv")
    with pytest.raises(TreeTableError, match="centimetres"):
        tree_table_from_rows([{"tree_id": 1, "x": 0, "y": 0, "dbh_m": 31.0}])


# ------------------------------------------------------------------------------------------------
# matching
# ------------------------------------------------------------------------------------------------


def test_position_matching_is_one_to_one_and_optimal():
    # nearest-first would give E1 -> F2 (0.5 m) and leave E2 and F1 unmatched; the assignment
    # pairs E1 -> F1 and E2 -> F2 (0.7 m each). E3 has no field tree, F3 no estimate.
    field = tree_table_from_rows(_rows(["F1", "F2", "F3"], [(0, 0), (1.2, 0), (10, 10)]))
    est = tree_table_from_rows(_rows(["E1", "E2", "E3"], [(0.7, 0), (1.9, 0), (-8, 5)]))
    m = match_trees(est, field, max_distance_m=1.0)
    pairs = {(str(est.tree_id[e]), str(field.tree_id[f])) for e, f in zip(m.estimated_index, m.field_index)}
    assert pairs == {("E1", "F1"), ("E2", "F2")}
    np.testing.assert_allclose(m.distance_m, [0.7, 0.7])
    assert [str(field.tree_id[i]) for i in m.omitted] == ["F3"]
    assert [str(est.tree_id[i]) for i in m.commission] == ["E3"]
    # a tighter gate: no pair
    m = match_trees(est, field, max_distance_m=0.6)
    assert len(m) == 1 and str(est.tree_id[m.estimated_index[0]]) == "E1"  # E1-F2 at 0.5 m
    with pytest.raises(ParameterError):
        match_trees(est, field, by="name")
    with pytest.raises(ParameterError):
        match_trees(est, field, max_distance_m=0)


def test_id_matching_ignores_positions():
    field = tree_table_from_rows(_rows(["1", "2", "3"], [(0, 0), (5, 0), (10, 0)]))
    est = tree_table_from_rows(_rows(["3", "1", "9"], [(0.1, 0), (5.1, 0), (10.1, 0)]))
    m = match_trees(est, field, by="id")
    pairs = {(str(est.tree_id[e]), str(field.tree_id[f])) for e, f in zip(m.estimated_index, m.field_index)}
    assert pairs == {("3", "3"), ("1", "1")}
    assert sorted(np.round(m.distance_m, 3)) == [5.1, 9.9]
    assert [str(field.tree_id[i]) for i in m.omitted] == ["2"]
    assert [str(est.tree_id[i]) for i in m.commission] == ["9"]
    # whole-number ids written as floats match their text form
    assert len(match_trees(tree_table_from_rows(_rows([3.0], [(0, 0)])), field, by="id")) == 1
    # by position the same tables pair by proximity instead
    m = match_trees(est, field, by="position")
    assert len(m) == 3 and np.allclose(m.distance_m, 0.1)


def test_large_plot_matches_every_tree_quickly():
    rng = np.random.default_rng(1)
    g = np.arange(0, 100, 2.5)
    xx, yy = np.meshgrid(g, g)
    xy = np.c_[xx.ravel(), yy.ravel()] + rng.uniform(-0.5, 0.5, (xx.size, 2))  # 1600 trees
    perm = rng.permutation(len(xy))
    field = tree_table_from_rows(_rows([f"f{i}" for i in range(len(xy))], xy))
    est = tree_table_from_rows(_rows([f"e{i}" for i in perm], xy[perm] + rng.normal(0, 0.15, xy.shape)))
    t0 = time.perf_counter()
    m = match_trees(est, field, max_distance_m=1.0)
    seconds = time.perf_counter() - t0
    print(f"\n{len(xy)} trees matched in {seconds:.2f} s")
    assert len(m) == len(xy)
    assert all(str(est.tree_id[e])[1:] == str(field.tree_id[f])[1:] for e, f in zip(m.estimated_index, m.field_index))
    assert seconds < 5.0


# ------------------------------------------------------------------------------------------------
# evaluation and files
# ------------------------------------------------------------------------------------------------


@pytest.fixture()
def two_runs():
    field = tree_table_from_rows(
        _rows(
            ["1", "2", "3", "4"],
            [(0, 0), (5, 0), (0, 5), (5, 5)],
            dbh_cm=[20.0, 30.0, 40.0, 35.0],
            height_m=[10.0, 20.0, 30.0, 40.0],
        )
    )
    ground = tree_table_from_rows(
        _rows(
            ["g1", "g2", "g3", "g9"],
            [(0.2, 0), (5, 0.3), (0, 5.1), (20, 20)],
            dbh_m=[0.22, 0.28, 0.43, 0.5],
            height_m=[12.0, 18.0, 33.0, 25.0],
        )
    )
    fused = tree_table_from_rows(
        _rows(
            ["u1", "u2", "u3", "u4"],
            [(0.1, 0), (5, 0.1), (0, 5), (5.2, 5)],
            dbh_m=[0.21, 0.30, 0.41, 0.36],
            height_m=[10.5, 19.5, 30.5, 39.0],
        )
    )
    return {"ground": evaluate(ground, field), "fused": evaluate(fused, field)}


def test_evaluate_two_runs(two_runs):
    g, f = two_runs["ground"], two_runs["fused"]
    assert (g.detection.matched, g.detection.omitted, g.detection.commission) == (3, 1, 1)
    assert (f.detection.matched, f.detection.omitted, f.detection.commission) == (4, 0, 0)
    assert g.detection.omission_rate == pytest.approx(0.25) and g.detection.commission_rate == pytest.approx(0.25)
    # ground DBH: the hand example (SS_res 0.0017, SS_tot 0.02 over trees 1-3)
    s = g.stats["dbh_m"]
    assert s.n == 3 and s.r2 == pytest.approx(0.915) and s.rmse == pytest.approx(math.sqrt(0.0017 / 3))
    assert s.bias == pytest.approx(0.01)
    # ground heights on trees 1-3: diffs 2, -2, 3
    h = g.stats["height_m"]
    assert h.rmse == pytest.approx(math.sqrt(17 / 3)) and h.r2 == pytest.approx(1 - 17 / 200)
    # fused heights on trees 1-4: diffs 0.5, -0.5, 0.5, -1 -> SS_res 1.75, SS_tot 500
    h = f.stats["height_m"]
    assert h.n == 4 and h.r2 == pytest.approx(1 - 1.75 / 500) and h.bias == pytest.approx(-0.125)
    assert h.rrmse_percent == pytest.approx(100 * math.sqrt(1.75 / 4) / 25)


def test_write_evaluation_files(two_runs, tmp_path):
    paths = write_evaluation(tmp_path / "eval", two_runs, title="plot 7")
    with open(paths["csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0])
    assert header[:3] == ["parameter", "label", "unit"]
    assert header[3:9] == ["n_ground", "n_fused", "r2_ground", "r2_fused", "rmse_ground", "rmse_fused"]
    dbh = next(r for r in rows if r["parameter"] == "dbh_m")
    assert float(dbh["r2_ground"]) == pytest.approx(0.915, abs=1e-5)
    assert int(dbh["n_fused"]) == 4 and float(dbh["rmse_ground"]) == pytest.approx(0.0238048, abs=1e-6)
    det = list(csv.DictReader(open(paths["detection"], newline="")))
    assert [(d["run"], d["matched"], d["omitted"], d["commission"]) for d in det] == [
        ("ground", "3", "1", "1"),
        ("fused", "4", "0", "0"),
    ]
    doc = json.loads(paths["json"].read_text())
    assert doc["runs"]["fused"]["parameters"]["height_m"]["n"] == 4
    assert doc["runs"]["ground"]["omitted_field_trees"] == ["4"]
    assert doc["runs"]["ground"]["commission_trees"] == ["g9"]
    assert any("dbh_cm" in n for n in doc["runs"]["ground"]["notes"]["field"])
    matches = list(csv.DictReader(open(paths["matches_ground"], newline="")))
    assert {(m["field_id"], m["estimated_id"]) for m in matches} == {("1", "g1"), ("2", "g2"), ("3", "g3")}
    for p in ("dbh_m", "height_m"):
        png = paths[f"scatter_{p}"]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        import matplotlib.image as mpimg

        img = mpimg.imread(png)
        assert img[..., :3].std() > 0.05  # not blank
    html = paths["html"].read_text()
    assert "plot 7" in html and "ground" in html and "fused" in html
    assert html.count("data:image/png;base64,") == 2
    assert "R²" in html and "rRMSE" in html
    with pytest.raises(ParameterError):
        write_evaluation(tmp_path / "x", {})
