"""E57 reading and writing with pye57 (libE57Format).

Reading gives each scan's points in its own coordinates (untransformed) and its pose as a 4x4
matrix mapping them into the file's common frame; the scanner sits at the origin of the scan's own
coordinates (the file origin, the default). The CRS of the common frame, when the file's
``coordinateMetadata`` names one (a WKT or ``EPSG:n``), is the scan's ``meta["crs"]`` when its pose
is the identity (its own coordinates are then the common frame's), else ``meta["e57_frame_crs"]``;
none is written (pye57 sets that field itself). Invalid points (``cartesianInvalidState`` / ``sphericalInvalidState`` non-zero) are
skipped.

Writing does not use ``pye57.E57.write_scan_raw``: that stores coordinates as float32, which loses
centimetres on georeferenced values. Coordinates are written as scaled integers (0.1 mm steps,
offset at the data), so any coordinate size keeps its precision and the pose is stored as given.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import ScanReadError, ScanWriteError
from .base import RawCloud
from .crs import crs_of_e57_root

#: Coordinate resolution of written E57 files, metres.
E57_SCALE = 1.0e-4
_WRITE_CHUNK = 1_000_000


@dataclass
class E57Entry:
    """One scan to write: own coordinates ``local + shift`` (metres), intensity, pose, name."""

    local: np.ndarray
    shift: np.ndarray
    intensity: Optional[np.ndarray]
    pose: np.ndarray
    name: str


def _open(path: Path):
    import pye57

    try:
        return pye57.E57(str(path), mode="r")
    except Exception as exc:  # libe57 E57Exception: bad checksum, bad length, not E57
        raise ScanReadError(f"{path}: cannot be read as E57 ({_short(exc)}); the file is truncated or corrupt") from exc


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def scan_count(path: Path) -> int:
    """Number of scans (data3D entries) in an E57 file."""
    e57 = _open(path)
    try:
        return int(e57.scan_count)
    except Exception as exc:
        raise ScanReadError(f"{path}: E57 structure cannot be read ({_short(exc)})") from exc
    finally:
        e57.close()


def read_e57(path: Path, indices: Optional[list[int]] = None) -> list[RawCloud]:
    """Read scans of an E57 file (all, or those at ``indices``) as raw clouds in own coordinates."""
    e57 = _open(path)
    try:
        try:
            count = int(e57.scan_count)
        except Exception as exc:
            raise ScanReadError(f"{path}: E57 structure cannot be read ({_short(exc)})") from exc
        if count == 0:
            raise ScanReadError(f"{path}: the E57 file holds no scans")
        wanted = list(range(count)) if indices is None else indices
        raws = [_read_one(e57, path, i, count) for i in wanted]
        crs = crs_of_e57_root(e57.root)  # the file's coordinateMetadata, when it names a CRS
        if crs is not None:
            for raw in raws:
                own = raw.pose is None or np.allclose(raw.pose, np.eye(4), atol=1e-9)
                raw.meta["crs" if own else "e57_frame_crs"] = crs
        return raws
    finally:
        e57.close()


#: the description forestreg gives each scan it writes into an E57 file
WRITTEN_BY = "written by forestreg"


def written_by_forestreg(path: Path) -> bool:
    """Whether the E57 file at ``path`` holds scans and every one of them was written by forestreg
    (its ``description``): an earlier output that may be replaced. False for a file that cannot
    be read as E57."""
    try:
        e57 = _open(Path(path))
    except ScanReadError:
        return False
    try:
        scans = e57.root["data3D"]
        count = scans.childCount()
        return count > 0 and all(
            scans[i].isDefined("description") and scans[i]["description"].value() == WRITTEN_BY for i in range(count)
        )
    except Exception:  # noqa: BLE001 - a structure libe57 cannot walk is not ours
        return False
    finally:
        e57.close()


def read_e57_crs(path: Path):
    """The CRS an E57 file's ``coordinateMetadata`` names (:func:`~forestreg.engine.io.crs.crs_of_e57_root`),
    its points not read; None without one or for a file that cannot be read."""
    try:
        e57 = _open(Path(path))
    except ScanReadError:
        return None
    try:
        return crs_of_e57_root(e57.root)
    finally:
        e57.close()


def _read_one(e57, path: Path, index: int, count: int) -> RawCloud:
    from pye57.utils import convert_spherical_to_cartesian

    try:
        header = e57.get_header(index)
        fields = set(header.point_fields)
        name = header["name"].value() if header.node.isDefined("name") else f"{path.stem} scan {index}"
        if {"cartesianX", "cartesianY", "cartesianZ"} <= fields:
            coords, state = ["cartesianX", "cartesianY", "cartesianZ"], "cartesianInvalidState"
        elif {"sphericalRange", "sphericalAzimuth", "sphericalElevation"} <= fields:
            coords, state = ["sphericalRange", "sphericalAzimuth", "sphericalElevation"], "sphericalInvalidState"
        else:
            raise ScanReadError(f"{path}: E57 scan {index} ({name}) has neither cartesian nor spherical coordinates")
        wanted = coords + [f for f in ("intensity", state) if f in fields]
        n = int(header.point_count)
        data, buffers = e57.make_buffers(wanted, max(n, 1))
        if n:
            header.points.reader(buffers).read()
        pose = _pose_matrix(header) if header.has_pose() else np.eye(4)
        has_pose = bool(header.has_pose())
    except ScanReadError:
        raise
    except Exception as exc:
        raise ScanReadError(f"{path}: E57 scan {index} cannot be read ({_short(exc)}); the file is corrupt") from exc
    data = {k: v[:n] for k, v in data.items()}
    valid = data[state] == 0 if state in data else np.ones(n, dtype=bool)
    values = np.column_stack([data[c][valid] for c in coords]).astype(np.float64)
    points = values if coords[0] == "cartesianX" else convert_spherical_to_cartesian(values)
    intensity = data["intensity"][valid] if "intensity" in data else None
    meta = {
        "e57_scan_index": index,
        "e57_scan_count": count,
        "e57_has_pose": has_pose,
        "e57_coordinates": "cartesian" if coords[0] == "cartesianX" else "spherical",
        "point_count_in_file": n,
        "dropped_invalid": int(n - valid.sum()),
    }
    return RawCloud(
        points=np.ascontiguousarray(points),
        intensity=intensity,
        name=str(name),
        pose=pose,
        meta=meta,
    )


def _pose_matrix(header) -> np.ndarray:
    """4x4 pose (own coordinates -> common frame) from an E57 header's quaternion + translation."""
    node = header.node["pose"]
    m = np.eye(4)
    if node.isDefined("rotation"):
        rot = node["rotation"]
        w, x, y, z = (float(rot[k].value()) for k in ("w", "x", "y", "z"))
        m[:3, :3] = quaternion_to_matrix(np.array([w, x, y, z]))
    if node.isDefined("translation"):
        tr = node["translation"]
        m[:3, 3] = [float(tr[k].value()) for k in ("x", "y", "z")]
    return m


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` with ``w >= 0`` of a 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def check_rigid(pose: np.ndarray, what: str) -> None:
    """Raise :class:`ScanWriteError` unless ``pose`` is a rigid 4x4 transform (E57 stores no scale);
    the check is :func:`forestreg.engine.core.transform.check_rigid`."""
    from ..core.errors import TransformError
    from ..core.transform import check_rigid as _check

    try:
        _check(pose, what, atol=1e-6)
    except TransformError as exc:
        raise ScanWriteError(f"{exc}; E57 stores only rotation + translation") from exc


def write_e57_file(tmp: Path, entries: list[E57Entry]) -> None:
    """Write scans as data3D entries of a new E57 file at ``tmp`` (existing content is replaced)."""
    import pye57

    e57 = pye57.E57(str(tmp), mode="w")
    try:
        for entry in entries:
            _write_entry(e57, entry)
    finally:
        e57.close()


def _write_entry(e57, entry: E57Entry) -> None:
    from pye57 import libe57

    imf = e57.image_file
    local, shift = entry.local, entry.shift
    n = len(local)
    offset = np.floor(local.min(axis=0) + shift)
    rel = local - (offset - shift)
    raw = np.round(rel / E57_SCALE).astype(np.int64)
    lo, hi = raw.min(axis=0), raw.max(axis=0)

    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
    node.set("name", libe57.StringNode(imf, entry.name))
    node.set("description", libe57.StringNode(imf, WRITTEN_BY))

    pose = libe57.StructureNode(imf)
    rotation = libe57.StructureNode(imf)
    for key, value in zip("wxyz", matrix_to_quaternion(entry.pose[:3, :3])):
        rotation.set(key, libe57.FloatNode(imf, float(value)))
    translation = libe57.StructureNode(imf)
    for key, value in zip("xyz", entry.pose[:3, 3]):
        translation.set(key, libe57.FloatNode(imf, float(value)))
    pose.set("rotation", rotation)
    pose.set("translation", translation)
    node.set("pose", pose)

    bounds = libe57.StructureNode(imf)
    for k, axis in enumerate("xyz"):
        bounds.set(f"{axis}Minimum", libe57.FloatNode(imf, float(offset[k] + lo[k] * E57_SCALE)))
        bounds.set(f"{axis}Maximum", libe57.FloatNode(imf, float(offset[k] + hi[k] * E57_SCALE)))
    node.set("cartesianBounds", bounds)

    prototype = libe57.StructureNode(imf)
    names = []
    for k, axis in enumerate("XYZ"):
        lo_k, hi_k = int(lo[k]) - 1, int(hi[k]) + 1
        prototype.set(f"cartesian{axis}", libe57.ScaledIntegerNode(imf, lo_k, lo_k, hi_k, E57_SCALE, float(offset[k])))
        names.append(f"cartesian{axis}")
    inten = None
    if entry.intensity is not None:
        inten = np.asarray(entry.intensity, dtype=np.float32)
        finite = np.isfinite(inten)
        i_lo = float(inten[finite].min()) if finite.any() else 0.0
        i_hi = float(inten[finite].max()) if finite.any() else 0.0
        inten = np.where(finite, inten, np.float32(i_lo))
        limits = libe57.StructureNode(imf)
        limits.set("intensityMinimum", libe57.FloatNode(imf, i_lo))
        limits.set("intensityMaximum", libe57.FloatNode(imf, i_hi))
        node.set("intensityLimits", limits)
        prototype.set("intensity", libe57.FloatNode(imf, i_lo, libe57.E57_SINGLE, i_lo, i_hi))
        names.append("intensity")

    points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
    node.set("points", points)
    e57.data3d.append(node)

    capacity = min(max(n, 1), _WRITE_CHUNK)
    arrays, buffers = e57.make_buffers(names, capacity)
    writer = points.writer(buffers)
    try:
        for start in range(0, n, capacity):
            stop = min(start + capacity, n)
            m = stop - start
            for k, axis in enumerate("XYZ"):
                # scaled value whose raw integer is exactly raw[:, k]
                arrays[f"cartesian{axis}"][:m] = raw[start:stop, k] * E57_SCALE + offset[k]
            if inten is not None:
                arrays["intensity"][:m] = inten[start:stop]
            writer.write(m)
    finally:
        writer.close()
