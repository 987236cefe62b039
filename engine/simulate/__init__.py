"""Forest plot and TLS scan simulator: the test bed, the demo data and a scan-layout planner.

* :func:`make_scene` draws a synthetic plot (:class:`ForestScene`) from a preset in
  :data:`PRESETS`: ``planted_conifer``, ``mixed_temperate``, ``rainforest``, ``sloped``,
  ``plantation_rows``, ``open_field``; round stems, or with ``stem_shapes="real"`` oval stems with
  bark relief and buttresses (:func:`with_stem_shapes`, :class:`Tree`);
* :func:`make_built_scene` (also through :func:`make_scene`) draws built scenes of
  :data:`BUILT_PRESETS`: ``corridor``, ``colonnade``, ``fence``, ``courtyard``, ``park``,
  ``campus`` (walls, posts in rows, few trees);
* :func:`simulate_tls_scan` casts the rays of one :class:`ScannerSetup` (Open3D ray casting) and
  returns a :class:`SimulatedScan`: the :class:`~forestreg.engine.core.scan.Scan` in the scanner's own
  frame, per-point material labels and the true pose (``p_world = pose @ p_socs``); a scanner may
  see a sector only (``ScannerSetup.azimuth_fov_deg``; instruments in :data:`SCANNER_PRESETS`);
* :func:`simulate_plot` scans a plot from several positions (in memory: the package writes no
  file; :func:`forestreg.engine.io.simulated.write_simulated_plot` writes the LAZ files and
  ``truth.json``); :func:`relative_pose` gives the true ``T`` (``p_reference = T @ p_moving``);
* :func:`simulate_scan_from_cloud` simulates a scan from a real merged cloud (paper section 4.3);
* :mod:`.wood` and :mod:`.branched_stand` grow trees as branching skeletons with leaves on the
  twigs (no crown shape filled): single broadleaves with known wood, and mixed stands with
  suppressed trees under dominant crowns, scanned full-dome (another crown model to check the
  tree rules on).

Example::

    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot, relative_pose
    plot = write_simulated_plot(simulate_plot("planted_conifer", [(0, 0), (10, 0)], seed=1), "demo")
    T_true = relative_pose(plot, "scan_01", "scan_02")
"""

from .built import BUILT_PRESETS, BuiltConfig, make_built_scene, stand_positions
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
from .scanner import SCANNER_PRESETS, ScannerSetup, SimulatedScan, scanner_options, simulate_tls_scan
from .scene import (
    PRESETS,
    STEM_SHAPES,
    Box,
    ForestScene,
    Liana,
    Post,
    PresetConfig,
    Shrub,
    Target,
    Terrain,
    Tree,
    make_scene,
    make_terrain,
    preset_names,
    with_stem_shapes,
)

__all__ = [
    "BUILT_PRESETS",
    "BackpackSetup",
    "Box",
    "BuiltConfig",
    "CoregistrationCase",
    "ForestScene",
    "Liana",
    "Material",
    "PRESETS",
    "Post",
    "PresetConfig",
    "SCANNER_PRESETS",
    "STEM_SHAPES",
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
    "make_built_scene",
    "make_scene",
    "make_terrain",
    "preset_names",
    "raycaster_for",
    "relative_pose",
    "scanner_options",
    "simulate_backpack_scan",
    "simulate_coregistration_case",
    "simulate_plot",
    "simulate_scan_from_cloud",
    "simulate_tls_scan",
    "simulate_uav_scan",
    "stand_positions",
    "uav_flight_lines",
    "with_stem_shapes",
]
