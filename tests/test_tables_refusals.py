"""Tables not taken at their word: ``forestreg change`` refuses
trees tables with repeated, unparseable or implausible rows, or in another unit, naming the column
and the lines (exit 2, nothing written) instead of answering with trees silently lost or counted
twice; it reads tables whatever their header's case and delimiter; ``evaluate`` calls an R2 over
equal field values undefined; a parameter file with a byte-order mark is read and a key outside
every section is refused; a folder and its own ``trees.csv`` are one input; headings lie in
[0, 360)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError, ScanDataError

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "height_m", "source", "dbh_quality", "height_quality", "flag"]


def _run(*argv) -> int:
    from forestreg.cli import main

    return main([*argv, "--progress", "none"])


def _stand(n=40, size=26.0, seed=0):
    rng = np.random.default_rng(seed)
    xy: list = []
    while len(xy) < n:
        p = rng.uniform(-size / 2, size / 2, 2)
        if all(np.hypot(*(p - q)) > 1.8 for q in xy):
            xy.append(p)
    return np.array(xy), rng.uniform(0.15, 0.45, n), rng.uniform(15.0, 25.0, n)


def _surveys(heading_deg=25.0, seed=0, removed=6):
    """BEFORE and AFTER rows (dicts of text, COLUMNS) of one stand: the ``removed`` trees nearest
    the centre gone, 1-3 cm DBH growth, AFTER turned by ``heading_deg`` and shifted."""
    rng = np.random.default_rng(seed + 3)
    xy, dbh, h = _stand(seed=seed)
    keep = np.sort(np.argsort(np.hypot(*xy.T))[removed:])
    t = math.radians(heading_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    a_xy = (xy[keep] + rng.normal(0, 0.01, (len(keep), 2)) - [300.0, -120.0]) @ rot  # p_before = R p_after + shift
    a_dbh = dbh[keep] + rng.uniform(0.01, 0.03, len(keep))

    def rows(p, d, hh, z):
        return [
            {
                "tree_id": str(k + 1),
                "x": f"{x:.4f}",
                "y": f"{y:.4f}",
                "z": f"{z:.3f}",
                "dbh_m": f"{dk:.4f}",
                "height_m": f"{hk:.2f}",
                "source": "stem",
                "dbh_quality": "stem curve; high",
                "height_quality": "top; high",
                "flag": "",
            }
            for k, ((x, y), dk, hk) in enumerate(zip(p, d, hh))
        ]

    return rows(xy, dbh, h, 0.0), rows(a_xy, a_dbh, h[keep] + 1.5, 12.0)


def _write(path: Path, rows, columns=COLUMNS, delimiter=",") -> Path:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, delimiter=delimiter, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([r.get(c, "") for c in columns])
    return path


def _pair(tmp_path: Path, after_rows=None, before_rows=None, **kw):
    before, after = _surveys(**kw)
    b = _write(tmp_path / "before.csv", before if before_rows is None else before_rows)
    a = _write(tmp_path / "after.csv", after if after_rows is None else after_rows)
    return b, a, before, after


def _refused(capsys, tmp_path, before, after, *extra) -> str:
    """Run ``change``; assert exit 2 and no output folder; the error text."""
    out = tmp_path / "out"
    assert _run("change", str(before), str(after), "--out", str(out), *extra) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# ------------------------------------------------------------------------------ rows twice


def test_change_refuses_a_table_with_every_row_twice(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    a = _write(tmp_path / "twice.csv", after + after)
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", a)
    n = len(after)
    assert f"{n} tree(s) listed twice" in err and "AFTER" in err and "twice.csv" in err
    assert f"lines 2 and {n + 2}" in err  # the header is line 1


def test_one_repeated_row_is_named_and_two_close_trees_of_other_sizes_are_not(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    a = _write(tmp_path / "one.csv", after[:5] + [dict(after[3], tree_id="99")] + after[5:])
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", a)
    assert "1 tree(s) listed twice" in err and "lines 5 and 7" in err
    # a fork: a second stem 3 cm away with another DBH is a tree of its own
    fork = dict(
        after[3], tree_id="99", x=f"{float(after[3]['x']) + 0.03:.4f}", dbh_m=f"{float(after[3]['dbh_m']) / 2:.4f}"
    )
    a = _write(tmp_path / "fork.csv", after + [fork])
    out = tmp_path / "fork_out"
    assert _run("change", str(tmp_path / "before.csv"), str(a), "--out", str(out)) == 0


# ------------------------------------------------------------------- DBH and coordinates


@pytest.mark.parametrize(
    "value, words",
    [
        ("-0.3", "zero or negative"),
        ("0", "zero or negative"),
        ("7.5", "above 5 m"),
        ("abc", "not a number"),
        ("inf", "not a number"),
    ],
)
def test_change_refuses_an_impossible_dbh_naming_the_column_and_lines(tmp_path, capsys, value, words):
    _, _, before, after = _pair(tmp_path)
    bad = [dict(r, dbh_m=value) if k in (2, 9) else r for k, r in enumerate(after)]
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "bad.csv", bad))
    assert "column dbh_m" in err and words in err and "lines 4, 11" in err and repr(value) in err


def test_ten_negative_dbh_are_refused_not_ten_removed_and_ten_new(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    bad = [dict(r, dbh_m="-" + r["dbh_m"]) if k < 10 else r for k, r in enumerate(after)]
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "neg.csv", bad))
    assert "column dbh_m is zero or negative at lines 2, 3, 4, 5, 6, 7, 8, 9 and 2 more" in err


def test_change_refuses_unparseable_coordinates_naming_the_column_and_lines(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    bad = [dict(r) for r in after]
    bad[3]["x"], bad[4]["y"], bad[5]["x"], bad[6]["y"] = "nan", "inf", "abc", ""
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "nan.csv", bad))
    assert "column x is not a finite number at lines 5, 7" in err and "'nan', 'abc'" in err
    assert "column y is not a finite number at lines 6, 8" in err and "'inf'" in err


def test_no_tree_is_silently_lost(tmp_path, capsys):
    """Every stem row of either table is in tree_changes.csv; rows without a stem are left out and
    said so."""
    before, after = _surveys()
    canopy = [dict(after[0], tree_id="500", source="canopy", dbh_m="", x="-280.0")]
    b = _write(tmp_path / "before.csv", before)
    a = _write(tmp_path / "after.csv", after + canopy)
    out = tmp_path / "out"
    assert _run("change", str(b), str(a), "--out", str(out)) == 0
    printed = capsys.readouterr().out
    assert "note: AFTER: 1 of 35 trees without a stem" in printed
    rows = list(csv.DictReader(open(out / "tree_changes.csv")))
    assert sum(1 for r in rows if r["tree_id_before"]) == len(before)
    assert sum(1 for r in rows if r["tree_id_after"]) == len(after)
    result = json.loads((out / "result.json").read_text())
    assert result["trees"]["persisting"] == len(after) and result["trees"]["new"] == 0
    assert any("without a stem" in n for n in result["notes"])


def test_the_engine_refuses_the_same_rows(tmp_path):
    from forestreg.engine.change import epoch_from_table

    _, after = _surveys()
    with pytest.raises(ScanDataError, match=r"column x is not a finite number at row 2 \(tree_id 2; x 'nan'\)"):
        epoch_from_table([dict(r, x="nan") if k == 1 else r for k, r in enumerate(after)], name="AFTER")
    with pytest.raises(ScanDataError, match="listed twice"):
        epoch_from_table(after + after[:1])


# ---------------------------------------------------------------------------------- units


def test_dbh_in_millimetres_under_dbh_m_is_a_unit_error(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    mm = [dict(r, dbh_m=f"{1000 * float(r['dbh_m']):.1f}") for r in after]
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "mm.csv", mm))
    assert "column dbh_m" in err and "millimetres" in err and "dbh_mm" in err and "unrelated" not in err
    cm = [dict(r, dbh_m=f"{100 * float(r['dbh_m']):.1f}") for r in after]
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "cm.csv", cm))
    assert "centimetres" in err and "dbh_cm" in err


def test_one_survey_in_feet_is_a_unit_error_and_units_after_reads_it(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    ft = [
        dict(r, x=f"{float(r['x']) / 0.3048:.4f}", y=f"{float(r['y']) / 0.3048:.4f}", z=f"{float(r['z']) / 0.3048:.4f}")
        for r in after
    ]
    a = _write(tmp_path / "after_ft.csv", ft)
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", a)
    assert "different units" in err and "AFTER looks like feet" in err and "--units-after ft" in err
    assert "unrelated" not in err
    # BEFORE in metres, both read as feet: BEFORE is the one to correct
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", a, "--units", "ft")
    assert "--units-before m" in err
    out = tmp_path / "out"
    assert _run("change", str(tmp_path / "before.csv"), str(a), "--units-after", "ft", "--out", str(out)) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["unit"] == "m" and result["unit_after"] == "ft"
    m = np.array(result["matrix"])
    p_after = np.array([[float(r["x"]), float(r["y"]), float(r["z"]), 1.0] for r in ft])
    p_before = np.array([[float(r["x"]), float(r["y"])] for r in before])
    moved = (p_after @ m.T)[:, :2]
    near = np.min(np.hypot(*(moved[:, None, :] - p_before[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert near.max() < 0.05  # every AFTER stem onto its BEFORE stem, in BEFORE's metres
    rows = list(csv.DictReader(open(out / "tree_changes.csv")))
    assert len(rows) == len(before) and sum(r["status"] == "persisting" for r in rows) == len(after)


def test_a_thinned_or_larger_survey_is_not_called_another_unit():
    from forestreg.engine.change import epoch_from_table, position_unit_mismatch

    before, after = _surveys(removed=0)
    b = epoch_from_table(before)
    thinned = epoch_from_table([r for k, r in enumerate(after) if k % 10 == 0 or k < 4])  # few stems, same extent
    assert position_unit_mismatch(b, thinned) is None
    assert position_unit_mismatch(b, epoch_from_table(after)) is None


# ------------------------------------------------------------------- tables, not clouds


def _renamed(rows, mapping):
    return [{mapping.get(k, k): v for k, v in r.items()} for r in rows]


def test_tables_in_any_case_delimiter_and_dbh_unit_are_read(tmp_path, capsys):
    from forestreg.engine.io.sniff import is_point_cloud_file, is_tree_table

    before, after = _surveys()
    b = _write(tmp_path / "before.csv", before)
    cm_rows = [dict(r, dbh_cm=f"{100 * float(r['dbh_m']):.2f}") for r in after]
    cm_cols = [c if c != "dbh_m" else "dbh_cm" for c in COLUMNS]
    cases = {
        "cm.csv": (cm_rows, cm_cols, ","),
        "upper.csv": (_renamed(after, {c: c.upper() for c in COLUMNS}), [c.upper() for c in COLUMNS], ","),
        "semicolon.csv": (after, COLUMNS, ";"),
        "tab.txt": (after, COLUMNS, "\t"),
        "mm_upper.csv": (
            [dict(r, DBH_MM=f"{1000 * float(r['dbh_m']):.1f}") for r in after],
            [c if c != "dbh_m" else "DBH_MM" for c in COLUMNS],
            ";",
        ),
    }
    for name, (rows, columns, delimiter) in cases.items():
        path = _write(tmp_path / name, rows, columns, delimiter)
        assert is_tree_table(path) and not is_point_cloud_file(path), name
        out = tmp_path / f"out_{name}"
        assert _run("change", str(b), str(path), "--out", str(out)) == 0, name
        printed = capsys.readouterr().out
        result = json.loads((out / "result.json").read_text())
        assert result["trees"]["persisting"] == len(after), name
        if name == "cm.csv":
            assert "note: AFTER: dbh_cm converted to metres (divided by 100)" in printed
            assert result["notes"] == ["AFTER: dbh_cm converted to metres (divided by 100)"]
            growth = [
                float(r["dbh_change_m"]) for r in csv.DictReader(open(out / "tree_changes.csv")) if r["dbh_change_m"]
            ]
            assert 0.009 < np.median(growth) < 0.031  # metres, as from dbh_m
    # a point list with an x y z header (and a tree id per point) stays a cloud
    cloud = tmp_path / "points.csv"
    cloud.write_text(
        "X,Y,Z,tree_id\n" + "".join(f"{i * 0.1:.1f},{i * 0.2:.1f},{i * 0.05:.2f},{i % 3}\n" for i in range(50))
    )
    assert not is_tree_table(cloud) and is_point_cloud_file(cloud)


def test_a_table_without_the_needed_columns_says_what_it_has_and_needs(tmp_path, capsys):
    _, _, before, after = _pair(tmp_path)
    columns = ["TREE", "X", "Y", "Diameter"]
    rows = [{"TREE": r["tree_id"], "X": r["x"], "Y": r["y"], "Diameter": r["dbh_m"]} for r in after]
    err = _refused(capsys, tmp_path, tmp_path / "before.csv", _write(tmp_path / "sheet.csv", rows, columns, ";"))
    assert "the table has columns TREE, X, Y, Diameter; it needs x, y and dbh_m (or dbh_cm, dbh_mm)" in err
    assert "three numbers" not in err


# --------------------------------------------------------------------------- same input


def test_a_folder_and_its_own_trees_csv_are_the_same_input(tmp_path, capsys):
    before, _ = _surveys()
    (tmp_path / "t1").mkdir()
    _write(tmp_path / "t1" / "trees.csv", before)
    err = _refused(capsys, tmp_path, tmp_path / "t1", tmp_path / "t1" / "trees.csv")
    assert "same file" in err
    err = _refused(capsys, tmp_path, tmp_path / "t1" / "trees.csv", tmp_path / "t1" / ".." / "t1")
    assert "same file" in err


def test_the_heading_found_is_reported_in_0_to_360(tmp_path):
    b, a, _, _ = _pair(tmp_path, heading_deg=0.0)
    out = tmp_path / "out"
    assert _run("change", str(b), str(a), "--out", str(out)) == 0
    heading = json.loads((out / "result.json").read_text())["evidence"]["coarse_heading_deg"]
    assert 0.0 <= heading < 360.0 and min(heading, 360.0 - heading) < 1.0


# ------------------------------------------------------------------------------ parameters


def test_a_parameter_file_with_a_byte_order_mark_is_read(tmp_path, capsys):
    from forestreg.engine.params import load_params

    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[registration]\nvop_radius_m = 12.5\n")
    assert load_params(path).registration.vop_radius_m == 12.5
    assert _run("params", "--params", str(path)) == 0


def test_a_key_outside_every_section_is_refused_naming_its_sections(tmp_path, capsys):
    from forestreg.engine.params import load_params

    path = tmp_path / "top.toml"
    path.write_text("vop_radius_m = 12.5\n", encoding="utf-8")
    with pytest.raises(ParameterError, match=r"vop_radius_m is outside every section: put it under \[registration\]"):
        load_params(path)
    assert _run("params", "--params", str(path)) == 2
    assert "put it under [registration]" in capsys.readouterr().err
    path.write_text("iterations = 3\n\n[trees]\n", encoding="utf-8")
    with pytest.raises(ParameterError, match=r"\[registration\.icp\] or .*\[change\.stem_icp\]"):
        load_params(path)
    path.write_text("vop_radius_mm = 3\n", encoding="utf-8")
    with pytest.raises(ParameterError, match="no section has a parameter of that name"):
        load_params(path)


# --------------------------------------------------------------------------------- evaluate


def _tables(tmp_path: Path, field_dbh, est_dbh):
    def write(name, dbh):
        rows = [
            {
                "tree_id": str(k + 1),
                "x": f"{3.0 * k:.1f}",
                "y": f"{(k % 2) * 4.0:.1f}",
                "dbh_m": f"{d}",
                "height_m": f"{18 + k}",
            }
            for k, d in enumerate(dbh)
        ]
        return _write(tmp_path / name, rows, ["tree_id", "x", "y", "dbh_m", "height_m"])

    return write("est.csv", est_dbh), write("field.csv", field_dbh)


def test_r2_over_equal_field_values_is_undefined_not_minus_1e30(tmp_path, capsys):
    from forestreg.engine.trees.evaluate import agreement, evaluate

    assert math.isnan(agreement([0.31, 0.29, 0.33], [0.35, 0.35, 0.35])["r2"])
    est, fld = _tables(tmp_path, [0.35, 0.35, 0.35], [0.31, 0.29, 0.33])
    ev = evaluate(est, fld)
    st = ev.stats["dbh_m"]
    assert math.isnan(st.r2) and st.r2_note.startswith("field values all equal")
    assert "dbh_m R2 n/a (field values all equal (0.35)) rRMSE 12.3 %" in ev.summary()
    out = tmp_path / "E"
    assert _run("evaluate", str(est), str(fld), "--out", str(out)) == 0
    doc = json.loads((out / "evaluation.json").read_text())
    dbh = (
        doc["runs"]["run"]["parameters"]["dbh_m"]
        if "run" in doc["runs"]
        else next(iter(doc["runs"].values()))["parameters"]["dbh_m"]
    )
    assert dbh["r2"] is None and dbh["r2_note"].startswith("field values all equal")
    html = (out / "report.html").read_text()
    assert 'title="R² undefined: field values all equal (0.35)">n/a</td>' in html
    assert "e+29" not in html and "e+30" not in html


def test_the_summary_of_a_single_field_tree_has_no_bare_separator(tmp_path):
    from forestreg.engine.trees.evaluate import evaluate

    est, fld = _tables(tmp_path, [0.3], [0.31, 0.29])
    line = evaluate(est, fld).summary()
    assert line.startswith("1 of 1 field trees matched; dbh_m R2 n/a (fewer than 2 pairs (1))")
    assert not line.rstrip().endswith(";")
    est, fld = _tables(tmp_path, [0.3], [0.31])
    no_values = evaluate(est, fld, parameters=["crown_area_m2"]).summary()
    assert no_values == "1 of 1 field trees matched"


def test_evaluate_prints_r2_as_undefined_on_constant_or_single_field_values(tmp_path):
    """The command's line: R2 "n/a" with its reason where field values are all equal or a single
    tree matched, never a -1e30, and no bare separator at the end."""
    import subprocess
    import sys

    est = tmp_path / "est.csv"
    est.write_text("tree_id,x,y,dbh_m,height_m\n1,0,0,0.3,20\n2,5,0,0.3,20\n3,0,5,0.3,20\n", encoding="utf-8")
    one = tmp_path / "one.csv"
    one.write_text("tree_id,x,y,dbh_m,height_m\n1,0,0,0.3,20\n", encoding="utf-8")
    for table, why in ((est, "field values all equal"), (one, "fewer than 2 pairs")):
        out = tmp_path / f"E_{table.stem}"
        field = tmp_path / f"field_{table.name}"  # the same records as field data (one file twice is refused)
        field.write_bytes(table.read_bytes())
        run = subprocess.run(
            [sys.executable, "-m", "forestreg.cli", "evaluate", str(table), str(field), "--out", str(out)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert run.returncode == 0, run.stderr
        first = run.stdout.splitlines()[0]
        assert "R2 n/a" in first and why in first and "e+" not in first and not first.rstrip().endswith(";"), first


def test_change_refuses_a_cloud_in_centimetres_naming_the_unit(tmp_path):
    """A survey's cloud in centimetres is refused by the one unit check every command shares
    (exit 2 in seconds, the likely unit named), before any tree is measured."""
    import subprocess
    import sys
    import time

    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import read_scan, write_scan

    plot = DATA / "pine_plot.laz"
    if not plot.is_file():
        pytest.skip(f"{plot} is absent")
    s = read_scan(plot)
    cm = tmp_path / "cm.laz"
    write_scan(Scan.from_points((s.points + s.origin_shift) * 100.0, name="cm"), cm)
    t = time.monotonic()
    run = subprocess.run(
        [sys.executable, "-m", "forestreg.cli", "change", str(cm), str(plot), "--out", str(tmp_path / "ch")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2, run.stderr
    assert "centimetres" in run.stderr and "BEFORE" in run.stderr
    assert time.monotonic() - t < 60
    assert not (tmp_path / "ch").exists()
