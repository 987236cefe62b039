"""COPC output (engine/io/copc.py), checked by reading the files back with laspy's CopcReader."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.copc import Bounds

from forestreg.engine.core.errors import ParameterError, ScanWriteError
from forestreg.engine.io import read_scan, write_point_chunks, write_points
from forestreg.engine.io.copc import CopcWriter, is_copc_path

SHIFT = np.array([512000.0, 6200000.0, 310.0])


def _cloud(n: int = 60_000, seed: int = 0):
    """A dense patch (like the ground under a scanner) in a sparser 40 x 30 x 12 m box."""
    rng = np.random.default_rng(seed)
    dense = rng.normal([3.0, -2.0, 0.0], [1.0, 1.0, 0.05], size=(n // 2, 3))
    sparse = rng.uniform([-20, -15, 0], [20, 15, 12], size=(n - n // 2, 3))
    pts = np.vstack([dense, sparse])
    return pts, rng.integers(0, 3000, n).astype(float), rng.integers(0, 7, n).astype(np.uint16)


def _write(path: Path, pts, inten, ids, **options) -> CopcWriter:
    lo, hi = pts.min(axis=0) + SHIFT - 0.5, pts.max(axis=0) + SHIFT + 0.5
    with CopcWriter(path, lo, hi, with_scan_id=True, **options) as w:
        for a in range(0, len(pts), 7_001):  # chunks of odd sizes
            w.write(pts[a : a + 7_001], SHIFT, intensity=inten[a : a + 7_001], scan_id=ids[a : a + 7_001])
    return w


def _rows(rec) -> np.ndarray:
    rows = np.column_stack([rec.X, rec.Y, rec.Z, rec.intensity, rec.scan_id]).astype(np.int64)
    return rows[np.lexsort(rows.T[::-1])]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """One file written with small nodes and a small memory budget, so nodes are split while
    streaming from the temporary files as well as in memory."""
    path = tmp_path_factory.mktemp("copc") / "cloud.copc.laz"
    pts, inten, ids = _cloud()
    w = _write(path, pts, inten, ids, node_points=1_500, memory_points=12_000)
    assert not any(p.name.startswith(".forestreg-tmp") for p in path.parent.iterdir()), "temporary folder removed"
    return path, pts, inten, ids, w


def test_round_trip_every_point_exactly_once(written):
    path, pts, inten, ids, w = written
    with laspy.CopcReader.open(path) as r:
        rec = r.query()
        header = r.header
        entries = r.root_page.entries
    assert header.point_count == len(pts) == len(rec) == sum(e.point_count for e in entries.values())
    assert max(k.level for k in entries) >= 3, "small nodes make a deep octree"
    assert max(e.point_count for e in entries.values()) <= 1_500, "no node over the budget"
    back = np.column_stack([rec.x, rec.y, rec.z]) - SHIFT
    # every point exactly once: the integer records (coordinates, intensity, scan id) as multisets
    scale = header.scales[0]
    steps = np.round((pts - (header.offsets - SHIFT)) / scale)
    expected = np.column_stack([steps, inten, ids]).astype(np.int64)
    assert np.array_equal(_rows(rec), expected[np.lexsort(expected.T[::-1])])
    assert np.abs(np.sort(back, axis=0) - np.sort(pts, axis=0)).max() <= scale
    assert np.array_equal(np.asarray(rec.point_source_id), np.asarray(rec.scan_id))
    assert np.allclose(header.mins, pts.min(axis=0) + SHIFT, atol=scale)
    assert np.allclose(header.maxs, pts.max(axis=0) + SHIFT, atol=scale)
    # a COPC file is a LAZ file: the ordinary reader sees the same points
    assert len(read_scan(path)) == len(pts)


def test_file_layout_follows_the_copc_specification(written):
    """LAS 1.4 point format 6, 'copc' info VLR first, LAZ with variable-size chunks, one chunk per
    node, the hierarchy in a 'copc' 1000 EVLR after the points, and its entries tiling the point data."""
    import struct

    path, pts, *_ = written
    data = path.read_bytes()
    assert data[:4] == b"LASF" and (data[24], data[25]) == (1, 4)
    header_size, point_offset, n_vlr, fmt = struct.unpack_from("<HIIB", data, 94)
    assert header_size == 375 and fmt & 0x3F == 6 and fmt & 0x80
    assert struct.unpack_from("<I", data, 107)[0] == 0, "legacy point count is 0 for point format 6"
    assert struct.unpack_from("<H", data, 6)[0] & 16, "WKT bit (required for point format 6)"
    user_id, record_id, length = struct.unpack_from("<16sHH", data, 377)
    assert (user_id.rstrip(b"\0"), record_id, length) == (b"copc", 1, 160)
    evlr_start, n_evlr, count = struct.unpack_from("<QIQ", data, 235)
    assert n_evlr == 1 and count == len(pts) and evlr_start > point_offset
    user_id, record_id, length = struct.unpack_from("<16sHQ", data, evlr_start + 2)
    assert (user_id.rstrip(b"\0"), record_id) == (b"copc", 1000) and evlr_start + 60 + length == len(data)
    with laspy.CopcReader.open(path) as r:
        import lazrs

        assert lazrs.LazVlr(r.laszip_vlr.record_data).uses_variable_size_chunks()
        assert r.copc_info.hierarchy_root_offset == evlr_start + 60 and r.copc_info.hierarchy_root_size == length
        entries = sorted(r.root_page.entries.values(), key=lambda e: e.offset)
    assert entries[0].offset == point_offset + 8, "the first chunk follows the chunk table offset"
    assert all(a.offset + a.byte_size == b.offset for a, b in zip(entries, entries[1:])), "chunks back to back"
    assert all(e.point_count > 0 for e in entries)


def test_nodes_hold_the_points_of_their_cube(written):
    path, *_ = written
    with laspy.CopcReader.open(path) as r:
        info, entries = r.copc_info, r.root_page.entries
        levels = sorted({k.level for k in entries})
        for level in levels:
            rec = r.level_query(level)
            xyz = np.column_stack([rec.x, rec.y, rec.z])
            cell = 2 * info.halfsize / 2**level
            keys = np.floor((xyz - (info.center - info.halfsize)) / cell).astype(int)
            found, counts = np.unique(keys, axis=0, return_counts=True)
            listed = {(k.x, k.y, k.z): e.point_count for k, e in entries.items() if k.level == level}
            assert {tuple(k): int(c) for k, c in zip(found, counts)} == listed


def test_bounds_query_returns_exactly_the_points_inside(written):
    """Every node the box touches is read: the query returns the same points as filtering the
    whole cloud's stored (0.1 mm) coordinates by the box."""
    path, pts, inten, ids, _ = written
    lo, hi = np.array([0.0, -5.0, -1.0]) + SHIFT, np.array([6.0, 1.0, 0.02]) + SHIFT
    with laspy.CopcReader.open(path) as r:
        rec = r.query(bounds=Bounds(mins=lo, maxs=hi))
        offsets, scale = r.header.offsets, r.header.scales[0]
    steps = np.round((pts - (offsets - SHIFT)) / scale)
    inside = ((steps >= np.round((lo - offsets) / scale)) & (steps <= np.round((hi - offsets) / scale))).all(axis=1)
    assert 1_000 < len(rec) < len(pts) / 2
    expected = np.column_stack([steps, inten, ids]).astype(np.int64)[inside]
    assert np.array_equal(_rows(rec), expected[np.lexsort(expected.T[::-1])])


def test_level_zero_is_an_even_subsample(written):
    path, pts, *_ = written
    with laspy.CopcReader.open(path) as r:
        info = r.copc_info
        top = r.level_query(0)
        coarse = r.query(level=range(0, 2))
    assert 0 < len(top) < len(pts) / 4
    xyz = np.column_stack([top.x, top.y, top.z]) - SHIFT
    # at most one point per cell of the root grid (spacing), and the sparse box is covered as
    # evenly as the dense patch: every occupied 4 m column of the cloud has level-0 points
    grid = np.floor((xyz + SHIFT - (info.center - info.halfsize)) / info.spacing).astype(np.int64)
    assert len(np.unique(grid, axis=0)) == len(grid)

    def cols(p):
        return {tuple(c) for c in np.floor(p[:, :2] / 4.0).astype(int)}

    assert cols(xyz) == cols(pts)
    assert len(top) < len(coarse) < len(pts)


def test_write_point_chunks_and_write_points_pick_copc_by_suffix(tmp_path):
    pts, inten, ids = _cloud(8_000, seed=3)
    target = tmp_path / "Merged.COPC.laz"
    assert is_copc_path(target) and not is_copc_path(tmp_path / "copc.laz")
    chunks = [(pts[:3_000], inten[:3_000], ids[:3_000]), (pts[3_000:], inten[3_000:], ids[3_000:])]
    n = write_point_chunks(
        target, chunks, bounds=(pts.min(axis=0), pts.max(axis=0)), origin_shift=SHIFT, with_scan_id=True
    )
    assert n == len(pts)
    with laspy.CopcReader.open(target) as r:
        assert len(r.query()) == len(pts) and np.bincount(r.query().scan_id).tolist() == np.bincount(ids).tolist()
    single = tmp_path / "one.copc.laz"
    write_points(single, pts, intensity=inten, origin_shift=SHIFT)
    with laspy.CopcReader.open(single) as r:
        assert len(r.query()) == len(pts) and "scan_id" not in set(r.header.point_format.dimension_names)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Merged.COPC.laz", "one.copc.laz"]


def test_identical_points_end_in_the_deepest_node(tmp_path):
    """Points that no grid separates do not recurse without end: the deepest node keeps them."""
    pts = np.vstack([np.zeros((3_000, 3)), np.random.default_rng(1).uniform(-1, 1, (500, 3))])
    path = tmp_path / "same.copc.laz"
    _write(path, pts, np.zeros(len(pts)), np.zeros(len(pts), dtype=np.uint16), node_points=100, memory_points=1_000)
    with laspy.CopcReader.open(path) as r:
        assert len(r.query()) == len(pts)


def test_bad_input_is_refused_with_no_partial_file(tmp_path):
    pts, inten, ids = _cloud(5_000, seed=4)
    target = tmp_path / "merged.copc.laz"
    bounds = (pts.min(axis=0), pts.max(axis=0))
    write_point_chunks(target, [(pts, inten, ids)], bounds=bounds, with_scan_id=True)
    before = target.read_bytes()

    def failing():
        yield pts[:2_000], inten[:2_000], ids[:2_000]
        raise RuntimeError("disk on fire")

    far = pts + [5_000.0, 0.0, 0.0]
    nan = pts.copy()
    nan[7] = np.nan
    cases = [
        ([(pts, inten, None)], ParameterError, "scan_id"),  # ids missing
        ([(far, inten, ids)], ScanWriteError, "outside the bounds"),
        ([(nan, inten, ids)], ParameterError, "NaN"),
        ([(pts[:0], None, ids[:0])], ParameterError, "no points"),
        (failing(), ScanWriteError, "disk on fire"),
    ]
    for chunks, error, words in cases:
        with pytest.raises(error) as info:
            write_point_chunks(target, chunks, bounds=bounds, with_scan_id=True)
        assert words in str(info.value) and "\n" not in str(info.value)
        assert str(target) in str(info.value) and ".tmp" not in str(info.value), (
            "the target is named, not a temporary file"
        )
        assert target.read_bytes() == before, "the previous file is left as it was"
        assert [p.name for p in tmp_path.iterdir()] == ["merged.copc.laz"], "no temporary file or folder left"
    with pytest.raises(ParameterError):
        CopcWriter(tmp_path / "x.copc.laz", np.ones(3), np.zeros(3))
