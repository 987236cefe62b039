"""Tests of forestreg.engine.io: round trips for every format, sniffing, errors, E57 poses, atomicity."""

from __future__ import annotations

import os
from pathlib import Path

import laspy
import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError, ScanDataError, ScanReadError, ScanWriteError
from forestreg.engine.core.scan import Scan
from forestreg.engine.io import (
    SUPPORTED_READ_SUFFIXES,
    SUPPORTED_WRITE_SUFFIXES,
    read_scan,
    read_scans,
    write_e57,
    write_points,
    write_scan,
)
from forestreg.engine.io.las import intensity_to_uint16

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
UTM = np.array([500_123.0, 5_200_456.0, 312.0])
MM = 1.0e-3


# ----------------------------------------------------------------------------------------- helpers


def cloud(n: int = 2000, seed: int = 0, center=(0.0, 0.0, 0.0), half: float = 15.0) -> tuple[np.ndarray, np.ndarray]:
    """Random points (m) in a cube around ``center`` and whole-number intensities."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-half, half, (n, 3)) + np.asarray(center, dtype=np.float64)
    intensity = rng.integers(0, 4000, n).astype(np.float64)
    return points, intensity


def rotation_z(angle: float, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = translation
    return m


def rotation_xyz(ax: float, ay: float, az: float, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [ax, ay, az]).as_matrix()
    m[:3, 3] = translation
    return m


def write_pcd(path: Path, points: np.ndarray, intensity: np.ndarray, kind: str) -> None:
    """A minimal PCD file (x y z as float64, intensity float32), ascii or binary."""
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\n"
        "SIZE 8 8 8 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA {kind}\n"
    )
    if kind == "ascii":
        body = "".join(f"{x:.6f} {y:.6f} {z:.6f} {i:g}\n" for (x, y, z), i in zip(points, intensity)).encode()
    else:
        rec = np.empty(len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("i", "<f4")])
        rec["x"], rec["y"], rec["z"], rec["i"] = points[:, 0], points[:, 1], points[:, 2], intensity
        body = rec.tobytes()
    path.write_bytes(header.encode() + body)


def assert_same_points(scan: Scan, expected: np.ndarray, tol: float = MM) -> None:
    assert len(scan) == len(expected)
    assert np.abs(scan.file_points - expected).max() < tol


# ---------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix", [".laz", ".las", ".ply", ".xyz", ".txt", ".e57"])
def test_write_points_round_trip(tmp_path: Path, suffix: str) -> None:
    points, intensity = cloud()
    path = tmp_path / f"cloud{suffix}"
    write_points(path, points, intensity=intensity)
    scan = read_scan(path)
    assert_same_points(scan, points)
    np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))
    assert scan.meta["format"] == {".txt": "xyz"}.get(suffix, suffix[1:])
    assert scan.meta["unit_scale"] == 1.0
    np.testing.assert_array_equal(scan.scanner_position_file, np.zeros(3))
    assert scan.name == "cloud"
    assert suffix in SUPPORTED_WRITE_SUFFIXES and suffix in SUPPORTED_READ_SUFFIXES


@pytest.mark.parametrize("suffix", [".laz", ".ply", ".xyz", ".e57"])
def test_write_scan_applies_matrix_and_keeps_intensity(tmp_path: Path, suffix: str) -> None:
    points, intensity = cloud(seed=1)
    scan = Scan.from_points(points, intensity=intensity, name="s1")
    matrix = rotation_xyz(0.1, -0.2, 0.7, translation=(12.5, -3.25, 1.0))
    path = tmp_path / f"moved{suffix}"
    write_scan(scan, path, matrix=matrix)
    expected = points @ matrix[:3, :3].T + matrix[:3, 3]
    back = read_scan(path)
    assert_same_points(back, expected)
    np.testing.assert_array_equal(back.intensity, intensity.astype(np.float32))


def test_scanner_position_and_unit_scale(tmp_path: Path) -> None:
    points, _ = cloud(seed=2)
    path = tmp_path / "plain.xyz"
    write_points(path, points)
    scan = read_scan(path, scanner_position=(1.0, 2.0, 3.0))
    np.testing.assert_allclose(scan.scanner_position_file, [1.0, 2.0, 3.0])
    assert scan.intensity is None
    feet = read_scan(path, scanner_position=[10.0, 0.0, 0.0], unit_scale=0.3048)
    np.testing.assert_allclose(feet.file_points, points * 0.3048, atol=1e-4)
    np.testing.assert_allclose(feet.scanner_position_file, [3.048, 0.0, 0.0])
    assert feet.meta["unit_scale"] == 0.3048
    with pytest.raises(ParameterError):
        read_scan(path, unit_scale=0.0)
    with pytest.raises(ParameterError):
        read_scan(path, scanner_position=(1.0, 2.0))


def test_utm_laz_keeps_submillimetre_precision(tmp_path: Path) -> None:
    points, intensity = cloud(seed=3, center=UTM)
    path = tmp_path / "utm.laz"
    write_points(path, points, intensity=intensity)
    scan = read_scan(path)
    assert np.abs(scan.origin_shift).max() > 1e5
    assert np.abs(scan.points).max() < 100.0
    assert_same_points(scan, points)
    with laspy.open(path) as reader:
        header = reader.header
        np.testing.assert_allclose(header.scales, 1e-4)
        assert np.all(np.abs(header.offsets - points.min(axis=0)) <= 1.0)
    # a second generation through write_scan stays within a millimetre
    again = tmp_path / "utm2.laz"
    write_scan(scan, again)
    assert_same_points(read_scan(again), points)


def test_write_points_with_origin_shift_and_scan_id(tmp_path: Path) -> None:
    points, intensity = cloud(seed=4)
    ids = np.arange(len(points)) % 3
    for suffix in (".laz", ".ply"):
        path = tmp_path / f"ids{suffix}"
        write_points(path, points, intensity=intensity, scan_id=ids, origin_shift=UTM)
        assert_same_points(read_scan(path), points + UTM)
    las = laspy.read(tmp_path / "ids.laz")
    assert las.scan_id.dtype == np.uint16
    np.testing.assert_array_equal(las.scan_id, ids)
    header = (tmp_path / "ids.ply").read_bytes()[:400]
    assert b"property ushort scan_id" in header and b"binary_little_endian" in header
    with pytest.raises(ParameterError):
        write_points(tmp_path / "bad.laz", points, scan_id=ids - 1)


def test_e57_write_points_splits_scan_ids(tmp_path: Path) -> None:
    points, _ = cloud(seed=5)
    ids = (np.arange(len(points)) % 2) * 7
    path = tmp_path / "ids.e57"
    write_points(path, points, scan_id=ids)
    scans = read_scans(path)
    assert [s.name for s in scans] == ["scan 0", "scan 7"]
    assert_same_points(scans[1], points[ids == 7])


def test_intensity_to_uint16() -> None:
    np.testing.assert_array_equal(intensity_to_uint16(np.array([0.0, 17.0, 65535.0])), [0, 17, 65535])
    np.testing.assert_array_equal(intensity_to_uint16(np.array([0.0, 0.5, 1.0])), [0, 32768, 65535])
    np.testing.assert_array_equal(intensity_to_uint16(np.array([-20.0, -10.0, 0.0, np.nan])), [0, 32768, 65535, 0])


def test_float_intensity_written_to_las(tmp_path: Path) -> None:
    points, _ = cloud(seed=6)
    reflectance = np.linspace(-25.0, 5.0, len(points))
    path = tmp_path / "db.las"
    write_points(path, points, intensity=reflectance)
    scan = read_scan(path)
    assert scan.intensity.min() == 0 and scan.intensity.max() == 65535
    assert np.all(np.diff(scan.intensity) >= 0)


# ----------------------------------------------------------------------------------- other readers


def test_ply_ascii_and_big_endian_with_faces(tmp_path: Path) -> None:
    points, intensity = cloud(n=50, seed=7)
    lines = [f"{x:.6f} {y:.6f} {z:.6f} {i:g}" for (x, y, z), i in zip(points, intensity)]
    text = (
        "\r\n".join(
            [
                "ply",
                "format ascii 1.0",
                "comment test",
                "element vertex 50",
                "property float64 x",
                "property float64 y",
                "property float64 z",
                "property float scalar_Intensity",
                "end_header",
                *lines,
            ]
        )
        + "\r\n"
    )
    (tmp_path / "a.ply").write_text(text, newline="")
    scan = read_scan(tmp_path / "a.ply")
    assert_same_points(scan, points)
    np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))

    rec = np.empty(50, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("reflectance", ">u2")])
    rec["x"], rec["y"], rec["z"], rec["reflectance"] = points[:, 0], points[:, 1], points[:, 2], intensity
    face = np.array([(3, 0, 1, 2)], dtype=[("n", "u1"), ("a", ">i4"), ("b", ">i4"), ("c", ">i4")])
    head = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 50\nproperty float x\nproperty float y\n"
        "property float z\nproperty ushort reflectance\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()
    (tmp_path / "b.ply").write_bytes(head + rec.tobytes() + face.tobytes())
    scan = read_scan(tmp_path / "b.ply")
    assert_same_points(scan, points, tol=1e-5 * 16)
    np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))


@pytest.mark.parametrize("kind", ["ascii", "binary"])
def test_pcd(tmp_path: Path, kind: str) -> None:
    points, intensity = cloud(n=300, seed=8)
    points[5] = np.nan  # an organised cloud's "no return"
    path = tmp_path / f"c_{kind}.pcd"
    write_pcd(path, points, intensity, kind)
    scan = read_scan(path)
    keep = np.isfinite(points).all(axis=1)
    assert_same_points(scan, points[keep])
    np.testing.assert_array_equal(scan.intensity, intensity[keep].astype(np.float32))
    assert scan.meta["dropped_invalid"] == 1 and scan.meta["format"] == "pcd"


def test_pcd_binary_compressed(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    points, intensity = cloud(n=300, seed=9)
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    pc.point["intensity"] = o3d.core.Tensor(intensity.astype(np.float32).reshape(-1, 1))
    path = tmp_path / "c.pcd"
    o3d.t.io.write_point_cloud(str(path), pc, write_ascii=False, compressed=True)
    scan = read_scan(path)
    assert_same_points(scan, points)
    np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))


@pytest.mark.parametrize(
    "header, sep, suffix, intensity_col",
    [
        ("", " ", ".xyz", True),
        ("X,Y,Z,Intensity\n", ",", ".csv", True),
        ("x;y;z;intensity\n", ";", ".txt", True),
        ("# exported\n//X Y Z Intensity R G B\n", "\t", ".asc", True),
    ],
)
def test_text_variants(tmp_path: Path, header: str, sep: str, suffix: str, intensity_col: bool) -> None:
    points, intensity = cloud(n=100, seed=10)
    rows = [
        sep.join([f"{v:.5f}" for v in p] + [f"{i:g}"] + (["1", "2", "3"] if "R G B" in header else []))
        for p, i in zip(points, intensity)
    ]
    path = tmp_path / f"t{suffix}"
    path.write_text(header + "\n".join(rows) + "\n")
    scan = read_scan(path)
    assert_same_points(scan, points)
    np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))


def test_text_with_decimal_commas(tmp_path: Path) -> None:
    """A spreadsheet's export in many locales, 1,25;3,50;0,75: read as the numbers it holds (it
    was read as twice the columns, integers and fractions apart, and refused as millimetres)."""
    points, intensity = cloud(n=100, seed=12)
    rows = [";".join(f"{v:.5f}".replace(".", ",") for v in (*p, i)) for p, i in zip(points, intensity)]
    scan = read_scan(_write(tmp_path / "comma.txt", "x;y;z;intensity\n" + "\n".join(rows) + "\n"))
    assert_same_points(scan, points)
    np.testing.assert_allclose(scan.intensity, intensity.astype(np.float32))
    bad = _write(tmp_path / "mixed.txt", "1,5;2,5;3,5\n1,5;2,5;x\n")
    with pytest.raises(ScanReadError, match="decimal commas"):
        read_scan(bad)


def test_text_pts_rgb_and_damaged_lines(tmp_path: Path) -> None:
    points, intensity = cloud(n=100, seed=11)
    body = "\n".join(f"{x:.4f} {y:.4f} {z:.4f} {int(i) - 2048} 10 20 30" for (x, y, z), i in zip(points, intensity))
    (tmp_path / "a.pts").write_text(f"{len(points)}\n{body}\n")
    scan = read_scan(tmp_path / "a.pts")
    assert_same_points(scan, points)
    np.testing.assert_array_equal(scan.intensity, (intensity - 2048).astype(np.float32))

    rgb = "\n".join(f"{x:.4f} {y:.4f} {z:.4f} 10 20 30" for x, y, z in points)
    assert read_scan(_write(tmp_path / "rgb.xyz", rgb)).intensity is None  # 6 columns: colours, not intensity

    damaged = body.splitlines()
    damaged[40] = "12.5 oops 3"
    scan = read_scan(_write(tmp_path / "damaged.xyz", "\n".join(damaged)))
    assert len(scan) == 99 and scan.meta["skipped_lines"] == 1

    broken = "\n".join(line if k % 3 else "1.0 2.0" for k, line in enumerate(body.splitlines()))
    with pytest.raises(ScanReadError, match="not x y z numbers"):
        read_scan(_write(tmp_path / "broken.xyz", broken))


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ------------------------------------------------------------------------------------------ sniffing


@pytest.mark.parametrize("name", ["actually_laz.txt", "actually_laz.ply", "no_suffix"])
def test_sniffs_laz_with_wrong_suffix(tmp_path: Path, name: str) -> None:
    points, intensity = cloud(seed=12)
    good = tmp_path / "good.laz"
    write_points(good, points, intensity=intensity)
    wrong = tmp_path / name
    wrong.write_bytes(good.read_bytes())
    scan = read_scan(wrong)
    assert scan.meta["format"] == "laz"
    assert_same_points(scan, points)


# -------------------------------------------------------------------------------------------- errors


def _las_bytes(tmp_path: Path, n: int = 2000, compress: bool = True) -> bytes:
    points, intensity = cloud(n=n, seed=13)
    path = tmp_path / ("src.laz" if compress else "src.las")
    write_points(path, points, intensity=intensity)
    return path.read_bytes()


def test_missing_folder_and_empty(tmp_path: Path) -> None:
    with pytest.raises(ScanReadError, match="no such file"):
        read_scan(tmp_path / "nope.laz")
    with pytest.raises(ScanReadError, match="folder"):
        read_scan(tmp_path)
    (tmp_path / "empty.laz").write_bytes(b"")
    with pytest.raises(ScanReadError, match="empty"):
        read_scan(tmp_path / "empty.laz")


def test_zero_point_las(tmp_path: Path) -> None:
    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.write(tmp_path / "zero.las")
    with pytest.raises(ScanReadError, match="no points"):
        read_scan(tmp_path / "zero.las")


def test_truncated_laz_and_las(tmp_path: Path) -> None:
    data = _las_bytes(tmp_path)
    (tmp_path / "cut.laz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ScanReadError, match="cut.laz") as info:
        read_scan(tmp_path / "cut.laz")
    assert "truncated" in str(info.value) and "chunk table" in str(info.value)  # known from the header
    (tmp_path / "tail.laz").write_bytes(data[:-4])  # the chunk table's end cut: laspy's reading says so
    with pytest.raises(ScanReadError, match="tail.laz") as info:
        read_scan(tmp_path / "tail.laz")
    assert "truncated" in str(info.value) and info.value.__cause__ is not None
    (tmp_path / "head.laz").write_bytes(data[:100])
    with pytest.raises(ScanReadError, match="too short"):
        read_scan(tmp_path / "head.laz")
    raw = _las_bytes(tmp_path, compress=False)
    (tmp_path / "cut.las").write_bytes(raw[:-100])
    with pytest.raises(ScanReadError, match="truncated"):
        read_scan(tmp_path / "cut.las")


def test_garbage_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    (tmp_path / "garbage.laz").write_bytes(rng.bytes(5000))
    with pytest.raises(ScanReadError, match="not a valid LAS/LAZ"):
        read_scan(tmp_path / "garbage.laz")
    # a LASF signature on random bytes: laspy alone would loop over a billion VLRs
    (tmp_path / "lasf.laz").write_bytes(b"LASF" + rng.bytes(5000))
    with pytest.raises(ScanReadError, match="lasf.laz"):
        read_scan(tmp_path / "lasf.laz")
    (tmp_path / "blob.bin").write_bytes(b"\x00\x01" + rng.bytes(5000))
    with pytest.raises(ScanReadError, match="unknown scan format"):
        read_scan(tmp_path / "blob.bin")
    (tmp_path / "words.txt").write_text("hello world\nthis is not a cloud\n")
    with pytest.raises(ScanReadError, match="no line with three numbers"):
        read_scan(tmp_path / "words.txt")
    (tmp_path / "bad.e57").write_bytes(b"ASTM-E57" + rng.bytes(3000))
    with pytest.raises(ScanReadError, match="bad.e57"):
        read_scan(tmp_path / "bad.e57")


def test_truncated_ply_and_e57(tmp_path: Path) -> None:
    points, intensity = cloud(seed=15)
    write_points(tmp_path / "c.ply", points, intensity=intensity)
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-50])
    with pytest.raises(ScanReadError, match="truncated"):
        read_scan(tmp_path / "cut.ply")
    write_points(tmp_path / "c.e57", points, intensity=intensity)
    data = (tmp_path / "c.e57").read_bytes()
    (tmp_path / "cut.e57").write_bytes(data[: len(data) // 2])
    with pytest.raises(ScanReadError, match="cut.e57") as info:
        read_scan(tmp_path / "cut.e57")
    assert info.value.__cause__ is not None


def test_nan_rows_only(tmp_path: Path) -> None:
    path = _write(tmp_path / "nan.xyz", "x y z\n" + "nan nan nan\n" * 20)
    with pytest.raises(ScanDataError, match="NaN"):
        read_scan(path)


def test_millimetre_cloud_needs_unit_scale(tmp_path: Path) -> None:
    points, _ = cloud(seed=16)
    path = tmp_path / "mm.xyz"
    write_points(path, points * 1000.0)
    with pytest.raises(ScanDataError, match="millimetres"):
        read_scan(path)
    scan = read_scan(path, unit_scale=0.001)
    assert_same_points(scan, points)


# ------------------------------------------------------------------------------------------------ E57


def test_e57_multi_scan_poses_round_trip(tmp_path: Path) -> None:
    poses = [np.eye(4), rotation_xyz(0.02, -0.01, 1.2, (20.0, -5.0, 0.5)), rotation_z(-2.5, (-8.0, 30.0, 1.0))]
    scans, raw = [], []
    for k in range(3):
        points, intensity = cloud(n=1500 + k, seed=20 + k)
        raw.append((points, intensity))
        scans.append(Scan.from_points(points, intensity=intensity, name=f"station {k}"))
    path = tmp_path / "project.e57"
    write_e57(path, scans, poses)
    back = read_scans(path)
    assert [s.name for s in back] == ["station 0", "station 1", "station 2"]
    for scan, (points, intensity), pose in zip(back, raw, poses):
        assert_same_points(scan, points)
        np.testing.assert_allclose(scan.pose, pose, atol=1e-12)
        np.testing.assert_array_equal(scan.intensity, intensity.astype(np.float32))
        np.testing.assert_array_equal(scan.scanner_position_file, np.zeros(3))
        assert scan.meta["format"] == "e57" and scan.meta["e57_scan_count"] == 3

    with pytest.raises(ScanReadError, match="3 scans.*scan_index"):
        read_scan(path)
    one = read_scan(path, scan_index=1)
    assert one.name == "station 1"
    np.testing.assert_allclose(one.pose, poses[1], atol=1e-12)
    with pytest.raises(ScanReadError, match="out of range"):
        read_scan(path, scan_index=3)
    with pytest.raises(ParameterError):
        read_scan(path, scan_index=-1)

    # poses default to scan.pose, then identity; unit_scale scales the translation
    write_e57(tmp_path / "default.e57", [back[1], scans[0]])
    again = read_scans(tmp_path / "default.e57", unit_scale=0.5)
    np.testing.assert_allclose(again[0].pose[:3, :3], poses[1][:3, :3], atol=1e-12)
    np.testing.assert_allclose(again[0].pose[:3, 3], poses[1][:3, 3] * 0.5, atol=1e-12)
    np.testing.assert_allclose(again[1].pose, np.eye(4))


def test_e57_utm_coordinates_and_non_rigid_pose(tmp_path: Path) -> None:
    points, intensity = cloud(seed=30, center=UTM)
    scan = Scan.from_points(points, intensity=intensity)
    path = tmp_path / "utm.e57"
    write_e57(path, [scan])
    back = read_scan(path)
    assert_same_points(back, points)
    assert np.abs(back.origin_shift).max() > 1e5
    with pytest.raises(ScanWriteError, match="rigid"):
        write_e57(tmp_path / "scaled.e57", [scan], [np.diag([2.0, 2.0, 2.0, 1.0])])
    assert not (tmp_path / "scaled.e57").exists()


def test_e57_invalid_points_skipped(tmp_path: Path) -> None:
    pye57 = pytest.importorskip("pye57")
    points, intensity = cloud(n=200, seed=31)
    state = np.zeros(200, dtype=np.int8)
    state[:10] = 2
    path = tmp_path / "invalid.e57"
    with pye57.E57(str(path), mode="w") as e57:
        e57.write_scan_raw(
            {
                "cartesianX": points[:, 0],
                "cartesianY": points[:, 1],
                "cartesianZ": points[:, 2],
                "intensity": intensity.astype(np.float32),
                "cartesianInvalidState": state,
            },
            name="raw",
            rotation=np.array([1.0, 0.0, 0.0, 0.0]),
            translation=np.array([1.0, 2.0, 3.0]),
        )
    scan = read_scan(path)
    assert_same_points(scan, points[10:])  # pye57 writes float32: still far below 1 mm here
    assert scan.meta["dropped_invalid"] == 10
    np.testing.assert_allclose(scan.pose[:3, 3], [1.0, 2.0, 3.0])


def test_e57_spherical_coordinates(tmp_path: Path) -> None:
    pye57 = pytest.importorskip("pye57")
    from pye57 import libe57

    rng = np.random.default_rng(33)
    n = 300
    columns = {
        "sphericalRange": rng.uniform(1.0, 30.0, n),
        "sphericalAzimuth": rng.uniform(-np.pi, np.pi, n),
        "sphericalElevation": rng.uniform(-1.0, 1.0, n),
        "sphericalInvalidState": np.r_[np.ones(5), np.zeros(n - 5)].astype(np.int8),
    }
    path = tmp_path / "spherical.e57"
    with pye57.E57(str(path), mode="w") as e57:
        imf = e57.image_file
        node, proto = libe57.StructureNode(imf), libe57.StructureNode(imf)
        node.set("guid", libe57.StringNode(imf, "{spherical-test}"))
        for name in list(columns)[:3]:
            proto.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, -100.0, 100.0))
        proto.set("sphericalInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
        points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
        node.set("points", points)
        e57.data3d.append(node)
        buffers = libe57.VectorSourceDestBuffer()
        for name, values in columns.items():
            buffers.append(libe57.SourceDestBuffer(imf, name, values, n, True, True))
        writer = points.writer(buffers)
        writer.write(n)
        writer.close()
    scan = read_scan(path)
    r, az, el = (columns[k][5:] for k in list(columns)[:3])
    expected = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    assert_same_points(scan, expected, tol=1e-9)
    assert scan.name == "spherical scan 0" and scan.meta["e57_coordinates"] == "spherical"
    np.testing.assert_array_equal(scan.pose, np.eye(4))


def test_scan_index_on_single_scan_files(tmp_path: Path) -> None:
    points, _ = cloud(seed=32)
    path = tmp_path / "one.laz"
    write_points(path, points)
    assert len(read_scan(path, scan_index=0)) == len(points)
    with pytest.raises(ScanReadError, match="single scan"):
        read_scan(path, scan_index=1)
    assert len(read_scans(path)) == 1


# ------------------------------------------------------------------------------------------- writing


def test_failed_write_leaves_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    points, intensity = cloud(seed=40)
    path = tmp_path / "out.laz"
    write_points(path, points, intensity=intensity)
    before = path.read_bytes()

    def broken_write(self, destination, do_compress=None, laz_backend=None):
        Path(destination).write_bytes(b"LASF partial")
        raise OSError("disk full")

    monkeypatch.setattr(laspy.LasData, "write", broken_write)
    with pytest.raises(ScanWriteError, match="disk full") as info:
        write_points(path, points[:10] + 1.0)
    assert isinstance(info.value.__cause__, OSError)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.laz"]


def test_new_files_get_normal_permissions(tmp_path: Path) -> None:
    points, _ = cloud(seed=43)
    path = tmp_path / "perm.ply"
    write_points(path, points)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    path.chmod(0o640)
    write_points(path, points)
    assert path.stat().st_mode & 0o777 == 0o640


def test_write_errors(tmp_path: Path) -> None:
    points, _ = cloud(seed=41)
    with pytest.raises(ScanWriteError, match="unsupported suffix"):
        write_points(tmp_path / "out.obj", points)
    with pytest.raises(ScanWriteError, match="does not exist"):
        write_points(tmp_path / "missing" / "out.laz", points)
    with pytest.raises(ParameterError):
        write_points(tmp_path / "out.laz", points[:, :2])
    with pytest.raises(ParameterError):
        write_scan(Scan.from_points(points), tmp_path / "out.laz", matrix=np.eye(3))
    with pytest.raises(ScanWriteError, match="no scans"):
        write_e57(tmp_path / "none.e57", [])
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_reading_does_not_modify_input(tmp_path: Path) -> None:
    points, intensity = cloud(seed=42)
    for suffix in (".laz", ".las", ".ply", ".xyz", ".e57"):
        path = tmp_path / f"in{suffix}"
        write_points(path, points, intensity=intensity)
        os.utime(path, ns=(1_000_000_000, 1_000_000_000))
        data, mtime = path.read_bytes(), path.stat().st_mtime_ns
        read_scans(path)
        assert path.read_bytes() == data and path.stat().st_mtime_ns == mtime


# ----------------------------------------------------------------------------------------- real data

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real data folder {DATA} is absent")


@needs_data
@pytest.mark.realdata
def test_real_tls_laz() -> None:
    scan = read_scan(DATA / "TLS_scan_scanner_at_origin.laz")
    assert len(scan) == 1_046_843
    extent = np.ptp(scan.points, axis=0)
    np.testing.assert_allclose(extent, [17.7, 20.9, 15.3], atol=0.1)
    np.testing.assert_array_equal(scan.origin_shift, np.zeros(3))
    np.testing.assert_array_equal(scan.scanner_position, np.zeros(3))


@needs_data
@pytest.mark.realdata
def test_real_cloud_txt() -> None:
    scan = read_scan(DATA / "cloud.txt")
    assert len(scan) == 14_667
    np.testing.assert_allclose(np.ptp(scan.points, axis=0), [2.5, 2.0, 3.7], atol=0.06)
    lo, hi = scan.file_points.min(axis=0), scan.file_points.max(axis=0)
    assert 253.5 < lo[2] < 254.0 and 257.0 < hi[2] < 258.0


def test_chunked_las_never_wraps_coordinates_outside_its_bounds(tmp_path):
    """Bounds too small for the points (a LAS header with empty bounds) are refused, not written
    as wrapped int32 coordinates; the target is left absent."""
    from forestreg.engine.core.errors import ScanWriteError
    from forestreg.engine.io import write_point_chunks

    pts = np.array([[500000.0, 6000000.0, 300.0], [500010.0, 6000005.0, 310.0]])
    target = tmp_path / "merged.laz"
    with pytest.raises(ScanWriteError, match="do not hold them"):
        write_point_chunks(target, [(pts, None, None)], bounds=(np.zeros(3), np.ones(3)))
    assert not target.exists() and not list(tmp_path.iterdir())
    assert write_point_chunks(target, [(pts, None, None)], bounds=(pts.min(axis=0), pts.max(axis=0))) == 2
    las = laspy.read(target)
    assert np.allclose(np.column_stack([las.x, las.y, las.z]), pts, atol=1e-4)


@pytest.mark.parametrize("kind", ["laz", "copc"])
def test_laz_points_are_decoded_straight_by_lazrs_as_laspy_reads_them(tmp_path: Path, kind: str) -> None:
    """LAZ points are decompressed straight from the file's chunks by lazrs (without Python's
    interpreter lock, a group of chunks per call): fixed-size chunks (a LAZ file, the last chunk
    short) and variable-size ones (COPC) give exactly laspy's x, y, z and intensity."""
    from forestreg.engine.io import las as las_module

    rng = np.random.default_rng(5)
    n = 123_457  # two full 50,000-point chunks and a short one
    pts = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(-2, 30, n)]) + [
        512_000.0,
        5_300_000.0,
        400.0,
    ]
    inten = rng.integers(1, 60_000, n).astype(np.uint16)
    path = tmp_path / f"cloud.{'copc.laz' if kind == 'copc' else 'laz'}"
    write_scan(Scan.from_points(pts, intensity=inten.astype(np.float32)), path)  # .copc.laz: COPC
    with laspy.open(str(path)) as reader:
        header = reader.header
        direct = np.empty((header.point_count, 3))
        direct_intensity = np.empty(header.point_count, dtype=np.uint16)
        assert las_module._read_laz_direct(path, header, direct, direct_intensity, 30_000) == n, (
            "the straight path was not taken"
        )
    ref = laspy.read(str(path))
    expected = np.column_stack([np.asarray(ref.x), np.asarray(ref.y), np.asarray(ref.z)])
    assert np.array_equal(direct, expected) and np.array_equal(direct_intensity, np.asarray(ref.intensity))
    raw = las_module.read_las(path)
    assert np.array_equal(raw.points, expected) and np.array_equal(raw.intensity, np.asarray(ref.intensity))
