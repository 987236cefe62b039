"""COPC (Cloud Optimized Point Cloud, https://copc.io) writing, out of core.

A COPC file is a LAZ 1.4 file (point format 6, here with an optional ``scan_id`` extra-bytes
dimension) whose points are grouped into the nodes of an octree, one variable-size LAZ chunk per
node; a ``copc`` info VLR (first VLR) gives the octree's cube and a hierarchy EVLR lists every
node's key, byte range and point count, so a viewer (QGIS, potree, ``laspy.CopcReader``) reads only
the nodes of the region and level of detail it shows. The nodes are additive: level 0 holds an even
subsample of the whole cloud (one point per cell of a 128^3 grid over the root cube, :func:`grid_bits`), each level
down holds one point per cell of a grid twice as fine among the points its ancestors did not take
(a sample larger than ``node_points`` is thinned on a coarser grid), and a node with few points
left (``node_points``) keeps them all, so nodes hold at most ``node_points`` points (only the
deepest possible nodes, 1.28 cm wide, keep more when that many points share them). Every point is stored exactly once.

Units and frame: points arrive as ``local + shift`` (metres, file coordinates of the output, as in
:class:`~forestreg.engine.io.las.LasChunkWriter`) and are stored as 0.1 mm integers
(:func:`~forestreg.engine.io.las.las_header`'s offset and scale); the octree cube is laid out on
that integer grid so no point sits on a node boundary.

Memory stays bounded whatever the number of points: points are streamed into the octree as they
come; a node whose points do not fit in ``memory_points`` is split while streaming (its grid sample
is kept, the rest is spilled into eight temporary files, one per child) and its children are
handled one after another the same way; a subtree that fits is built in memory. Each node is
compressed and written as soon as it is complete; the header and hierarchy are written last. The
temporary files live in a folder beside the output and are removed when the writer ends, also on
error. Peak memory is about ``memory_points`` x 16 bytes plus a few grids, the caller's chunk aside;
the temporary files take 16 bytes per point at most (twice that briefly while a node is split).
"""

from __future__ import annotations

import datetime
import math
import os
import shutil
import struct
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.cells import cell_bits, first_in_cells
from ..core.errors import ParameterError, ScanWriteError
from .las import LAS_SCALE, intensity_to_uint16

__all__ = ["COPC_SUFFIX", "CopcWriter", "is_copc_path", "write_copc"]

#: Output names ending in this (any case) are written as COPC.
COPC_SUFFIX = ".copc.laz"
#: A node with at most this many points left keeps them all (a leaf).
NODE_POINTS = 100_000
#: Points of one subtree built in memory; larger nodes are split while streaming from disk.
MEMORY_POINTS = 1_000_000
#: Points handled at a time when streaming.
BATCH_POINTS = 1_000_000

#: Working record of a point (16 bytes): LAS integer coordinates, intensity, scan id.
_REC = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2"), ("scan_id", "<u2")])
_HEADER_SIZE = 375
_VLR_HEAD = 54
_EVLR_HEAD = 60
_INFO_SIZE = 160
_ENTRY = struct.Struct("<iiiiQii")  # VoxelKey (level, x, y, z), offset, byte size, point count
_HEADER = struct.Struct("<4sHH16sBB32s32sHHHIIBHI5I3d3d6dQQIQ15Q")


def grid_bits(node_points: int) -> int:
    """Cells per side of a node's sampling grid, as a power of two: 128 for the default
    :data:`NODE_POINTS` (a surface crossing a node then leaves some 16k-100k points in it),
    coarser for smaller nodes."""
    return int(min(7, max(2, round(math.log2(math.sqrt(node_points / 4.0))))))


def is_copc_path(path) -> bool:
    """Whether an output path names a COPC file (``*.copc.laz``)."""
    return Path(path).name.lower().endswith(COPC_SUFFIX)


def _las_record_dtype(with_scan_id: bool) -> np.dtype:
    """LAS point format 6 (30 bytes), plus a uint16 ``scan_id`` extra-bytes dimension."""
    fields = [
        ("X", "<i4"),
        ("Y", "<i4"),
        ("Z", "<i4"),
        ("intensity", "<u2"),
        ("returns", "u1"),
        ("flags", "u1"),
        ("classification", "u1"),
        ("user_data", "u1"),
        ("scan_angle", "<i2"),
        ("point_source_id", "<u2"),
        ("gps_time", "<f8"),
    ]
    if with_scan_id:
        fields.append(("scan_id", "<u2"))
    return np.dtype(fields)


def _vlr(user_id: str, record_id: int, description: str, data: bytes) -> bytes:
    return struct.pack("<H16sHH32s", 0, user_id.encode(), record_id, len(data), description.encode()) + data


class CopcWriter:
    """Writes one COPC file from points that arrive chunk by chunk (see the module docstring).

    Parameters
    ----------
    path : file to write (the caller makes it atomic; the temporary folder goes beside it).
    lo, hi : (3,) bounds holding every point to come, file coordinates, metres (generous is fine;
        the octree's cube is made from them, the written header has the points' own bounds).
    with_scan_id : write a uint16 ``scan_id`` extra dimension (also put in ``point_source_id``,
        which viewers offer for colouring); every :meth:`write` then needs one id per point.
    node_points, memory_points : leaf size and in-memory subtree size, points (see the module;
        default :data:`NODE_POINTS`, :data:`MEMORY_POINTS`).
    label : the file's name in error messages (default ``path``; the caller's target when ``path``
        is a temporary file).
    crs : the coordinate reference system of the coordinates (a
        :class:`~forestreg.engine.io.crs.Crs`): an OGC WKT VLR after the COPC info VLR.

    Use as a context manager: on a clean exit the file is written; on an exception nothing more is
    written and the temporary folder is removed.
    """

    def __init__(
        self,
        path: Path,
        lo: np.ndarray,
        hi: np.ndarray,
        *,
        with_scan_id: bool = False,
        node_points: Optional[int] = None,
        memory_points: Optional[int] = None,
        label: Optional[str] = None,
        crs=None,
    ) -> None:
        self.label = str(path) if label is None else str(label)
        # the WKT VLR's record: the WKT, NUL-terminated (the WKT bit of the global encoding is always set)
        self._wkt = b"" if crs is None or not crs.wkt else crs.wkt.encode("utf-8") + b"\0"
        lo = np.asarray(lo, dtype=np.float64).reshape(3)
        hi = np.asarray(hi, dtype=np.float64).reshape(3)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
            raise ParameterError(
                f"{self.label}: bounds must be finite with hi >= lo, got {lo.tolist()} .. {hi.tolist()}"
            )
        node_points = NODE_POINTS if node_points is None else node_points
        memory_points = MEMORY_POINTS if memory_points is None else memory_points
        if int(node_points) < 1 or int(memory_points) < int(node_points):
            raise ParameterError("node_points must be 1 or more and memory_points at least node_points")
        self.path = Path(path)
        self.with_scan_id = bool(with_scan_id)
        self.node_points = int(node_points)
        self.memory_points = int(memory_points)
        self.offset = np.floor(lo)
        scale = LAS_SCALE
        while float((hi - self.offset).max()) / scale > 2.0e9:
            scale *= 10.0
        self.scale = scale
        # the cube: integer steps m .. m + 2**s - 1 per axis, edges half a step off the points
        self.m = np.floor((lo - self.offset) / scale).astype(np.int64)
        top = np.ceil((hi - self.offset) / scale).astype(np.int64)
        side = int((top - self.m).max()) + 1
        self.g = grid_bits(self.node_points)
        self.s = max(int(math.ceil(math.log2(side))), self.g + 1)
        if (self.m < -(2**31)).any() or (self.m + 2**self.s > 2**31).any():
            raise ScanWriteError(
                f"{self.label}: the bounds {lo.tolist()} .. {hi.tolist()} are too large for one COPC file"
            )
        self.max_level = self.s - self.g
        self._las_dtype = _las_record_dtype(self.with_scan_id)
        self.count = 0
        self._nodes: list[tuple[int, int, int, int, int]] = []  # key + point count, in file order
        self._mins = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
        self._maxs = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
        self._closed = False
        self._spill = Path(tempfile.mkdtemp(prefix=f".forestreg-tmp-copc-{self.path.name}.", dir=self.path.parent))
        self._files = 0
        try:
            import lazrs

            self._laz_vlr = lazrs.LazVlr.new_for_compression(6, 2 if self.with_scan_id else 0, True)
            self._fh = open(self.path, "w+b")
            self._fh.write(self._head_bytes(0, 0))
            self._compressor = lazrs.LasZipCompressor(self._fh, self._laz_vlr)
            self._open_chunk = False
            self._root = _Node(self, (0, 0, 0, 0))
        except BaseException:
            self._cleanup()
            raise

    # ------------------------------------------------------------------------------- input

    def write(
        self,
        local: np.ndarray,
        shift: np.ndarray,
        *,
        intensity: Optional[np.ndarray] = None,
        scan_id: Optional[np.ndarray] = None,
    ) -> None:
        """Add points ``local + shift`` ((N, 3), metres) with optional intensities (mapped to uint16
        per call, :func:`~forestreg.engine.io.las.intensity_to_uint16`) and scan ids."""
        local = np.asarray(local, dtype=np.float64)
        n = len(local)
        if n == 0:
            return
        if self.with_scan_id and scan_id is None:
            raise ParameterError(f"{self.label}: every chunk needs a scan_id per point")
        shift = np.asarray(shift, dtype=np.float64).reshape(3)
        inten = None if intensity is None else intensity_to_uint16(intensity)
        for a in range(0, n, BATCH_POINTS):
            b = min(n, a + BATCH_POINTS)
            rec = np.zeros(b - a, dtype=_REC)
            steps = np.round((local[a:b] - (self.offset - shift)) / self.scale)
            lo, hi = steps.min(axis=0), steps.max(axis=0)
            if (lo < self.m).any() or (hi >= self.m + 2**self.s).any():
                outside = ((steps < self.m) | (steps >= self.m + 2**self.s)).any(axis=1)
                raise ScanWriteError(
                    f"{self.label}: {int(outside.sum())} points lie outside the bounds given for the file "
                    f"({(self.offset + self.m * self.scale).tolist()} and {2**self.s * self.scale:.1f} m on)"
                )
            rec["X"], rec["Y"], rec["Z"] = steps[:, 0], steps[:, 1], steps[:, 2]
            self._mins = np.minimum(self._mins, lo.astype(np.int64))
            self._maxs = np.maximum(self._maxs, hi.astype(np.int64))
            if inten is not None:
                rec["intensity"] = inten[a:b]
            if self.with_scan_id:
                rec["scan_id"] = np.asarray(scan_id[a:b]).astype(np.uint16)
            self._root.feed(rec)
            self.count += b - a

    # ------------------------------------------------------------------------------ octree

    def _cells(self, rec: np.ndarray, shift_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Integer cell coordinates of the points on the grid of cells ``2**shift_bits`` steps wide
        (the half-step offset of the cube included, hence ``2 * rel + 1``)."""
        out = []
        for axis, name in enumerate("XYZ"):
            rel = rec[name].astype(np.int64) - self.m[axis]
            out.append((2 * rel + 1) >> (shift_bits + 1))
        return out[0], out[1], out[2]

    def _grid_index(self, rec: np.ndarray, key: tuple[int, int, int, int], bits: Optional[int] = None) -> np.ndarray:
        """Each point's cell in the node's sampling grid of ``2**bits`` cells a side (default the
        writer's grid, 128: cells 0 .. 128^3 - 1)."""
        level, kx, ky, kz = key
        g = self.g if bits is None else bits
        cx, cy, cz = self._cells(rec, self.s - level - g)
        return ((cx - (kx << g)) << (2 * g)) | ((cy - (ky << g)) << g) | (cz - (kz << g))

    def _octant(self, rec: np.ndarray, level: int) -> np.ndarray:
        """Which child (0..7, x bit 4, y bit 2, z bit 1) of its level-``level`` node each point is
        in (uint8)."""
        cx, cy, cz = self._cells(rec, self.s - level - 1)
        return (((cx & 1) << 2) | ((cy & 1) << 1) | (cz & 1)).astype(np.uint8)

    @staticmethod
    def _by_octant(rec: np.ndarray, octant: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points grouped by child (order kept within each; a radix sort) and the counts."""
        order = np.argsort(octant, kind="stable")
        return rec[order], np.bincount(octant, minlength=8)

    def _child_key(self, key: tuple[int, int, int, int], octant: int) -> tuple[int, int, int, int]:
        level, x, y, z = key
        return (level + 1, 2 * x + (octant >> 2 & 1), 2 * y + (octant >> 1 & 1), 2 * z + (octant & 1))

    def _cells_bits(self) -> np.ndarray:
        """No cell claimed yet in a node's sampling grid (the finest: 128^3 cells)."""
        return cell_bits(1 << (3 * self.g))

    def _thin(self, key: tuple[int, int, int, int], rec: np.ndarray) -> np.ndarray:
        """A node's sample that exceeds ``node_points`` (a volume of branches fills many cells)
        thinned on coarser grids (64, 32, ... cells a side) until it fits: a boolean mask."""
        sel = np.arange(len(rec))
        bits = self.g
        while len(sel) > self.node_points and bits > 1:
            bits -= 1
            sel = sel[first_in_cells(self._grid_index(rec[sel], key, bits), self._cells_bits())]
        mask = np.zeros(len(rec), dtype=bool)
        mask[sel] = True
        return mask

    def _build(self, key: tuple[int, int, int, int], rec: np.ndarray) -> None:
        """Write the subtree of the points ``rec`` (all in memory) under the node ``key``."""
        level = key[0]
        if len(rec) <= self.node_points or level >= self.max_level:
            self._emit(key, rec)
            return
        grid = self._grid_index(rec, key)
        keep = first_in_cells(grid, self._cells_bits())
        if int(keep.sum()) > self.node_points:
            chosen = np.flatnonzero(keep)
            keep[chosen[~self._thin(key, rec[chosen])]] = False
        self._emit(key, rec[keep])
        rest = rec[~keep]
        del rec, grid, keep
        rest, counts = self._by_octant(rest, self._octant(rest, level))
        start = 0
        for o in range(8):
            if counts[o]:
                self._build(self._child_key(key, o), rest[start : start + counts[o]])
            start += counts[o]

    def _emit(self, key: tuple[int, int, int, int], rec: np.ndarray) -> None:
        """Compress the points of one node as one LAZ chunk."""
        n = len(rec)
        if n == 0:
            return
        out = np.zeros(n, dtype=self._las_dtype)
        for name in ("X", "Y", "Z", "intensity"):
            out[name] = rec[name]
        out["returns"] = 0x11  # return 1 of 1
        if self.with_scan_id:
            out["scan_id"] = rec["scan_id"]
            out["point_source_id"] = rec["scan_id"]
        if self._open_chunk:
            self._compressor.finish_current_chunk()
        self._compressor.compress_many(out.view(np.uint8))
        self._open_chunk = True
        self._nodes.append((*key, n))

    def _spill_file(self) -> Path:
        self._files += 1
        return self._spill / f"{self._files}.bin"

    # ------------------------------------------------------------------------------ output

    def close(self) -> None:
        """Finish the octree and write the file (hierarchy EVLR, then the final header)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.count == 0:
                raise ParameterError(f"{self.label}: there are no points to write")
            self._root.finish()
            self._root = None
            self._compressor.done()
            start = _HEADER_SIZE + len(self._vlrs(0, 0))
            self._fh.seek(start)
            import lazrs

            table = lazrs.read_chunk_table(self._fh, self._laz_vlr)
            if [c for c, _ in table] != [n for *_, n in self._nodes]:
                raise ScanWriteError(f"{self.label}: the LAZ chunk table does not match the octree nodes")
            pos = start + 8
            page = bytearray()
            for (level, x, y, z, n), (_, size) in zip(self._nodes, table):
                page += _ENTRY.pack(level, x, y, z, pos, size, n)
                pos += size
            self._fh.seek(0, os.SEEK_END)
            evlr_start = self._fh.tell()
            self._fh.write(struct.pack("<H16sHQ32s", 0, b"copc", 1000, len(page), b"COPC hierarchy") + bytes(page))
            self._fh.seek(0)
            self._fh.write(self._head_bytes(evlr_start, len(page)))
            self._fh.close()
        finally:
            self._cleanup()

    def abort(self) -> None:
        """Stop without finishing the file (the caller removes it); remove the temporary folder."""
        self._closed = True
        self._cleanup()

    def _cleanup(self) -> None:
        fh = getattr(self, "_fh", None)
        if fh is not None and not fh.closed:
            fh.close()
        self._root = None
        shutil.rmtree(self._spill, ignore_errors=True)

    def _vlrs(self, evlr_start: int, page_size: int) -> bytes:
        half = 2 ** (self.s - 1) * self.scale
        centre = self.offset + (self.m - 0.5 + 2 ** (self.s - 1)) * self.scale
        copc = struct.pack(
            "<3dddQQdd88x",
            *centre,
            half,
            2 * half / (1 << self.g),
            evlr_start + _EVLR_HEAD if evlr_start else 0,
            page_size,
            0.0,
            0.0,
        )
        out = _vlr("copc", 1, "COPC info", copc)
        out += _vlr("laszip encoded", 22204, "lazrs variable chunks", bytes(self._laz_vlr.record_data()))
        if self.with_scan_id:
            extra = struct.pack("<2xBB32s4x120x32s", 3, 0, b"scan_id", b"scan index")
            out += _vlr("LASF_Spec", 4, "extra bytes", extra)
        if self._wkt:
            out += _vlr("LASF_Projection", 2112, "OGC WKT coordinate system", self._wkt)
        return out

    def _head_bytes(self, evlr_start: int, page_size: int) -> bytes:
        """Public header and VLRs; bounds and counts are the written points' (zeros until known)."""
        vlrs = self._vlrs(evlr_start, page_size)
        n = sum(c for *_, c in self._nodes) if evlr_start else 0
        if n:
            mins = self.offset + self._mins * self.scale
            maxs = self.offset + self._maxs * self.scale
        else:
            mins = maxs = np.zeros(3)
        today = datetime.date.today()
        counts = [n] + [0] * 14
        return (
            _HEADER.pack(
                b"LASF",
                0,
                16,
                bytes(16),
                1,
                4,
                b"forestreg",
                b"forestreg",
                today.timetuple().tm_yday,
                today.year,
                _HEADER_SIZE,
                _HEADER_SIZE + len(vlrs),
                2 + int(self.with_scan_id) + int(bool(self._wkt)),
                6 | 0x80,
                self._las_dtype.itemsize,
                0,
                0,
                0,
                0,
                0,
                0,
                self.scale,
                self.scale,
                self.scale,
                *self.offset,
                maxs[0],
                mins[0],
                maxs[1],
                mins[1],
                maxs[2],
                mins[2],
                0,
                evlr_start,
                1 if evlr_start else 0,
                n,
                *counts,
            )
            + vlrs
        )

    def __enter__(self) -> "CopcWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class _Node:
    """A node that takes points as they stream in: kept in memory while they fit in
    ``memory_points``, else sampled on its grid batch by batch with the rest spilled to eight
    child files, which :meth:`finish` then handles one at a time."""

    def __init__(self, writer: CopcWriter, key: tuple[int, int, int, int]) -> None:
        self.w = writer
        self.key = key
        self.held: list[np.ndarray] = []
        self.count = 0
        self.occ: Optional[np.ndarray] = None
        self.kept: list[np.ndarray] = []
        self.children: list[Optional[tuple[Path, object]]] = [None] * 8
        self.child_counts = [0] * 8

    def feed(self, rec: np.ndarray) -> None:
        if self.occ is None:
            self.held.append(rec)
            self.count += len(rec)
            if self.count > self.w.memory_points and self.key[0] < self.w.max_level:
                self.occ = self.w._cells_bits()
                held, self.held = self.held, []
                for part in held:
                    self._split(part)
            return
        self.count += len(rec)
        self._split(rec)

    def _split(self, rec: np.ndarray) -> None:
        w = self.w
        keep = first_in_cells(w._grid_index(rec, self.key), self.occ)
        self.kept.append(rec[keep])
        self._spill(rec[~keep])

    def _spill(self, rest: np.ndarray) -> None:
        """Append points to the files of the children they fall in."""
        w = self.w
        rest, counts = w._by_octant(rest, w._octant(rest, self.key[0]))
        start = 0
        for o in range(8):
            stop = start + int(counts[o])
            if stop > start:
                if self.children[o] is None:
                    path = w._spill_file()
                    self.children[o] = (path, open(path, "wb"))
                rest[start:stop].tofile(self.children[o][1])
                self.child_counts[o] += stop - start
            start = stop

    def finish(self) -> None:
        w = self.w
        if self.occ is None:
            rec = np.concatenate(self.held) if len(self.held) > 1 else self.held[0]
            self.held = []
            w._build(self.key, rec)
            return
        self.occ = None
        kept = np.concatenate(self.kept)
        self.kept = []
        if len(kept) > w.node_points:
            fits = w._thin(self.key, kept)
            self._spill(kept[~fits])
            kept = kept[fits]
        w._emit(self.key, kept)
        del kept
        for o in range(8):
            if self.children[o] is not None:
                self.children[o][1].close()
        for o in range(8):
            if self.children[o] is None:
                continue
            path = self.children[o][0]
            child = _Node(w, w._child_key(self.key, o))
            with open(path, "rb") as fh:
                while True:
                    data = fh.read(BATCH_POINTS * _REC.itemsize)
                    if not data:
                        break
                    child.feed(np.frombuffer(data, dtype=_REC).copy())
            path.unlink()
            child.finish()


def write_copc(path: Path, cloud, **options) -> None:
    """Write the points ``cloud.local + cloud.shift`` (a :class:`~forestreg.engine.io.base.PointsToWrite`,
    metres) as one COPC file; ``options`` go to :class:`CopcWriter`."""
    local = np.asarray(cloud.local, dtype=np.float64)
    if not len(local):
        raise ParameterError(f"{path}: there are no points to write")
    lo, hi = local.min(axis=0) + cloud.shift, local.max(axis=0) + cloud.shift
    with CopcWriter(
        path, lo, hi, with_scan_id=cloud.scan_id is not None, crs=getattr(cloud, "crs", None), **options
    ) as out:
        out.write(local, cloud.shift, intensity=cloud.intensity, scan_id=cloud.scan_id)
