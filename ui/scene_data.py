"""What the 3D view draws: decimated scan points placed before or after registration (no Qt).

*Before* registration every scan is drawn in its own coordinates, centred on its scanner (so the
scans overlap at the origin, as they come off the scanner). *After* registration every placed
scan is drawn in the project frame (the centre scan's coordinates) through its pose, centred on
the centre scanner; scans without a pose are left out and named. Points are decimated to a
budget shared by the scans (default 200 000) so the view stays fluid on large scans; the subset
of each scan is drawn once and reused (it depends only on the file).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..app.plot import Project, ScanCache
from ..engine.report.views import scan_colours

#: Points drawn in the 3D view, all scans together.
DEFAULT_POINT_BUDGET = 200_000


@dataclass
class SceneCloud:
    """One scan as drawn: decimated points (float32, display frame), colour, scanner position."""

    name: str
    points: np.ndarray
    colour: str
    scanner: np.ndarray
    total_points: int


@dataclass
class Scene:
    """Everything the 3D view draws, and which scans could not be drawn and why."""

    mode: str  # "before" or "after"
    clouds: list[SceneCloud] = field(default_factory=list)
    missing: dict[str, str] = field(default_factory=dict)

    @property
    def point_count(self) -> int:
        return int(sum(len(c.points) for c in self.clouds))


class PreviewCache:
    """Decimated file-coordinate points of each scan of one project, read through a ScanCache."""

    def __init__(self, scans: ScanCache, budget: int = DEFAULT_POINT_BUDGET) -> None:
        self.scans = scans
        self.budget = int(budget)
        self._subsets: dict[tuple[str, str, int], tuple[np.ndarray, np.ndarray, int]] = {}

    def subset(self, project: Project, name: str, per_scan: int) -> tuple[np.ndarray, np.ndarray, int]:
        """(points (M, 3) float64 file coordinates, scanner (3,) file coordinates, total points)."""
        key = (name, str(project.scan(name).path), per_scan)
        if key not in self._subsets:
            scan = self.scans(name)
            n = len(scan)
            if n > per_scan:
                idx = np.random.default_rng(len(self._subsets) + 7).choice(n, per_scan, replace=False)
                idx.sort()
                pts = scan.points[idx] + scan.origin_shift
            else:
                pts = scan.file_points
            self._subsets[key] = (pts, scan.scanner_position_file.copy(), n)
        return self._subsets[key]


def build_scene(
    project: Project,
    cache: PreviewCache,
    mode: str,
    progress: Optional[Callable[[float, str], None]] = None,
) -> Scene:
    """Place the decimated scans for ``mode`` ("before" or "after"); see the module docstring."""
    if mode not in ("before", "after"):
        raise ValueError(f"mode must be 'before' or 'after', not {mode!r}")
    scene = Scene(mode=mode)
    if not project.scans:
        return scene
    colours = scan_colours(project)
    poses = project.poses() if mode == "after" else {}
    names = [s.name for s in project.scans]
    if mode == "after":
        for n in names:
            if poses.get(n) is None:
                scene.missing[n] = "not registered"
        names = [n for n in names if poses.get(n) is not None]
    per_scan = max(1000, cache.budget // max(len(names), 1))
    origin: Optional[np.ndarray] = None
    if mode == "after" and project.centre is not None:
        try:
            _, centre_scanner, _ = cache.subset(project, project.centre, per_scan)
            origin = centre_scanner
        except Exception as exc:  # noqa: BLE001 - shown to the user as a missing scan
            scene.missing[project.centre] = str(exc)
    for k, name in enumerate(names):
        if progress is not None:
            progress(k / max(len(names), 1), f"reading {name}")
        try:
            pts, scanner, total = cache.subset(project, name, per_scan)
        except Exception as exc:  # noqa: BLE001 - a scan that cannot be read is named, not fatal
            scene.missing[name] = str(exc)
            continue
        if mode == "after":
            pose = poses[name]
            shift = origin if origin is not None else np.zeros(3)
            placed = pts @ pose[:3, :3].T + (pose[:3, 3] - shift)
            scanner_placed = pose[:3, :3] @ scanner + pose[:3, 3] - shift
        else:
            placed = pts - scanner
            scanner_placed = np.zeros(3)
        scene.clouds.append(
            SceneCloud(name, placed.astype(np.float32), colours.get(name, "#777777"), scanner_placed, total)
        )
    if progress is not None:
        progress(1.0, "3D view ready")
    return scene
