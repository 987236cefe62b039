"""LAS/LAZ reading and writing with laspy (LAZ through the lazrs backend).

laspy trusts the header: a damaged header (say, a huge VLR count) makes it loop or allocate
for a long time, so the public header is checked with :mod:`struct` first.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import ScanReadError, ScanWriteError
from .base import PointsToWrite, RawCloud, tune_allocator
from .crs import crs_of_las_header

#: Coordinate resolution written to LAS/LAZ, metres (keeps sub-mm steps for UTM-sized values).
LAS_SCALE = 1.0e-4
#: Bytes of the LAS 1.0-1.2 public header; 1.3 and 1.4 headers are longer.
_MIN_HEADER = 227
_VLR_HEADER = 54
_EVLR_HEADER = 60
#: Smallest point record per point format 0..10 (bytes).
_MIN_RECORD = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)


def _check_header(path: Path) -> tuple[int, bool]:
    """Check the LAS public header; return ``(point_count, compressed)``.

    Raises
    ------
    ScanReadError
        The header is inconsistent with itself or the file size (truncated or corrupt file).
    """
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(375)
    if len(head) < _MIN_HEADER or not head.startswith(b"LASF"):
        raise ScanReadError(f"{path}: is too short to be a LAS/LAZ file ({size} bytes); it is truncated or corrupt")
    major, minor = head[24], head[25]
    header_size, offset, n_vlr = struct.unpack_from("<HII", head, 94)
    fmt_byte, record_len, legacy_count = struct.unpack_from("<BHI", head, 104)
    scales = struct.unpack_from("<3d", head, 131)
    point_format = fmt_byte & 0x3F
    compressed = bool(fmt_byte & 0xC0)

    def bad(what: str) -> ScanReadError:
        return ScanReadError(f"{path}: has a corrupt LAS header ({what}); the file is damaged or not a LAS/LAZ file")

    if major != 1 or minor > 4:
        raise bad(f"version {major}.{minor}")
    if header_size < _MIN_HEADER or header_size > size:
        raise bad(f"header size {header_size}")
    if offset < header_size or offset > size:
        if offset > size:
            raise ScanReadError(
                f"{path}: is truncated (the point data should start at byte {offset}, the file has {size})"
            )
        raise bad(f"point data offset {offset}")
    if n_vlr * _VLR_HEADER > offset - header_size:
        raise bad(f"{n_vlr} VLRs do not fit before the points")
    if point_format >= len(_MIN_RECORD) or record_len < _MIN_RECORD[point_format]:
        raise bad(f"point format {point_format} with {record_len}-byte records")
    if not all(np.isfinite(scales)) or any(s == 0 for s in scales):
        raise bad(f"coordinate scales {scales}")
    count = legacy_count
    if minor >= 4 and len(head) >= 255:
        n_evlr = struct.unpack_from("<I", head, 243)[0]
        if n_evlr * _EVLR_HEADER > size:
            raise bad(f"{n_evlr} extended VLRs")
        count = struct.unpack_from("<Q", head, 247)[0] or legacy_count
    data_bytes = size - offset
    if not compressed and count * record_len > data_bytes:
        raise ScanReadError(
            f"{path}: is truncated: the header announces {count:,} points "
            f"({count * record_len:,} bytes) but only {data_bytes:,} bytes follow"
        )
    if not compressed:
        # what follows the points in LAS 1.3/1.4: waveform packets and extended VLRs, where given
        ends = [size]
        if minor >= 3 and len(head) >= 235:
            ends.append(struct.unpack_from("<Q", head, 227)[0])
        if minor >= 4 and len(head) >= 243:
            ends.append(struct.unpack_from("<Q", head, 235)[0])
        end = min((e for e in ends if offset < e <= size), default=size)
        records = (end - offset) // record_len
        if records > count:
            raise ScanReadError(
                f"{path}: has an inconsistent LAS header: it announces {count:,} points, but {records:,} point records "
                "follow it (read as it says, the rest would be lost); repair the header (e.g. LAStools: lasinfo -repair)"
            )
    if compressed and count > 0 and data_bytes < 8:
        raise ScanReadError(
            f"{path}: is truncated: the header announces {count:,} points but no compressed data follow"
        )
    if compressed and count > 0:  # LAZ: the points start with the offset of the chunk table (-1: none)
        with open(path, "rb") as fh:
            fh.seek(offset)
            (table,) = struct.unpack("<q", fh.read(8))
        if table != -1 and table + 8 > size:
            raise ScanReadError(
                f"{path}: is truncated: its compressed points end at byte {table:,} (their chunk table), "
                f"the file has {size:,}"
            )
    return count, compressed


def check_las_header(path: Path) -> tuple[int, bool]:
    """The point count and whether the points are compressed, from a LAS/LAZ public header
    checked against itself and the file's size; ScanReadError for a damaged or truncated file
    (before laspy, which would follow a damaged header's counts)."""
    return _check_header(Path(path))


def las_header_bounds(path: Path) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """Lower and upper corner (x, y, z) of a LAS/LAZ file's points as its public header states
    them (file coordinates), the header checked first (:func:`check_las_header`) and no point
    read; None when the header leaves them empty (all zeros), not finite or the wrong way round
    (some writers do). ScanReadError for a damaged or truncated file."""
    check_las_header(Path(path))
    with open(path, "rb") as fh:
        head = fh.read(_MIN_HEADER)
    max_x, min_x, max_y, min_y, max_z, min_z = struct.unpack_from("<6d", head, 179)
    lo, hi = np.array([min_x, min_y, min_z]), np.array([max_x, max_y, max_z])
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()) or not (
        (lo != 0).any() or (hi != 0).any()
    ):
        return None
    return lo, hi


#: Points decoded per chunk when reading: bounds the memory of the raw point records (about 30 to
#: 70 bytes a point) while the coordinates fill one preallocated array.
READ_CHUNK_POINTS = 500_000


def _read_chunks(reader, points: np.ndarray, intensity: Optional[np.ndarray], chunk_points: int) -> int:
    """Decode the points of an open laspy reader into ``points`` and ``intensity``, ``chunk_points``
    at a time; returns how many were read."""
    total, n = len(points), 0
    for chunk in reader.chunk_iterator(max(1, int(chunk_points))):
        k = len(chunk)
        if k == 0:
            break
        k = min(k, total - n)
        points[n : n + k, 0] = chunk.x[:k]
        points[n : n + k, 1] = chunk.y[:k]
        points[n : n + k, 2] = chunk.z[:k]
        if intensity is not None:
            intensity[n : n + k] = chunk.intensity[:k]
        n += k
        if n >= total:
            break
    return n


def _read_laz_direct(
    path: Path, header, points: np.ndarray, intensity: Optional[np.ndarray], chunk_points: int
) -> Optional[int]:
    """Decode a LAZ file's points into ``points`` (scaled x, y, z) and ``intensity`` straight with
    lazrs, a group of LAZ chunks (about ``chunk_points`` points) per call; returns the points read,
    or None when the file is not laid out as this expects (no LASzip VLR, another record size, a
    chunk table that does not add up), for laspy's reader to take over.

    Each call decompresses its chunks in parallel *without holding Python's interpreter lock*
    (laspy's reader makes lazrs read through a Python file object, taking the lock for every few
    kB: a thread running Python beside it slowed a 3 M-point read from 0.5 to 2.4 s). The values
    are laspy's: ``X * scale + offset`` in float64."""
    try:
        import lazrs
    except ImportError:
        return None
    vlr = next(
        (
            v
            for v in header.vlrs
            if getattr(v, "record_id", None) == 22204 and str(getattr(v, "user_id", "")).startswith("laszip")
        ),
        None,
    )
    if vlr is None:
        return None
    total = len(points)
    dtype = header.point_format.dtype()
    try:
        laz = lazrs.LazVlr(vlr.record_data)
        if laz.item_size() != dtype.itemsize:
            return None
        with open(path, "rb") as f:
            f.seek(int(header.offset_to_point_data))
            table = [(int(p), int(b)) for p, b in lazrs.read_chunk_table(f, laz)]
            if not table:
                return None
            if not laz.uses_variable_size_chunks():  # every chunk holds chunk_size points, the last the rest
                size = int(laz.chunk_size())
                table = [(size, b) for _, b in table[:-1]] + [(total - size * (len(table) - 1), table[-1][1])]
            if any(p <= 0 or b <= 0 for p, b in table) or sum(p for p, _ in table) != total:
                return None
            position = int(header.offset_to_point_data) + 8  # after the chunk table's offset
            scales, offsets = np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, dtype=np.float64)
            xyz_only = lazrs.DecompressionSelection(
                lazrs.SELECTIVE_DECOMPRESS_XY_RETURNS_CHANNEL | lazrs.SELECTIVE_DECOMPRESS_Z
            )
            groups, k = [], 0
            while k < len(table):
                group = [table[k]]
                while k + len(group) < len(table) and sum(p for p, _ in group) < chunk_points:
                    group.append(table[k + len(group)])
                groups.append(group)
                k += len(group)
            # one buffer for every group's compressed bytes and one for its records, reused: a
            # fresh ~15 MB buffer each time is fresh pages from the system, zeroed on first touch
            # (~40 ms of a 3 M-point read, on one core while the decompression's threads wait)
            compressed_all = np.empty(max(sum(b for _, b in g) for g in groups), dtype=np.uint8)
            raw_all = np.empty(max(sum(p for p, _ in g) for g in groups) * dtype.itemsize, dtype=np.uint8)
            n = 0
            for group in groups:
                count, size_bytes = sum(p for p, _ in group), sum(b for _, b in group)
                f.seek(position)
                compressed = compressed_all[:size_bytes]
                if f.readinto(compressed) != size_bytes:
                    return None
                raw = raw_all[: count * dtype.itemsize]
                if intensity is None:  # x, y, z alone (LAZ 1.4 layers; older formats decode every field)
                    lazrs.decompress_points_with_chunk_table(compressed, vlr.record_data, raw, group, xyz_only)
                else:
                    lazrs.decompress_points_with_chunk_table(compressed, vlr.record_data, raw, group)
                records = raw.view(dtype)
                for axis, name in enumerate(("X", "Y", "Z")):  # scaled in place: no temporary arrays
                    column = points[n : n + count, axis]
                    np.multiply(records[name], scales[axis], out=column)
                    column += offsets[axis]
                if intensity is not None:
                    intensity[n : n + count] = records["intensity"]
                n += count
                position += size_bytes
            return n
    except Exception:  # damaged or unusual: laspy reads it, or says what is wrong
        return None


def read_las(path: Path, *, chunk_points: int = READ_CHUNK_POINTS, with_intensity: bool = True) -> RawCloud:
    """Read a LAS/LAZ file: scaled x, y, z as float64 (file units) and intensity (not with
    ``with_intensity=False``: then a LAZ 1.4 file's other layers are not even decompressed).

    The points are decoded in chunks of ``chunk_points`` (LAZ chunks decompressed in parallel by
    lazrs), so the peak memory is the coordinate array plus one chunk of raw records, whatever
    the file's size. Intensity is dropped when it is zero for every point (the file holds none).
    """
    import laspy  # local import: keeps `import forestreg.engine.io` light

    tune_allocator()
    count, compressed = _check_header(path)
    backend = laspy.LazBackend.detect_available()
    try:
        with laspy.open(str(path), laz_backend=backend[0] if backend else None) as reader:
            header = reader.header
            total = int(header.point_count)
            has_intensity = with_intensity and "intensity" in header.point_format.dimension_names
            points = np.empty((total, 3), dtype=np.float64)
            intensity_all = np.empty(total, dtype=np.uint16) if has_intensity else None
            n = _read_laz_direct(path, header, points, intensity_all, chunk_points) if compressed else None
            if n is None:
                n = _read_chunks(reader, points, intensity_all, chunk_points)
            version = f"{header.version.major}.{header.version.minor}"
            point_format = header.point_format.id
            crs = crs_of_las_header(header)
    except Exception as exc:  # laspy, lazrs and struct errors: the file is damaged
        raise ScanReadError(
            f"{path}: cannot be read as {'LAZ' if compressed else 'LAS'} ({_short(exc)}); the file is truncated or corrupt"
        ) from exc
    if n < count:
        raise ScanReadError(f"{path}: is truncated: the header announces {count:,} points, only {n:,} could be read")
    if n < total:
        points = points[:n]
        intensity_all = None if intensity_all is None else intensity_all[:n]
    intensity: Optional[np.ndarray] = None
    if intensity_all is not None and n and intensity_all.any():
        intensity = intensity_all
    meta = {
        "las_version": version,
        "las_point_format": point_format,
        "compressed": compressed,
        "point_count_in_file": n,
    }
    if crs is not None:
        meta["crs"] = crs
    return RawCloud(points=points, intensity=intensity, meta=meta)


def read_las_crs(path: Path):
    """The CRS a LAS/LAZ file's header declares (:func:`~forestreg.engine.io.crs.crs_of_las_header`),
    its points not read; None without one, or for a file that cannot be read (its reading says why)."""
    import laspy

    try:
        check_las_header(Path(path))
        with laspy.open(str(path)) as f:
            return crs_of_las_header(f.header)
    except Exception:  # noqa: BLE001 - damaged: the reader reports it where the points are read
        return None


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def intensity_to_uint16(intensity: np.ndarray) -> np.ndarray:
    """Map intensities to LAS uint16.

    Integer-valued data within 0..65535 are kept as they are; values within 0..1 are scaled by
    65535; anything else (floats, negative dB reflectance) is mapped linearly from its
    min..max onto 0..65535. Non-finite values become 0.
    """
    values = np.asarray(intensity, dtype=np.float64)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(len(values), dtype=np.uint16)
    v = np.where(finite, values, 0.0)
    lo, hi = float(v[finite].min()), float(v[finite].max())
    if lo >= 0.0 and hi <= 65535.0 and np.array_equal(v, np.round(v)):
        out = v
    elif lo >= 0.0 and hi <= 1.0:
        out = v * 65535.0
    elif hi > lo:
        out = (v - lo) / (hi - lo) * 65535.0
    else:
        out = np.zeros_like(v)
    out = np.where(finite, out, 0.0)
    return np.clip(np.round(out), 0, 65535).astype(np.uint16)


def las_header(
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    extra_dims: Sequence[tuple[str, type, str]] = (),
    system_identifier: str = "forestreg",
    crs=None,
):
    """A LAS 1.4 point format 6 header for points within ``lo``..``hi`` (file coordinates,
    metres; bounds may be generous): offsets the floor of ``lo``, scales :data:`LAS_SCALE` (coarser
    only if the extent would overflow int32), so georeferenced coordinates keep 0.1 mm steps; extra
    bytes dimensions ``(name, dtype, description)``; with ``crs`` (a
    :class:`~forestreg.engine.io.crs.Crs`) an OGC WKT VLR naming the coordinates' CRS."""
    import laspy

    offset = np.floor(np.asarray(lo, dtype=np.float64))
    scale = LAS_SCALE
    while float((np.asarray(hi, dtype=np.float64) - offset).max()) / scale > 2.0e9:
        scale *= 10.0
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = offset
    header.scales = np.array([scale, scale, scale])
    header.generating_software = "forestreg"
    header.system_identifier = system_identifier
    for name, dtype, description in extra_dims:
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dtype, description=description))
    add_crs(header, crs)
    return header


def add_crs(header, crs) -> None:
    """Put ``crs`` (a :class:`~forestreg.engine.io.crs.Crs`, or None: nothing) into a LAS 1.4
    header as an OGC WKT VLR (laspy's ``add_crs``; the WKT bit of the global encoding set)."""
    if crs is None:
        return
    found = crs.to_pyproj()
    if found is None:  # no pyproj: the file is written without its CRS
        return
    header.add_crs(found)


def _fill(
    record, local: np.ndarray, shift: np.ndarray, offset: np.ndarray, scale: float, intensity: Optional[np.ndarray]
) -> None:
    """Set the integer coordinates (``local + shift`` in the header's offset and scale), single
    returns and intensity of a laspy point record or LasData of ``len(local)`` points."""
    rel = local - (offset - shift)  # small numbers: no precision lost to large offsets
    steps = np.round(rel / scale)
    if len(steps) and float(np.abs(steps).max()) > np.iinfo(np.int32).max:
        # never a silent int32 wrap: the points lie far outside the bounds the header was made for
        raise ScanWriteError(
            f"points lie more than {np.iinfo(np.int32).max * scale / 1000:.0f} km from the header offset "
            f"{np.asarray(offset).tolist()}: the bounds given for the file do not hold them"
        )
    record.X = steps[:, 0].astype(np.int32)
    record.Y = steps[:, 1].astype(np.int32)
    record.Z = steps[:, 2].astype(np.int32)
    record.return_number = np.ones(len(local), dtype=np.uint8)
    record.number_of_returns = np.ones(len(local), dtype=np.uint8)
    if intensity is not None:
        record.intensity = intensity_to_uint16(intensity)


def las_points(
    local: np.ndarray,
    shift: np.ndarray,
    *,
    intensity: Optional[np.ndarray] = None,
    extra_dims: Sequence[tuple[str, type, str]] = (),
    system_identifier: str = "forestreg",
    crs=None,
):
    """A ``laspy.LasData`` (LAS 1.4, point format 6, header :func:`las_header` of the data's
    bounds) of the points ``local + shift`` (file coordinates, metres), single returns, with empty
    extra-bytes dimensions ``(name, dtype, description)`` for the caller to fill; ``crs`` as
    :func:`las_header`."""
    import laspy

    header = las_header(
        local.min(axis=0) + shift,
        local.max(axis=0) + shift,
        extra_dims=extra_dims,
        system_identifier=system_identifier,
        crs=crs,
    )
    las = laspy.LasData(header)
    _fill(las, local, shift, header.offsets, float(header.scales[0]), intensity)
    return las


class LasChunkWriter:
    """Writes one LAS/LAZ file chunk by chunk, so a cloud larger than memory can be written.

    The header is made up front from bounds that hold every point to come (file coordinates,
    metres; generous bounds cost nothing but a coarser scale beyond 200 km); the written header's
    bounds and counts are the points'. Each :meth:`write` takes points ``local + shift`` with
    optional intensity and a ``scan_id`` per point when the writer was made ``with_scan_id``.
    Intensities are mapped to uint16 chunk by chunk (:func:`intensity_to_uint16`): map them over
    the whole cloud first when they are not uint16 already. ``extra_dims`` (name, dtype,
    description) are further extra-bytes dimensions, filled through :meth:`write`'s ``fields``;
    ``crs`` (a :class:`~forestreg.engine.io.crs.Crs`) is written as a WKT VLR.
    """

    def __init__(
        self,
        path: Path,
        lo: np.ndarray,
        hi: np.ndarray,
        *,
        compress: bool,
        with_scan_id: bool = False,
        extra_dims: Sequence[tuple[str, type, str]] = (),
        system_identifier: str = "forestreg",
        crs=None,
    ) -> None:
        import laspy

        extra = ([("scan_id", np.uint16, "scan index")] if with_scan_id else []) + list(extra_dims)
        self.header = las_header(lo, hi, extra_dims=extra, system_identifier=system_identifier, crs=crs)
        self.with_scan_id = with_scan_id
        self._writer = laspy.open(str(path), mode="w", header=self.header, do_compress=compress)
        self.count = 0

    def write(
        self,
        local: np.ndarray,
        shift: np.ndarray,
        *,
        intensity: Optional[np.ndarray] = None,
        scan_id: Optional[np.ndarray] = None,
        fields: Optional[dict[str, np.ndarray]] = None,
    ) -> None:
        """Append points ``local + shift`` (N, 3), metres; ``fields`` maps point dimension names
        (standard ones such as ``point_source_id`` or the ``extra_dims``) to (N,) values."""
        import laspy

        if len(local) == 0:
            return
        record = laspy.ScaleAwarePointRecord.zeros(len(local), header=self.header)
        _fill(
            record,
            np.asarray(local, dtype=np.float64),
            np.asarray(shift, dtype=np.float64),
            self.header.offsets,
            float(self.header.scales[0]),
            intensity,
        )
        if self.with_scan_id:
            record.scan_id = np.asarray(scan_id).astype(np.uint16)
        for name, values in (fields or {}).items():
            record[name] = values
        self._writer.write_points(record)
        self.count += len(local)

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> "LasChunkWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_las(tmp: Path, cloud: PointsToWrite, *, compress: bool) -> None:
    """Write points ``cloud.local + cloud.shift`` (file coordinates, metres) as LAS 1.4 point
    format 6 (:func:`las_points`); ``scan_id`` becomes a uint16 extra-bytes dimension named ``scan_id``;
    ``cloud.crs`` a WKT VLR."""
    extra = [("scan_id", np.uint16, "scan index")] if cloud.scan_id is not None else []
    las = las_points(cloud.local, cloud.shift, intensity=cloud.intensity, extra_dims=extra, crs=cloud.crs)
    if cloud.scan_id is not None:
        las.scan_id = np.asarray(cloud.scan_id).astype(np.uint16)
    las.write(str(tmp), do_compress=compress)


#: Points written per chunk of a fused cloud.
WRITE_CHUNK_POINTS = 1 << 20


def write_fused(
    path: str | os.PathLike[str],
    result,
    *,
    origin_shift: Optional[np.ndarray] = None,
    unit_scale: float = 1.0,
    crs=None,
) -> None:
    """Write a fused cloud (:class:`~forestreg.engine.coreg.fusion.FusionResult`: ``points``,
    ``source``, ``extra``) as LAS 1.4 (point format 6), LAZ if ``path`` ends in ``.laz``.

    Coordinates are ``(result.points + origin_shift) / unit_scale`` (file coordinates in the
    file's units; shift default zero, metres), at 0.1 mm resolution. Each point's source (1
    ground-based, 2 UAV) is in ``point_source_id`` and in an extra uint8 dimension ``source``;
    ``result.extra["intensity"]``, when present, becomes the intensity. Written
    :data:`WRITE_CHUNK_POINTS` points at a time, atomically (temporary file, then renamed). ``crs``
    (a :class:`~forestreg.engine.io.crs.Crs`, the UAV cloud's frame) is written as a WKT VLR.
    """

    target = str(path)
    suffix = os.path.splitext(target)[1].lower()
    if suffix not in (".las", ".laz"):
        raise ScanWriteError(f"{target}: the fused cloud is written as .las or .laz, not {suffix or 'no extension'}")
    pts = np.asarray(result.points, dtype=np.float64)
    if len(pts) == 0:
        raise ScanWriteError(f"{target}: the fused cloud is empty; nothing to write")
    scale = float(unit_scale)
    shift = (np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64).reshape(3)) / scale
    lo = (
        np.min(
            [(pts[i : i + WRITE_CHUNK_POINTS] / scale).min(axis=0) for i in range(0, len(pts), WRITE_CHUNK_POINTS)],
            axis=0,
        )
        + shift
    )
    hi = (
        np.max(
            [(pts[i : i + WRITE_CHUNK_POINTS] / scale).max(axis=0) for i in range(0, len(pts), WRITE_CHUNK_POINTS)],
            axis=0,
        )
        + shift
    )
    intensity = result.extra.get("intensity")
    intensity = None if intensity is None else intensity_to_uint16(intensity)  # over the whole cloud, then by chunk
    source = np.asarray(result.source)
    with atomic_path(target) as tmp:
        with LasChunkWriter(
            tmp,
            lo,
            hi,
            compress=suffix == ".laz",
            system_identifier="forestreg fusion",
            extra_dims=[("source", np.uint8, "1 ground-based, 2 UAV")],
            crs=crs,
        ) as out:
            for i in range(0, len(pts), WRITE_CHUNK_POINTS):
                part = source[i : i + WRITE_CHUNK_POINTS]
                out.write(
                    pts[i : i + WRITE_CHUNK_POINTS] / scale,
                    shift,
                    intensity=None if intensity is None else intensity[i : i + WRITE_CHUNK_POINTS],
                    fields={"point_source_id": part.astype(np.uint16), "source": part.astype(np.uint8)},
                )
