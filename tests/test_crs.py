"""Coordinate reference systems: read from the real clips (WKT VLR, GeoTIFF keys), given with
``--crs``, written into LAS/LAZ/COPC, carried to the outputs in the same frame (and only there),
named in ``result.json``; two CRSs refused by ``fuse`` without ``--crs``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.core.errors import UsageError
from forestreg.engine.io import read_crs, read_scan, write_point_chunks, write_points, write_scan
from forestreg.engine.io.crs import Crs, as_crs, frame_crs, parse_crs
from forestreg.engine.io.gpkg import layer_names, read_layer

pytest.importorskip("pyproj")

UTM18 = "EPSG:32618"
UTM12 = "EPSG:26912"


# ----------------------------------------------------------------------------- reading the real clips


def test_the_crs_of_the_real_clips_is_read(shared_data):
    als = read_scan(shared_data / "spanner_ALS_Clip.laz")  # an OGC WKT VLR: a compound CRS
    assert als.crs is not None
    assert als.crs.epsg == "EPSG:6341+5703" and "UTM zone 12N" in als.crs.name
    conifer = read_scan(shared_data / "lidR_MixedConifer.laz")  # GeoTIFF keys
    assert conifer.crs.epsg == UTM12 and "UTM zone 12N" in conifer.crs.name
    serc_als = read_crs(shared_data / "SERC_transect_als.laz")  # GeoTIFF keys, header only
    serc_drone = read_crs(shared_data / "SERC_transect_drone.laz")  # a WKT VLR, another name for the same CRS
    assert serc_als.epsg == serc_drone.epsg == UTM18
    assert serc_als.same_as(serc_drone) and not serc_als.same_as(conifer.crs)
    assert read_scan(shared_data / "spanner_MLS_Clip.laz").crs is None  # the same plot, no CRS in its file
    assert read_crs(shared_data / "pine_plot.laz") is None


def test_fusing_the_real_serc_trunk_keeps_its_crs(shared_data, tmp_path, capsys):
    out = tmp_path / "fused.laz"
    assert (
        main(
            [
                "fuse",
                str(shared_data / "SERC_trunk_tls.laz"),
                str(shared_data / "SERC_trunk_drone.laz"),
                "--out",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    assert read_scan(out).crs.epsg == UTM18


def test_trees_of_the_real_als_clip_carry_its_crs_into_layers(shared_data, tmp_path):
    out = tmp_path / "trees"
    assert (
        main(
            [
                "trees",
                str(shared_data / "spanner_ALS_Clip.laz"),
                "--out",
                str(out),
                "--no-cylinders",
                "--no-report",
                "-q",
            ]
        )
        == 0
    )
    n_trees = len((out / "trees.csv").read_text().strip().splitlines()) - 1
    rows, facts = read_layer(out / "layers.gpkg", "trees")
    assert len(rows) == n_trees > 0
    assert facts["srs_id"] == 100000 and "UTM zone 12N" in facts["definition"]  # no single EPSG code: its WKT


# ----------------------------------------------------------------------------- parsing and deciding


def test_crs_given_by_the_user():
    assert parse_crs("EPSG:32618").epsg == UTM18
    assert parse_crs("32618").same_as(parse_crs(UTM18))
    assert as_crs(32618).epsg == UTM18
    compound = parse_crs("EPSG:6341+5703")
    assert compound.epsg == "EPSG:6341+5703" and compound.epsg_code is None
    assert Crs.from_dict(compound.to_dict()).same_as(compound)
    with pytest.raises(UsageError, match="not a coordinate reference system"):
        parse_crs("EPSG:99999999")


def test_the_frame_decides_the_crs_and_disagreements_are_said():
    utm18, utm12 = parse_crs(UTM18), parse_crs(UTM12)
    frame = frame_crs({"ground": None, "uav": utm18}, "uav", names={"ground": "g.laz", "uav": "u.laz"})
    assert frame.crs.epsg == UTM18 and frame.source == "file u.laz" and not frame.agree
    entry = frame.to_dict(frames={"keypoints_ground.csv": frame.label_of("ground")})
    assert entry["inputs"] == {"ground": None, "uav": utm18.label}
    assert "no CRS" in entry["frames"]["keypoints_ground.csv"] and entry["notes"]
    # the outputs' frame declares none: no CRS, and the note says where the other input was
    frame = frame_crs({"ground": utm18, "uav": None}, "uav")
    assert frame.crs is None and "declares no CRS" in frame.notes[0]
    with pytest.raises(UsageError, match="two CRSs"):
        frame_crs({"ground": utm12, "uav": utm18}, "uav", refuse_mixed="fuse")
    frame = frame_crs({"ground": utm12, "uav": utm18}, "uav", utm12, refuse_mixed="fuse")  # --crs says which wins
    assert frame.crs.epsg == UTM12 and frame.source == "--crs" and any("wins" in n for n in frame.notes)
    assert frame_crs({"a": utm18, "b": parse_crs("32618")}, "a").agree


# ----------------------------------------------------------------------------- writing


def _cloud(seed: int = 0, n: int = 4000, offset=(500_000.0, 4_300_000.0, 100.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0, 30, (n, 2)), rng.uniform(0, 10, n)] + np.asarray(offset)


@pytest.mark.parametrize("name", ["c.las", "c.laz", "c.copc.laz"])
def test_las_laz_and_copc_store_the_crs(tmp_path, name):
    utm = parse_crs(UTM18)
    write_points(tmp_path / name, _cloud(), crs=utm)
    back = read_scan(tmp_path / name)
    assert back.crs.same_as(utm)
    import laspy

    with laspy.open(tmp_path / name) as f:
        assert f.header.global_encoding.wkt and f.header.parse_crs().to_epsg() == 32618
    write_points(tmp_path / ("local_" + name), _cloud())
    assert read_scan(tmp_path / ("local_" + name)).crs is None


def test_a_moved_scan_keeps_no_crs_unless_its_new_frame_has_one(tmp_path):
    utm = parse_crs(UTM18)
    write_points(tmp_path / "a.laz", _cloud(), crs=utm)
    scan = read_scan(tmp_path / "a.laz")
    write_scan(scan, tmp_path / "same.laz")  # written where it is: its CRS
    assert read_scan(tmp_path / "same.laz").crs.same_as(utm)
    move = np.eye(4)
    move[:3, 3] = [5.0, 0.0, 0.0]
    assert scan.transformed(move).crs is None
    write_scan(scan, tmp_path / "moved.laz", matrix=move)
    assert read_scan(tmp_path / "moved.laz").crs is None
    write_scan(
        scan, tmp_path / "moved_utm12.laz", matrix=move, crs=parse_crs(UTM12)
    )  # the caller names the new frame's
    assert read_scan(tmp_path / "moved_utm12.laz").crs.epsg == UTM12
    chunks = [(_cloud(1)[:, :] - [500_000.0, 4_300_000.0, 0.0], None, None)]
    write_point_chunks(
        tmp_path / "chunks.laz",
        chunks,
        bounds=(np.zeros(3), np.array([30.0, 30.0, 120.0])),
        origin_shift=np.array([500_000.0, 4_300_000.0, 0.0]),
        crs=utm,
    )
    assert read_scan(tmp_path / "chunks.laz").crs.same_as(utm)


# ----------------------------------------------------------------------------- the commands


def _canopy_pair(tmp_path: Path, ground_crs=None, uav_crs=None) -> tuple[Path, Path]:
    """Two small clouds of one frame (a flat ground: no canopy), each written with a CRS or none."""
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 30, (20000, 2)), rng.normal(0, 0.02, 20000)]
    paths = []
    for name, pts, crs in (("ground", ground, ground_crs), ("uav", ground + [0, 0, 0.1], uav_crs)):
        paths.append(tmp_path / f"{name}.laz")
        write_points(paths[-1], pts, crs=None if crs is None else parse_crs(crs))
    return paths[0], paths[1]


def test_fusing_two_crs_without_crs_exits_2_and_with_crs_takes_it(tmp_path, capsys):
    ground, uav = _canopy_pair(tmp_path, UTM12, UTM18)
    out = tmp_path / "fused.laz"
    assert main(["fuse", str(ground), str(uav), "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two CRSs" in err[0] and "--crs" in err[0]
    assert not out.exists()
    assert main(["fuse", str(ground), str(uav), "--out", str(out), "--crs", UTM18, "-q"]) == 0
    assert read_scan(out).crs.epsg == UTM18


def test_fusing_a_local_cloud_onto_a_georeferenced_one_takes_the_uav_crs(tmp_path, capsys):
    ground, uav = _canopy_pair(tmp_path, None, UTM18)
    out = tmp_path / "fused.laz"
    assert main(["fuse", str(ground), str(uav), "--out", str(out), "-q"]) == 0
    assert read_scan(out).crs.epsg == UTM18
    assert "ground.laz declares no CRS" in capsys.readouterr().out


def test_a_bad_crs_option_exits_2_before_any_work(tmp_path, capsys):
    ground, uav = _canopy_pair(tmp_path)
    assert main(["coregister", str(ground), str(uav), "--out", str(tmp_path / "co"), "--crs", "no such crs", "-q"]) == 2
    assert "not a coordinate reference system" in capsys.readouterr().err
    assert not (tmp_path / "co").exists()


def test_coregistration_result_names_the_uav_frame_and_each_cloud(tmp_path, capsys):
    """A co-registration that fails at once (flat clouds: no canopy) still says the frames."""
    ground, uav = _canopy_pair(tmp_path, None, UTM18)
    out = tmp_path / "co"
    assert main(["coregister", str(ground), str(uav), "--out", str(out), "-q"]) == 1
    crs = json.loads((out / "result.json").read_text())["crs"]
    assert crs["epsg"] == UTM18 and crs["source"] == "file uav.laz" and crs["frame"] == "uav"
    assert crs["inputs"]["ground"] is None and "UTM zone 18N" in crs["inputs"]["uav"]
    assert "no CRS" in crs["frames"]["keypoints_ground.csv"] and "UTM zone 18N" in crs["frames"]["layers.gpkg"]
    assert "layers.gpkg" in [p.name for p in out.iterdir()]
    assert read_layer(out / "layers.gpkg", "keypoints")[1]["srs_id"] == 32618


@pytest.fixture(scope="module")
def plot_files(tmp_path_factory, sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (7.0, 2.0), (-5.0, 6.0)), seed=3, step=0.5, size=30.0)
    folder = tmp_path_factory.mktemp("plot")
    paths = []
    for s in plot.scans:
        paths.append(folder / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    return paths


def test_a_pair_takes_the_reference_crs_and_says_the_moving_scan_had_none(plot_files, tmp_path):
    ref = tmp_path / "ref.laz"
    write_scan(
        read_scan(plot_files[0]), ref, crs=parse_crs(UTM18)
    )  # the reference georeferenced, the moving scan local
    out = tmp_path / "pair"
    assert main(["register", str(ref), str(plot_files[1]), "--out", str(out), "--write-registered", "-q"]) == 0
    crs = json.loads((out / "result.json").read_text())["crs"]
    assert crs["epsg"] == UTM18 and crs["frame"] == "reference" and crs["inputs"]["moving"] is None
    assert any("scan_02.laz declares no CRS" in n for n in crs["notes"])
    registered = out / f"{plot_files[1].stem}_registered.laz"
    assert registered.name in crs["frames"]
    assert read_scan(registered).crs.epsg == UTM18


def test_a_plot_carries_the_crs_to_poses_merged_registered_and_layers(plot_files, tmp_path):
    out = tmp_path / "plot"
    code = main(
        [
            "plot",
            *map(str, plot_files),
            "--out",
            str(out),
            "--merged",
            str(out / "merged.laz"),
            "--registered-dir",
            str(tmp_path / "registered"),
            "--crs",
            UTM18,
            "-q",
        ]
    )
    assert code == 0
    crs = json.loads((out / "poses.json").read_text())["crs"]
    assert crs["epsg"] == UTM18 and crs["source"] == "--crs" and crs["frame"] == plot_files[0].name
    assert read_scan(out / "merged.laz").crs.epsg == UTM18
    assert all(read_scan(p).crs.epsg == UTM18 for p in (tmp_path / "registered").glob("*.laz"))
    assert layer_names(out / "layers.gpkg") == ["scanners", "links", "plot_outline"]
    scanners, facts = read_layer(out / "layers.gpkg", "scanners")
    assert facts["srs_id"] == 32618 and len(scanners) == 3
    assert {r["status"] for r in scanners} == {"centre", "ok"}
    centre = next(r for r in scanners if r["status"] == "centre")
    np.testing.assert_allclose(centre["geom"][1], read_scan(plot_files[0]).scanner_position_file, atol=1e-6)
    links, _ = read_layer(out / "layers.gpkg", "links")
    assert len(links) == 2 and all(r["status"] == "ok" and r["geom"][0] == "LINESTRING" for r in links)
    assert all(r["sigma_translation_m"] is not None for r in links)
    # the plot's outline is that of the points measured (the merged cloud), not of the scans' boxes
    (outline,), _ = read_layer(out / "layers.gpkg", "plot_outline")
    assert outline["outline_of"] == "the registered scans' stem-height slices"
    merged = read_scan(out / "merged.laz").points
    from scipy.spatial import ConvexHull

    cloud_area = ConvexHull(np.asarray(merged)[:, :2]).volume
    assert 0.5 * cloud_area < outline["area_m2"] <= 1.01 * cloud_area


def _trees_table(path: Path, xy: np.ndarray, dbh: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["tree_id,x,y,z,dbh_m,height_m"]
    lines += [f"{i + 1},{x:.3f},{y:.3f},0,{d:.3f},{15 + 20 * d:.2f}" for i, ((x, y), d) in enumerate(zip(xy, dbh))]
    path.write_text("\n".join(lines) + "\n")


def test_a_resurvey_takes_before_crs_and_names_it_in_result_and_layers(tmp_path):
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 40, (30, 2))
    dbh = rng.uniform(0.15, 0.5, 30)
    turn = np.radians(25.0)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    _trees_table(tmp_path / "before" / "trees.csv", xy, dbh)
    _trees_table(tmp_path / "after" / "trees.csv", xy @ rot.T + [12.0, -3.0], dbh + 0.01)
    out = tmp_path / "change"
    assert (
        main(
            [
                "change",
                str(tmp_path / "before" / "trees.csv"),
                str(tmp_path / "after" / "trees.csv"),
                "--out",
                str(out),
                "--crs",
                UTM18,
                "--no-report",
                "-q",
            ]
        )
        == 0
    )
    crs = json.loads((out / "result.json").read_text())["crs"]
    assert crs["epsg"] == UTM18 and crs["frame"] == "before" and crs["source"] == "--crs"
    rows, facts = read_layer(out / "layers.gpkg", "tree_changes")
    assert facts["srs_id"] == 32618
    assert len(rows) == len((out / "tree_changes.csv").read_text().strip().splitlines()) - 1


def test_trees_moved_by_a_transform_take_its_target_crs_only(shared_data, tmp_path):
    """A cloud moved by a co-registration's transform lands in the target's frame: the layers take
    the CRS the co-registration's ``result.json`` names, never the moved cloud's own."""
    from forestreg.app.trees import transform_target_crs

    co = tmp_path / "co"
    co.mkdir()
    (co / "transform.txt").write_text("1 0 0 2\n0 1 0 -3\n0 0 1 0\n0 0 0 1\n")
    (co / "result.json").write_text(json.dumps({"status": "ok", "crs": parse_crs(UTM12).to_dict()}))
    out = tmp_path / "trees"
    assert (
        main(
            [
                "trees",
                str(shared_data / "spanner_ALS_Clip.laz"),
                "--out",
                str(out),
                "--transform",
                str(co / "transform.txt"),
                "--no-cylinders",
                "--no-report",
                "-q",
            ]
        )
        == 0
    )
    assert read_layer(out / "layers.gpkg", "trees")[1]["srs_id"] == 26912
    (co / "result.json").write_text(json.dumps({"status": "ok"}))  # a target frame without a CRS: local
    assert transform_target_crs(co / "transform.txt") is None
    assert transform_target_crs(tmp_path / "nowhere" / "transform.txt") is None


# ----------------------------------------------------------------------------- the CRS's unit

USFT = 1200.0 / 3937.0


@pytest.fixture(scope="module")
def pine_in_feet(shared_data, tmp_path_factory):
    """The real pine plot as a US State Plane file: coordinates in US survey feet with its CRS."""
    pts = read_scan(shared_data / "pine_plot.laz").points + np.array([300_000.0, 60_000.0, 20.0])
    path = tmp_path_factory.mktemp("feet") / "pine_ftus.laz"
    write_points(path, pts / USFT, crs=parse_crs("EPSG:2263"))
    return path


def test_a_cloud_whose_crs_is_in_feet_is_refused_as_metres_and_read_as_feet(
    shared_data, pine_in_feet, tmp_path, capsys
):
    assert main(["trees", str(pine_in_feet), "--out", str(tmp_path / "m"), "--no-cylinders", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "US survey feet" in err and "--units usft" in err
    assert not (tmp_path / "m").exists()
    out = tmp_path / "ft"
    args = ["trees", str(pine_in_feet), "--units", "usft", "--out", str(out), "--no-cylinders", "--no-report", "-q"]
    assert main(args) == 0
    ref = tmp_path / "ref"
    assert (
        main(["trees", str(shared_data / "pine_plot.laz"), "--out", str(ref), "--no-cylinders", "--no-report", "-q"])
        == 0
    )
    feet, metres = _heights(out / "trees.csv"), _heights(ref / "trees.csv")
    assert len(feet) == len(metres) > 10
    assert np.allclose(np.sort(feet), np.sort(metres), atol=0.05)  # the sizes in metres, as from the metric file


def _heights(path: Path) -> np.ndarray:
    import csv

    with open(path, newline="") as f:
        return np.array([float(r["height_m"]) for r in csv.DictReader(f) if r["height_m"]])


def test_crs_units_that_cannot_be_read_are_named(tmp_path):
    from forestreg.app.common import UnitError, check_units
    from forestreg.app.units import crs_unit_problem

    feet = parse_crs("EPSG:2263")
    assert crs_unit_problem(feet, "usft") is None and crs_unit_problem(feet, "ft") is None  # 2 ppm apart
    assert "--units usft" in crs_unit_problem(feet, "m")
    assert crs_unit_problem(parse_crs(UTM18), "m") is None
    assert "--units m" in crs_unit_problem(parse_crs(UTM18), "cm")
    assert "geographic" in crs_unit_problem(parse_crs("EPSG:4326"), "m")
    assert "geocentric" in crs_unit_problem(parse_crs("EPSG:4978"), "m")
    assert "mixes units" in crs_unit_problem(parse_crs("EPSG:32618+6360"), "m")  # UTM metres, NAVD88 feet
    assert crs_unit_problem(parse_crs("EPSG:2263+6360"), "usft") is None  # feet on all three axes
    assert crs_unit_problem(None, "m") is None
    # the Python API: a scan read in its CRS's unit passes the check of a function taking metres
    path = tmp_path / "ft.laz"
    write_points(path, _cloud(n=20_000, offset=(1_000_000.0, 200_000.0, 50.0)) / USFT, crs=feet)
    check_units(read_scan(path, unit_scale=USFT), "m", "api")
    with pytest.raises(UnitError, match="US survey feet"):
        check_units(read_scan(path), "m", "api")


def test_a_local_file_in_feet_read_as_metres_is_warned_about(shared_data, tmp_path, caplog):
    """Without a CRS nothing in the points tells feet from metres (a tree's height over its
    diameter is the same in both): the pine plot in feet gives 56 m pines, and the run says that
    only the tallest old-growth stands are so tall and how to give feet. In metres it is silent."""
    from forestreg.app.units import tall_stand_note

    path = tmp_path / "pine_ft.laz"
    write_points(path, read_scan(shared_data / "pine_plot.laz").points / 0.3048)
    out = tmp_path / "ft"
    assert main(["trees", str(path), "--out", str(out), "--no-cylinders", "--no-report", "-q"]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("--units ft" in w and "m tall at the median" in w for w in warned), warned
    assert np.median(_heights(out / "trees.csv")) > 45.0
    assert tall_stand_note([20.0, 25.0, 30.0, 28.0, 22.0]) is None
    assert tall_stand_note([60.0] * 4) is None  # too few trees to say
    assert tall_stand_note([60.0] * 5, units="ft") is None  # the unit was given
    assert "--units ft" in tall_stand_note([60.0] * 5)


@pytest.mark.parametrize(
    "crs, said", [("EPSG:4326", "geographic"), ("EPSG:4978", "geocentric"), ("EPSG:2236", "US survey feet")]
)
@pytest.mark.parametrize("command", ["trees", "register", "plot"])
def test_a_crs_given_on_the_command_line_is_checked_as_a_files_own(shared_data, tmp_path, capsys, crs, said, command):
    """``--crs`` wins over the files' CRS, so it is held to the same checks: a local cloud in
    metres declared in latitude and longitude, Earth-centred coordinates or State Plane feet gave
    outputs in that CRS with exit 0."""
    cloud = shared_data / "pine_plot.laz"
    scans = [cloud] if command == "trees" else [cloud, shared_data / "LPine1_demo.laz"]
    out = tmp_path / "out"
    assert main([command, *map(str, scans), "--crs", crs, "--out", str(out), "-q"]) == 2
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and line.count("--crs") >= 1 and said in line
    assert not out.exists()
