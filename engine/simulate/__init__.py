"""Forest plot and TLS scan simulator: the test bed, the demo data and a scan-layout planner.

* :func:`make_scene` draws a synthetic plot (:class:`ForestScene`) from a preset in
  :data:`PRESETS`: ``planted_conifer``, ``mixed_temperate``, ``rainforest``, ``sloped``,
  ``open_field``;
* :func:`simulate_tls_scan` casts the rays of one :class:`ScannerSetup` (Open3D ray casting) and
  returns a :class:`SimulatedScan`: the :class:`~forestreg.engine.core.scan.Scan` in the scanner's own
  frame, per-point material labels and the true pose (``p_world = pose @ p_socs``);
* :func:`simulate_plot` scans a plot from several positions, optionally writes LAZ files and
  ``truth.json``; :func:`relative_pose` gives the true ``T`` (``p_reference = T @ p_moving``);
* :func:`simulate_scan_from_cloud` simulates a scan from a real merged cloud (paper section 4.3).

Example::

    from forestreg.engine.simulate import simulate_plot, relative_pose
    plot = simulate_plot("planted_conifer", [(0, 0), (10, 0)], seed=1, out_dir="demo")
    T_true = relative_pose(plot, "scan_01", "scan_02")
"""

from .from_cloud import estimate_point_spacing, simulate_scan_from_cloud
from .mesh import Material, SceneMesh, SceneRaycaster, build_scene_mesh, raycaster_for
from .platforms import (
    BackpackSetup,
    CoregistrationCase,
    SimulatedCloud,
    UavSetup,
    backpack_path,
    canopy_point_density,
    simulate_backpack_scan,
    simulate_coregistration_case,
    simulate_uav_scan,
    uav_flight_lines,
)
from .plot import SimulatedPlot, relative_pose, simulate_plot
from .scanner import ScannerSetup, SimulatedScan, simulate_tls_scan
from .scene import (
    Box,
    ForestScene,
    Liana,
    PRESETS,
    PresetConfig,
    Shrub,
    Target,
    Terrain,
    Tree,
    make_scene,
    make_terrain,
)

__all__ = [
    "BackpackSetup",
    "Box",
    "CoregistrationCase",
    "ForestScene",
    "Liana",
    "Material",
    "PRESETS",
    "PresetConfig",
    "SceneMesh",
    "SceneRaycaster",
    "ScannerSetup",
    "SimulatedCloud",
    "Shrub",
    "SimulatedPlot",
    "SimulatedScan",
    "Target",
    "Terrain",
    "Tree",
    "UavSetup",
    "backpack_path",
    "build_scene_mesh",
    "canopy_point_density",
    "estimate_point_spacing",
    "make_scene",
    "make_terrain",
    "raycaster_for",
    "relative_pose",
    "simulate_backpack_scan",
    "simulate_coregistration_case",
    "simulate_plot",
    "simulate_scan_from_cloud",
    "simulate_tls_scan",
    "simulate_uav_scan",
    "uav_flight_lines",
]
