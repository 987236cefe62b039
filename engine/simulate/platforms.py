"""UAV LiDAR and backpack laser scanner simulators: the test bed of ground/UAV co-registration.

Both platforms carry a spinning multi-beam sensor like the Velodyne VLP-16 of the paper (table 2):
16 channels from -15 to +15 deg out of the rotation plane, one firing of all channels every
``azimuth_step_deg`` of rotation, ``rotation_hz`` turns a second (about 288 000 pulses a second at
0.2 deg and 10 Hz). The rays are cast at the scene's meshes (:func:`~.mesh.raycaster_for`), one
origin per group of rays (a rotation, or a sector of one): within a group the platform moves by a
few centimetres, which only shifts *where* the pulses sample, never *where* the points are. Every
point is ``origin + direction * (range + noise)`` in the scene ("world") frame exactly: there is no
GNSS/IMU/SLAM trajectory error.

* :func:`simulate_uav_scan` flies serpentine lines (:func:`uav_flight_lines`) at ``altitude_m``
  above the ground at the plot centre, the sensor's rotation axis along the flight direction so
  that it sweeps across track; returns within ``swath_half_angle_deg`` of nadir (in the sweep) are
  kept. The point density over the plot is about
  ``pulses in the swath per second / (line spacing * speed)`` (:attr:`UavSetup.nominal_density_per_m2`),
  288 points/m2 with the defaults, the paper's 250-300 (table 1). Few points reach the ground under
  the crowns because the foliage meshes stop most rays.
* :func:`simulate_backpack_scan` walks a path at ``speed_m_s`` with the sensor ``height_m`` above
  the ground, its rotation axis tilted ``tilt_deg`` back from vertical; the path (a serpentine by
  default, or the user's waypoints) goes around stems, reflector poles and buildings.
* :func:`simulate_coregistration_case` simulates one plot seen from the air and from the ground
  (backpack or merged TLS scans over a central sub-area), the ground data in their own frame under a
  known misalignment: ``p_uav = matrix @ p_ground`` exactly.

Frames: the scene frame (plot centred on the origin, x east, y north, z up, metres); headings are
mathematical azimuths in degrees (counter-clockwise from +x).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import ParameterError, ScanDataError
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..core.scan import Scan
from ..core.transform import apply as apply_transform
from ..core.transform import fit_rigid
from .mesh import Material, SceneRaycaster, raycaster_for
from .plot import simulate_plot
from .scanner import intensity_model
from .scene import ForestScene, given_or_made_scene

ProgressCallback = Callable[[float, str], None]

#: The most rays handed to the ray caster in one call.
MAX_RAYS_PER_CAST = 2_000_000


# --------------------------------------------------------------------------------------------
# setups
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpinningSensor(Params):
    """The spinning multi-channel laser both platforms carry (defaults: a Velodyne VLP-16, paper
    table 2): the channels fire together every ``azimuth_step_deg`` of rotation."""

    rotation_hz: float = _p(10.0, "Hz", 1.0, 50.0, "Sensor rotations per second", "5-20 Hz")
    azimuth_step_deg: float = _p(0.2, "deg", 0.05, 5.0, "Rotation between two firings of the channels", "0.1-0.4 deg")
    n_channels: int = _p(16, "", 1, 128, "Laser channels, spread evenly over the vertical field of view", "VLP-16")
    vertical_fov_deg: float = _p(
        30.0, "deg", 0.0, 90.0, "Spread of the channels out of the rotation plane (along track on a UAV)", "30 deg"
    )

    @property
    def channel_elevations_deg(self) -> np.ndarray:
        """Elevations (deg) of the channels, spread evenly over the field of view (VLP-16: -15..15 by 2)."""
        if self.n_channels == 1:
            return np.zeros(1)
        return np.linspace(-self.vertical_fov_deg / 2.0, self.vertical_fov_deg / 2.0, int(self.n_channels))


@dataclass(frozen=True)
class UavSetup(SpinningSensor):
    """A UAV LiDAR flight (paper section 3.2.2 and table 2: VLP-16 at 86 m).

    The flight lines run along ``heading_deg`` (alternating direction, serpentine), ``line_spacing_m``
    apart, across the plot plus ``margin_m`` on either side, each long enough for the forward and
    backward looking channels to cover the plot.
    """

    altitude_m: float = _p(86.0, "m", 10.0, 500.0, "Flight height above the ground at the plot centre", "86 m")
    speed_m_s: float = _p(5.0, "m/s", 0.5, 30.0, "Ground speed along the flight lines", "3.6 m/s")
    line_spacing_m: float = _p(50.0, "m", 2.0, 1000.0, "Distance between neighbouring flight lines")
    heading_deg: float = _p(0.0, "deg", -360.0, 360.0, "Direction of the first flight line (counter-clockwise from +x)")
    line_offset_m: float = _p(
        0.0, "m", -1000.0, 1000.0, "Across-track shift of the line pattern (0: a line passes over the plot centre)"
    )
    margin_m: Optional[float] = _p(
        None,
        "m",
        0.0,
        2000.0,
        "Lines are flown over the plot plus this margin on either side; empty = the half swath at the ground, so every line that can see the plot is flown",
    )
    swath_half_angle_deg: float = _p(45.0, "deg", 1.0, 89.0, "Returns are kept within this angle of nadir in the sweep")
    max_range_m: float = _p(100.0, "m", 1.0, 2000.0, "Farthest return", "100 m")
    range_noise_m: float = _p(0.03, "m", 0.0, 1.0, "Standard deviation of the range noise", "+-3 cm")
    density_scale: float = _p(
        1.0, "", 1e-4, 4.0, "Fraction of the sensor's pulses fired (scales the point density; 1 = the real sensor)"
    )

    @property
    def pulses_per_second(self) -> float:
        """Rays fired per second within the swath."""
        return (
            self.n_channels
            * self.rotation_hz
            * 2.0
            * self.swath_half_angle_deg
            / self.azimuth_step_deg
            * self.density_scale
        )

    @property
    def nominal_density_per_m2(self) -> float:
        """Rays per m2 of a plot fully inside the flown block: pulses in the swath per second over
        the area the block advances per second (line spacing times speed)."""
        return self.pulses_per_second / (self.line_spacing_m * self.speed_m_s)


@dataclass(frozen=True)
class BackpackSetup(SpinningSensor):
    """A walk with a backpack (or handheld) laser scanner (paper section 3.2.3 and table 2).

    The path is ``waypoints`` (scene-frame (x, y) pairs) when given, otherwise a serpentine over a
    square of side ``extent_m`` centred on ``centre``: lines along x, ``line_spacing_m`` apart.
    Positions closer than ``clearance_m`` to a stem, a target pole or a building are pushed out.
    Each rotation is cast in ``sectors_per_rotation`` groups, each from the sensor's position at
    the middle of the sector.
    """

    height_m: float = _p(1.8, "m", 0.2, 5.0, "Sensor height above the ground")
    speed_m_s: float = _p(1.2, "m/s", 0.1, 5.0, "Walking speed")
    tilt_deg: float = _p(45.0, "deg", 0.0, 90.0, "Tilt of the rotation axis back from vertical")
    min_range_m: float = _p(0.5, "m", 0.0, 10.0, "Nearer returns are dropped (the operator and the backpack)")
    max_range_m: float = _p(
        30.0, "m", 1.0, 200.0, "Farthest return (a walking scanner's useful range)", "15-20 m (HLS)"
    )
    range_noise_m: float = _p(0.025, "m", 0.0, 1.0, "Standard deviation of the range noise", "+-(2-3) cm")
    density_scale: float = _p(
        0.25,
        "",
        1e-4,
        4.0,
        "Fraction of the sensor's pulses fired; the default gives about the paper's 5-10 thousand points/m2 in the walked area, 1 = the real sensor",
    )
    waypoints: Optional[tuple[tuple[float, float], ...]] = _p(
        None, "m", None, None, "Path as (x, y) pairs in the scene frame; empty = a serpentine"
    )
    extent_m: Optional[float] = _p(
        None,
        "m",
        1.0,
        1000.0,
        "Side of the square walked in a serpentine; empty = the plot less edge_margin_m on each side",
    )
    centre: tuple[float, float] = _p((0.0, 0.0), "m", None, None, "Centre of the serpentine")
    line_spacing_m: float = _p(6.0, "m", 0.5, 100.0, "Distance between the serpentine's lines")
    edge_margin_m: float = _p(2.0, "m", 0.0, 100.0, "Default serpentine: distance kept from the plot edge")
    clearance_m: float = _p(
        0.5, "m", 0.0, 5.0, "Least distance between the sensor path and a stem surface, target pole or building"
    )
    sectors_per_rotation: int = _p(4, "", 1, 64, "Ray groups per rotation, each cast from its own position")
    slam_tilt_deg: float = _p(
        0.0,
        "deg",
        0.0,
        20.0,
        "SLAM map error: constant tilt of the whole map (about a horizontal axis through the walk's start)",
        "real MLS: ~1-2 deg",
    )
    slam_tilt_azimuth_deg: float = _p(
        30.0, "deg", -360.0, 360.0, "Direction (mathematical azimuth) in which the map tilts down"
    )
    slam_drift_deg: float = _p(
        0.0, "deg", 0.0, 20.0, "SLAM map error: rotation drift accumulated linearly over the walk (its heading part)"
    )
    slam_drift_tilt_deg: float = _p(
        0.0, "deg", 0.0, 20.0, "SLAM map error: tilt drift accumulated linearly over the walk (about the x axis)"
    )
    slam_drift_m: tuple[float, float, float] = _p(
        (0.0, 0.0, 0.0), "m", None, None, "SLAM map error: position drift (x, y, z) accumulated linearly over the walk"
    )

    def _check(self) -> None:
        drift = tuple(float(v) for v in self.slam_drift_m)
        if len(drift) != 3 or not all(math.isfinite(v) and abs(v) <= 50.0 for v in drift):
            raise ParameterError(f"slam_drift_m must be three finite numbers within 50 m, got {self.slam_drift_m!r}")
        object.__setattr__(self, "slam_drift_m", drift)
        if self.waypoints is not None:
            wp = np.asarray(self.waypoints, dtype=np.float64)
            if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 2 or not np.isfinite(wp).all():
                raise ParameterError("waypoints must be at least two finite (x, y) pairs")
            object.__setattr__(self, "waypoints", tuple((float(x), float(y)) for x, y in wp))
        c = tuple(float(v) for v in self.centre)
        if len(c) != 2 or not all(math.isfinite(v) for v in c):
            raise ParameterError(f"centre must be an (x, y) pair, got {self.centre!r}")
        object.__setattr__(self, "centre", c)
        if self.min_range_m >= self.max_range_m:
            raise ParameterError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")

    @property
    def pulses_per_second(self) -> float:
        return self.n_channels * self.rotation_hz * 360.0 / self.azimuth_step_deg * self.density_scale

    @property
    def has_slam_error(self) -> bool:
        return bool(self.slam_tilt_deg or self.slam_drift_deg or self.slam_drift_tilt_deg or any(self.slam_drift_m))

    def slam_error(self, fraction: float, start: np.ndarray) -> np.ndarray:
        """4x4 map error of the SLAM trajectory at ``fraction`` (0-1) of the walk: world -> map
        (``p_map = E @ p_world``). A constant tilt of ``slam_tilt_deg`` (the map sinks towards
        ``slam_tilt_azimuth_deg``) and a drift growing linearly with time (rotation about z by
        ``fraction * slam_drift_deg``, about x by ``fraction * slam_drift_tilt_deg``, a shift of
        ``fraction * slam_drift_m``), all about the walk's ``start`` (world frame, metres)."""
        az = math.radians(self.slam_tilt_azimuth_deg)
        axis = np.array([-math.sin(az), math.cos(az), 0.0])  # tilting about it lowers the azimuth side
        rot = _axis_rotation(axis, math.radians(self.slam_tilt_deg))
        rot = rot @ _axis_rotation(np.array([0.0, 0.0, 1.0]), math.radians(fraction * self.slam_drift_deg))
        rot = rot @ _axis_rotation(np.array([1.0, 0.0, 0.0]), math.radians(fraction * self.slam_drift_tilt_deg))
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = start - rot @ start + fraction * np.asarray(self.slam_drift_m)
        return m


def _axis_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """3x3 rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1.0 - math.cos(angle_rad)) * (k @ k)


# --------------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SimulatedCloud:
    """A simulated point cloud in the scene (world) frame and its truth.

    Attributes
    ----------
    points : (N, 3) float64, metres, world frame.
    labels : (N,) uint8 :class:`~.mesh.Material` of each point.
    object_ids : (N,) int32 id of the tree/shrub/target/box hit (0 = ground).
    trajectory : (M, 3) float64 sensor positions (world frame), in time order: one per ray group.
    meta : counts, densities and the settings.
    intensity : optional (N,) float32 16-bit-scale intensities.
    """

    points: np.ndarray
    labels: np.ndarray
    object_ids: np.ndarray
    trajectory: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    intensity: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, mask_or_index: np.ndarray) -> "SimulatedCloud":
        """The cloud with a subset of its points (same trajectory and meta)."""
        idx = np.asarray(mask_or_index)
        return SimulatedCloud(
            points=_readonly(np.ascontiguousarray(self.points[idx])),
            labels=_readonly(np.ascontiguousarray(self.labels[idx])),
            object_ids=_readonly(np.ascontiguousarray(self.object_ids[idx])),
            trajectory=self.trajectory,
            meta=dict(self.meta),
            intensity=None if self.intensity is None else _readonly(np.ascontiguousarray(self.intensity[idx])),
        )

    def to_scan(self, name: str = "cloud", matrix: Optional[np.ndarray] = None) -> Scan:
        """A :class:`~forestreg.engine.core.scan.Scan` of these points, mapped by ``matrix`` (4x4,
        ``p_out = matrix @ p_world``) when given. The scanner position is the trajectory position
        horizontally nearest the middle of the points (mapped likewise); coordinates beyond 10 km
        get a local origin shift rounded from it (:meth:`Scan.from_points`)."""
        pts = self.points
        start = None
        if len(self.trajectory) and len(pts):
            mid = (pts[:, :2].min(axis=0) + pts[:, :2].max(axis=0)) / 2.0
            start = self.trajectory[int(np.argmin(np.hypot(*(self.trajectory[:, :2] - mid).T)))]
        if matrix is not None:
            m = np.asarray(matrix, dtype=np.float64)
            if m.shape != (4, 4) or not np.isfinite(m).all():
                raise ParameterError("matrix must be a finite 4x4 array")
            pts = apply_transform(m, pts)
            if start is not None:
                start = m[:3, :3] @ start + m[:3, 3]
        meta = {k: v for k, v in self.meta.items() if isinstance(v, (int, float, str, bool))}
        meta["simulated"] = True
        return Scan.from_points(pts, scanner_position=start, intensity=self.intensity, name=name, meta=meta)


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _cloud(chunks: "_Chunks", trajectory: np.ndarray, meta: dict[str, Any], what: str) -> SimulatedCloud:
    points, labels, objs, inten = chunks.arrays()
    if len(points) < 10:
        raise ScanDataError(
            f"the simulated {what} returned only {len(points)} points: the sensor sees nothing of the "
            "plot (check the path, altitude and ranges)"
        )
    counts = {m.name.lower(): int(c) for m in Material if (c := int((labels == m).sum()))}
    meta = dict(meta)
    meta.update(n_points=len(points), n_rays=chunks.n_rays, material_counts=counts)
    return SimulatedCloud(
        points=_readonly(points),
        labels=_readonly(labels),
        object_ids=_readonly(objs),
        trajectory=_readonly(np.ascontiguousarray(trajectory, dtype=np.float64)),
        meta=meta,
        intensity=_readonly(inten),
    )


class _Chunks:
    """Casts ray groups and collects the returns."""

    def __init__(
        self, caster: SceneRaycaster, min_range_m: float, max_range_m: float, noise_m: float, rng: np.random.Generator
    ) -> None:
        self.caster = caster
        self.min_range = min_range_m
        self.max_range = max_range_m
        self.noise = noise_m
        self.rng = rng
        self.n_rays = 0
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> None:
        """Cast unit ``directions`` (N, 3) float64 from ``origin`` (3,), world frame."""
        for a in range(0, len(directions), MAX_RAYS_PER_CAST):
            d = directions[a : a + MAX_RAYS_PER_CAST]
            self.n_rays += len(d)
            idx, t, mat, obj, cosi = self.caster.cast(origin, d)
            keep = (t >= self.min_range) & (t <= self.max_range)
            if not keep.any():
                continue
            idx, r = idx[keep], t[keep]
            mat, obj, cosi = mat[keep], obj[keep], cosi[keep]
            if self.noise > 0:
                r = r + self.rng.normal(0.0, self.noise, size=len(r))
            pts = origin[None, :] + d[idx] * r[:, None]
            inten = intensity_model(mat, cosi, r, self.max_range, self.rng)
            self.parts.append((pts, mat, obj, inten))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if not self.parts:
            return np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0, np.int32), np.zeros(0, np.float32)
        return tuple(np.concatenate([p[k] for p in self.parts]) for k in range(4))  # type: ignore[return-value]


def _mesh_bounds(caster: SceneRaycaster) -> tuple[np.ndarray, np.ndarray]:
    """(min xyz, max xyz) over every triangle of the scene."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for part in caster.mesh.parts.values():
        if len(part.vertices):
            lo = np.minimum(lo, part.vertices.min(axis=0))
            hi = np.maximum(hi, part.vertices.max(axis=0))
    return lo, hi


def _as_progress(progress: Optional[Union[ProgressCallback, Progress]]) -> Progress:
    return progress if isinstance(progress, Progress) else Progress(progress)


# --------------------------------------------------------------------------------------------
# UAV
# --------------------------------------------------------------------------------------------


def uav_flight_lines(scene: ForestScene, setup: UavSetup) -> np.ndarray:
    """(L, 2, 2) start and end (x, y) of each flight line, in flying order (serpentine).

    Lines are ``line_spacing_m`` apart across ``heading_deg``, over the plot plus the margin; each
    runs past the plot by the along-track reach of the outermost channel at the ground.
    """
    xmin, xmax, ymin, ymax = scene.extent
    cx, cy = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    h = math.radians(setup.heading_deg)
    fwd = np.array([math.cos(h), math.sin(h)])
    left = np.array([-math.sin(h), math.cos(h)])
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]]) - [cx, cy]
    along = corners @ fwd
    across = corners @ left
    z_centre = float(scene.ground_z(cx, cy))
    depth = setup.altitude_m + max(z_centre - float(np.min(scene.terrain.heights)), 0.0)
    half_swath = depth * math.tan(math.radians(setup.swath_half_angle_deg))
    margin = half_swath if setup.margin_m is None else setup.margin_m
    lo, hi = across.min() - margin, across.max() + margin
    k0 = math.ceil((lo - setup.line_offset_m) / setup.line_spacing_m - 1e-9)
    k1 = math.floor((hi - setup.line_offset_m) / setup.line_spacing_m + 1e-9)
    if k1 < k0:  # spacing wider than the block: one line nearest the centre
        k0 = k1 = int(round(-setup.line_offset_m / setup.line_spacing_m))
    offsets = setup.line_offset_m + np.arange(k0, k1 + 1) * setup.line_spacing_m
    reach = (
        depth
        * math.tan(math.radians(setup.vertical_fov_deg / 2.0))
        / math.cos(math.radians(setup.swath_half_angle_deg))
    )
    a0, a1 = along.min() - reach - 1.0, along.max() + reach + 1.0
    lines = np.empty((len(offsets), 2, 2))
    for i, c in enumerate(offsets):
        start = np.array([cx, cy]) + c * left + a0 * fwd
        end = np.array([cx, cy]) + c * left + a1 * fwd
        lines[i] = (start, end) if i % 2 == 0 else (end, start)
    return lines


def simulate_uav_scan(
    scene: ForestScene,
    setup: UavSetup = UavSetup(),
    *,
    seed: int = 0,
    progress: Optional[Union[ProgressCallback, Progress]] = None,
) -> SimulatedCloud:
    """Fly ``setup`` over ``scene`` and return the UAV LiDAR cloud (world frame).

    The sensor frame: rotation axis along the flight direction, azimuth 0 at nadir turning
    towards the left of the track; a channel at elevation ``e`` looks ``e`` degrees forward
    (positive) or backward. One ray group per rotation, cast from the sensor's position when it
    looks at nadir; each rotation starts at a random phase (the firings are not synchronised with
    the turn), so coarse steps still sample the ground evenly.

    ``meta`` holds ``n_points``, ``n_rays``, ``material_counts``, ``n_lines``, ``n_rotations``,
    ``flight_time_s``, ``density_per_m2`` (all points over the plot area),
    ``canopy_density_per_m2`` (see :func:`canopy_point_density`) and ``nominal_density_per_m2``.

    Raises
    ------
    ParameterError
        The altitude does not clear the canopy.
    ScanDataError
        Nothing of the plot is seen (fewer than 10 returns).
    """
    prog = _as_progress(progress)
    prog(0.0, "building meshes and ray-casting structure")
    caster = raycaster_for(scene)
    lo, hi = _mesh_bounds(caster)
    xmin, xmax, ymin, ymax = scene.extent
    cx, cy = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    z_flight = float(scene.ground_z(cx, cy)) + setup.altitude_m
    if z_flight < hi[2] + 1.0:
        raise ParameterError(
            f"flight height {setup.altitude_m} m above the plot centre does not clear the canopy "
            f"(highest object {hi[2] - float(scene.ground_z(cx, cy)):.1f} m above it)"
        )
    lines = uav_flight_lines(scene, setup)
    rng_phase = np.random.default_rng([int(seed), 211])
    chunks = _Chunks(caster, 0.0, setup.max_range_m, setup.range_noise_m, np.random.default_rng([int(seed), 212]))

    step = setup.azimuth_step_deg / setup.density_scale
    swath = setup.swath_half_angle_deg
    n_az = max(int(math.floor(2.0 * swath / step + 1e-9)), 1)
    eps = np.radians(setup.channel_elevations_deg)
    ce, se = np.cos(eps), np.sin(eps)
    buf = 0.5
    box_lo, box_hi = lo[:2] - buf, hi[:2] + buf
    depth_max = z_flight - lo[2]
    reach = depth_max * math.hypot(
        math.tan(math.radians(swath)),
        math.tan(math.radians(setup.vertical_fov_deg / 2.0)) / math.cos(math.radians(swath)),
    )
    reach = min(reach, setup.max_range_m) + buf
    dist_per_rot = setup.speed_m_s / setup.rotation_hz

    trajectory: list[np.ndarray] = []
    n_rot_total = 0
    n_rot_cast = 0
    rot_per_chunk = max(1, MAX_RAYS_PER_CAST // (n_az * len(eps)))
    lengths = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    total_len = float(lengths.sum())
    done_len = 0.0
    for li, (start, end) in enumerate(lines):
        length = float(np.linalg.norm(end - start))
        fwd2 = (end - start) / length
        fwd = np.array([fwd2[0], fwd2[1], 0.0])
        left = np.array([-fwd2[1], fwd2[0], 0.0])
        down = np.array([0.0, 0.0, -1.0])
        n_rot = int(math.floor(length / dist_per_rot)) + 1
        s = np.arange(n_rot) * dist_per_rot
        pos = np.column_stack([start[0] + s * fwd2[0], start[1] + s * fwd2[1], np.full(n_rot, z_flight)])
        phases = rng_phase.uniform(0.0, step, size=n_rot)
        trajectory.append(pos)
        n_rot_total += n_rot
        # rotations whose footprint can reach the scene
        gap = np.maximum(np.maximum(box_lo - pos[:, :2], pos[:, :2] - box_hi), 0.0)
        near = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) <= reach)
        # sweep angles that can reach the scene's box: tan(phi) = across / drop for every channel,
        # and across and drop are the same all along a straight, level line
        corners = np.array(
            [[box_lo[0], box_lo[1]], [box_hi[0], box_lo[1]], [box_hi[0], box_hi[1]], [box_lo[0], box_hi[1]]]
        )
        across = (corners - start) @ left[:2]
        drops = (z_flight - hi[2], z_flight - lo[2])
        ang = np.degrees([math.atan2(c, h) for c in (across.min(), across.max()) for h in drops])
        j0 = max(int(math.floor((ang.min() + swath) / step)) - 1, 0)
        j1 = min(int(math.ceil((ang.max() + swath) / step)) + 1, n_az)
        if j1 <= j0:
            near = near[:0]
        for a in range(0, len(near), rot_per_chunk):
            rows = near[a : a + rot_per_chunk]
            phi = np.radians(-swath + phases[rows, None] + np.arange(j0, j1)[None, :] * step)  # (R, A)
            cp, sp = np.cos(phi), np.sin(phi)
            # d = ce (cos(phi) down + sin(phi) left) + se fwd, shape (R, A, C, 3)
            horiz = cp[..., None] * down + sp[..., None] * left  # (R, A, 3)
            d = ce[None, None, :, None] * horiz[:, :, None, :] + se[None, None, :, None] * fwd
            o = pos[rows]
            dz = d[..., 2]
            t_top = (hi[2] - o[:, 2, None, None]) / dz
            t_bot = (lo[2] - o[:, 2, None, None]) / dz
            keep = t_top <= setup.max_range_m
            for k in range(2):
                p_top = o[:, k, None, None] + t_top * d[..., k]
                p_bot = o[:, k, None, None] + t_bot * d[..., k]
                keep &= (np.maximum(p_top, p_bot) >= box_lo[k]) & (np.minimum(p_top, p_bot) <= box_hi[k])
            for j, r in enumerate(rows):
                sel = keep[j]
                if sel.any():
                    chunks.cast(pos[r], d[j][sel])
                    n_rot_cast += 1
            frac = (done_len + length * (a + len(rows)) / max(len(near), 1)) / total_len
            prog(0.02 + 0.93 * frac, f"flight line {li + 1}/{len(lines)}")
        done_len += length

    traj = np.concatenate(trajectory) if trajectory else np.zeros((0, 3))
    meta: dict[str, Any] = {
        "platform": "uav",
        "preset": scene.preset,
        "scene_seed": scene.seed,
        "seed": int(seed),
        "setup": dataclasses.asdict(setup),
        "n_lines": len(lines),
        "n_rotations": n_rot_total,
        "n_rotations_cast": n_rot_cast,
        "flight_time_s": n_rot_total / setup.rotation_hz,
        "flight_height_z_m": z_flight,
        "nominal_density_per_m2": setup.nominal_density_per_m2,
    }
    cloud = _cloud(chunks, traj, meta, "UAV flight")
    prog(0.97, "measuring point density")
    area = (xmax - xmin) * (ymax - ymin)
    cloud.meta["density_per_m2"] = len(cloud) / area
    cloud.meta["canopy_density_per_m2"] = canopy_point_density(cloud.points, scene)
    prog(1.0, "done")
    return cloud


def canopy_point_density(
    points: np.ndarray,
    scene: ForestScene,
    *,
    cell_m: float = 1.0,
    min_height_m: float = 2.0,
    extent: Optional[tuple[float, float, float, float]] = None,
) -> float:
    """Points per m2 over the canopy: all points in the ``cell_m`` grid cells (over ``extent``,
    default the plot) whose highest point stands at least ``min_height_m`` above the ground,
    divided by those cells' area. NaN when no cell has canopy."""
    pts = np.asarray(points, dtype=np.float64)
    xmin, xmax, ymin, ymax = extent if extent is not None else scene.extent
    nx = int(math.floor((xmax - xmin) / cell_m + 1e-9))
    ny = int(math.floor((ymax - ymin) / cell_m + 1e-9))
    if nx < 1 or ny < 1 or len(pts) == 0:
        return float("nan")
    i = np.floor((pts[:, 0] - xmin) / cell_m).astype(np.int64)
    j = np.floor((pts[:, 1] - ymin) / cell_m).astype(np.int64)
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    i, j = i[inside], j[inside]
    height = pts[inside, 2] - scene.ground_z(pts[inside, 0], pts[inside, 1])
    cell = j * nx + i
    top = np.full(nx * ny, -np.inf)
    np.maximum.at(top, cell, height)
    count = np.bincount(cell, minlength=nx * ny)
    canopy = top >= min_height_m
    if not canopy.any():
        return float("nan")
    return float(count[canopy].sum() / (canopy.sum() * cell_m * cell_m))


# --------------------------------------------------------------------------------------------
# backpack
# --------------------------------------------------------------------------------------------


def backpack_waypoints(scene: ForestScene, setup: BackpackSetup) -> np.ndarray:
    """(K, 2) planned path of ``setup``: its waypoints, or the default serpentine."""
    if setup.waypoints is not None:
        return np.asarray(setup.waypoints, dtype=np.float64)
    xmin, xmax, ymin, ymax = scene.extent
    side = setup.extent_m
    if side is None:
        side = min(xmax - xmin, ymax - ymin) - 2.0 * setup.edge_margin_m
        if side < 1.0:
            raise ParameterError(f"the plot is too small for an edge margin of {setup.edge_margin_m} m")
    cx, cy = setup.centre
    half = side / 2.0
    n = max(2, int(round(side / setup.line_spacing_m)) + 1)
    ys = np.linspace(cy - half, cy + half, n)
    wp = []
    for k, y in enumerate(ys):
        xs = (cx - half, cx + half) if k % 2 == 0 else (cx + half, cx - half)
        wp.extend([(xs[0], y), (xs[1], y)])
    return np.asarray(wp)


def _obstacles(scene: ForestScene, clearance_m: float, height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Round keep-out zones at walking height: (K, 2) centres and (K,) radii (stems at several
    heights as they lean, target poles, buildings and fence posts as their circumscribed circles)."""
    centres, radii = [], []
    for t in scene.trees:
        r = t.dbh_m / 2.0 * (1.0 + t.flare)
        for h in np.arange(0.0, height_m + 0.25, 0.5):  # a leaning stem moves with height
            centres.append(t.point_at_height(float(h))[:2])
            radii.append(r + clearance_m)
    for tg in scene.targets:
        centres.append(np.array([tg.x, tg.y]))
        radii.append(max(tg.radius_m, tg.pole_radius_m) + clearance_m)
    for bx in scene.boxes:  # buildings and posts, as their circumscribed circles; rails are stepped over
        if getattr(bx, "kind", "") != "fence_rail":
            centres.append(np.array([bx.x, bx.y]))
            radii.append(0.5 * math.hypot(bx.size[0], bx.size[1]) + clearance_m)
    if not centres:
        return np.zeros((0, 2)), np.zeros(0)
    return np.asarray(centres), np.asarray(radii)


#: A path passing within this distance of an obstacle's centre goes round its left side (so
#: that rounding cannot make it alternate sides).
_SIDE_TOLERANCE_M = 1e-6


def _push_out(
    xy: np.ndarray, tangent: np.ndarray, scene: ForestScene, clearance_m: float, height_m: float, passes: int = 10
) -> np.ndarray:
    """Move path points to at least ``clearance_m`` from stems, target poles and buildings.

    A point inside a keep-out zone moves across the path (perpendicular to its unit ``tangent``),
    to the side of the obstacle's centre it is on, until it is out: a straight path through a stem
    becomes a continuous detour round it. A few passes, as leaving one zone may enter another.
    """
    out = xy.copy()
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    centres, radii = _obstacles(scene, clearance_m, height_m)
    for _ in range(passes):
        moved = False
        near = cKDTree(out).query_ball_point(centres, radii) if len(centres) else []
        for c, r, candidates in zip(centres, radii, near):
            if not candidates:
                continue
            idx = np.asarray(candidates, dtype=np.int64)
            v = out[idx] - c
            sel = np.einsum("ij,ij->i", v, v) < r * r
            if not sel.any():
                continue
            moved = True
            idx, v = idx[sel], v[sel]
            t, n = tangent[idx], normal[idx]
            along = np.einsum("ij,ij->i", v, t)
            side = np.where(np.einsum("ij,ij->i", v, n) >= -_SIDE_TOLERANCE_M, 1.0, -1.0)
            across = side * np.sqrt(np.maximum(r * r - along * along, 0.0))
            out[idx] = c + along[:, None] * t + across[:, None] * n
        if not moved:
            break
    return out


def _densify(wp: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ~``step_m`` along a polyline (every vertex kept) and their unit tangents."""
    pts, tans = [], []
    for a, b in zip(wp[:-1], wp[1:]):
        seg = b - a
        length = float(np.hypot(*seg))
        if length < 1e-9:
            continue
        n = max(1, int(math.ceil(length / step_m)))
        f = np.arange(n)[:, None] / n
        pts.append(a + f * seg)
        tans.append(np.repeat((seg / length)[None, :], n, axis=0))
    pts.append(wp[-1:])
    tans.append(tans[-1][-1:] if tans else np.array([[1.0, 0.0]]))
    return np.concatenate(pts), np.concatenate(tans)


def _resample(poly: np.ndarray, spacing: float) -> np.ndarray:
    """Points every ``spacing`` metres of arc length along a polyline (starting at its start)."""
    seg = np.hypot(*np.diff(poly, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = int(math.floor(s[-1] / spacing + 1e-9)) + 1
    q = np.arange(n) * spacing
    return np.column_stack([np.interp(q, s, poly[:, 0]), np.interp(q, s, poly[:, 1])])


def backpack_path(scene: ForestScene, setup: BackpackSetup) -> np.ndarray:
    """(M, 3) sensor positions of the walk, one per ray group (``sectors_per_rotation`` per
    rotation), evenly spaced in time at ``speed_m_s``, clear of stems, target poles and buildings,
    ``height_m`` above the ground (world frame)."""
    wp = backpack_waypoints(scene, setup)
    xmin, xmax, ymin, ymax = scene.extent
    outside = (wp[:, 0] < xmin) | (wp[:, 0] > xmax) | (wp[:, 1] < ymin) | (wp[:, 1] > ymax)
    if outside.any():
        raise ParameterError(
            f"backpack waypoint(s) {np.flatnonzero(outside).tolist()} lie outside the plot {scene.extent}"
        )
    dense, tangent = _densify(wp, 0.02)
    clear = _push_out(dense, tangent, scene, setup.clearance_m, setup.height_m)
    clear[:, 0] = np.clip(clear[:, 0], xmin, xmax)
    clear[:, 1] = np.clip(clear[:, 1], ymin, ymax)
    spacing = setup.speed_m_s / (setup.rotation_hz * setup.sectors_per_rotation)
    path_len = float(np.hypot(*np.diff(clear, axis=0).T).sum())
    if path_len < 2.0 * spacing:
        raise ParameterError(f"the backpack path is only {path_len:.2f} m long")
    xy = _resample(clear, spacing)
    # chords between the pushed points cut into the keep-out circles by micrometres: push again
    tangent = np.gradient(xy, axis=0)
    tangent /= np.maximum(np.hypot(tangent[:, 0], tangent[:, 1]), 1e-12)[:, None]
    xy = _push_out(xy, tangent, scene, setup.clearance_m, setup.height_m)
    # where stems stand closer than twice the clearance the margins overlap: at least stay
    # out of the wood itself
    xy = _push_out(xy, tangent, scene, min(setup.clearance_m, 0.05), setup.height_m, passes=1)
    z = scene.ground_z(xy[:, 0], xy[:, 1]) + setup.height_m
    return np.column_stack([xy, z])


def simulate_backpack_scan(
    scene: ForestScene,
    setup: BackpackSetup = BackpackSetup(),
    *,
    seed: int = 0,
    progress: Optional[Union[ProgressCallback, Progress]] = None,
) -> SimulatedCloud:
    """Walk ``setup``'s path through ``scene`` with a backpack laser scanner; the cloud (world frame).

    Sensor frame: rotation axis tilted ``tilt_deg`` back from vertical (in the walking direction's
    vertical plane), azimuth 0 looking forward-up; the walker faces along the path. The
    trajectory holds one position per ray group; ``meta`` holds ``path_length_m``,
    ``duration_s``, ``speed_m_s`` (measured on the trajectory), ``n_rotations`` and the counts.

    Raises
    ------
    ParameterError
        Waypoints outside the plot, or a path too short to walk.
    ScanDataError
        Nothing is seen (fewer than 10 returns).
    """
    prog = _as_progress(progress)
    prog(0.0, "building meshes and ray-casting structure")
    caster = raycaster_for(scene)
    prog(0.02, "planning the walk")
    traj = backpack_path(scene, setup)
    n_groups = len(traj)
    sectors = setup.sectors_per_rotation
    # heading from the path's direction (central differences)
    dxy = np.gradient(traj[:, :2], axis=0)
    heading = np.arctan2(dxy[:, 1], dxy[:, 0])
    bad = np.hypot(dxy[:, 0], dxy[:, 1]) < 1e-12
    if bad.any():
        heading[bad] = 0.0

    step = setup.azimuth_step_deg / setup.density_scale
    n_az = max(int(math.floor(360.0 / step + 1e-9)), sectors)
    bounds = np.linspace(0, n_az, sectors + 1).round().astype(int)
    eps = np.radians(setup.channel_elevations_deg)
    ce, se = np.cos(eps), np.sin(eps)
    tau = math.radians(setup.tilt_deg)
    # sensor axes in the walker's frame (forward, left, up)
    x_s = np.array([math.cos(tau), 0.0, math.sin(tau)])
    y_s = np.array([0.0, 1.0, 0.0])
    z_s = np.array([-math.sin(tau), 0.0, math.cos(tau)])
    body = np.column_stack([x_s, y_s, z_s])  # sensor -> walker
    rng_phase = np.random.default_rng([int(seed), 311])
    chunks = _Chunks(
        caster, setup.min_range_m, setup.max_range_m, setup.range_noise_m, np.random.default_rng([int(seed), 312])
    )
    n_rot = int(math.ceil(n_groups / sectors))
    phases = rng_phase.uniform(0.0, step, size=n_rot)
    report_every = max(1, n_groups // 50)
    true_parts: list[np.ndarray] = []
    for g in range(n_groups):
        rot, sec = divmod(g, sectors)
        az = np.radians(phases[rot] + np.arange(bounds[sec], bounds[sec + 1]) * step)
        ca, sa = np.cos(az), np.sin(az)
        d_s = np.empty((len(az), len(eps), 3))
        d_s[..., 0] = ca[:, None] * ce[None, :]
        d_s[..., 1] = sa[:, None] * ce[None, :]
        d_s[..., 2] = se[None, :]
        ch, sh = math.cos(heading[g]), math.sin(heading[g])
        rz = np.array([[ch, -sh, 0.0], [sh, ch, 0.0], [0.0, 0.0, 1.0]])
        rot_m = rz @ body
        n_before = len(chunks.parts)
        chunks.cast(traj[g], d_s.reshape(-1, 3) @ rot_m.T)
        if setup.has_slam_error:  # the SLAM map places this group's points with its pose error
            err = setup.slam_error(g / max(n_groups - 1, 1), traj[0])
            for k in range(n_before, len(chunks.parts)):
                pts, *rest = chunks.parts[k]
                true_parts.append(pts)
                chunks.parts[k] = (apply_transform(err, pts), *rest)
        if g % report_every == 0:
            prog(0.03 + 0.95 * g / n_groups, f"walking: {g / (setup.rotation_hz * sectors):.0f} s")

    path_len = float(np.linalg.norm(np.diff(traj, axis=0), axis=1).sum())
    duration = (n_groups - 1) / (setup.rotation_hz * sectors)
    xy_len = float(np.hypot(*np.diff(traj[:, :2], axis=0).T).sum())
    meta: dict[str, Any] = {
        "platform": "backpack",
        "preset": scene.preset,
        "scene_seed": scene.seed,
        "seed": int(seed),
        "setup": dataclasses.asdict(setup),
        "n_rotations": n_rot,
        "path_length_m": path_len,
        "horizontal_path_length_m": xy_len,
        "duration_s": duration,
        "speed_m_s": xy_len / duration if duration > 0 else float("nan"),
    }
    if setup.has_slam_error and true_parts:
        mapped = np.concatenate([p[0] for p in chunks.parts])
        truth = np.concatenate(true_parts)
        fit = fit_rigid(mapped, truth)  # the best rigid map -> world: what a registration can recover
        left = apply_transform(fit, mapped) - truth
        meta["slam_fit_matrix"] = fit.tolist()
        meta["slam_residual_rms_m"] = float(np.sqrt(np.mean(np.sum(left**2, axis=1))))
        meta["slam_residual_max_m"] = float(np.sqrt(np.max(np.sum(left**2, axis=1))))
    cloud = _cloud(chunks, traj, meta, "backpack walk")
    prog(1.0, "done")
    return cloud


# --------------------------------------------------------------------------------------------
# ground / UAV co-registration case
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CoregistrationCase:
    """One plot seen from the air and from the ground, with the true ground -> UAV transform.

    Attributes
    ----------
    ground : the ground data (backpack, or merged TLS scans) in the ground platform's own frame.
    uav : the UAV cloud in the UAV frame (world frame plus ``world_offset``).
    matrix : 4x4 ground frame -> UAV frame: ``p_uav = matrix @ p_ground`` (homogeneous columns).
        With a SLAM map error (:attr:`BackpackSetup.slam_tilt_deg` and the drifts) it holds the
        best rigid answer: the least-squares rigid fit of the drifted map onto the true points
        (``meta["slam_residual_rms_m"]`` is what no rigid transform can remove).
    scene : the simulated plot (world frame).
    ground_cloud, uav_cloud : the same points in the world frame (without ``world_offset``), with
        their ``labels`` ((N,) uint8 :class:`~.mesh.Material`) and ``object_ids`` ((N,) int32 tree
        ids; 0 = ground), row-aligned with the scans.
    world_offset : (3,) added to world coordinates to make UAV coordinates.
    misalignment : 4x4 ground frame -> world frame (``matrix`` less the world offset).
    meta : settings and counts.
    """

    ground: Scan
    uav: Scan
    matrix: np.ndarray
    scene: ForestScene
    ground_cloud: SimulatedCloud
    uav_cloud: SimulatedCloud
    world_offset: np.ndarray
    misalignment: np.ndarray
    meta: Mapping[str, Any] = field(default_factory=dict)


#: scene overrides (:func:`~.scene.make_scene`) of a leaf-on broadleaf stand for
#: :func:`simulate_coregistration_case`: dominant crowns up to 28 m over suppressed trees from 6 m,
#: leafy crowns (leaf area density 0.5) spreading 1 m + 5 x DBH. The UAV sees the dominant crowns'
#: foliage and few stems; a backpack sees the stems, the lower crowns and the tops through gaps: of
#: ~27 UAV and ~11 ground-based canopy keypoints, at most 2 match.
LEAF_ON_BROADLEAF: Mapping[str, Any] = {
    "conifer_fraction": 0.0,
    "leaf_area_density": 0.5,
    "stems_per_ha": 1000.0,
    "height_m": (6.0, 28.0),
    "dbh_power": 1.5,
    "crown_radius_ab": (1.0, 5.0),
    "crown_base_fraction": (0.35, 0.55),
}


def _derived_seed(seed: int, stream: int) -> int:
    return int(np.random.SeedSequence([int(seed), 8117, int(stream)]).generate_state(1)[0])


def misalignment_matrix(heading_deg: float, offset_m: Sequence[float]) -> np.ndarray:
    """4x4 rotation about z by ``heading_deg`` followed by the translation ``offset_m``."""
    a = math.radians(heading_deg)
    m = np.eye(4)
    m[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    m[:3, 3] = np.asarray(offset_m, dtype=np.float64)
    return m


def _rigid_inverse(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def clear_position(
    scene: ForestScene, xy: Sequence[float], clearance_m: float = 1.0, search_m: float = 5.0
) -> np.ndarray:
    """The point nearest ``xy`` (on a 0.25 m grid within ``search_m``) at least ``clearance_m``
    from every stem surface, shrub, target and building, where a tripod can stand."""
    xy = np.asarray(xy, dtype=np.float64)
    c, r = _obstacles(scene, clearance_m, 2.0)
    extra_c = [np.array([s.x, s.y]) for s in scene.shrubs] + [np.array([b.x, b.y]) for b in scene.boxes]
    extra_r = [s.radius_m + clearance_m for s in scene.shrubs] + [
        0.5 * math.hypot(b.size[0], b.size[1]) + clearance_m for b in scene.boxes
    ]
    if extra_c:
        c = np.vstack([c, extra_c]) if len(c) else np.asarray(extra_c)
        r = np.concatenate([r, extra_r])
    g = np.arange(-search_m, search_m + 1e-9, 0.25)
    gx, gy = np.meshgrid(g, g)
    cand = np.column_stack([gx.ravel(), gy.ravel()])
    cand = cand[np.argsort(np.hypot(cand[:, 0], cand[:, 1]), kind="stable")] + xy
    xmin, xmax, ymin, ymax = scene.extent
    cand = cand[(cand[:, 0] > xmin + 1) & (cand[:, 0] < xmax - 1) & (cand[:, 1] > ymin + 1) & (cand[:, 1] < ymax - 1)]
    if len(c) == 0:
        return cand[0] if len(cand) else xy
    d = np.hypot(cand[:, None, 0] - c[None, :, 0], cand[:, None, 1] - c[None, :, 1])
    ok = np.flatnonzero((d >= r[None, :]).all(axis=1))
    if len(ok) == 0:
        raise ParameterError(f"no clear spot for a scanner within {search_m} m of {xy.tolist()}")
    return cand[ok[0]]


def simulate_coregistration_case(
    preset: str = "planted_conifer",
    *,
    seed: int = 0,
    size_m: float = 40.0,
    ground_platform: str = "backpack",
    ground_extent_m: Optional[float] = None,
    heading_deg: float = 30.0,
    offset_m: Sequence[float] = (5.0, -3.0, 1.5),
    uav_density_scale: float = 1.0,
    backpack_density_scale: float = 0.25,
    tls_step_deg: float = 0.2,
    world_offset: Sequence[float] = (0.0, 0.0, 0.0),
    uav_setup: Optional[UavSetup] = None,
    backpack_setup: Optional[BackpackSetup] = None,
    tls_positions: Optional[Sequence[Sequence[float]]] = None,
    scene: Optional[ForestScene] = None,
    progress: Optional[Union[ProgressCallback, Progress]] = None,
    **scene_overrides: Any,
) -> CoregistrationCase:
    """Simulate a ground/UAV co-registration problem with a known answer (paper section 4.1).

    Parameters
    ----------
    preset, seed, size_m, scene_overrides : the plot (:func:`~.scene.make_scene`); or ``scene``.
    ground_platform : ``"backpack"`` (:func:`simulate_backpack_scan`, a serpentine over the
        ground area) or ``"tls"`` (scans from ``tls_positions``, default the centre and four
        points a quarter of the ground area's side out diagonally, moved to clear spots, merged).
    ground_extent_m : side of the central square the ground data cover (they are cropped to it);
        default 0.6 of the plot (the paper's 30 m ground plots in 50 m UAV plots).
    heading_deg, offset_m : the misalignment of the ground frame: ``p_world = R_z(heading) @
        p_ground + offset``.
    uav_density_scale : ``UavSetup.density_scale`` (1 = the paper's ~280 points/m2).
    backpack_density_scale : ``BackpackSetup.density_scale`` (0.25 = the paper's 5-10 thousand
        points/m2).
    tls_step_deg : angular step of the TLS scans.
    world_offset : added to the UAV cloud (e.g. ``(500000, 5000000, 200)`` for UTM-like numbers).
    uav_setup, backpack_setup : full control of the platforms (``uav_density_scale`` is then
        ignored; the backpack setup's path is used as given).
    """
    prog = _as_progress(progress)
    if ground_platform not in ("backpack", "tls"):
        raise ParameterError(f"ground_platform must be 'backpack' or 'tls', got {ground_platform!r}")
    off = np.asarray(offset_m, dtype=np.float64).reshape(-1)
    w_off = np.asarray(world_offset, dtype=np.float64).reshape(-1)
    if off.shape != (3,) or w_off.shape != (3,) or not (np.isfinite(off).all() and np.isfinite(w_off).all()):
        raise ParameterError("offset_m and world_offset must be three finite numbers each")
    if not math.isfinite(heading_deg):
        raise ParameterError(f"heading_deg must be finite, got {heading_deg}")
    prog(0.0, "building the scene")
    scene = given_or_made_scene(scene, preset, seed, size_m, scene_overrides)
    xmin, xmax, ymin, ymax = scene.extent
    cx, cy = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    plot_side = min(xmax - xmin, ymax - ymin)
    extent_m = 0.6 * plot_side if ground_extent_m is None else float(ground_extent_m)
    if not (4.0 <= extent_m <= plot_side):
        raise ParameterError(f"ground_extent_m must be within 4 m and the plot side {plot_side} m, got {extent_m}")

    uav = uav_setup if uav_setup is not None else UavSetup(density_scale=uav_density_scale)
    prog(0.02, "UAV flight")
    uav_cloud = simulate_uav_scan(scene, uav, seed=_derived_seed(seed, 1), progress=prog.sub(0.02, 0.5))

    half = extent_m / 2.0
    prog(0.5, f"ground data ({ground_platform})")
    if ground_platform == "backpack":
        bp = backpack_setup
        if bp is None:
            bp = BackpackSetup(extent_m=max(extent_m - 4.0, 2.0), centre=(cx, cy), density_scale=backpack_density_scale)
        raw = simulate_backpack_scan(scene, bp, seed=_derived_seed(seed, 2), progress=prog.sub(0.5, 0.95))
    else:
        if tls_positions is None:
            q = extent_m / 4.0
            wanted = [(cx, cy), (cx + q, cy + q), (cx - q, cy + q), (cx - q, cy - q), (cx + q, cy - q)]
        else:
            wanted = [tuple(p) for p in tls_positions]
        pos = [clear_position(scene, p, 1.0) for p in wanted]
        plot = simulate_plot(
            scene.preset,
            [tuple(p) for p in pos],
            seed=_derived_seed(seed, 3),
            angular_step_deg=tls_step_deg,
            scene=scene,
            clearance_m=0.0,
            progress=prog.sub(0.5, 0.95),
        )
        raw = SimulatedCloud(
            points=np.concatenate([s.world_points() for s in plot.scans]),
            labels=np.concatenate([s.labels for s in plot.scans]),
            object_ids=np.concatenate([s.object_ids for s in plot.scans]),
            trajectory=np.asarray([s.position for s in plot.scans]),
            meta={"platform": "tls", "n_scans": len(plot.scans), "angular_step_deg": tls_step_deg},
            intensity=np.concatenate([s.scan.intensity for s in plot.scans]),
        )
    inside = (np.abs(raw.points[:, 0] - cx) <= half) & (np.abs(raw.points[:, 1] - cy) <= half)
    ground_cloud = raw.subset(inside)
    ground_cloud.meta["ground_extent_m"] = extent_m
    ground_cloud.meta["n_points_before_crop"] = len(raw)

    prog(0.96, "placing the frames")
    frame = misalignment_matrix(heading_deg, off)  # ground frame -> map frame (the world without SLAM error)
    ground = ground_cloud.to_scan(f"{ground_platform}_ground", matrix=_rigid_inverse(frame))
    mis = frame
    if "slam_fit_matrix" in raw.meta:  # a drifted/tilted SLAM map: the best rigid map -> world
        mis = np.asarray(raw.meta["slam_fit_matrix"], dtype=np.float64) @ frame
    to_uav = np.eye(4)
    to_uav[:3, 3] = w_off
    matrix = to_uav @ mis
    uav_scan = uav_cloud.to_scan("uav", matrix=to_uav if w_off.any() else None)
    for a in (matrix, mis, w_off):
        a.setflags(write=False)
    meta = {
        "preset": scene.preset,
        "seed": int(seed),
        "size_m": plot_side,
        "ground_platform": ground_platform,
        "ground_extent_m": extent_m,
        "heading_deg": float(heading_deg),
        "offset_m": off.tolist(),
        "world_offset": w_off.tolist(),
        "n_ground_points": len(ground),
        "n_uav_points": len(uav_scan),
        "uav_canopy_density_per_m2": uav_cloud.meta.get("canopy_density_per_m2"),
        "slam_residual_rms_m": raw.meta.get("slam_residual_rms_m", 0.0),
        "conventions": "p_uav = matrix @ p_ground; p_world = misalignment @ p_ground; p_uav = p_world + world_offset",
    }
    prog(1.0, "done")
    return CoregistrationCase(
        ground=ground,
        uav=uav_scan,
        matrix=matrix,
        scene=scene,
        ground_cloud=ground_cloud,
        uav_cloud=uav_cloud,
        world_offset=w_off,
        misalignment=mis,
        meta=meta,
    )
