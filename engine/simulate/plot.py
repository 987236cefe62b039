"""Simulate a whole multi-scan TLS plot: scene, scans and the ground truth, in memory
(:func:`forestreg.engine.io.simulated.write_simulated_plot` writes the files and ``truth.json``).

Truth (``SimulatedPlot.truth``, ``truth.json``)
-----------------------------------------------
A JSON-able dict::

    {
      "format": "forestreg-simulated-plot", "version": 1,
      "preset", "seed", "size_m", "angular_step_deg", "scene_overrides",
      "conventions": {...},                        # frames in words
      "scene": {n_trees, stems_per_ha, slope_deg, ...},
      "scans": [{"name", "file", "index", "position": [x, y, z] (optical centre, world),
                 "yaw_deg", "tilt_deg", "tilt_azimuth_deg", "seed", "n_points",
                 "matrix": 4x4 SOCS -> world (p_world = matrix @ p_socs),
                 "targets_socs": [{"id", "x", "y", "z", "n_points"}]}],  # n_points: reflector hits
      "trees": [{"id", "x", "y", "z", "dbh_m", "height_m", "lean_deg", "lean_azimuth_deg",
                 "crown_base_m", "crown_radius_m", "shape", "breast_height_xyz"}],
      "targets": [{"id", "x", "y", "z", "ground_z", "radius_m"}],
      "posts": [{"id", "x", "y", "z", "radius_m", "height_m", "kind"}],    # built scenes only
      "walls": [{"id", "x", "y", "z", "size", "yaw_deg", "kind"}],         # built scenes only
    }

A scan whose scanner sees less than the full turn also records ``azimuth_fov_deg`` and
``azimuth_centre_deg`` (SOCS), and one with its own elevation spacing ``elevation_step_deg``.

World = the scene frame (plot centred on the origin, z up). The true registration of a moving
scan onto a reference scan is ``relative_pose(truth, reference, moving)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import numpy as np

from ..core.errors import ParameterError, UnknownNameError
from ..core.jsonable import to_jsonable
from .mesh import Material, raycaster_for
from .scanner import ScannerSetup, SimulatedScan, field_of_view_meta, simulate_tls_scan
from .scene import BREAST_HEIGHT_M, FIXED_BOX_KINDS, ForestScene, given_or_made_scene

ProgressCallback = Callable[[float, str], None]


@dataclass(frozen=True, eq=False)
class SimulatedPlot:
    """A simulated plot: the scene, its scans (in order) and the truth dict; ``out_dir`` and
    ``files`` once :func:`~forestreg.engine.io.simulated.write_simulated_plot` wrote it."""

    scene: ForestScene
    scans: tuple[SimulatedScan, ...]
    truth: dict[str, Any]
    out_dir: Optional[Path] = None
    files: tuple[Path, ...] = ()
    meta: Mapping[str, Any] = field(default_factory=dict)

    def scan(self, name_or_index: Union[str, int]) -> SimulatedScan:
        """A scan by name (``"scan_01"``) or 0-based index."""
        if isinstance(name_or_index, (int, np.integer)):
            return self.scans[int(name_or_index)]
        for s in self.scans:
            if s.name == name_or_index:
                return s
        raise UnknownNameError(f"no scan named {name_or_index!r}; scans are {[s.name for s in self.scans]}")

    def relative_pose(self, reference: Union[str, int], moving: Union[str, int]) -> np.ndarray:
        return relative_pose(self, reference, moving)


def _scan_name(i: int) -> str:
    return f"scan_{i + 1:02d}"


def scan_seed(seed: int, index: int) -> int:
    """The seed of scan ``index`` of a plot simulated with ``seed``."""
    return int(np.random.SeedSequence([int(seed), 31337, int(index)]).generate_state(1)[0])


def simulate_plot(
    preset: str,
    positions: Sequence[Sequence[float]],
    *,
    seed: int = 0,
    angular_step_deg: float = 0.2,
    tilted: Optional[Mapping[int, Union[float, Sequence[float]]]] = None,
    size_m: float = 60.0,
    progress: Optional[ProgressCallback] = None,
    yaw_deg: Optional[Sequence[Optional[float]]] = None,
    clearance_m: float = 1.0,
    scanner_options: Optional[Mapping[str, Any]] = None,
    scene: Optional[ForestScene] = None,
    **scene_overrides: Any,
) -> SimulatedPlot:
    """Simulate TLS scans of a plot from several positions.

    Parameters
    ----------
    preset : scene preset (see :data:`~.scene.PRESETS` and the built scenes of
        :data:`~.built.BUILT_PRESETS`).
    positions : (x, y) scanner positions in the scene frame (plot centred on the origin); the
        same (x, y) twice is fine (e.g. a level and a tilted scan at one spot).
    seed : seeds the scene and every scan (yaw, noise); the same arguments give the same plot.
    angular_step_deg : the scanner's angular resolution.
    tilted : maps a position index (0-based) to a tilt in degrees, or to a pair
        ``(tilt_deg, tilt_azimuth_deg)``; without an azimuth one is drawn from the seed.
    size_m : plot side (m).
    progress : optional ``progress(fraction, message)`` callback.
    yaw_deg : optional heading per position (None entries drawn from the seed).
    clearance_m : objects standing within this distance of a scanner position are removed from
        the scene first (an operator sets up in a gap); 0 keeps everything.
    scanner_options : extra :class:`~.scanner.ScannerSetup` fields for every scan
        (``height_m``, ``elevation_min_deg``, ``max_range_m``, ``range_noise_m``,
        ``azimuth_fov_deg``, ...; an instrument's: :func:`~.scanner.scanner_options`).
    scene : use this scene instead of drawing one from the preset (then ``preset`` is only a
        label and ``scene_overrides`` must be empty).
    scene_overrides : :class:`~.scene.PresetConfig` fields, e.g. ``slope_deg=18``.
    """
    report = progress or (lambda f, m: None)
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) == 0:
        raise ParameterError(f"positions must be a list of (x, y) pairs, got shape {pos.shape}")
    tilted = dict(tilted or {})
    for k in tilted:
        if not (0 <= int(k) < len(pos)):
            raise ParameterError(f"tilted refers to position {k}, but there are {len(pos)} positions")
    if yaw_deg is not None and len(yaw_deg) != len(pos):
        raise ParameterError(f"{len(yaw_deg)} yaw angles for {len(pos)} positions")
    options = dict(scanner_options or {})
    bad = set(options) & {"x", "y", "yaw_deg", "tilt_deg", "tilt_azimuth_deg", "angular_step_deg", "name"}
    if bad:
        raise ParameterError(f"scanner_options cannot set {', '.join(sorted(bad))}; use the dedicated arguments")

    report(0.0, "building the scene")
    scene = given_or_made_scene(scene, preset, seed, size_m, scene_overrides)
    xmin, xmax, ymin, ymax = scene.extent
    outside = (pos[:, 0] <= xmin) | (pos[:, 0] >= xmax) | (pos[:, 1] <= ymin) | (pos[:, 1] >= ymax)
    if outside.any():
        raise ParameterError(
            f"scanner position(s) {np.flatnonzero(outside).tolist()} lie outside the plot "
            f"{scene.extent}; the plot is centred on the origin"
        )
    if clearance_m > 0:
        scene = scene.cleared(pos, clearance_m)
    report(0.03, "building meshes and ray-casting structure")
    caster = raycaster_for(scene)

    scans: list[SimulatedScan] = []
    truth_scans: list[dict[str, Any]] = []
    n = len(pos)
    for i in range(n):
        name = _scan_name(i)
        s_seed = scan_seed(seed, i)
        srng = np.random.default_rng([s_seed, 5])
        tilt, tilt_az = 0.0, 0.0
        if i in tilted:
            tv = tilted[i]
            if isinstance(tv, (tuple, list, np.ndarray)):
                tilt, tilt_az = float(tv[0]), float(tv[1])
            else:
                tilt, tilt_az = float(tv), float(srng.uniform(0.0, 360.0))
        setup = ScannerSetup(
            x=float(pos[i, 0]),
            y=float(pos[i, 1]),
            yaw_deg=None if yaw_deg is None or yaw_deg[i] is None else float(yaw_deg[i]),
            tilt_deg=tilt,
            tilt_azimuth_deg=tilt_az,
            angular_step_deg=angular_step_deg,
            name=name,
            **options,
        )
        frac0 = 0.05 + 0.9 * i / n
        report(frac0, f"scanning {name} ({i + 1}/{n})")
        sim = simulate_tls_scan(scene, setup, seed=s_seed, raycaster=caster)
        scans.append(sim)
        truth_scans.append(_scan_truth(scene, sim, i, s_seed))

    truth = {
        "format": "forestreg-simulated-plot",
        "version": 1,
        "preset": scene.preset if scene is not None else preset,
        "seed": int(seed),
        "size_m": float(scene.extent[1] - scene.extent[0]),
        "angular_step_deg": float(angular_step_deg),
        "scene_overrides": to_jsonable(scene_overrides, nan_as_null=True),
        "clearance_m": float(clearance_m),
        "conventions": {
            "world": "scene frame: plot centred on the origin, x east, y north, z up, metres",
            "matrix": "4x4 SOCS -> world: p_world = matrix @ p_socs (homogeneous column vectors)",
            "relative": "true registration of moving onto reference: "
            "T = inv(matrix_reference) @ matrix_moving, p_reference = T @ p_moving",
            "angles": "degrees; azimuths counter-clockwise from +x",
        },
        "scene": to_jsonable(scene.summary(), nan_as_null=True),
        "scans": truth_scans,
        "trees": [_tree_truth(t) for t in scene.trees],
        "targets": [
            {"id": t.id, "x": t.x, "y": t.y, "z": t.z, "ground_z": t.ground_z, "radius_m": t.radius_m}
            for t in scene.targets
        ],
        "materials": {m.name.lower(): int(m) for m in Material},
    }
    truth.update(_built_truth(scene))
    report(1.0, "done")
    return SimulatedPlot(
        scene=scene,
        scans=tuple(scans),
        truth=truth,
        meta={"n_triangles": caster.mesh.n_triangles, "triangles": caster.mesh.counts()},
    )


def _scan_truth(scene: ForestScene, sim: SimulatedScan, index: int, s_seed: int) -> dict[str, Any]:
    setup = sim.setup
    assert setup is not None
    targets = []
    labels = sim.labels
    objs = sim.object_ids
    for t in scene.targets:
        c = sim.to_socs(t.centre)
        n_hits = int(((labels == Material.TARGET) & (objs == t.id)).sum()) if objs is not None else 0
        targets.append({"id": t.id, "x": float(c[0]), "y": float(c[1]), "z": float(c[2]), "n_points": n_hits})
    return {
        "name": sim.name,
        "file": None,
        "index": index,
        "position": [float(v) for v in sim.pose[:3, 3]],
        "yaw_deg": float(setup.yaw_deg or 0.0),
        "tilt_deg": float(setup.tilt_deg),
        "tilt_azimuth_deg": float(setup.tilt_azimuth_deg),
        "height_m": float(setup.height_m),
        "seed": int(s_seed),
        "n_points": int(len(sim.scan)),
        "matrix": [[float(v) for v in row] for row in sim.pose],
        "targets_socs": targets,
        **field_of_view_meta(setup),
    }


def _built_truth(scene: ForestScene) -> dict[str, Any]:
    """The posts and the walls/blocks of a built scene (nothing for a forest scene)."""
    out: dict[str, Any] = {}
    if scene.posts:
        out["posts"] = [
            {"id": p.id, "x": p.x, "y": p.y, "z": p.z, "radius_m": p.radius_m, "height_m": p.height_m, "kind": p.kind}
            for p in scene.posts
        ]
    walls = [b for b in scene.boxes if b.kind in FIXED_BOX_KINDS]
    if walls:
        out["walls"] = [
            {"id": b.id, "x": b.x, "y": b.y, "z": b.z, "size": list(b.size), "yaw_deg": b.yaw_deg, "kind": b.kind}
            for b in walls
        ]
    return out


def _tree_truth(t: Any) -> dict[str, Any]:
    bh = t.point_at(BREAST_HEIGHT_M)
    return {
        "id": t.id,
        "x": t.x,
        "y": t.y,
        "z": t.z,
        "dbh_m": t.dbh_m,
        "height_m": t.height_m,
        "lean_deg": t.lean_deg,
        "lean_azimuth_deg": t.lean_azimuth_deg,
        "crown_base_m": t.crown_base_m,
        "crown_radius_m": t.crown_radius_m,
        "shape": t.shape,
        "breast_height_xyz": [float(v) for v in bh],
    }


def _matrices(truth_or_plot: Any) -> dict[str, np.ndarray]:
    if isinstance(truth_or_plot, SimulatedPlot):
        return {s.name: np.asarray(s.pose, dtype=np.float64) for s in truth_or_plot.scans}
    if isinstance(truth_or_plot, (str, Path)):
        truth_or_plot = json.loads(Path(truth_or_plot).read_text(encoding="utf-8"))
    if isinstance(truth_or_plot, Mapping) and "scans" in truth_or_plot:
        return {s["name"]: np.asarray(s["matrix"], dtype=np.float64) for s in truth_or_plot["scans"]}
    raise ParameterError("relative_pose needs a SimulatedPlot, a truth dict or the path of a truth.json")


def relative_pose(truth_or_plot: Any, reference_name: Union[str, int], moving_name: Union[str, int]) -> np.ndarray:
    """The true 4x4 ``T`` with ``p_reference = T @ p_moving`` (SOCS to SOCS).

    ``truth_or_plot``: a :class:`SimulatedPlot`, its truth dict, or the path of a ``truth.json``.
    Scans are named (``"scan_01"``) or given by 0-based index.
    """
    mats = _matrices(truth_or_plot)
    names = list(mats)

    def get(key: Union[str, int]) -> np.ndarray:
        if isinstance(key, (int, np.integer)):
            return mats[names[int(key)]]
        if key not in mats:
            raise UnknownNameError(f"no scan named {key!r}; scans are {names}")
        return mats[key]

    ref = get(reference_name)
    mov = get(moving_name)
    return np.linalg.solve(ref, mov)
