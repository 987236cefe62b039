"""Per-scan preparation for System A: reduce, level, find the ground, extract VOPs.

Frames: a :class:`PreparedScan` holds its points in the *levelled scanner frame* (LSF): metres,
the scanner at the origin, z up, the heading of the scan's own frame kept. ``local_to_lsf`` maps
the scan's local frame (see :class:`~forestreg.engine.core.scan.Scan`) into it.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from ..core.cells import cell_bits, claim_cell
from ..core.jit import kernel
from ..geometry.voxel import VoxelGrid, claim_voxel, voxel_bitmap, voxel_grid
from .ground import GroundGrid, ground_grid, lowest_voxel_ground, scanner_height_above_ground
from .level import estimate_up_direction, levelling_rotation, tilt_deg
from .params import RegistrationParams
from .vop import (
    VisualOcclusionPoints,
    angular_spacing,
    connected_components,
    density_mode,
    outermost_candidates,
    polar,
    shadow_is_empty,
    slice_layer,
    trunk_axis,
)


@dataclass(frozen=True)
class PreparedScan:
    """A scan reduced to ``D_c``, levelled, with its ground (levelled scanner frame, metres;
    ``points`` are float32: within ``D_c`` of the scanner they keep micrometre steps)."""

    points: np.ndarray
    local_to_lsf: np.ndarray
    ground_mask: np.ndarray
    ground: GroundGrid
    scanner_height_m: float
    tilt_deg: float
    levelled: bool
    icp_grid: Optional[VoxelGrid] = None
    """The points' voxel grid at the finest ICP stage's voxel (``icp.voxel_m`` or the last
    correspondence distance / 2.5): made here, where both scans are prepared in parallel."""
    derived: dict = field(default_factory=dict, compare=False, repr=False)
    """What is computed from this scan for registration settings (slice layers, VOPs per radius,
    the ICP reference), kept by :func:`derived` so the links of a plot compute each once."""

    @property
    def nbytes(self) -> int:
        """Bytes held by the points, ground mask and ICP grid (for caches with a memory budget)."""
        grid = (
            0
            if self.icp_grid is None
            else self.icp_grid.centroids.nbytes + self.icp_grid.order.nbytes + self.icp_grid.starts.nbytes
        )
        return int(self.points.nbytes + self.ground_mask.nbytes + grid)


def derived(prepared: PreparedScan, key: tuple, make):
    """``make()`` computed once per ``key`` for a prepared scan (``key`` holds everything the
    result depends on besides the scan, e.g. the registration parameters and a VOP radius)."""
    memo = prepared.derived
    if key not in memo:
        memo[key] = make()
    return memo[key]


def scan_identity(scan) -> tuple:
    """What tells a scan's points apart from another's, for caches: name, scanner position (local
    frame, metres, to the nanometre), point count, and the first and last point."""
    pts = scan.points
    return (
        scan.name,
        tuple(np.round(np.asarray(scan.scanner_position, dtype=float), 9)),
        len(pts),
        tuple(pts[0]) if len(pts) else (),
        tuple(pts[-1]) if len(pts) else (),
    )


class PreparedScans:
    """Prepared scans kept between the links of a plot, most recently used first, up to
    ``max_bytes`` (default :data:`PREPARED_CACHE_BYTES`): a scan in three links is reduced,
    levelled, grounded, gridded and sliced once, and its VOPs found once per radius. Thread-safe;
    a scan over the budget is still prepared, used and let go.

    Scans are told apart by name, scanner position, point count and the first and last point, and
    preparations by every registration parameter and the vertical given.
    """

    def __init__(self, max_bytes: Optional[int] = None) -> None:
        import threading
        from collections import OrderedDict

        self.max_bytes = PREPARED_CACHE_BYTES if max_bytes is None else int(max_bytes)
        self._prepared: "OrderedDict[tuple, PreparedScan]" = OrderedDict()
        self._lock = threading.Lock()
        #: stand-ins (scans without points) -> (key, scan identity, their preparation)
        self._pinned: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
        #: what let-go preparations leave behind: key -> (local_to_lsf, their derived results)
        self._outlines: dict[tuple, tuple[np.ndarray, dict]] = {}
        #: how many preparations were made (a scan let go and needed again is prepared again)
        self.made = 0

    def _let_go(self) -> None:
        """Drop the least recently used kept preparation (the lock is held), keeping its outline:
        the LSF matrix, slice layers and VOPs (a few MB even at 30 M points), which a plot's
        report draws without preparing the scan again."""
        key, prepared = self._prepared.popitem(last=False)
        # the derived dict itself: a link still running on this preparation (a stand-in) may add
        # its layers and VOPs after it was let go; what else lands there is let go by release()
        self._outlines[key] = (prepared.local_to_lsf, prepared.derived)

    def outline(
        self, identity: tuple, params: RegistrationParams, up: Optional[np.ndarray] = None
    ) -> Optional[tuple[np.ndarray, dict]]:
        """``(local_to_lsf, {derived key: value})`` of the scan of ``identity`` for ``params``:
        its kept preparation's matrix, slice layers and VOPs (keys as for :func:`derived`), or
        what it left when it was let go; None when it was never prepared for ``params``."""
        key = self._key(identity, params, up)
        with self._lock:
            found = (
                (self._prepared[key].local_to_lsf, self._prepared[key].derived)
                if key in self._prepared
                else self._outlines.get(key)
            )
            if found is None:
                return None
            return found[0], {k: v for k, v in list(found[1].items()) if k and k[0] in ("layers", "vops")}

    @staticmethod
    def _key(identity: tuple, params: RegistrationParams, up: Optional[np.ndarray]) -> tuple:
        return (identity, params, None if up is None else tuple(np.asarray(up, dtype=float)))

    def kept(
        self, identity: tuple, params: RegistrationParams, up: Optional[np.ndarray] = None
    ) -> Optional[PreparedScan]:
        """The kept preparation of the scan of ``identity`` (:func:`scan_identity`) for ``params``,
        or None (marked as just used when found)."""
        key = self._key(identity, params, up)
        with self._lock:
            if key in self._prepared:
                self._prepared.move_to_end(key)
                return self._prepared[key]
        return None

    def stand_in(
        self,
        frame,
        identity: tuple,
        prepared: PreparedScan,
        params: RegistrationParams,
        up: Optional[np.ndarray] = None,
    ):
        """A stand-in for a scan whose preparation for ``params`` is ``prepared``: ``frame`` (the
        scan without its points, :meth:`~forestreg.engine.core.scan.Scan.without_points`) copied,
        which :meth:`get` answers with ``prepared`` for as long as the stand-in lives, so a link
        can run without the scan's points in memory. ``identity`` is the scan's
        :func:`scan_identity` (taken while its points were there)."""
        import dataclasses

        light = dataclasses.replace(frame)
        with self._lock:
            self._pinned[light] = (self._key(identity, params, up), identity, prepared)
        return light

    def get(self, scan, params: RegistrationParams, up: Optional[np.ndarray] = None) -> PreparedScan:
        """The prepared ``scan`` (a :class:`~forestreg.engine.core.scan.Scan`, or a stand-in from
        :meth:`stand_in`) for ``params``."""
        with self._lock:
            pinned = self._pinned.get(scan)
        key = self._key(scan_identity(scan) if pinned is None else pinned[1], params, up)
        if pinned is not None and pinned[0] == key:
            return pinned[2]
        pts = scan.points
        with self._lock:
            if key in self._prepared:
                self._prepared.move_to_end(key)
                return self._prepared[key]
            if pinned is not None:
                raise ValueError(f"{scan.name}: a stand-in without points cannot be prepared for other parameters")
            # room first: a scan being prepared should not sit beside one that is about to be dropped
            incoming = len(pts) * PREPARED_BYTES_PER_POINT
            while self._prepared and sum(p.nbytes for p in self._prepared.values()) + incoming > self.max_bytes:
                self._let_go()
        prepared = prepare_scan(pts, scan.scanner_position, params, up=up)
        with self._lock:
            self.made += 1
            self._prepared[key] = prepared
            while len(self._prepared) > 1 and sum(p.nbytes for p in self._prepared.values()) > self.max_bytes:
                self._let_go()
        return prepared

    def clear(self) -> None:
        """Let go of every kept preparation (stand-ins still alive keep theirs; outlines stay)."""
        with self._lock:
            while self._prepared:
                self._let_go()

    def release(self, key: tuple) -> None:
        """Let go of what was derived under ``key`` from every kept scan (e.g. the ICP trees of
        a link's reference, large and cheap to build again)."""
        with self._lock:
            for prepared in self._prepared.values():
                prepared.derived.pop(key, None)
            for _, found in self._outlines.values():
                found.pop(key, None)


#: Bytes of prepared scans a :class:`PreparedScans` keeps by default (a 3 M-point scan holds
#: about 60 MB prepared; two 30 M-point scans fit).
PREPARED_CACHE_BYTES = 1_500_000_000
#: Bytes a scan takes prepared, per point given, at most (float32 points, the ground mask, the
#: ICP grid's member order and a share of its voxels): what :meth:`PreparedScans.get` makes room for.
PREPARED_BYTES_PER_POINT = 20


def reduce_to_range(points: np.ndarray, scanner_xy: np.ndarray, max_range_m: float) -> np.ndarray:
    """Mask of the points within ``max_range_m`` horizontally of the scanner (paper eq. 1): one
    compiled pass, the squared distances in float64 (no temporaries)."""
    mask = np.empty(len(points), dtype=bool)
    xy = np.asarray(scanner_xy, dtype=np.float64)
    _range_mask(np.asarray(points), float(xy[0]), float(xy[1]), float(max_range_m) ** 2, mask)
    return mask


@kernel
def _range_mask(points, sx, sy, r2, mask):  # pragma: no cover - compiled
    for i in range(points.shape[0]):
        dx = np.float64(points[i, 0]) - sx
        dy = np.float64(points[i, 1]) - sy
        mask[i] = dx * dx + dy * dy <= r2


def prepare_scan(
    points_local: np.ndarray,
    scanner_local: np.ndarray,
    params: RegistrationParams,
    *,
    up: Optional[np.ndarray] = None,
) -> PreparedScan:
    """Reduce, level and ground one scan (:func:`centre_scan`, then :func:`prepare_centred`).

    Parameters
    ----------
    points_local : (N, 3) points in the scan's local frame, metres.
    scanner_local : (3,) scanner position in that frame.
    up : optional known vertical direction in the scan's frame (from an inclination sensor); by
        default estimated from the data when ``params.level_tilted``.
    """
    return prepare_centred(centre_scan(points_local, scanner_local, params, up=up), scanner_local, params, up=up)


@dataclass(frozen=True)
class CentredScan:
    """The first step of a preparation: the points within ``1.6 D_c`` (3D) of the scanner,
    scanner-centred, float32 (the scan's axes, metres), thinned to the first point of each pixel
    of :func:`thinning_pixels` (angular pixels seen from the scanner), and the
    :func:`~.level.level_sample` of those within ``level_radius_m``, that estimates the vertical (None when it is
    not estimated). Once made, the scan's own points are no longer needed (a caller holding them in
    the only reference can let them go before the rest)."""

    points: np.ndarray
    near: Optional[np.ndarray]


def centre_scan(
    points_local: np.ndarray, scanner_local: np.ndarray, params: RegistrationParams, *, up: Optional[np.ndarray] = None
) -> CentredScan:
    """The :class:`CentredScan` of a scan's points (local frame, metres) around its scanner
    position (the same frame); ``up`` as for :func:`prepare_scan` (given: no points kept to
    estimate it)."""
    reach = params.max_range_m
    estimate = up is None and params.level_tilted
    # generous before levelling; the vertical is estimated from a sample of the points within
    # level_radius_m (one a level_voxel_m voxel)
    centred, near = _centred_float32(
        points_local,
        scanner_local,
        (reach * 1.6) ** 2,
        params.level_radius_m**2 if estimate else None,
        thinning=thinning_pixels(params),
        level_voxel_m=params.level_voxel_m,
    )
    return CentredScan(centred, near)


#: The smallest pixel a scan is thinned to, metres across (at the inner edge of its shell; see
#: :func:`thinning_pixels`): finer than every later step's scale (the 5 cm component and ICP
#: voxels, the 0.1 m angular-grid distance step and mean-shift bandwidth, the 0.5 m ground voxels).
THINNING_FLOOR_M = 0.02
#: Points closer to the scanner than this are all kept (metres).
THINNING_NEAR_M = 0.25
#: Ratio of a thinning shell's outer radius to its inner one.
THINNING_SHELL_RATIO = 1.25


@dataclass(frozen=True)
class ThinningPixels:
    """Angular pixels (as seen from the scanner) a scan is thinned to, the first point of each
    kept. Shell ``k`` holds the points at ranges ``near_m * ratio**k`` up to ``ratio`` times that
    (the last shell: every range beyond) and is cut into ``columns[k]`` azimuth x ``rows[k]``
    elevation pixels of ``step_rad[k]``; its bits start at ``offset[k]`` of a bitmap of ``bits``."""

    step_rad: np.ndarray
    columns: np.ndarray
    rows: np.ndarray
    offset: np.ndarray
    near_m: float
    ratio: float

    @property
    def bits(self) -> int:
        return int(self.offset[-1] + self.columns[-1] * self.rows[-1])


def thinning_pixels(params: RegistrationParams, floor_m: float = THINNING_FLOOR_M) -> ThinningPixels:
    """The pixels a scan is thinned to before it is prepared: half the angular grid's step ``I_A``
    (0.05 deg by default) where that spans at least ``floor_m`` (beyond 23 m with the defaults),
    and nearer the scanner pixels ``floor_m`` across at the inner edge of their shell (ranges in
    steps of :data:`THINNING_SHELL_RATIO`). Every later step works at this resolution or coarser;
    a scan made at ``I_A`` keeps every point beyond about 15 m and about one point per 2 cm nearer,
    and a finer or densified file of the same scene about as many, so its preparation, VOPs and ICP cost
    what a scan at ``I_A`` costs, whatever the file holds."""
    finest = np.radians(params.angular_step_deg / 2.0)
    far_m = floor_m / finest
    shells = max(0, int(np.ceil(np.log(far_m / THINNING_NEAR_M) / np.log(THINNING_SHELL_RATIO))))
    inner = THINNING_NEAR_M * THINNING_SHELL_RATIO ** np.arange(shells + 1)
    step = np.maximum(floor_m / inner, finest)
    step[-1] = finest
    columns = np.ceil(2.0 * np.pi / step).astype(np.int64)
    rows = np.ceil(np.pi / step).astype(np.int64) + 1
    offset = np.concatenate([[0], np.cumsum(columns * rows)[:-1]]).astype(np.int64)
    return ThinningPixels(step, columns, rows, offset, THINNING_NEAR_M, THINNING_SHELL_RATIO)


def prepare_centred(
    centred_scan: CentredScan,
    scanner_local: np.ndarray,
    params: RegistrationParams,
    *,
    up: Optional[np.ndarray] = None,
    with_icp_grid: bool = True,
) -> PreparedScan:
    """Level, reduce to ``D_c`` and ground a :class:`CentredScan` (made with the same ``up``)
    whose scanner lies at ``scanner_local`` (the scan's local frame, metres). With
    ``with_icp_grid=False`` its ``icp_grid`` is left None, for the caller to make
    (``voxel_grid(prepared.points, icp_grid_voxel(params))``) beside other work."""
    reach = params.max_range_m
    centred, near = centred_scan.points, centred_scan.near
    del centred_scan
    if near is not None:
        estimate = estimate_up_direction(near, sampled=True)
        del near
        tilt = tilt_deg(estimate.up)
        levelled = tilt >= params.tilt_threshold_deg
        up = estimate.up if levelled else np.array([0.0, 0.0, 1.0])
        if not levelled:
            tilt = 0.0
    else:
        up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
        tilt = tilt_deg(up)
        levelled = tilt > 0.0
    rotation = levelling_rotation(up)
    if levelled:
        centred = centred @ rotation.T.astype(np.float32)
    lsf = centred[reduce_to_range(centred, np.zeros(2), reach)]
    del centred
    local_to_lsf = np.eye(4)
    local_to_lsf[:3, :3] = rotation
    local_to_lsf[:3, 3] = -rotation @ scanner_local
    ground_mask = lowest_voxel_ground(lsf, params.ground_voxel_m)
    grid = ground_grid(lsf[ground_mask], cell_m=params.ground_voxel_m)
    height = scanner_height_above_ground(grid, np.zeros(3))
    return PreparedScan(
        icp_grid=voxel_grid(lsf, icp_grid_voxel(params)) if with_icp_grid else None,
        points=lsf,
        local_to_lsf=local_to_lsf,
        ground_mask=ground_mask,
        ground=grid,
        scanner_height_m=height,
        tilt_deg=tilt,
        levelled=levelled,
    )


def icp_grid_voxel(params: RegistrationParams) -> float:
    """The voxel (metres) of a prepared scan's ICP grid: the finest ICP stage's, ``icp.voxel_m``
    or the last correspondence distance / 2.5 (:func:`~forestreg.engine.geometry.icp.icp`)."""
    return params.icp.finest_voxel_m


def _centred_float32(
    points: np.ndarray,
    origin: np.ndarray,
    max_d2: float,
    near_d2: Optional[float] = None,
    *,
    thinning: Optional[ThinningPixels] = None,
    level_voxel_m: float = RegistrationParams.level_voxel_m,
) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """The points within ``sqrt(max_d2)`` (3D) of ``origin``, shifted so that ``origin`` is 0, as
    float32 (a 50 m neighbourhood keeps micrometre steps), with ``thinning`` only the first of
    each of its pixels (seen from ``origin``), and, with ``near_d2``, the
    :func:`~.level.level_sample` of those within ``sqrt(near_d2)`` (the first of each
    ``level_voxel_m`` voxel; else None); both in the points' order. One compiled pass
    writes the kept points into the results: no float64 copy of the cloud, no distances or masks
    (the results may be views of buffers sized for every point, of which only the rows written
    are ever touched)."""
    origin = np.asarray(origin, dtype=np.float64)
    out = np.empty((len(points), 3), dtype=np.float32)
    near = np.empty((len(points) if near_d2 is not None else 0, 3), dtype=np.float32)
    radius = float(np.sqrt(near_d2)) if near_d2 is not None else 0.0
    occupied = voxel_bitmap(level_voxel_m, radius) if near_d2 is not None else np.zeros(0, dtype=np.uint64)
    t = thinning
    if t is None:
        step, columns, rows, offset, near_m, log_ratio = (
            np.zeros(0),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            0.0,
            1.0,
        )
    else:
        step, columns, rows, offset, near_m, log_ratio = (
            t.step_rad,
            t.columns,
            t.rows,
            t.offset,
            t.near_m,
            float(np.log(t.ratio)),
        )
    pixels = cell_bits(0 if t is None else t.bits)
    # the limits as float32, as numpy compares a float32 array with a Python float
    kept, close = _centre_rows(
        np.asarray(points),
        origin,
        np.float32(max_d2),
        np.float32(-1.0 if near_d2 is None else near_d2),
        level_voxel_m,
        int(np.ceil(radius / level_voxel_m)),
        occupied,
        step,
        columns,
        rows,
        offset,
        near_m,
        log_ratio,
        pixels,
        out,
        near,
    )
    return out[:kept], (near[:close].copy() if near_d2 is not None else None)


@kernel
def _centre_rows(
    points,
    origin,
    max_d2,
    near_d2,
    voxel_m,
    half,
    occupied,
    step,
    columns,
    rows,
    offset,
    near_m,
    log_ratio,
    pixels,
    out,
    near,
):  # pragma: no cover - compiled
    """:func:`_centred_float32` in one pass: each coordinate minus the origin in float64, then
    float32; the squared distance summed in float32 (x, then y, then z); with thinning pixels
    (``step`` not empty: :class:`ThinningPixels`' arrays, one bit a pixel in ``pixels``) a kept
    row beyond ``near_m`` must also be the first of its pixel (:func:`~..core.cells.claim_cell`);
    kept rows packed in order, those within ``near_d2`` (negative: none) that claim their voxel
    (``voxel_m``, the bitmap ``occupied``, ``half`` cells a side:
    :func:`~..geometry.voxel.claim_voxel`) into ``near``."""
    kept = 0
    close = 0
    last = step.shape[0] - 1
    for i in range(points.shape[0]):
        x = np.float32(np.float64(points[i, 0]) - origin[0])
        y = np.float32(np.float64(points[i, 1]) - origin[1])
        z = np.float32(np.float64(points[i, 2]) - origin[2])
        d2 = x * x
        d2 += y * y
        d2 += z * z
        if d2 <= max_d2:
            if last >= 0:
                xf, yf, zf = np.float64(x), np.float64(y), np.float64(z)
                r = np.sqrt(xf * xf + yf * yf + zf * zf)
                if r >= near_m:
                    k = min(np.int64(np.log(r / near_m) / log_ratio), last)
                    s = step[k]
                    col = min(max(np.int64((np.arctan2(yf, xf) + np.pi) / s), 0), columns[k] - 1)
                    row = min(
                        max(np.int64((np.arctan2(zf, np.sqrt(xf * xf + yf * yf)) + 0.5 * np.pi) / s), 0), rows[k] - 1
                    )
                    if not claim_cell(offset[k] + row * columns[k] + col, pixels):
                        continue
            out[kept, 0] = x
            out[kept, 1] = y
            out[kept, 2] = z
            kept += 1
            if d2 <= near_d2 and claim_voxel(x, y, z, voxel_m, half, occupied):
                near[close, 0] = x
                near[close, 1] = y
                near[close, 2] = z
                close += 1
    return kept, close


@dataclass(frozen=True)
class SliceLayer:
    """The points of one slice layer (levelled scanner frame), sorted by azimuth."""

    xyz: np.ndarray
    azimuth: np.ndarray
    distance: np.ndarray
    offset_m: float


def slice_layers(prepared: PreparedScan, params: RegistrationParams) -> list[SliceLayer]:
    """The slice layers of a prepared scan, one per ``slice_offsets_m`` (non-ground points only)."""
    z = prepared.points[:, 2]
    half = params.slice_thickness_m / 2.0
    offsets = np.asarray(params.slice_offsets_m, dtype=np.float64)
    if params.follow_terrain:  # the layers lie between these heights wherever the ground is
        low = float(prepared.ground.heights.min()) + prepared.scanner_height_m + offsets.min() - half
        high = float(prepared.ground.heights.max()) + prepared.scanner_height_m + offsets.max() + half
    else:
        low, high = offsets.min() - half, offsets.max() + half
    pts = prepared.points[~prepared.ground_mask & (z >= low - 1e-3) & (z <= high + 1e-3)]
    layers = []
    for offset in params.slice_offsets_m:
        if params.follow_terrain:
            mask = slice_layer(
                pts,
                prepared.ground,
                centre_height_m=prepared.scanner_height_m + offset,
                thickness_m=params.slice_thickness_m,
            )
        else:
            mask = slice_layer(pts, None, centre_height_m=offset, thickness_m=params.slice_thickness_m)
        xyz = pts[mask]
        az, dist = polar(xyz[:, :2])
        order = np.argsort(az, kind="stable")
        layers.append(SliceLayer(xyz=xyz[order], azimuth=az[order], distance=dist[order], offset_m=float(offset)))
    return layers


def extract_vops(layers: Sequence[SliceLayer], params: RegistrationParams, radius_m: float) -> VisualOcclusionPoints:
    """VOPs of a scan from its slice layers within ``radius_m`` (``D_r``), layers merged keeping
    the lowest layer's VOP where several layers see the same trunk."""
    found: list[VisualOcclusionPoints] = []
    for index, layer in enumerate(layers):
        found.append(_layer_vops(layer, params, radius_m, index))
    return _merge_layers(found, [layer.offset_m for layer in layers], params.ground_voxel_m)


def _layer_vops(
    layer: SliceLayer, params: RegistrationParams, radius_m: float, layer_index: int
) -> VisualOcclusionPoints:
    cand = outermost_candidates(
        layer.azimuth,
        layer.distance,
        angular_step_deg=params.angular_step_deg,
        radial_step_m=params.radial_step_m,
        radius_m=radius_m,
    )
    if len(cand) < params.min_component_points:
        return VisualOcclusionPoints.empty()
    pts = layer.xyz[cand]
    spacing = angular_spacing(layer.xyz[layer.distance <= radius_m])
    labels = connected_components(pts, link_m=params.component_voxel_m, spacing_rad=spacing)
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    xy, z, bark, radius, support, rejected = [], [], [], [], [], []
    min_height = params.min_component_height_fraction * params.slice_thickness_m
    for members in np.split(order, bounds):
        if len(members) < params.min_component_points:
            continue
        comp = pts[members]
        if np.ptp(comp[:, 2]) < min_height:
            continue
        if max(np.ptp(comp[:, 0]), np.ptp(comp[:, 1])) > params.max_component_width_m:
            continue
        mode = density_mode(comp[:, :2], bandwidth_m=params.mean_shift_bandwidth_m)
        if not shadow_is_empty(
            mode,
            layer.azimuth,
            layer.xyz[:, :2],
            gap_m=params.visibility_gap_m,
            width_m=params.radial_step_m,
            max_range_m=params.max_range_m,
        ):
            rejected.append(mode)
            continue
        if params.centre_on_trunk_axis:
            axis, r = trunk_axis(comp[:, :2], mode)
        else:
            axis, r = mode, 0.0
        xy.append(axis)
        z.append(float(np.median(comp[:, 2])))
        bark.append(mode)
        radius.append(r)
        support.append(len(members))
    if not xy:
        empty = VisualOcclusionPoints.empty()
        return VisualOcclusionPoints(
            empty.xy,
            empty.z,
            empty.bark_xy,
            empty.radius,
            empty.support,
            empty.layer,
            np.array(rejected).reshape(-1, 2),
        )
    n = len(xy)
    return VisualOcclusionPoints(
        xy=np.array(xy),
        z=np.array(z),
        bark_xy=np.array(bark),
        radius=np.array(radius),
        support=np.array(support, dtype=np.int64),
        layer=np.full(n, layer_index, dtype=np.int64),
        rejected_xy=np.array(rejected).reshape(-1, 2),
    )


def _merge_layers(
    per_layer: Sequence[VisualOcclusionPoints], offsets_m: Sequence[float], merge_distance_m: float
) -> VisualOcclusionPoints:
    """Combine the layers' VOPs; a VOP within ``merge_distance_m`` of one from a lower layer (or an
    earlier VOP of the same layer) is the same trunk and dropped (paper: keep the bottom-most)."""
    if len(per_layer) == 1:
        return per_layer[0]
    kept: list[int] = []
    allv = VisualOcclusionPoints(
        xy=np.concatenate([v.xy for v in per_layer]),
        z=np.concatenate([v.z for v in per_layer]),
        bark_xy=np.concatenate([v.bark_xy for v in per_layer]),
        radius=np.concatenate([v.radius for v in per_layer]),
        support=np.concatenate([v.support for v in per_layer]),
        layer=np.concatenate([v.layer for v in per_layer]),
        rejected_xy=np.concatenate([v.rejected_xy for v in per_layer]),
    )
    if len(allv) == 0:
        return allv
    order = np.argsort(np.asarray(offsets_m)[allv.layer], kind="stable")
    for idx in order:
        if kept:
            d = np.hypot(*(allv.xy[kept] - allv.xy[idx]).T)
            if d.min() < merge_distance_m:
                continue
        kept.append(int(idx))
    sel = np.array(sorted(kept))
    return VisualOcclusionPoints(
        xy=allv.xy[sel],
        z=allv.z[sel],
        bark_xy=allv.bark_xy[sel],
        radius=allv.radius[sel],
        support=allv.support[sel],
        layer=allv.layer[sel],
        rejected_xy=allv.rejected_xy,
    )
