"""A terrestrial laser scanner: rays over a spherical grid, cast at a scene's meshes.

Scanner frame (SOCS)
--------------------
The scanner sits at the origin of its own frame. A beam at azimuth ``phi`` (counter-clockwise
from the scanner's +x) and elevation ``theta`` (up from the scanner's xy plane) has direction
``(cos theta cos phi, cos theta sin phi, sin theta)``. The scanner takes one beam every
``angular_step_deg`` in azimuth over the full turn ``[0, 360)`` and in elevation from
``elevation_min_deg`` to ``elevation_max_deg`` (every ``elevation_step_deg`` when given: a
scanner of a few laser lines), column by column (the order of the points).

Field of view
-------------
``azimuth_fov_deg`` below 360 limits the columns to a sector of that width centred on the SOCS
azimuth ``azimuth_centre_deg`` (0 = the scanner's +x, which points along ``yaw_deg`` in the scene
frame): ``round(fov / step)`` columns, evenly spaced, half a column in from each edge of the
sector. A forward-looking laser on a robot sees about 180 deg ahead; a scanner whose sector stops
short of the full turn (a tripod leg, the operator, a 300 deg sector) misses the rest.
:data:`SCANNER_PRESETS` holds such instruments as :class:`ScannerSetup` fields
(:func:`scanner_options`).

Pose
----
``pose`` (4x4) maps SOCS to the scene frame: ``p_world = pose @ p_socs``, with rotation
``R = R_tilt @ R_z(yaw)`` and translation the scanner's optical centre ``(x, y, ground + height)``.
``R_tilt`` turns by ``tilt_deg`` about the horizontal axis perpendicular to the azimuth
``tilt_azimuth_deg`` (scene frame), leaning the scanner's z axis *towards* that azimuth: a
30 deg tilt with the default elevation window (-40..60 deg) looks up to the zenith on that side.

Returns
-------
A beam that hits nothing, hits beyond ``max_range_m``, or hits closer than ``min_range_m`` gives
no point (a too-close hit still blocks the beam). The range of a hit gets Gaussian noise of
``range_noise_m`` along the beam. Intensity is a plausible 16-bit value (0-65535): a material
reflectance times an incidence-angle falloff ``0.25 + 0.75 cos(i)``, a mild range falloff and
5 % multiplicative noise; retro-reflective targets are near the top of the scale and hardly depend
on the angle (about 50 000-62 000 against at most ~35 000 for anything else).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import numpy as np

from ..core.errors import ParameterError
from ..core.scan import Scan
from ..core.transform import apply as apply_transform
from .mesh import Material, SceneRaycaster, raycaster_for
from .scene import ForestScene

#: Reflectance (0-1) per material for the intensity model.
REFLECTANCE = {
    Material.GROUND: 0.30,
    Material.TRUNK: 0.40,
    Material.BRANCH: 0.38,
    Material.LEAF: 0.50,
    Material.SHRUB: 0.45,
    Material.LIANA: 0.36,
    Material.TARGET_POLE: 0.30,
    Material.TARGET: 0.95,
    Material.STRUCTURE: 0.55,
}

#: Full scale of the simulated intensity.
INTENSITY_SCALE = 65535.0

#: Rays cast per batch (bounds the memory of a fine scan).
RAY_BATCH = 1_000_000


@dataclass(frozen=True)
class ScannerSetup:
    """Where and how a simulated scanner stands and scans.

    ``(x, y)`` in the scene frame; the optical centre is ``height_m`` above the ground there (or
    at ``z`` if given). ``yaw_deg=None`` draws a random heading from the scan's seed.
    """

    x: float
    y: float
    height_m: float = 1.5
    yaw_deg: Optional[float] = None
    tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 0.0
    angular_step_deg: float = 0.1
    elevation_min_deg: float = -40.0
    elevation_max_deg: float = 60.0
    min_range_m: float = 1.5
    max_range_m: float = 80.0
    range_noise_m: float = 0.005
    name: str = "scan"
    #: absolute z of the optical centre (scene frame); None = ground + height_m
    z: Optional[float] = None
    #: horizontal field of view (deg): 360 = the full turn; less = a sector
    azimuth_fov_deg: float = 360.0
    #: SOCS azimuth (deg, counter-clockwise from the scanner's +x) of the sector's centre
    azimuth_centre_deg: float = 0.0
    #: spacing of the elevation lines (deg); None = ``angular_step_deg``
    elevation_step_deg: Optional[float] = None

    def __post_init__(self) -> None:
        if not (0.005 <= self.angular_step_deg <= 10.0):
            raise ParameterError(f"angular step must be within 0.005-10 deg, got {self.angular_step_deg}")
        if not (-90.0 <= self.elevation_min_deg < self.elevation_max_deg <= 90.0):
            raise ParameterError(
                f"elevation window must satisfy -90 <= min < max <= 90 deg, got "
                f"{self.elevation_min_deg}..{self.elevation_max_deg}"
            )
        if not (0.0 <= self.min_range_m < self.max_range_m):
            raise ParameterError(f"ranges must satisfy 0 <= min < max, got {self.min_range_m}..{self.max_range_m}")
        if self.range_noise_m < 0.0:
            raise ParameterError(f"range noise must be >= 0, got {self.range_noise_m}")
        if not (0.0 <= self.tilt_deg <= 90.0):
            raise ParameterError(f"tilt must be within 0-90 deg, got {self.tilt_deg}")
        if not (0.0 < self.azimuth_fov_deg <= 360.0):
            raise ParameterError(f"azimuth field of view must be within (0, 360] deg, got {self.azimuth_fov_deg}")
        if self.elevation_step_deg is not None and not (0.005 <= self.elevation_step_deg <= 90.0):
            raise ParameterError(f"elevation step must be within 0.005-90 deg, got {self.elevation_step_deg}")

    @property
    def full_turn(self) -> bool:
        """Whether the scanner sees the full 360 deg in azimuth."""
        return self.azimuth_fov_deg >= 360.0

    def in_field_of_view(self, azimuth_deg: Any) -> Any:
        """Whether SOCS azimuths (deg) lie within the horizontal field of view."""
        a = np.asarray(azimuth_deg, dtype=np.float64)
        if self.full_turn:
            return np.ones(a.shape, dtype=bool) if a.ndim else True
        off = (a - self.azimuth_centre_deg + 180.0) % 360.0 - 180.0
        out = np.abs(off) <= self.azimuth_fov_deg / 2.0 + 1e-9
        return out if a.ndim else bool(out)

    def resolved(self, seed: int = 0) -> "ScannerSetup":
        """This setup with a concrete yaw (drawn from ``seed`` when ``yaw_deg`` is None)."""
        if self.yaw_deg is not None:
            return self
        yaw = float(np.random.default_rng([int(seed), 7919]).uniform(0.0, 360.0))
        return dataclasses.replace(self, yaw_deg=yaw)

    def rotation(self) -> np.ndarray:
        """3x3 rotation SOCS -> scene frame (``R_tilt @ R_z(yaw)``); needs a resolved yaw."""
        yaw = math.radians(self.yaw_deg or 0.0)
        rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        if self.tilt_deg == 0.0:
            return rz
        a = math.radians(self.tilt_azimuth_deg)
        axis = np.array([-math.sin(a), math.cos(a), 0.0])  # z x (cos a, sin a, 0)
        return rotation_about(axis, math.radians(self.tilt_deg)) @ rz


#: Instruments as :class:`ScannerSetup` fields (see :func:`scanner_options`):
#:
#: * ``tls``: a terrestrial laser scanner on a tripod, the full turn (the defaults);
#: * ``sector_300``: a tripod scanner sweeping a 300 deg sector: 60 deg behind it unseen (a
#:   tripod leg, the operator, a scan stopped short);
#: * ``robot_forward``: a forward-looking laser on a wheeled robot, 0.7 m above the ground, 180 deg
#:   wide, a band of -20..+20 deg in elevation, ranges 0.3-33 m;
#: * ``robot_lines``: the same with 16 laser lines 2 deg apart (-15..+15 deg), as a 16-line
#:   spinning lidar cut to its forward half.
SCANNER_PRESETS: dict[str, dict[str, Any]] = {
    "tls": {},
    "sector_300": {"azimuth_fov_deg": 300.0},
    "robot_forward": {
        "azimuth_fov_deg": 180.0,
        "height_m": 0.7,
        "elevation_min_deg": -20.0,
        "elevation_max_deg": 20.0,
        "min_range_m": 0.3,
        "max_range_m": 33.0,
    },
    "robot_lines": {
        "azimuth_fov_deg": 180.0,
        "height_m": 0.7,
        "elevation_min_deg": -15.0,
        "elevation_max_deg": 15.0,
        "elevation_step_deg": 2.0,
        "min_range_m": 0.3,
        "max_range_m": 33.0,
    },
}


def scanner_options(name: str, **overrides: Any) -> dict[str, Any]:
    """The :class:`ScannerSetup` fields of the instrument ``name`` in :data:`SCANNER_PRESETS`,
    with ``overrides`` on top (e.g. as ``scanner_options`` of :func:`~.plot.simulate_plot`)."""
    if name not in SCANNER_PRESETS:
        raise ParameterError(f"unknown scanner {name!r}; choose one of {', '.join(SCANNER_PRESETS)}")
    return {**SCANNER_PRESETS[name], **overrides}


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle_rad`` about unit ``axis`` (right-handed)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * kx + (1.0 - math.cos(angle_rad)) * (kx @ kx)


def angular_grid(
    step_deg: float,
    el_min_deg: float,
    el_max_deg: float,
    *,
    azimuth_fov_deg: float = 360.0,
    azimuth_centre_deg: float = 0.0,
    elevation_step_deg: Optional[float] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths ``[0, 360)`` (or those of the sector, see the module docstring) and elevations
    ``el_min..el_max`` (inclusive, every ``elevation_step_deg``, default ``step_deg``) in degrees."""
    if azimuth_fov_deg >= 360.0:
        n_az = int(round(360.0 / step_deg))
        az = np.arange(n_az) * (360.0 / n_az)
    else:
        n_az = max(1, int(round(azimuth_fov_deg / step_deg)))
        width = azimuth_fov_deg / n_az
        az = (azimuth_centre_deg - azimuth_fov_deg / 2.0 + (np.arange(n_az) + 0.5) * width) % 360.0
    el_step = step_deg if elevation_step_deg is None else elevation_step_deg
    n_el = int(math.floor((el_max_deg - el_min_deg) / el_step + 1e-9)) + 1
    el = el_min_deg + np.arange(n_el) * el_step
    return az, el


def directions(az_deg: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    """Unit beam directions (N, 3) in SOCS for paired azimuth/elevation arrays (degrees)."""
    a = np.radians(az_deg)
    e = np.radians(el_deg)
    ce = np.cos(e)
    return np.column_stack([ce * np.cos(a), ce * np.sin(a), np.sin(e)])


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A simulated scan and its truth.

    Attributes
    ----------
    scan : the :class:`~forestreg.engine.core.scan.Scan`: points in SOCS (scanner at the origin),
        16-bit-scale intensity, no prior pose (the truth stays here, not in the scan).
    labels : (N,) uint8 :class:`~.mesh.Material` of each point.
    object_ids : (N,) int32 id of the tree/shrub/liana/target/box each point hit (0 = ground).
    pose : 4x4 float64, SOCS -> scene/world frame: ``p_world = pose @ p_socs``.
    setup : the scanner setup with its resolved yaw.
    """

    scan: Scan
    labels: np.ndarray
    pose: np.ndarray
    setup: Optional[ScannerSetup] = None
    object_ids: Optional[np.ndarray] = None
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.scan.name

    @property
    def position(self) -> np.ndarray:
        """The scanner's optical centre in the world frame."""
        return self.pose[:3, 3].copy()

    def world_points(self) -> np.ndarray:
        """(N, 3) points in the world frame (``pose`` applied)."""
        return apply_transform(self.pose, self.scan.points)

    def to_socs(self, world_xyz: np.ndarray) -> np.ndarray:
        """World-frame points (…, 3) in this scan's SOCS."""
        p = np.asarray(world_xyz, dtype=np.float64)
        return (p - self.pose[:3, 3]) @ self.pose[:3, :3]


def field_of_view_meta(setup: ScannerSetup) -> dict[str, Any]:
    """The sector and elevation lines of a setup that differs from a full-turn scanner on its
    angular grid (empty for a full-turn scanner: its records stay as they were)."""
    out: dict[str, Any] = {}
    if not setup.full_turn:
        out["azimuth_fov_deg"] = float(setup.azimuth_fov_deg)
        out["azimuth_centre_deg"] = float(setup.azimuth_centre_deg)
    if setup.elevation_step_deg is not None:
        out["elevation_step_deg"] = float(setup.elevation_step_deg)
    return out


def scanner_pose(scene: ForestScene, setup: ScannerSetup) -> np.ndarray:
    """4x4 SOCS -> world of a setup with a resolved yaw."""
    z = setup.z if setup.z is not None else float(scene.ground_z(setup.x, setup.y)) + setup.height_m
    pose = np.eye(4)
    pose[:3, :3] = setup.rotation()
    pose[:3, 3] = [setup.x, setup.y, z]
    return pose


def intensity_model(
    material: np.ndarray, cos_incidence: np.ndarray, ranges: np.ndarray, max_range_m: float, rng: np.random.Generator
) -> np.ndarray:
    """Plausible 16-bit-scale intensities (float32, integral values 0-65535)."""
    lut = np.zeros(max(int(m) for m in Material) + 1)
    for m, r in REFLECTANCE.items():
        lut[int(m)] = r
    rho = lut[material]
    target = material == Material.TARGET
    angular = np.where(target, 0.92 + 0.08 * cos_incidence, 0.25 + 0.75 * cos_incidence)
    rng_fall = 1.0 - 0.25 * np.clip(ranges / max_range_m, 0.0, 1.0)
    noise = 1.0 + 0.05 * rng.standard_normal(len(material))
    val = INTENSITY_SCALE * 0.92 * rho * angular * rng_fall * noise
    return np.clip(np.round(val), 0.0, INTENSITY_SCALE).astype(np.float32)


def simulate_tls_scan(
    scene: ForestScene,
    setup: ScannerSetup,
    *,
    seed: int = 0,
    raycaster: Optional[SceneRaycaster] = None,
) -> SimulatedScan:
    """Scan ``scene`` from ``setup``; see the module docstring for frames and models.

    Parameters
    ----------
    scene : the plot.
    setup : scanner position, heading, tilt, angular grid, ranges and noise.
    seed : seeds the yaw (when ``setup.yaw_deg`` is None), the range and intensity noise.
    raycaster : a prebuilt :class:`~.mesh.SceneRaycaster` of ``scene`` (default: built once per
        scene object and cached).

    Raises
    ------
    ScanDataError
        When fewer than 10 beams return (the scanner is in a closed box or a void).
    """
    setup = setup.resolved(seed)
    caster = raycaster if raycaster is not None else raycaster_for(scene)
    pose = scanner_pose(scene, setup)
    rot = pose[:3, :3]
    origin = pose[:3, 3]
    rng = np.random.default_rng([int(seed), 104729])

    az, el = angular_grid(
        setup.angular_step_deg,
        setup.elevation_min_deg,
        setup.elevation_max_deg,
        azimuth_fov_deg=setup.azimuth_fov_deg,
        azimuth_centre_deg=setup.azimuth_centre_deg,
        elevation_step_deg=setup.elevation_step_deg,
    )
    n_el = len(el)
    az_r, el_r = np.radians(az), np.radians(el)
    ca, sa = np.cos(az_r), np.sin(az_r)
    ce, se = np.cos(el_r), np.sin(el_r)
    rot32 = rot.astype(np.float32)
    cols_per_batch = max(1, RAY_BATCH // n_el)
    pts_l, lab_l, obj_l, int_l = [], [], [], []
    n_rays = 0
    n_blocked_near = 0
    for c0 in range(0, len(az), cols_per_batch):
        c1 = min(c0 + cols_per_batch, len(az))
        # beam directions of columns c0..c1 (column-major: azimuth outer, elevation inner)
        d = np.empty((c1 - c0, n_el, 3), dtype=np.float32)
        d[..., 0] = ca[c0:c1, None] * ce[None, :]
        d[..., 1] = sa[c0:c1, None] * ce[None, :]
        d[..., 2] = se[None, :]
        d = d.reshape(-1, 3)
        idx, t, mat, obj, cosi = caster.cast(origin, d @ rot32.T)
        n_rays += len(d)
        near = t < setup.min_range_m
        n_blocked_near += int(near.sum())
        keep = ~near & (t <= setup.max_range_m)
        if not keep.any():
            continue
        idx, r = idx[keep], t[keep]
        if setup.range_noise_m > 0:
            r = r + rng.normal(0.0, setup.range_noise_m, size=len(r))
        # exact (float64) beam directions of the returns
        ia = c0 + idx // n_el
        ie = idx % n_el
        d64 = np.column_stack([ca[ia] * ce[ie], sa[ia] * ce[ie], se[ie]])
        pts_l.append(d64 * r[:, None])
        lab_l.append(mat[keep])
        obj_l.append(obj[keep])
        int_l.append(intensity_model(mat[keep], cosi[keep], r, setup.max_range_m, rng))

    points = np.concatenate(pts_l) if pts_l else np.zeros((0, 3))
    labels = np.concatenate(lab_l) if lab_l else np.zeros(0, dtype=np.uint8)
    objs = np.concatenate(obj_l) if obj_l else np.zeros(0, dtype=np.int32)
    inten = np.concatenate(int_l) if int_l else np.zeros(0, dtype=np.float32)
    meta = {
        "simulated": True,
        "simulator": "forestreg.engine.simulate",
        "preset": scene.preset,
        "scene_seed": scene.seed,
        "seed": int(seed),
        "angular_step_deg": setup.angular_step_deg,
        "elevation_min_deg": setup.elevation_min_deg,
        "elevation_max_deg": setup.elevation_max_deg,
        "min_range_m": setup.min_range_m,
        "max_range_m": setup.max_range_m,
        "range_noise_m": setup.range_noise_m,
        "n_rays": n_rays,
        "n_blocked_near": n_blocked_near,
    }
    meta.update(field_of_view_meta(setup))
    scan = Scan.from_points(points, scanner_position=np.zeros(3), intensity=inten, name=setup.name, meta=meta)
    labels.setflags(write=False)
    objs.setflags(write=False)
    pose.setflags(write=False)
    return SimulatedScan(
        scan=scan,
        labels=labels,
        pose=pose,
        setup=setup,
        object_ids=objs,
        meta={"n_rays": n_rays, "n_points": len(points), "n_blocked_near": n_blocked_near},
    )
