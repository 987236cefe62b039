"""What the plot's views show, for the HTML report and the GUI alike (no plotting here): the
state and colour of each scan, and the top view of a registered plot (slices, VOPs and scanners
of every scan in the project frame, with the VOP pairs of each link that coincide there).

Frames: the project frame (the centre scan's file coordinates), metres.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import ForestregError
from ..core.transform import apply as apply_transform
from ..tls.params import RegistrationParams
from ..tls.plot import ScanCache
from ..tls.prepare import derived, extract_vops, prepare_scan, slice_layers
from ..tls.project import Link, Project
from .topview import MOVING_COLOUR, REFERENCE_COLOUR  # noqa: E402 - the pair figures' colours

#: VOP radius (D_r, m) drawn for a scan whose link does not say which one it used.
DEFAULT_VOP_RADIUS_M = 15.0
#: At most this many slice points are drawn in the top view (all scans together).
MAX_TOP_VIEW_POINTS = 100_000
#: Scan colours: the pair figure's reference and moving colours first; no green (matched VOPs).
SCAN_COLOURS = (
    REFERENCE_COLOUR,
    MOVING_COLOUR,
    "#7b3fb5",
    "#8c564b",
    "#e377c2",
    "#17becf",
    "#bcbd22",
    "#d62728",
    "#393b79",
    "#7f7f7f",
    "#ff9896",
    "#637939",
)


def _num(value: Any) -> bool:
    return (
        isinstance(value, (int, float, np.integer, np.floating))
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


#: Colour of matched VOP pairs.
MATCH_COLOUR = "#2ca02c"


# ------------------------------------------------------------------------------------------------
# scan states and colours
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanState:
    """How a scan ended up: ``status`` is "centre", "registered" or "failed"."""

    name: str
    status: str
    reason: str = ""
    reference: Optional[str] = None


def scan_states(project: Project) -> dict[str, ScanState]:
    """Per scan: centre / registered / failed, with the reason of a failure (from its link)."""
    poses = project.poses()
    out: dict[str, ScanState] = {}
    for s in project.scans:
        link = project.link_of(s.name)
        ref = link.reference if link is not None else None
        if s.name == project.centre:
            out[s.name] = ScanState(s.name, "centre")
        elif poses.get(s.name) is not None:
            out[s.name] = ScanState(s.name, "registered", reference=ref)
        elif link is None:
            out[s.name] = ScanState(s.name, "failed", "not linked to any scan")
        elif not isinstance(link.result, Mapping):
            out[s.name] = ScanState(s.name, "failed", "not registered yet (its link was never run)", ref)
        elif link.result.get("status") != "ok":
            out[s.name] = ScanState(s.name, "failed", failure_reason(link.result), ref)
        else:
            out[s.name] = ScanState(s.name, "failed", f"its reference scan {ref} could not be registered", ref)
    return out


def failure_reason(result: Mapping[str, Any]) -> str:
    """The reason a link failed, with the references its retries tried."""
    reason = (
        str(result.get("reason") or "").strip() or f"status {result.get('status', 'unknown')!s} (no reason recorded)"
    )
    retried = result.get("retried")
    if isinstance(retried, list) and retried:
        tries = "; ".join(
            f"onto {t.get('reference', '?')}: {t.get('reason', '') or 'failed'}"
            for t in retried
            if isinstance(t, Mapping)
        )
        reason += f" (also tried {tries})"
    return reason


def scan_colours(project: Project) -> dict[str, str]:
    """One colour per scan, in project order (the centre scan gets the first)."""
    names = [project.centre] if project.centre is not None else []
    names += [s.name for s in project.scans if s.name != project.centre]
    return {n: SCAN_COLOURS[k % len(SCAN_COLOURS)] for k, n in enumerate(names)}


# ------------------------------------------------------------------------------------------------
# top view data
# ------------------------------------------------------------------------------------------------


@dataclass
class ScanView:
    """One registered scan in the project frame (metres)."""

    name: str
    scanner: np.ndarray
    slice_xy: np.ndarray
    vops_xy: np.ndarray
    radius_m: float
    points: int
    slice_points: int


@dataclass
class LinkView:
    """The VOPs of a link's two scans that coincide in the project frame (after registration)."""

    moving: str
    reference: str
    pairs: np.ndarray  # (K, 2, 2): reference xy, moving xy
    radius_m: float


@dataclass
class TopView:
    scans: dict[str, ScanView] = field(default_factory=dict)
    links: list[LinkView] = field(default_factory=list)
    problems: dict[str, str] = field(default_factory=dict)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    match_distance_m: float = 0.2


# Prepared slices per ScanCache: a report read from the same cache reuses them.
_PREPARED: "weakref.WeakKeyDictionary[ScanCache, dict]" = weakref.WeakKeyDictionary()


def _cache_for(scans: ScanCache) -> dict:
    try:
        return _PREPARED.setdefault(scans, {})
    except TypeError:  # pragma: no cover - an object that takes no weak reference
        return {}


def _slice_params(params: RegistrationParams) -> RegistrationParams:
    """The parameters the slice and VOPs depend on, normalised for caching."""
    return params.replace(vop_radius_m=None) if params.vop_radius_m is not None else params


def _result_params(link: Link, project: Project) -> RegistrationParams:
    """The parameters a link was run with (its stored result's, else the project's with the link's
    overrides), with the slice layers of the attempt it chose (a fallback may have added layers)."""
    result = link.result if isinstance(link.result, Mapping) else {}
    params = link.params(project.params)
    stored = result.get("parameters")
    if isinstance(stored, Mapping):
        try:
            params = RegistrationParams.from_mapping(stored)
        except (ForestregError, TypeError, ValueError):
            pass
    offsets = _chosen_slice_offsets(result)
    if offsets is not None and tuple(offsets) != tuple(params.slice_offsets_m):
        try:
            params = params.replace(slice_offsets_m=tuple(offsets))
        except (ForestregError, TypeError, ValueError):
            pass
    return params


def _chosen_slice_offsets(result: Mapping[str, Any]) -> Optional[tuple[float, ...]]:
    """The slice offsets (dh) of the coarse attempt a result kept, where the result says."""

    def clean(value: Any) -> Optional[tuple[float, ...]]:
        if isinstance(value, (list, tuple)) and value and all(_num(v) for v in value):
            return tuple(float(v) for v in value)
        return None

    direct = clean(result.get("slice_offsets_m"))
    if direct is not None:
        return direct
    attempts = result.get("attempts")
    if not isinstance(attempts, list):
        return None
    keys = ("vop_radius_m", "reference_vops", "moving_vops", "matched")
    for a in attempts:
        if isinstance(a, Mapping) and all(a.get(k) == result.get(k) for k in keys):
            offsets = clean(a.get("slice_offsets_m"))
            if offsets is not None:
                return offsets
    return None


def _known_tilt(project: Project, name: str) -> Optional[float]:
    """The tilt (deg) the registration estimated for a scan, from any link result naming it."""
    for link in project.links:
        result = link.result if isinstance(link.result, Mapping) else {}
        for side, key in ((link.moving, "moving_tilt_deg"), (link.reference, "reference_tilt_deg")):
            value = result.get(key)
            if side == name and isinstance(value, (int, float)) and math.isfinite(value):
                return float(value)
    return None


def _link_radius(link: Optional[Link]) -> Optional[float]:
    if link is None:
        return None
    result = link.result if isinstance(link.result, Mapping) else {}
    for value in (result.get("vop_radius_m"), link.vop_radius_m):
        if isinstance(value, (int, float)) and math.isfinite(value) and value > 0:
            return float(value)
    return None


def _scan_radius(project: Project, name: str) -> float:
    """The D_r a scan's VOPs are drawn at: its own link's, for the centre scan the largest of the
    links onto it, else :data:`DEFAULT_VOP_RADIUS_M`."""
    if name == project.centre:
        radii = [_link_radius(link) for link in project.links if link.reference == name and link.ok]
        radii = [r for r in radii if r is not None]
        return max(radii) if radii else DEFAULT_VOP_RADIUS_M
    return _link_radius(project.link_of(name)) or DEFAULT_VOP_RADIUS_M


class _Prepared:
    """A scan's slice layers in its LSF and the matrix LSF -> file, with VOPs per radius."""

    def __init__(self, project: Project, scans: ScanCache, name: str, params: RegistrationParams) -> None:
        cache = getattr(scans, "prepared", None)
        outline = scans.outline(name, params) if cache is not None else None
        if outline is not None and ("layers", params) in outline[1]:
            # drawn from what the links' preparation left (kept or let go): the scan is neither
            # read nor prepared again (ten 30 M-point scans: minutes and the run's memory peak)
            scan = scans.frame(name)
            local_to_lsf, found = outline
            layers = found[("layers", params)]
            self.points = scans.point_count(name)
        else:
            if cache is not None:
                # the preparation the links of this run made (the same parameters give the same
                # scan), through a stand-in: the points are read (and prepared) only when not kept
                scan = scans.for_link(name, params)
                prepared = cache.get(scan, params)
                self.points = scans.point_count(name)
            else:
                scan = scans(name)
                self.points = len(scan)
                tilt = _known_tilt(project, name)
                up = np.array([0.0, 0.0, 1.0]) if tilt == 0.0 else None
                prepared = prepare_scan(scan.points, scan.scanner_position, params, up=up)
            layers = derived(prepared, ("layers", params), lambda: slice_layers(prepared, params))
            local_to_lsf, found = prepared.local_to_lsf, prepared.derived
        self.params = params
        self.layers = layers
        # the VOPs the links found are reused; the prepared scan itself (its points and ICP grid,
        # hundreds of MB for a 30 M-point scan) is not kept: a plot's views hold every scan
        self._found = {key[2]: v for key, v in found.items() if len(key) == 3 and key[0] == "vops" and key[1] == params}
        self.lsf_to_file = scan.local_to_file_matrix() @ np.linalg.inv(local_to_lsf)
        self.scanner_file = scan.scanner_position_file
        self._vops: dict[float, np.ndarray] = {}

    def slice_xyz(self) -> np.ndarray:
        return np.concatenate([layer.xyz for layer in self.layers]) if self.layers else np.zeros((0, 3))

    def vops_xyz(self, radius: float) -> np.ndarray:
        """VOPs within ``radius`` as (N, 3) LSF points (horizontal position, slice height)."""
        key = round(float(radius), 6)
        if key not in self._vops:
            if float(radius) not in self._found:
                self._found[float(radius)] = extract_vops(self.layers, self.params, float(radius))
            v = self._found[float(radius)]
            self._vops[key] = np.column_stack([v.xy, v.z]) if len(v) else np.zeros((0, 3))
        return self._vops[key]


def _prepared(project: Project, scans: ScanCache, name: str, params: RegistrationParams) -> _Prepared:
    cache = _cache_for(scans)
    params = _slice_params(params)
    entry = project.scan(name)
    key = (name, str(entry.path), params)  # a known tilt only saves the estimate: same result
    if key not in cache:
        cache[key] = _Prepared(project, scans, name, params)
    return cache[key]


def compute_top_view(project: Project, scans: ScanCache) -> TopView:
    """Slices, VOPs and scanners of every registered scan in the project frame, and the VOP pairs
    of each successful link that coincide there (within ``match_distance_m``, mutual nearest)."""
    poses = project.poses()
    view = TopView(match_distance_m=float(project.params.match_distance_m))
    registered = [s.name for s in project.scans if poses.get(s.name) is not None]
    per_scan_limit = max(2000, MAX_TOP_VIEW_POINTS // max(len(registered), 1))
    rng = np.random.default_rng(0)
    for name in registered:
        link = project.link_of(name)
        params = _result_params(link, project) if (link is not None and name != project.centre) else project.params
        try:
            prep = _prepared(project, scans, name, params)
            radius = _scan_radius(project, name)
            to_project = poses[name] @ prep.lsf_to_file
            pts = prep.slice_xyz()
            n_slice = len(pts)
            if len(pts) > per_scan_limit:
                pts = pts[rng.choice(len(pts), per_scan_limit, replace=False)]
            vops = prep.vops_xyz(radius)
            view.scans[name] = ScanView(
                name=name,
                scanner=apply_transform(poses[name], prep.scanner_file[None, :])[0],
                slice_xy=apply_transform(to_project, pts)[:, :2],
                vops_xy=apply_transform(to_project, vops)[:, :2],
                radius_m=radius,
                points=prep.points,
                slice_points=n_slice,
            )
        except (ForestregError, OSError, ValueError, KeyError) as exc:
            view.problems[name] = f"could not be drawn: {exc}"
    if project.centre in view.scans:
        view.origin = view.scans[project.centre].scanner.copy()
    for link in project.links:
        if not link.ok or link.moving not in view.scans or link.reference not in view.scans:
            continue
        params = _result_params(link, project)
        radius = _link_radius(link) or DEFAULT_VOP_RADIUS_M
        try:
            side = {}
            for name in (link.reference, link.moving):
                prep = _prepared(project, scans, name, params)
                side[name] = apply_transform(poses[name] @ prep.lsf_to_file, prep.vops_xyz(radius))[:, :2]
        except (ForestregError, OSError, ValueError, KeyError):
            continue
        pairs = _coinciding(side[link.reference], side[link.moving], project.params.match_distance_m)
        view.links.append(LinkView(link.moving, link.reference, pairs, radius))
    return view


def _coinciding(reference_xy: np.ndarray, moving_xy: np.ndarray, distance: float) -> np.ndarray:
    """Mutual nearest VOPs closer than ``distance``: (K, 2, 2) [reference xy, moving xy]."""
    if len(reference_xy) == 0 or len(moving_xy) == 0:
        return np.zeros((0, 2, 2))
    d_mr, i_mr = cKDTree(reference_xy).query(moving_xy)
    _, i_rm = cKDTree(moving_xy).query(reference_xy)
    keep = (d_mr < distance) & (i_rm[i_mr] == np.arange(len(moving_xy)))
    return np.stack([reference_xy[i_mr[keep]], moving_xy[keep]], axis=1)
