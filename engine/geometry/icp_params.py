"""The settings of one point-to-plane ICP (:func:`~forestreg.engine.geometry.icp.icp`), in a module
of their own: a product's parameters nest them without importing the ICP and its kernels."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p

__all__ = ["IcpParams"]


@dataclass(frozen=True)
class IcpParams(Params):
    """Settings of one coarse-to-fine point-to-plane ICP; each product nests its own, with its own defaults.

    The class defaults are the pair registration's; :func:`icp` takes them as
    ``**params.keywords()``. Distances in metres."""

    voxel_m: float = _p(
        0.05,
        "m",
        0.005,
        5.0,
        "Voxel size to which both clouds are thinned (a stage thins to at least its distance / 2.5)",
    )
    max_distances_m: tuple[float, ...] = _p(
        (0.5, 0.2, 0.08), "m", 0.001, 100.0, "Correspondence distance of each stage, largest first"
    )
    iterations: int = _p(40, "iterations", 1, 10000, "Most iterations per stage")
    max_moving_points: int = _p(
        30000, "points", 100, 100_000_000, "At most this many moving points (a fixed random subset) are used per stage"
    )
    final_tolerance_m: float = _p(
        1e-5, "m", 0.0, 1.0, "The last stage stops when an update moves the cloud less than this..."
    )
    final_tolerance_deg: float = _p(
        1e-4, "deg", 0.0, 10.0, "...and turns it less than this (earlier stages stop at 0.1 mm and 0.001 deg)"
    )
    normal_neighbours: int = _p(
        12, "points", 3, 200, "Neighbours of a reference point whose covariance gives its normal"
    )

    def _check(self) -> None:
        if not self.max_distances_m:
            raise ParameterError("max_distances_m: needs at least one value")

    def check_within(
        self,
        section: str,
        *,
        voxel_m: tuple[float, float],
        distances_m: tuple[float, float],
        iterations: tuple[int, int],
    ) -> None:
        """Raise :class:`ParameterError` naming ``[section]`` when a setting lies outside the
        product's own range (each product's ICP works at its own scale: a pair's voxel of 4 m or
        a distance of 90 m is absurd where a co-registration's coarse stage is not)."""
        checks = [
            ("voxel_m", (self.voxel_m,), voxel_m),
            ("max_distances_m", self.max_distances_m, distances_m),
            ("iterations", (self.iterations,), iterations),
        ]
        for name, values, (lo, hi) in checks:
            for v in values:
                if not lo <= v <= hi:
                    raise ParameterError(f"[{section}] {name} = {v} is outside {lo}..{hi}")

    @property
    def finest_voxel_m(self) -> float:
        """The voxel (metres) of the finest stage: ``voxel_m`` or the last distance / 2.5."""
        return max(self.voxel_m, min(self.max_distances_m) / 2.5)

    def keywords(self) -> dict:
        """These settings as the keyword arguments of :func:`icp`."""
        return {
            "voxel_m": self.voxel_m,
            "max_distances_m": self.max_distances_m,
            "iterations": self.iterations,
            "max_moving_points": self.max_moving_points,
            "final_tolerance": (self.final_tolerance_m, self.final_tolerance_deg),
            "normal_neighbours": self.normal_neighbours,
        }
