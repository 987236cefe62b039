"""``layers.gpkg``: the GeoPackage written with sqlite3 alone opens with sqlite3 (and with GDAL
where pyogrio or fiona is installed), holds the standard's tables, the CRS's ``srs_id`` and WKT,
geometries that decode to what was written (the trees' breast-height positions), a QGIS style per
layer; it is written fast and atomically."""

from __future__ import annotations

import math
import sqlite3
import struct
import time
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.core.errors import ParameterError
from forestreg.engine.io.gpkg import (
    CUSTOM_SRS_ID,
    Layer,
    decode_geometry,
    encode_geometry,
    layer_names,
    read_crs,
    read_layer,
    write_geopackage,
)

pyproj = pytest.importorskip("pyproj")

from forestreg.engine.io.crs import parse_crs  # noqa: E402 - after the pyproj check


def _layers():
    points = [np.array([500010.0, 4300020.0, 101.3]), np.array([500012.5, 4300021.0, 102.0]), None]
    line = [np.array([[500010.0, 4300020.0, 101.3], [500012.5, 4300021.0, 102.0]])]
    ring = [np.array([[500000.0, 4300000.0], [500030.0, 4300000.0], [500030.0, 4300030.0], [500000.0, 4300030.0]])]
    return [
        Layer(
            "trees",
            "POINT",
            ("tree_id", "dbh_m", "flag", "ok"),
            [
                {"tree_id": 1, "dbh_m": 0.31, "flag": "", "ok": True},
                {"tree_id": 2, "dbh_m": math.nan, "flag": "top missing", "ok": False},
                {"tree_id": 3, "dbh_m": np.float64(0.2), "flag": None},
            ],
            points,
            z=True,
            style="<qgis/>",
        ),
        Layer("links", "LINESTRING", ("status",), [{"status": "ok"}], line, z=True),
        Layer("plot_outline", "POLYGON", ("name",), [{"name": "plot"}], ring),
    ]


def test_the_geopackage_has_the_standard_tables_and_the_crs(tmp_path):
    path = write_geopackage(tmp_path / "layers.gpkg", _layers(), parse_crs("EPSG:32618"))
    con = sqlite3.connect(path)
    try:
        assert con.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47  # "GPKG"
        assert con.execute("PRAGMA user_version").fetchone()[0] == 10200
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        srs = {
            r[0]: r[1:]
            for r in con.execute(
                "SELECT srs_id, organization, organization_coordsys_id, definition FROM gpkg_spatial_ref_sys"
            )
        }
        assert {4326, -1, 0, 32618} <= set(srs)  # the three rows the standard requires, and the CRS
        assert srs[32618][:2] == ("EPSG", 32618) and "UTM zone 18N" in srs[32618][2]
        contents = {
            r[0]: r[1:]
            for r in con.execute("SELECT table_name, data_type, srs_id, min_x, min_y, max_x, max_y FROM gpkg_contents")
        }
        assert contents["trees"][:2] == ("features", 32618)
        assert contents["trees"][2:] == (500010.0, 4300020.0, 500012.5, 4300021.0)
        assert contents["layer_styles"][0] == "attributes"
        geometry_columns = {
            r[0]: r[1:]
            for r in con.execute(
                "SELECT table_name, column_name, geometry_type_name, srs_id, z, m FROM gpkg_geometry_columns"
            )
        }
        assert geometry_columns == {
            "trees": ("geom", "POINT", 32618, 1, 0),
            "links": ("geom", "LINESTRING", 32618, 1, 0),
            "plot_outline": ("geom", "POLYGON", 32618, 0, 0),
        }
        assert con.execute("SELECT COUNT(*) FROM trees").fetchone()[0] == 3
        types = {r[1]: r[2] for r in con.execute("PRAGMA table_info(trees)")}
        assert types == {
            "fid": "INTEGER",
            "geom": "POINT",
            "tree_id": "INTEGER",
            "dbh_m": "REAL",
            "flag": "TEXT",
            "ok": "BOOLEAN",
        }
        assert con.execute("SELECT dbh_m FROM trees WHERE tree_id = 2").fetchone()[0] is None  # NaN: NULL
        styles = con.execute(
            "SELECT f_table_name, f_geometry_column, useAsDefault, styleQML FROM layer_styles"
        ).fetchall()
        assert styles == [("trees", "geom", 1, "<qgis/>")]
        blob = con.execute("SELECT geom FROM trees WHERE tree_id = 1").fetchone()[0]
    finally:
        con.close()
    # the GeoPackage binary header: magic, version 0, little-endian with an x/y envelope, srs_id
    assert blob[:3] == b"GP\x00" and blob[3] == 0b11
    assert struct.unpack("<i", blob[4:8])[0] == 32618
    assert struct.unpack("<4d", blob[8:40]) == (500010.0, 500010.0, 4300020.0, 4300020.0)
    assert blob[40] == 1 and struct.unpack("<I", blob[41:45])[0] == 1001  # little-endian WKB Point Z
    assert read_crs(path).epsg == "EPSG:32618"


def test_geometries_decode_to_what_was_written(tmp_path):
    layers = _layers()
    path = write_geopackage(tmp_path / "layers.gpkg", layers, parse_crs("EPSG:32618"))
    assert layer_names(path) == ["trees", "links", "plot_outline"]
    trees, facts = read_layer(path, "trees")
    assert facts["srs_id"] == 32618 and facts["z"] and facts["geometry_type"] == "POINT"
    for row, shape in zip(trees, layers[0].shapes):
        if shape is None:
            assert row["geom"] == (None, None)
        else:
            assert row["geom"][0] == "POINT"
            np.testing.assert_array_equal(row["geom"][1], shape)
    (line,), _ = read_layer(path, "links")
    np.testing.assert_array_equal(line["geom"][1], layers[1].shapes[0])
    (outline,), _ = read_layer(path, "plot_outline")
    ring = outline["geom"][1]
    assert len(ring) == 5 and np.array_equal(ring[0], ring[-1])  # closed on writing
    np.testing.assert_array_equal(ring[:4], layers[2].shapes[0])
    kind, coords, srs = decode_geometry(encode_geometry("POINT", np.array([1.0, 2.0]), -1, False))
    assert (kind, srs) == ("POINT", -1) and coords.tolist() == [1.0, 2.0]


def test_local_and_compound_crs(tmp_path):
    local = write_geopackage(tmp_path / "local.gpkg", _layers())
    assert read_layer(local, "trees")[1]["srs_id"] == -1 and read_crs(local) is None
    compound = parse_crs("EPSG:6341+5703")
    path = write_geopackage(tmp_path / "compound.gpkg", _layers(), compound)
    _, facts = read_layer(path, "trees")
    assert facts["srs_id"] == CUSTOM_SRS_ID and facts["organization"] == "NONE"
    assert "UTM zone 12N" in facts["definition"] and "NAVD88" in facts["definition"]
    assert read_crs(path).same_as(compound)


def test_bad_layers_are_refused_and_a_failed_write_leaves_the_file_as_it_was(tmp_path):
    path = write_geopackage(tmp_path / "layers.gpkg", _layers())
    before = path.read_bytes()
    for bad in (
        Layer("x y", "POINT", (), [], []),
        Layer("a", "CIRCLE", (), [], []),
        Layer("a", "POINT", ("geom",), [{}], [None]),
        Layer("a", "POINT", (), [{}], []),
    ):
        with pytest.raises(ParameterError):
            write_geopackage(path, [bad])
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layers.gpkg"]  # no temporary file left


def test_styles_are_qml_documents_qgis_reads():
    from forestreg.app import layers

    for style in (
        layers._trees_style(),
        layers._crowns_style(),
        layers._changes_style(),
        layers._scanners_style(),
        layers._links_style(),
        layers._outline_style(),
        layers._keypoints_style(),
        layers._next_scans_style(),
    ):
        root = ET.fromstring(style.split("\n", 1)[1])
        assert root.tag == "qgis"
        renderer = root.find("renderer-v2")
        assert renderer.get("type") == "RuleRenderer"
        rules, symbols = renderer.find("rules").findall("rule"), renderer.find("symbols").findall("symbol")
        assert rules and len(rules) == len(symbols)
        assert {r.get("symbol") for r in rules} == {s.get("name") for s in symbols}
    trees = ET.fromstring(layers._trees_style().split("\n", 1)[1])
    filters = [r.get("filter") or "" for r in trees.iter("rule")]
    assert sum('"dbh_m" <' in f or '"dbh_m" >=' in f for f in filters) == 5  # graduated by DBH
    assert any('"flag"' in f for f in filters)  # flagged trees marked
    changes = [r.get("filter") or "" for r in ET.fromstring(layers._changes_style().split("\n", 1)[1]).iter("rule")]
    assert all(any(f"'{s}'" in f for f in changes) for s in ("persisting", "removed", "new", "outside"))

    # the next scans: markers numbered by rank (QGIS simple labelling over each point)
    plan = ET.fromstring(layers._next_scans_style().split("\n", 1)[1])
    assert plan.get("labelsEnabled") == "1" and "Labeling" in plan.get("styleCategories")
    text = plan.find("labeling/settings/text-style")
    assert (
        plan.find("labeling").get("type") == "simple"
        and text.get("fieldName") == "rank"
        and text.get("isExpression") == "0"
    )
    assert plan.find("labeling/settings/placement").get("placement") == "1"  # over the point
    assert [r.get("filter") for r in plan.iter("rule")] == ['"rank" = 1', '"rank" > 1']
    assert plan[-1].tag == "layerGeometryType" and plan[-1].text == "0"


def test_the_next_scans_layer_holds_each_suggestion_at_its_position(tmp_path):
    from forestreg.app.layers import NEXT_SCAN_COLUMNS, plan_layers
    from forestreg.engine.tls.plan import Suggestion

    found = [
        Suggestion(500_012.5, 4_300_008.0, "scan_01.laz", 14, 10, 15.0, 8.1, 4.25, 30.0, 2.1),
        Suggestion(499_990.0, 4_300_021.5, "scan_02.laz", 11, 10, 20.0, 9.4, 3.5, 12.0, 0.8),
    ]
    path = write_geopackage(
        tmp_path / "plan.gpkg", plan_layers(SimpleNamespace(suggestions=tuple(found))), parse_crs("EPSG:32618")
    )
    rows, facts = read_layer(path, "next_scans")
    assert (
        layer_names(path) == ["next_scans"]
        and facts["srs_id"] == 32618
        and facts["geometry_type"] == "POINT"
        and not facts["z"]
    )
    assert [r["rank"] for r in rows] == [1, 2] and [r["links_to"] for r in rows] == ["scan_01.laz", "scan_02.laz"]
    for r, s in zip(rows, found):
        assert r["geom"][0] == "POINT" and r["geom"][1].tolist() == [s.x, s.y]
        assert (r["shared_stems"], r["needed"], r["vop_radius_m"], r["new_stem_area_m2"]) == (
            s.shared_stems,
            10,
            s.radius_m,
            4.25 if s is found[0] else 3.5,
        )
        assert r["reason"] == s.reason and "(10 needed)" in r["reason"]
    assert set(rows[0]) == {"fid", "geom", *NEXT_SCAN_COLUMNS}
    assert facts["extent"] == (499_990.0, 4_300_008.0, 500_012.5, 4_300_021.5)
    empty = write_geopackage(tmp_path / "none.gpkg", plan_layers(SimpleNamespace(suggestions=())))
    assert read_layer(empty, "next_scans")[0] == [] and read_layer(empty, "next_scans")[1]["srs_id"] == -1


def _inventory(n: int, seed: int = 0):
    """A stand-in for a tree inventory of ``n`` trees with crown outlines (what the layers read)."""
    rng = np.random.default_rng(seed)
    trees, rows = [], []
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    for i in range(n):
        base = np.array([rng.uniform(0, 300), rng.uniform(0, 300), rng.uniform(0, 5)])
        lean = np.radians(rng.uniform(0, 5))
        axis = np.array([np.sin(lean), 0.0, np.cos(lean)])
        r = rng.uniform(1, 4)
        outline = base[:2] + np.c_[r * np.cos(angles), r * np.sin(angles)]
        crown = SimpleNamespace(outline=outline, crown_width_ew_m=2 * r, crown_width_ns_m=2 * r)
        stem = SimpleNamespace(base=base, axis=axis, x=base[0], y=base[1])
        trees.append(SimpleNamespace(tree_id=i + 1, stem=stem, crown=crown))
        rows.append(
            {
                "tree_id": i + 1,
                "x": base[0],
                "y": base[1],
                "z": base[2],
                "dbh_m": rng.uniform(0.05, 0.6),
                "height_m": 20.0,
                "lean_deg": np.degrees(lean),
                "crown_area_m2": np.pi * r * r,
                "flag": "" if i % 5 else "top missing",
            }
        )
    shift = np.array([500_000.0, 4_300_000.0, 0.0])
    return SimpleNamespace(
        trees=trees,
        rows=lambda: [{**r, "x": r["x"] + shift[0], "y": r["y"] + shift[1]} for r in rows],
        origin_shift=shift,
    )


def test_a_thousand_trees_with_crowns_are_written_within_2_s_and_decode_to_their_positions(tmp_path):
    from forestreg.app.layers import BREAST_HEIGHT_M, trees_layers, write_layers

    inventory = _inventory(1000)
    t0 = time.perf_counter()
    path = write_layers(
        tmp_path,
        trees_layers(inventory, outline=np.array([[0, 0], [300, 0], [300, 300], [0, 300.0]])),
        parse_crs("EPSG:32618"),
    )
    seconds = time.perf_counter() - t0
    assert seconds < 2.0, f"{seconds:.2f} s for 1,000 trees"
    trees, facts = read_layer(path, "trees")
    assert len(trees) == 1000 and facts["srs_id"] == 32618
    shift = inventory.origin_shift
    for row, t in zip(trees, inventory.trees):
        bh = t.stem.base + t.stem.axis * BREAST_HEIGHT_M / t.stem.axis[2] + shift
        np.testing.assert_allclose(row["geom"][1], bh, atol=1e-9)
        assert abs(row["geom"][1][2] - (row["z"] + BREAST_HEIGHT_M)) < 1e-9  # 1.3 m above the stem base
        # the breast-height point leans off the base by at most 1.3 m times the lean's tangent
        off = math.hypot(row["geom"][1][0] - row["x"], row["geom"][1][1] - row["y"])
        assert off <= BREAST_HEIGHT_M * math.tan(math.radians(row["lean_deg"])) + 1e-9
    crowns, _ = read_layer(path, "crowns")
    assert len(crowns) == 1000 and crowns[1]["geom"][0] == "POLYGON"
    np.testing.assert_allclose(crowns[1]["geom"][1][:-1], inventory.trees[1].crown.outline + shift[:2], atol=1e-9)
    assert len(read_layer(path, "plot_outline")[0]) == 1


def test_trees_layers_hold_every_column_of_trees_csv(shared_data, tmp_path):
    out = tmp_path / "trees"
    assert (
        main(
            [
                "trees",
                str(shared_data / "pine_plot.laz"),
                "--out",
                str(out),
                "--no-cylinders",
                "--no-report",
                "--crs",
                "EPSG:32618",
                "-q",
            ]
        )
        == 0
    )
    header = (out / "trees.csv").read_text().splitlines()[0].split(",")
    lines = (out / "trees.csv").read_text().strip().splitlines()[1:]
    trees, facts = read_layer(out / "layers.gpkg", "trees")
    assert facts["srs_id"] == 32618 and len(trees) == len(lines) > 5
    assert [c for c in trees[0] if c not in ("fid", "geom")] == header
    for row in trees:
        assert abs(row["geom"][1][2] - row["z"] - 1.3) < 1e-6
        assert (
            math.hypot(row["geom"][1][0] - row["x"], row["geom"][1][1] - row["y"])
            <= 1.3 * math.tan(math.radians(row["lean_deg"])) + 1e-3
        )
    crowns, _ = read_layer(out / "layers.gpkg", "crowns")
    assert 0 < len(crowns) <= len(trees)
    assert all(r["outline"] == "convex hull of the crown points" for r in crowns)
    (outline,), _ = read_layer(out / "layers.gpkg", "plot_outline")
    assert 80.0 < outline["area_m2"] < 110.0  # a 10 x 10 m plot


def test_gdal_reads_the_geopackage(tmp_path):
    """Where pyogrio or fiona (GDAL) is installed: every layer, its feature count and CRS."""
    path = write_geopackage(tmp_path / "layers.gpkg", _layers(), parse_crs("EPSG:32618"))
    try:
        import pyogrio
    except ImportError:
        pyogrio = None
    if pyogrio is not None:
        listed = {name: kind for name, kind in pyogrio.list_layers(path)}
        assert (
            listed["trees"] == "Point Z" and listed["links"] == "LineString Z" and listed["plot_outline"] == "Polygon"
        )
        info = pyogrio.read_info(path, layer="trees")
        assert info["features"] == 3 and info["crs"] == "EPSG:32618"
        return
    fiona = pytest.importorskip("fiona", reason="neither pyogrio nor fiona (GDAL) is installed")
    with fiona.open(path, layer="trees") as src:
        assert len(src) == 3 and "32618" in str(src.crs)
