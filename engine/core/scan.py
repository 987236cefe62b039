"""The :class:`Scan` type: one set-up of a scanner and its points.

Frames
------
*File coordinates* are the coordinates as they stand in the input file (metres). Georeferenced
clouds (UTM and the like) have coordinates too large for float32 steps, so a scan keeps its points
in a *local frame*: ``file = local + origin_shift``. For a scan in its scanner's own coordinate
system (SOCS) the shift is zero and the local frame is the SOCS.

The scanner position is kept in the local frame; by convention it is the file
origin ``(0, 0, 0)`` unless a position is given (E57 pose, project file, or option).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Union

import numpy as np

from .errors import ScanDataError

#: Coordinates larger than this (m) are shifted to a local origin on reading.
LARGE_COORDINATE_M = 1.0e4
#: A scan whose extent exceeds this (m) is taken to be in the wrong units (mm, cm).
log = logging.getLogger("forestreg")

MAX_EXTENT_M = 5.0e3
#: At most this share of a scan's points may lie more than half MAX_EXTENT_M from its median and
#: be dropped as strays; more, and the cloud as a whole is taken to be in the wrong units.
MAX_STRAY_FRACTION = 0.001
#: The fewest points a scan may have.
MIN_POINTS = 10
#: At most this fraction of non-finite rows is dropped; more is an error.
MAX_NONFINITE_FRACTION = 0.5


@dataclass(frozen=True, eq=False)
class Scan:
    """Points of one scan, float64, in a local frame (``file = points + origin_shift``).

    Build one with :meth:`Scan.from_points`, which validates and shifts; the arrays are read-only.

    Attributes
    ----------
    points : (N, 3) float64 array, metres, local frame.
    scanner_position : (3,) float64 array, metres, local frame.
    origin_shift : (3,) float64 array, metres: add to local coordinates to get file coordinates.
    intensity : optional (N,) float32 array, the file's intensity/reflectance as stored.
    source : the file the scan was read from, if any.
    name : a short human name (the file stem, or the E57 scan name).
    pose : optional 4x4 float64 prior pose mapping file coordinates of this scan into a common
        frame (an E57 pose, a project pose); ``None`` when unknown.
    meta : free-form facts about reading (format, dropped rows, unit scale, ...); ``meta["crs"]``
        the coordinate reference system of the file coordinates when the file declares one
        (:class:`~forestreg.engine.io.crs.Crs`).
    """

    points: np.ndarray
    scanner_position: np.ndarray
    origin_shift: np.ndarray
    intensity: Optional[np.ndarray] = None
    source: Optional[Path] = None
    name: str = ""
    pose: Optional[np.ndarray] = None
    meta: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,
        *,
        scanner_position: Optional[np.ndarray] = None,
        intensity: Optional[np.ndarray] = None,
        source: Optional[Path | str] = None,
        name: Optional[str] = None,
        pose: Optional[np.ndarray] = None,
        origin_shift: Optional[np.ndarray] = None,
        meta: Optional[Mapping[str, Any]] = None,
        take_ownership: bool = False,
    ) -> "Scan":
        """Validate file-coordinate points and build a scan.

        Parameters
        ----------
        points : (N, 3) array of file coordinates, metres. Rows with NaN or infinite values are
            dropped (counted in ``meta["dropped_nonfinite"]``); if more than half are, it fails.
        scanner_position : (3,) scanner position in file coordinates; default the file origin.
        intensity : optional (N,) intensities, row-aligned with ``points``.
        take_ownership : the caller hands ``points`` over (a reader's private float64 array): it is
            shifted in place and kept, instead of copied (saves one copy of the cloud).
        origin_shift : (3,) local-origin shift to use; by default zero for small coordinates and
            a rounded position near the data for georeferenced ones.

        Raises
        ------
        ScanDataError
            Too few points, mostly non-finite values, or an extent that says the units are wrong.
        """
        label = name or (Path(source).name if source is not None else "scan")
        display_name = name or (Path(source).stem if source is not None else "scan")
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanDataError(f"{label}: points must be an (N, 3) array, got shape {pts.shape}")
        n_in = len(pts)
        # a finite total means every value is finite (NaN and +-inf propagate): the row-by-row
        # test only for clouds that hold some
        with np.errstate(invalid="ignore", over="ignore"):  # +inf + -inf: NaN, and no warning
            total = pts.sum()
        finite = np.isfinite(pts).all(axis=1) if not np.isfinite(total) else None
        n_bad = 0 if finite is None else int(n_in - finite.sum())
        if n_in and n_bad > MAX_NONFINITE_FRACTION * n_in:
            raise ScanDataError(
                f"{label}: {n_bad} of {n_in} points have NaN or infinite coordinates; "
                "the file is damaged or was exported without valid coordinates"
            )
        if n_bad:
            pts = pts[finite]
            log.warning(
                "%s: %d of %d points (%.1f %%) have NaN or infinite coordinates and were dropped",
                label,
                n_bad,
                n_in,
                100.0 * n_bad / n_in,
            )
        if len(pts) < MIN_POINTS:
            raise ScanDataError(f"{label}: only {len(pts)} valid points; a scan needs at least {MIN_POINTS}")
        # column by column: a reduction along the long axis is many times faster than min(axis=0)
        lo = np.array([pts[:, k].min() for k in range(3)])
        hi = np.array([pts[:, k].max() for k in range(3)])
        extent = float((hi - lo).max())
        if extent > MAX_EXTENT_M:
            # a few returns far off (a bad range, a ghost at 1e300) are strays, dropped as the
            # non-finite ones are; a cloud that is large as a whole is in another unit
            middle = np.median(pts[:: max(1, len(pts) // 100_000)], axis=0)
            stray = np.abs(pts - middle).max(axis=1) > MAX_EXTENT_M / 2.0
            n_stray = int(stray.sum())
            if 0 < n_stray <= MAX_STRAY_FRACTION * len(pts):
                pts = pts[~stray]
                log.warning(
                    "%s: %d of %d points lie more than %.0f m from the rest and were dropped as strays",
                    label,
                    n_stray,
                    len(pts) + n_stray,
                    MAX_EXTENT_M / 2.0,
                )
                lo = np.array([pts[:, k].min() for k in range(3)])
                hi = np.array([pts[:, k].max() for k in range(3)])
                extent = float((hi - lo).max())
        if extent > MAX_EXTENT_M:
            raise ScanDataError(
                f"{label}: the points span {extent:,.0f} units; a forest scan spans at most a few "
                "hundred metres. The file is probably in millimetres or centimetres: give its unit "
                "(CLI --units mm|cm|ft, API unit_scale=0.001|0.01|0.3048)"
            )
        if extent <= 0.0:
            raise ScanDataError(f"{label}: all points coincide; this is not a scan")

        scanner_file = np.zeros(3) if scanner_position is None else np.asarray(scanner_position, dtype=np.float64)
        if scanner_file.shape != (3,) or not np.isfinite(scanner_file).all():
            raise ScanDataError(f"{label}: scanner position must be three finite numbers, got {scanner_position!r}")
        if origin_shift is None:
            if np.abs(np.concatenate([lo, hi])).max() > LARGE_COORDINATE_M:
                near = scanner_file if scanner_position is not None else (lo + hi) / 2.0
                shift = np.round(near)
            else:
                shift = np.zeros(3)
        else:
            shift = np.asarray(origin_shift, dtype=np.float64).reshape(3)

        inten = None
        if intensity is not None:
            inten = np.asarray(intensity, dtype=np.float32).reshape(-1)
            if len(inten) != n_in:
                raise ScanDataError(f"{label}: {len(inten)} intensities for {n_in} points")
            if n_bad:
                inten = inten[finite]
            inten = _readonly(np.ascontiguousarray(inten))

        pose_arr = None
        if pose is not None:
            pose_arr = np.asarray(pose, dtype=np.float64)
            if pose_arr.shape != (4, 4) or not np.isfinite(pose_arr).all():
                raise ScanDataError(f"{label}: a pose must be a finite 4x4 matrix")
            pose_arr = _readonly(pose_arr.copy())

        info = dict(meta or {})
        info["dropped_nonfinite"] = n_bad
        # where the scanner position came from: given (reader, option, project) or the file origin
        info.setdefault("scanner_position", "given" if scanner_position is not None else "file origin")
        return cls(
            points=_readonly(_shifted(pts, shift, in_place=take_ownership and pts is points)),
            scanner_position=_readonly(scanner_file - shift),
            origin_shift=_readonly(shift.copy()),
            intensity=inten,
            source=Path(source) if source is not None else None,
            name=display_name,
            pose=pose_arr,
            meta=info,
        )

    def __len__(self) -> int:
        return len(self.points)

    @property
    def file_points(self) -> np.ndarray:
        """(N, 3) float64 points in file coordinates (a new array)."""
        return self.points + self.origin_shift

    @property
    def crs(self):
        """The coordinate reference system of the file coordinates
        (:class:`~forestreg.engine.io.crs.Crs`; None: local coordinates, or a moved scan)."""
        return self.meta.get("crs")

    @property
    def scanner_position_file(self) -> np.ndarray:
        """(3,) scanner position in file coordinates."""
        return self.scanner_position + self.origin_shift

    def without_points(self) -> "Scan":
        """The scan's frame, scanner position, name, pose and facts, with no points (for what needs
        to know where a scan is, not its points: a large cloud can then be let go)."""
        empty = np.zeros((0, 3))
        empty.setflags(write=False)
        return dataclasses.replace(self, points=empty, intensity=None)

    def local_to_file_matrix(self) -> np.ndarray:
        """4x4 matrix mapping this scan's local frame to its file coordinates."""
        m = np.eye(4)
        m[:3, 3] = self.origin_shift
        return m

    def subset(self, mask_or_index: np.ndarray) -> "Scan":
        """A scan with a subset of the points (same frame, shift, scanner, pose)."""
        idx = np.asarray(mask_or_index)
        return Scan(
            points=_readonly(np.ascontiguousarray(self.points[idx])),
            scanner_position=self.scanner_position,
            origin_shift=self.origin_shift,
            intensity=None if self.intensity is None else _readonly(np.ascontiguousarray(self.intensity[idx])),
            source=self.source,
            name=self.name,
            pose=self.pose,
            meta=self.meta,
        )

    def transformed(self, matrix: np.ndarray) -> "Scan":
        """This scan moved by a rigid 4x4 ``matrix`` acting on *file* coordinates
        (``p_new = matrix @ p_file``), e.g. a co-registration result; the new origin shift is the
        old one moved and rounded to whole metres, so local coordinates stay small. The moved scan
        has no CRS (``meta["crs"]`` dropped): its coordinates are in another frame."""
        m = np.asarray(matrix, dtype=np.float64)
        rot, t = m[:3, :3], m[:3, 3]
        moved_shift = rot @ self.origin_shift + t
        new_shift = np.round(moved_shift)
        offset = moved_shift - new_shift
        return Scan(
            points=_readonly(np.ascontiguousarray(self.points @ rot.T + offset)),
            scanner_position=rot @ self.scanner_position + offset,
            origin_shift=new_shift,
            intensity=self.intensity,
            source=self.source,
            name=self.name,
            pose=None,
            meta={**{k: v for k, v in self.meta.items() if k != "crs"}, "transformed_by": m.tolist()},
        )

    def __repr__(self) -> str:
        src = f", source={str(self.source)!r}" if self.source else ""
        return f"Scan(name={self.name!r}, points={len(self)}{src})"


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _shifted(points: np.ndarray, shift: np.ndarray, *, in_place: bool) -> np.ndarray:
    """``points - shift`` as a C-contiguous array; in place when allowed (no second copy)."""
    if in_place and points.flags.c_contiguous and points.flags.writeable:
        if shift.any():
            points -= shift
        return points
    return np.ascontiguousarray(points - shift)


#: A scan, or a function without arguments that reads it (called once, where the scan is
#: needed: a registration or co-registration can then let its points go early).
ScanSource = Union[Scan, Callable[[], Scan]]


def check_points(points: Any, what: str = "points", *, min_points: int = 1) -> np.ndarray:
    """``points`` as a float64 (N, 3) array of x, y, z (metres), or :class:`ScanDataError` saying
    what is wrong: not (N, 3), fewer than ``min_points`` points (0: an empty array is fine), or
    points with NaN or infinite coordinates. ``what`` names the points in the message."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ScanDataError(f"{what}: expected an (N, 3) array of x, y, z, got shape {p.shape}")
    if len(p) < min_points:
        raise ScanDataError(
            f"{what} is empty"
            if len(p) == 0 and min_points <= 1
            else f"{what} needs at least {min_points} points, got {len(p)}"
        )
    bad = ~np.isfinite(p).all(axis=1) if not np.isfinite(p.sum()) else None
    if bad is not None and bad.any():
        raise ScanDataError(
            f"{what}: {int(bad.sum())} of {len(p)} points have NaN or infinite coordinates; remove them first"
        )
    return p
