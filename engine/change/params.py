"""Parameters of the change detection between two surveys of one plot (``[change]``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.uncertainty import UncertaintyParams
from ..geometry.icp_params import IcpParams
from ..geometry.solution_params import DistinctParams, MarginParams
from .growth import GrowthParams

__all__ = ["ChangeParams"]


@dataclass(frozen=True)
class ChangeParams(Params):
    """Settings of the re-survey registration (persisting stems, then stem slices and terrain) and
    of the tree matching. Distances in metres, angles in degrees. The trees of each survey are
    measured with the ``[trees]`` parameters."""

    #: the settings once named here, now in ``[change.stem_icp]`` and ``[change.margin]``
    _moved: ClassVar[dict[str, str]] = {
        "icp_voxel_m": "stem_icp.voxel_m",
        "icp_max_distances_m": "stem_icp.max_distances_m",
        "icp_iterations": "stem_icp.iterations",
        "min_match_margin": "margin.min_lead",
        "min_match_margin_fraction": "margin.min_lead_fraction",
    }

    # --- stems that persist: the coarse match from any heading
    match_distance_m: float = _p(
        0.3,
        "m",
        0.02,
        2.0,
        "Stems of the two surveys closer than this after the coarse match are taken as one stem (the coarse matcher's D_t)",
    )
    angle_step_deg: float = _p(0.1, "deg", 0.01, 5.0, "Rotation step of the coarse search over every heading")
    dbh_change_range_m: tuple[float, float] = _p(
        (-0.03, 0.12),
        "m",
        -1.0,
        1.0,
        "Plausible DBH change (after minus before) of a persisting stem; a pair outside is not one stem",
    )
    min_persisting: int = _p(
        6, "stems", 3, 10000, "Fewest persisting stems (matched, DBH-consistent) to register the surveys"
    )
    min_persisting_fraction: float = _p(
        0.25, "1", 0.0, 1.0, "...and at least this fraction of the smaller survey's stems (unrelated plots match few)"
    )
    #: when another heading and shift is a distinct solution, and the best one's lead over it
    distinct: DistinctParams = DistinctParams()
    margin: MarginParams = MarginParams(min_lead=3, min_lead_fraction=0.25)
    #: how the stated uncertainty counts the distinct solutions, and the widest it may be
    uncertainty: UncertaintyParams = UncertaintyParams()
    # --- refinement on stem slices and terrain (not crowns)
    icp: bool = _p(
        True,
        "",
        None,
        None,
        "Refine on the persisting stems' slices and the terrain (clouds only; tables are registered on stem positions)",
    )
    #: the ICP of that refinement (the stem slices thinned to 2 cm)
    stem_icp: IcpParams = IcpParams(
        voxel_m=0.02, max_distances_m=(0.25, 0.1, 0.05), iterations=30, max_moving_points=40000
    )
    slice_heights_m: tuple[float, float] = _p(
        (0.5, 3.0), "m", 0.0, 10.0, "Heights above the ground of the stem slices used by the refinement"
    )
    max_icp_correction_m: float = _p(
        0.3,
        "m",
        0.01,
        5.0,
        "The refinement may move the stem solution by at most this much (more: it slid on the terrain)",
    )
    # --- trees matched across the surveys
    tree_match_distance_m: float = _p(
        0.5, "m", 0.05, 5.0, "Trees of the two surveys closer than this after the registration are one tree"
    )
    presence_points: int = _p(
        25,
        "points",
        1,
        100000,
        "Points of the other survey on a stem (1-2.5 m above the ground, within its radius + 5 cm) that show the stem is still (or already) there",
    )
    partial_presence_points: int = _p(
        8,
        "points",
        1,
        100000,
        "Fewer points than presence_points but at least this many on the stem's surface (within 3 cm of its circle, in two or more 20 deg sectors): the stem was partly seen (occluded) in the other survey, not absent",
    )
    max_new_dbh_m: float = _p(
        0.2,
        "m",
        0.01,
        5.0,
        "A stem of the later survey alone thicker than this is not taken as new (a tree grown in since is thin): where the earlier survey shows no stem, its place was occluded there",
    )
    min_new_bound_pairs: int = _p(
        10,
        "trees",
        0,
        100000,
        "With at least this many stems measured in both surveys, a tree grown in may be no thicker than the earlier survey's thin stems (5th percentile of its DBH) plus what its persisting trees grew at most (95th percentile of their DBH differences), where that is below max_new_dbh_m; thicker: its place was occluded, persisting (0 = max_new_dbh_m alone)",
    )
    removed_place_points: int = _p(
        2,
        "points",
        0,
        100000,
        "A tree of the earlier survey is removed only where the later survey (with ground) has at least this many returns (stem band or ground) within its radius + removed_place_margin_m of where it stood: the empty place seen; fewer, its place was hidden there (occluded) and it is not compared (status outside)",
    )
    removed_place_margin_m: float = _p(
        0.3, "m", 0.0, 5.0, "How far beyond a stem's radius the returns that show its place empty are counted"
    )
    coverage_radius_m: float = _p(
        1.5,
        "m",
        0.1,
        20.0,
        "A tree of the later survey is outside the earlier one when that survey has no point within this distance of it (never a new tree where the earlier survey was blind)",
    )
    #: how a persisting stem's diameter growth is measured from the sectors both surveys saw
    growth: GrowthParams = GrowthParams()
    max_dbh_change_sigma_m: float = _p(
        0.01,
        "m",
        0.001,
        1.0,
        "A DBH change whose 1-sigma uncertainty exceeds this is withheld (flagged): too uncertain to tell growth",
    )
    height_outlier_m: float = _p(
        1.5,
        "m",
        0.1,
        50.0,
        "A height change farther than this (and 3 robust sigma) from the median change of the persisting trees is withheld (flagged): a top unseen in one survey, not growth",
    )
    max_dbh_decrease_sigma: float = _p(
        3.0, "sigma", 0.0, 100.0, "A DBH that shrank by more than this many sigma is flagged"
    )
    # --- each survey's trees and their uncertainties
    #: simulated stands: a high-trust height is within 0.3 m of the truth for most trees
    height_sigma_m: tuple[float, float, float] = _p(
        (0.3, 0.6, 1.5),
        "m",
        0.0,
        100.0,
        "1-sigma uncertainty of a tree height the inventory trusts high, medium, low (the top's sampling)",
    )
    table_dbh_sigma_m: tuple[float, float, float] = _p(
        (0.006, 0.012, 0.03),
        "m",
        0.0,
        1.0,
        "1-sigma uncertainty of a DBH trusted high, medium, low when no circle fit tells it (a trees table)",
    )
    #: clouds with ground hold ~0 % of their points 0.5 m below it, clouds without 2-10 %
    no_ground_fraction: float = _p(
        0.005,
        "1",
        0.0,
        1.0,
        "Fraction of a cloud's points more than 0.5 m below the ground found above which the cloud has no ground (heights then above its lowest points)",
    )
    stem_band_m: tuple[float, float] = _p(
        (0.3, 3.0),
        "m",
        0.0,
        10.0,
        "Heights above the ground of the band kept for the stem slices and the presence checks (holds slice_heights_m and 1-2.5 m)",
    )
    no_ground_band_margin_m: float = _p(
        2.0,
        "m",
        0.0,
        10.0,
        "In a cloud without ground, the stem band kept reaches this much further down and up: its heights are above its lowest points, and the other survey's ground under a stem may lie that far off",
    )

    def _check(self) -> None:
        self.stem_icp.check_within(
            "change.stem_icp", voxel_m=(0.005, 0.5), distances_m=(0.005, 5.0), iterations=(1, 500)
        )
        lo, hi = self.dbh_change_range_m
        if not lo < 0.0 < hi:
            raise ParameterError("dbh_change_range_m must hold 0: (lowest, highest) with lowest < 0 < highest")
        if len(self.slice_heights_m) != 2 or not self.slice_heights_m[0] < self.slice_heights_m[1]:
            raise ParameterError("slice_heights_m must be (low, high) with low < high")
        lo, hi = self.stem_band_m
        if not (
            lo < hi and lo <= self.slice_heights_m[0] and self.slice_heights_m[1] <= hi and lo <= 1.0 and hi >= 2.5
        ):
            raise ParameterError(
                "stem_band_m must be (low, high) with low < high, holding slice_heights_m and 1-2.5 m (the presence check)"
            )
