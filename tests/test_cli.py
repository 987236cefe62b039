"""The command line: files written, exit codes, errors, against the simulator's truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.core.errors import ParameterError
from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import read_scan, write_scan


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory, sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    folder = tmp_path_factory.mktemp("pair")
    paths = []
    for s in plot.scans:
        path = folder / f"{s.scan.name}.laz"
        write_scan(s.scan, path)
        paths.append(path)
    return paths, plot.relative_pose(0, 1)


def test_register_writes_result_transform_vops_and_registered_scan(pair_files, tmp_path):
    (ref, mov), truth = pair_files
    before = mov.read_bytes()
    out = tmp_path / "out"
    code = main(["register", str(ref), str(mov), "--out", str(out), "--dr", "15", "--write-registered", "--quiet"])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "ok" and result["reason"] == ""
    for key in (
        "reference_vops",
        "moving_vops",
        "matched",
        "icp",
        "timings",
        "second_matched",
        "score_gap_m",
        "parameters",
    ):
        assert key in result
    matrix = np.array(result["matrix"])
    rot, trans = rigid_errors(matrix, truth)
    assert rot < 0.05 and trans < 0.02
    assert np.allclose(np.loadtxt(out / "transform.txt"), matrix, atol=1e-8)
    assert result["vop_radius_m"] == 15.0
    for name, count in (("reference_vops.csv", result["reference_vops"]), ("moving_vops.csv", result["moving_vops"])):
        rows = (out / name).read_text().strip().splitlines()
        assert rows[0].startswith("id,x,y,z") and len(rows) == count + 1
    matched = [r for r in (out / "moving_vops.csv").read_text().splitlines()[1:] if r.split(",")[-1]]
    assert len(matched) == result["matched"]
    assert (out / "registration.png").stat().st_size > 10_000
    registered = read_scan(out / f"{mov.stem}_registered.laz")
    moving = read_scan(mov)
    expected = moving.file_points @ truth[:3, :3].T + truth[:3, 3]
    assert np.abs(registered.file_points - expected).max() < 0.03
    assert mov.read_bytes() == before, "the input file was modified"


def test_register_failure_exits_1_with_reason(tmp_path, sim_plot):
    plot = sim_plot("open_field", ((0.0, 0.0), (10.0, 0.0)), seed=7)
    paths = []
    for s in plot.scans:
        paths.append(tmp_path / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    code = main(["register", str(paths[0]), str(paths[1]), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 1
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["status"] == "failed" and result["matrix"] is None and result["reason"]
    assert not (tmp_path / "out" / "transform.txt").exists()


@pytest.mark.parametrize("content", [b"", b"LASF" + b"\x00" * 10, b"not a point cloud at all\n"])
def test_bad_input_exits_2_with_a_clear_message(tmp_path, capsys, content, pair_files):
    bad = tmp_path / "bad.laz"
    bad.write_bytes(content)
    code = main(["register", str(pair_files[0][0]), str(bad), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "bad.laz" in err and "Traceback" not in err


def test_params_file_and_cli_overrides(tmp_path, pair_files):
    params = tmp_path / "p.toml"
    params.write_text("[registration]\nmatch_distance_m = 0.25\nslice_offsets_m = [0.0, 0.5]\n")
    (ref, mov), truth = pair_files
    out = tmp_path / "out"
    assert (
        main(["register", str(ref), str(mov), "--out", str(out), "--params", str(params), "--dr", "12", "--quiet"]) == 0
    )
    used = json.loads((out / "result.json").read_text())["parameters"]
    assert used["match_distance_m"] == 0.25 and used["slice_offsets_m"] == [0.0, 0.5] and used["vop_radius_m"] == 12.0


def test_unknown_parameter_is_an_error(tmp_path, pair_files, capsys):
    params = tmp_path / "p.toml"
    params.write_text("match_distanse_m = 0.25\n")
    (ref, mov), _ = pair_files
    assert main(["register", str(ref), str(mov), "--out", str(tmp_path / "o"), "--params", str(params), "--quiet"]) == 2
    assert "match_distanse_m" in capsys.readouterr().err


def test_scanner_position_for_georeferenced_scans(tmp_path, pair_files):
    """UTM-sized coordinates with the scanner given: same answer in the files' own frames."""
    (ref, mov), truth = pair_files
    shift_ref, shift_mov = np.array([512345.0, 5212345.0, 310.0]), np.array([512400.0, 5212300.0, 312.0])
    geo = []
    for path, shift in ((ref, shift_ref), (mov, shift_mov)):
        scan = read_scan(path)
        moved = tmp_path / f"geo_{path.name}"
        translate = np.eye(4)
        translate[:3, 3] = shift
        write_scan(scan, moved, matrix=translate)
        geo.append(moved)
    out = tmp_path / "out"
    code = main(
        [
            "register",
            str(geo[0]),
            str(geo[1]),
            "--out",
            str(out),
            "--dr",
            "15",
            "--quiet",
            "--scanner-position",
            ",".join(map(str, shift_ref)),
            "--scanner-position",
            ",".join(map(str, shift_mov)),
        ]
    )
    assert code == 0
    matrix = np.array(json.loads((out / "result.json").read_text())["matrix"])
    # compare near the data: in the scanners' frames (in UTM coordinates a 0.001 deg error alone
    # moves the matrix's translation by metres)
    from_ref, to_mov = np.eye(4), np.eye(4)
    from_ref[:3, 3] = -shift_ref
    to_mov[:3, 3] = shift_mov
    rot, trans = rigid_errors(from_ref @ matrix @ to_mov, truth)
    assert rot < 0.05 and trans < 0.02


def test_params_command_prints_a_loadable_toml(tmp_path, capsys):
    from forestreg.engine.params import ProductParams, load_params

    assert main(["params", "--toml"]) == 0
    text = capsys.readouterr().out
    for section in (
        "[registration]",
        "[coregistration]",
        "[coregistration.keypoints]",
        "[fusion]",
        "[trees]",
        "[trees.qsm]",
    ):
        assert section in text
    path = Path(tmp_path / "defaults.toml")
    path.write_text(text)
    assert load_params(path) == ProductParams()
    # a file that sets a few values of several sections
    path.write_text(
        "[registration]\nvop_radius_m = 12.0\n[trees.stems]\nband_low_m = 1.1\n[fusion]\nnoise_method = 'global'\n"
    )
    p = load_params(path)
    assert p.registration.vop_radius_m == 12.0 and p.trees.stems.band_low_m == 1.1 and p.fusion.noise_method == "global"
    assert p.coregistration == ProductParams().coregistration
    # a typo is named with its section
    path.write_text("[trees.stems]\nband_lo_m = 1.1\n")
    with pytest.raises(ParameterError, match=r"trees\.stems.*band_lo_m"):
        load_params(path)


def test_given_vertical_for_a_tilted_scan(tmp_path, sim_plot):
    """--up gives the moving scan's vertical (as an inclination sensor would): it is used as is."""
    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (0.3, 0.2)), seed=6, tilted=((1, 30.0),))
    paths = []
    for s in plot.scans:
        paths.append(tmp_path / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    up = np.linalg.inv(plot.scans[1].pose[:3, :3]) @ np.array([0.0, 0.0, 1.0])
    out = tmp_path / "out"
    code = main(
        [
            "register",
            str(paths[0]),
            str(paths[1]),
            "--out",
            str(out),
            "--dr",
            "10",
            "--quiet",
            "--up=0,0,1",
            "--up=" + ",".join(f"{v:.9f}" for v in up),
        ]
    )
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert result["moving_tilt_deg"] == pytest.approx(30.0, abs=0.01)
    rot, trans = rigid_errors(np.array(result["matrix"]), plot.relative_pose(0, 1))
    assert rot < 0.05 and trans < 0.02
