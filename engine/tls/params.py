"""Parameters of System A: the pair registration, the scanner-position estimate and the whole-survey
registration, each one frozen dataclass.

Defaults are the paper's table 2 (Guan et al. 2020) where the paper gives a value; the rest are
ours and documented in the field metadata (``unit``, ``range``, ``help``, ``paper``), which also
builds the GUI's parameter panel and the README's table. Distances in metres, angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.uncertainty import UncertaintyParams
from ..geometry.icp_params import IcpParams
from ..geometry.solution_params import DistinctParams, MarginParams

__all__ = ["PlanParams", "RegistrationParams", "ScannerPositionParams", "SurveyParams"]


@dataclass(frozen=True)
class RegistrationParams(Params):
    """Every setting of marker-free pair registration (System A; defaults: Guan et al. 2020, table 2)."""

    #: the settings once named here, now in ``[registration.icp]``, ``[registration.margin]`` and
    #: ``[registration.distinct]``
    _moved: ClassVar[dict[str, str]] = {
        "icp_voxel_m": "icp.voxel_m",
        "icp_max_distances_m": "icp.max_distances_m",
        "icp_iterations": "icp.iterations",
        "min_match_margin": "margin.min_lead",
        "min_match_margin_fraction": "margin.min_lead_fraction",
        "distinct_rotation_deg": "distinct.rotation_deg",
        "distinct_translation_m": "distinct.translation_m",
    }

    # --- data reduction and ground (paper 2.4, 2.5.1)
    max_range_m: float = _p(
        30.0, "m", 5.0, 200.0, "Points farther than this horizontally from the scanner are dropped", "D_c = 30 m"
    )
    ground_voxel_m: float = _p(
        0.5, "m", 0.1, 2.0, "Voxel size for the lowest-voxel ground points", "voxel size = 0.5 m"
    )
    # --- slicing (paper 2.5.2)
    slice_thickness_m: float = _p(0.2, "m", 0.05, 1.0, "Thickness of each slice layer", "dZ = 0.2 m")
    slice_offsets_m: tuple[float, ...] = _p(
        (0.0,),
        "m",
        -1.0,
        5.0,
        "Heights of the slice layers relative to the scanner height; several for slopes or understory",
        "dh (table 3)",
    )
    fallback_slice_offsets_m: tuple[float, ...] = _p(
        (0.6, 1.2),
        "m",
        -1.0,
        5.0,
        "Slice layers added (above the understory) when no confident match is found at slice_offsets_m; empty = no second try",
    )
    follow_terrain: bool = _p(
        True,
        "",
        None,
        None,
        "Slice at a constant height above the local ground (the scanner's own height above ground + dh) instead of a flat plane: keeps trunks in the slice on slopes. Off = the paper's flat slice",
    )
    # --- angular grid and visual occlusion points
    angular_step_deg: float = _p(
        0.1,
        "deg",
        0.01,
        2.0,
        "Angular resolution of the angular grid and rotation step of the coarse search",
        "I_A = 0.1 deg",
    )
    radial_step_m: float = _p(
        0.1, "m", 0.02, 1.0, "Distance resolution of the angular grid; width of the visibility buffer", "I_D = 0.1 m"
    )
    vop_radius_m: Optional[float] = _p(
        None,
        "m",
        2.0,
        100.0,
        "Radius around the scanner in which VOPs are extracted; empty = choose automatically (tries increasing radii)",
        "D_r (table 3)",
    )
    auto_vop_radii_m: tuple[float, ...] = _p(
        (10.0, 15.0, 20.0, 25.0),
        "m",
        2.0,
        100.0,
        "The radii tried in turn when vop_radius_m is empty (those within 3 m of max_range_m)",
    )
    tilted_partner_vop_radius_m: float = _p(
        10.0,
        "m",
        2.0,
        100.0,
        "VOP radius of the links of a tilted scan whose level partner is not named, tried against every registered level scan (the partner stands at the same spot)",
        "D_r ~ 10 m (sec. 4.3)",
    )
    visibility_gap_m: float = _p(0.5, "m", 0.0, 5.0, "Start of the visibility buffer behind a candidate", "D_e = 0.5 m")
    component_voxel_m: float = _p(
        0.05, "m", 0.01, 0.5, "Voxel size of the connected-component labelling of candidate points"
    )
    min_component_points: int = _p(8, "points", 2, 10000, "Smallest connected component kept as a trunk candidate")
    min_component_height_fraction: float = _p(
        0.5, "1", 0.0, 1.0, "A trunk component spans at least this fraction of the slice thickness vertically"
    )
    max_component_width_m: float = _p(
        2.0, "m", 0.1, 10.0, "Components wider than this (walls, rocks, dense bushes) are not trunks"
    )
    mean_shift_bandwidth_m: float = _p(
        0.1, "m", 0.01, 1.0, "Flat-kernel radius of the mean shift that finds a component's density mode"
    )
    centre_on_trunk_axis: bool = _p(
        True,
        "",
        None,
        None,
        "Move each VOP from the visible bark to the estimated trunk axis (half the arc width behind it along the ray), so VOPs of one trunk from two scans coincide. Off = the paper's density mode",
    )
    # --- horizontal coarse registration (paper 2.5.3)
    match_distance_m: float = _p(0.2, "m", 0.01, 2.0, "Match distance threshold of the overlap score", "D_t = 0.2 m")
    # --- evidence
    min_vops: int = _p(4, "VOPs", 3, 1000, "Fewest VOPs per scan to attempt a registration")
    min_matched: int = _p(
        4, "VOPs", 3, 1000, "Fewest matched VOPs for a registration to count (the paper sees failures below 3)"
    )
    #: the lead of the best solution over the best distinct alternative
    margin: MarginParams = MarginParams()
    #: when an alternative is a distinct solution (the VOP centroid's displacement)
    distinct: DistinctParams = DistinctParams()
    max_free_space_violation: float = _p(
        0.15,
        "1",
        0.0,
        1.0,
        "Largest fraction of one scan's slice points allowed where the other scanner saw empty space, after ICP (a wrong match puts trunks there)",
    )
    free_space_bin_deg: float = _p(
        0.5, "deg", 0.05, 10.0, "A scanner saw empty space up to its first return in each azimuth bin of this width..."
    )
    free_space_margin_m: float = _p(
        0.5, "m", 0.0, 5.0, "...and the other scan's points count as inside it when at least this much nearer"
    )
    free_space_near_m: float = _p(2.0, "m", 0.0, 50.0, "Points nearer to the scanner than this are not tested")
    free_space_reach_m: float = _p(15.0, "m", 1.0, 200.0, "...nor those farther than this")
    # --- levelling of tilted scans
    level_tilted: bool = _p(
        True,
        "",
        None,
        None,
        "Detect a tilted scanner from its own data (ground and trunk directions) and level the scan before slicing",
    )
    tilt_threshold_deg: float = _p(
        10.0,
        "deg",
        0.1,
        45.0,
        "Estimated tilts below this are treated as a level scanner (small tilts are taken up by the ground fit and ICP)",
    )
    level_voxel_m: float = _p(
        0.1, "m", 0.02, 1.0, "The scan's vertical is estimated from the normals of one point per voxel of this size"
    )
    level_radius_m: float = _p(15.0, "m", 2.0, 100.0, "...of the points within this distance of the scanner")
    # --- fine registration (ICP, paper 2.6)
    icp: IcpParams = IcpParams()
    icp_min_fitness: float = _p(
        0.1,
        "1",
        0.0,
        1.0,
        "Least fraction of the moving points in the shared area that must have a reference point within the last ICP distance",
    )
    icp_max_correction_m: float = _p(
        1.0,
        "m",
        0.0,
        10.0,
        "ICP may move the coarse result by at most this much (more means the coarse result was wrong)",
    )
    # --- the stated uncertainty (trunks matched after ICP)
    #: the ICP voxel grid and the VOP step: no registration is stated better than this
    min_uncertainty_m: float = _p(
        0.002, "m", 0.0, 1.0, "Floor of a pair's stated 1-sigma translation uncertainty (and of its vertical part)"
    )
    min_uncertainty_deg: float = _p(0.005, "deg", 0.0, 10.0, "Floor of a pair's stated 1-sigma rotation uncertainty")
    #: how the stated uncertainty counts the fit's precision, weak directions and alternatives,
    #: and the widest it may be for an "ok"
    uncertainty: UncertaintyParams = UncertaintyParams()
    # --- registration from targets (manual method, paper 2.7)
    manual_max_target_rmse_m: float = _p(
        0.10,
        "m",
        0.001,
        10.0,
        "Largest RMS residual of the target fit (more: target ids mixed up or targets mis-picked); also the inlier distance that finds the suspect targets",
    )
    manual_max_icp_rotation_deg: float = _p(
        5.0,
        "deg",
        0.01,
        180.0,
        "ICP may turn the target fit by at most this much (more: the targets and the clouds disagree)",
    )
    manual_min_target_spread_m: float = _p(
        0.02,
        "m",
        0.0,
        10.0,
        "Shared targets closer than this (RMS) to one straight line are refused: they leave the rotation about it undetermined",
    )

    def _check(self) -> None:
        self.icp.check_within("registration.icp", voxel_m=(0.01, 0.5), distances_m=(0.005, 5.0), iterations=(1, 1000))
        if self.free_space_near_m >= self.free_space_reach_m:
            raise ParameterError(
                f"free_space_near_m ({self.free_space_near_m} m) must be smaller than free_space_reach_m "
                f"({self.free_space_reach_m} m): otherwise no point is tested for the free-space check"
            )
        for name in ("slice_offsets_m", "auto_vop_radii_m"):
            if not getattr(self, name):
                raise ParameterError(f"{name}: needs at least one value")
        if self.vop_radius_m is not None and self.vop_radius_m >= self.max_range_m:
            raise ParameterError(
                f"vop_radius_m ({self.vop_radius_m} m) must be smaller than max_range_m ({self.max_range_m} m): "
                "the visibility check needs points beyond the VOP radius"
            )
        steps = 360.0 / self.angular_step_deg
        if abs(steps - round(steps)) > 1e-6:
            raise ParameterError(f"angular_step_deg = {self.angular_step_deg} must divide 360")


@dataclass(frozen=True)
class ScannerPositionParams(Params):
    """Settings of the scanner-position estimate (metres)."""

    cell_m: float = _p(0.25, unit="m", lo=0.05, hi=2.0, help="grid cell of the density map")
    smooth_m: float = _p(
        1.5,
        unit="m",
        lo=0.2,
        hi=10.0,
        help="Gaussian smoothing of the density map (wider than the blind circle under the scanner)",
    )
    disc_m: float = _p(
        4.0, unit="m", lo=1.0, hi=15.0, help="radius of the mean shift over near-ground points around the peak"
    )
    ground_band_m: float = _p(
        0.3,
        unit="m",
        lo=0.05,
        hi=2.0,
        help="points within this height of the lowest in their 0.5 m cell count as ground",
    )
    near_m: float = _p(
        3.0, unit="m", lo=0.5, hi=10.0, help="radius of the disc whose point count tests a candidate position"
    )
    min_peak_ratio: float = _p(
        3.0,
        unit="1",
        lo=1.0,
        hi=100.0,
        help="the disc at the scanner must hold this many times the points of an average occupied disc",
    )
    max_second_ratio: float = _p(
        0.6,
        unit="1",
        lo=0.1,
        hi=1.0,
        help="a second density peak this strong (6 m or more away) means several scanners: refused",
    )
    default_height_m: float = _p(
        1.5, unit="m", lo=0.1, hi=5.0, help="instrument height used when the ground profile does not give one"
    )
    origin_keep_distance_m: float = _p(
        1.0,
        unit="m",
        lo=0.0,
        hi=10.0,
        help="an estimate this close to the file origin confirms the origin (kept exactly)",
    )


@dataclass(frozen=True)
class SurveyParams(Params):
    """Settings of a whole-survey registration."""

    pairs: str = _p(
        "within",
        help="which extra pairs to register: 'within' (scanners within max_distance_m), 'all', or 'centre' (none)",
    )
    max_distance_m: float = _p(25.0, unit="m", lo=1.0, hi=1000.0, help="scanners within this distance are paired")
    closure_sigmas: float = _p(
        4.0, unit="sigma", lo=1.0, hi=100.0, help="a loop of links must close within this many stated sigmas"
    )
    prior_position_tolerance_m: float = _p(
        6.0,
        unit="m",
        lo=0.0,
        hi=1000.0,
        help="how far each scan's prior position (GNSS, georeferenced file) may be off",
    )
    prior_heading_tolerance_deg: float = _p(
        35.0, unit="deg", lo=0.0, hi=180.0, help="how far each scan's prior heading (compass) may be off"
    )
    fixed: tuple[str, ...] = _p((), help="scans held at their prior poses (besides the frame scan)")
    min_closure_m: float = _p(
        0.03,
        unit="m",
        lo=0.0,
        hi=10.0,
        help="a loop closes within at least this translation, whatever its stated sigmas (they have floors too)",
    )
    min_closure_deg: float = _p(
        0.1, unit="deg", lo=0.0, hi=10.0, help="a loop closes within at least this rotation, whatever its stated sigmas"
    )

    def _check(self) -> None:
        if self.pairs not in ("within", "all", "centre"):
            raise ParameterError(f"pairs must be 'within', 'all' or 'centre', not {self.pairs!r}")


@dataclass(frozen=True)
class PlanParams(Params):
    """Settings of the next-scan planner (``forestreg plan``): where a scan would link to the
    placed scans and see the most stem surface not yet seen (plan frame: the centre scan's file
    coordinates seen from above, metres)."""

    radius_m: Optional[float] = _p(
        None,
        "m",
        2.0,
        500.0,
        "Plot radius around the centre scan's scanner within which stems and ground count and scans are suggested; empty = from the ground the placed scans saw",
    )
    grid_m: float = _p(1.0, "m", 0.1, 10.0, "Spacing of the candidate scanner positions")
    clearance_m: float = _p(
        0.6,
        "m",
        0.0,
        5.0,
        "A suggested scanner stands at least this far from the bark of every mapped stem and from whatever a placed scan saw at the slice height (shrubs, rocks)",
    )
    min_shared_stems: int = _p(
        10,
        "stems",
        3,
        1000,
        "Trunk shadows a suggested scan must be expected to share with a placed scan within one registration radius D_r (predicted from the stem map, falling off with distance as the placed links bore the map out); the pair needs min_matched and a lead over a chance match, the rest is a margin",
    )
    stem_band_m: float = _p(
        2.0, "m", 0.1, 20.0, "Height of the band of bark counted as stem area (stem area = arc length x this height)"
    )
    arc_bins: int = _p(36, "bins", 8, 360, "Each stem's circumference is followed in this many arcs")
    patch_m: float = _p(
        0.5,
        "m",
        0.05,
        5.0,
        "A patch of bark (one arc, this tall) counts as seen once a scan put a point on it: the chance is 1 - exp(-n) for the n points the scan's angular step puts there",
    )
    merge_m: float = _p(0.4, "m", 0.05, 2.0, "Trunk shadows of different scans within this distance are one stem")
    azimuth_step_deg: float = _p(0.25, "deg", 0.01, 5.0, "Angular step of the occlusion map of a scanner position")
    ground_cell_m: float = _p(
        1.0,
        "m",
        0.1,
        10.0,
        "Cell of the grid of the plot's ground: seen (a placed scan has ground points in it) or in view of a scanner position",
    )
    min_visible_fraction: float = _p(
        0.5,
        "1",
        0.0,
        1.0,
        "A stem casts a trunk shadow from a position when at least this fraction of its width is not hidden by nearer stems",
    )
