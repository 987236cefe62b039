"""Manual (target-based) registration: the paper's comparison method (sec. 2.7).

The operator identifies the same high-reflectance targets (reflectors) in two scans; a rigid
transform is fitted to these tie points by least squares (>= 3 shared, non-collinear targets) and
is the coarse result; then **the same ICP** as the marker-free registration refines it
(:func:`forestreg.engine.tls.pair.fine_registration`). The module also

* reads and writes target lists (CSV ``scan,target,x,y,z``, file coordinates, metres);
* finds reflectors in a scan from its intensity (:func:`detect_reflectors`) and names the
  detections after known or approximate target positions (:func:`match_detected_to_known`);
* computes the paper's per-plot accuracy figure (its table 5, :func:`target_residuals`): the mean
  distance between the centres of one target seen from different scans, all in the project frame.

Frames: target coordinates are in each scan's *file coordinates*; ``TargetFit.matrix`` and
``ManualResult.matrix`` map moving file coordinates to reference file coordinates
(``p_reference = matrix @ p_moving``, homogeneous column vectors), as ``PairResult.matrix`` does.
"""

from __future__ import annotations

import csv
import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..core.errors import TargetError
from ..core.outcome import Outcome, StepTimer
from ..core.progress import CancelToken, Progress, ProgressCallback
from ..core.scan import Scan
from ..core.transform import apply, fit_rigid, rotation_angle_deg
from ..geometry.cluster import connected_clusters
from ..geometry.icp import IcpResult
from .pair import file_to_lsf_matrix, fine_registration, lsf_to_file_matrix
from .params import RegistrationParams
from .prepare import prepare_scan

log = logging.getLogger("forestreg")

#: Target id -> (3,) centre in one scan's file coordinates, metres.
Targets = dict[str, np.ndarray]

#: The columns a target CSV must have (more columns are allowed and ignored).
CSV_COLUMNS = ("scan", "target", "x", "y", "z")
#: The limits of a registration from targets (RegistrationParams.manual_*) when none are given.
_LIMITS = RegistrationParams()


# --------------------------------------------------------------------------------------------
# Target files
# --------------------------------------------------------------------------------------------


def read_targets_csv(path: str | Path) -> dict[str, Targets]:
    """Read a target list: a CSV with a header naming the columns ``scan,target,x,y,z``.

    ``scan`` is the scan's file name (e.g. ``scan_01.laz``), ``target`` the target id (any text),
    ``x, y, z`` its centre in that scan's file coordinates (metres). Column order is free, names
    are case-insensitive, extra columns are ignored; ``,``, ``;`` or tab separate the fields;
    blank lines and lines starting with ``#`` are skipped.

    Returns ``{scan: {target: (3,) array}}`` in file order.

    Raises
    ------
    TargetError
        Missing or unreadable file, empty file, no header or a missing column, a value that is
        not a finite number, an empty scan or target name, or the same (scan, target) twice; the
        message gives the line.
    """
    from ..io.base import read_text_lines

    p, lines = read_text_lines(path, TargetError, "target file")
    if not lines:
        raise TargetError(
            f"target file {p} is empty; it needs a header line 'scan,target,x,y,z' and one line per target"
        )
    header_no, header_line = lines[0]
    delimiter = next((d for d in (",", ";", "\t") if d in header_line), ",")
    rows = list(csv.reader([line for _, line in lines], delimiter=delimiter))
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise TargetError(
            f"target file {p}, line {header_no}: missing column(s) {', '.join(missing)}; "
            f"the first line must name the columns scan,target,x,y,z (found: {', '.join(header) or 'nothing'})"
        )
    dupes = sorted({h for h in header if header.count(h) > 1 and h in CSV_COLUMNS})
    if dupes:
        raise TargetError(f"target file {p}, line {header_no}: column(s) {', '.join(dupes)} appear twice")
    col = {c: header.index(c) for c in CSV_COLUMNS}
    if len(rows) == 1:
        raise TargetError(f"target file {p} has a header but no targets")
    out: dict[str, Targets] = {}
    for (line_no, _), row in zip(lines[1:], rows[1:]):
        if len(row) < len(header):
            raise TargetError(f"target file {p}, line {line_no}: {len(row)} fields, the header names {len(header)}")
        scan = row[col["scan"]].strip()
        target = row[col["target"]].strip()
        if not scan or not target:
            raise TargetError(f"target file {p}, line {line_no}: the scan and target names must not be empty")
        xyz = []
        for c in ("x", "y", "z"):
            raw = row[col[c]].strip()
            try:
                v = float(raw)
            except ValueError:
                raise TargetError(f"target file {p}, line {line_no}: {c} = {raw!r} is not a number") from None
            if not math.isfinite(v):
                raise TargetError(f"target file {p}, line {line_no}: {c} = {raw!r} is not a finite number")
            xyz.append(v)
        per_scan = out.setdefault(scan, {})
        if target in per_scan:
            raise TargetError(f"target file {p}, line {line_no}: target {target!r} of scan {scan!r} is listed twice")
        per_scan[target] = np.array(xyz, dtype=np.float64)
    return out


def targets_for(targets_by_scan: Mapping[str, Targets], scan: Scan) -> Targets:
    """The targets of ``scan`` in a target list keyed by scan file name: looked up by the scan's
    file name, then its stem, then ``scan.name``.

    Raises TargetError naming the scans the list has when none fits.
    """
    keys = []
    if scan.source is not None:
        keys += [scan.source.name, scan.source.stem]
    keys.append(scan.name)
    for k in keys:
        if k in targets_by_scan:
            return dict(targets_by_scan[k])
    by_stem = {Path(k).stem: k for k in targets_by_scan}
    for k in keys:
        if Path(k).stem in by_stem:
            return dict(targets_by_scan[by_stem[Path(k).stem]])
    raise TargetError(
        f"the target list has no targets for scan {keys[0]!r}; it lists {', '.join(map(repr, targets_by_scan)) or 'no scans'}"
    )


# --------------------------------------------------------------------------------------------
# Rigid fit to targets
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TargetFit:
    """Least-squares rigid fit of the moving scan's targets onto the reference scan's.

    Attributes
    ----------
    matrix : 4x4 moving file -> reference file coordinates.
    target_ids : the shared target ids used, in order.
    residuals_m : (n,) distance of each target after the fit (``|matrix @ moving - reference|``).
    rmse_m : RMS of the residuals, metres.
    """

    matrix: np.ndarray
    target_ids: list[str]
    residuals_m: np.ndarray
    rmse_m: float

    @property
    def worst_id(self) -> str:
        """The target with the largest residual."""
        return self.target_ids[int(np.argmax(self.residuals_m))]

    def to_dict(self) -> dict[str, Any]:
        return {
            "matrix": self.matrix.tolist(),
            "target_ids": list(self.target_ids),
            "residuals_m": {t: float(r) for t, r in zip(self.target_ids, self.residuals_m)},
            "rmse_m": self.rmse_m,
        }


def _as_targets(targets: Mapping[str, Any], label: str) -> Targets:
    out: Targets = {}
    for k, v in targets.items():
        a = np.asarray(v, dtype=np.float64).reshape(-1)
        if a.shape != (3,) or not np.isfinite(a).all():
            raise TargetError(f"{label} target {k!r}: a centre must be three finite numbers, got {v!r}")
        out[str(k)] = a
    return out


def shared_target_ids(reference_targets: Mapping[str, Any], moving_targets: Mapping[str, Any]) -> list[str]:
    """Ids present in both target sets, in the reference's order."""
    mov = {str(k) for k in moving_targets}
    return [str(k) for k in reference_targets if str(k) in mov]


def fit_to_targets(
    reference_targets: Mapping[str, Any],
    moving_targets: Mapping[str, Any],
    *,
    min_spread_m: float = _LIMITS.manual_min_target_spread_m,
) -> TargetFit:
    """Least-squares rigid transform (no scale) ``reference ~ matrix @ moving`` from the targets
    the two sets share (by id). ``min_spread_m``: the least RMS distance of the shared targets
    from one straight line (:attr:`RegistrationParams.manual_min_target_spread_m`).

    Raises
    ------
    TargetError
        Fewer than 3 shared targets (the message lists the shared ids and both sets), or shared
        targets on (nearly) one straight line, which leave the rotation about it undetermined.
    """
    ref = _as_targets(reference_targets, "reference")
    mov = _as_targets(moving_targets, "moving")
    ids = shared_target_ids(ref, mov)
    if len(ids) < 3:
        raise TargetError(
            f"only {len(ids)} shared target(s) ({', '.join(ids) or 'none'}); a rigid fit needs at least 3. "
            f"Reference targets: {', '.join(ref) or 'none'}; moving targets: {', '.join(mov) or 'none'}"
        )
    a = np.array([mov[i] for i in ids])
    b = np.array([ref[i] for i in ids])
    for pts, label in ((b, "reference"), (a, "moving")):
        spread = _line_spread(pts)
        if spread < min_spread_m:
            raise TargetError(
                f"the shared targets {', '.join(ids)} lie on one straight line in the {label} scan "
                f"(within {100 * spread:.1f} cm): the rotation about that line is undetermined; add a target off the line"
            )
    matrix = fit_rigid(a, b)
    res = np.linalg.norm(apply(matrix, a) - b, axis=1)
    return TargetFit(matrix=matrix, target_ids=ids, residuals_m=res, rmse_m=float(np.sqrt(np.mean(res**2))))


def _line_spread(points: np.ndarray) -> float:
    """RMS distance (m) of points from their best-fitting straight line."""
    c = points - points.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return float(np.sqrt(np.sum(s[1:] ** 2) / len(points)))


def suspect_targets(
    reference_targets: Mapping[str, Any],
    moving_targets: Mapping[str, Any],
    *,
    inlier_m: float = _LIMITS.manual_max_target_rmse_m,
    min_spread_m: float = _LIMITS.manual_min_target_spread_m,
) -> list[str]:
    """Shared targets inconsistent with the largest mutually consistent subset (the likely mixed
    up or mis-picked ones), worst first; empty when all fit or no consistent subset of 3 exists.

    Every triple of shared targets (a random 3000 of them when there are many) is fitted; the
    fit under which most targets lie within ``inlier_m`` (ties: smallest RMS) defines the
    consensus, which is refitted; the others are the suspects. Triples closer than
    ``min_spread_m`` to one straight line are not fitted.
    """
    return _consensus_outliers(reference_targets, moving_targets, inlier_m, min_spread_m) or []


def _consensus_outliers(
    reference_targets: Mapping[str, Any], moving_targets: Mapping[str, Any], inlier_m: float, min_spread_m: float
) -> Optional[list[str]]:
    """:func:`suspect_targets`, but None when no 3 targets agree (no consensus at all)."""
    ref = _as_targets(reference_targets, "reference")
    mov = _as_targets(moving_targets, "moving")
    ids = shared_target_ids(ref, mov)
    if len(ids) < 4:
        return None
    a = np.array([mov[i] for i in ids])
    b = np.array([ref[i] for i in ids])
    triples = list(itertools.combinations(range(len(ids)), 3))
    if len(triples) > 3000:
        rng = np.random.default_rng(0)
        triples = [triples[k] for k in rng.choice(len(triples), 3000, replace=False)]
    best: Optional[tuple[int, float, np.ndarray]] = None
    for t in triples:
        t = list(t)
        if _line_spread(b[t]) < min_spread_m:
            continue
        m = fit_rigid(a[t], b[t])
        d = np.linalg.norm(apply(m, a) - b, axis=1)
        inl = d <= inlier_m
        key = (int(inl.sum()), -float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else -np.inf)
        if best is None or key > best[:2]:
            best = (key[0], key[1], inl)
    if best is None or best[0] < 3:
        return None
    inl = best[2]
    m = fit_rigid(a[inl], b[inl])
    d = np.linalg.norm(apply(m, a) - b, axis=1)
    out = [k for k in np.argsort(-d) if d[k] > inlier_m]
    return [ids[k] for k in out]


# --------------------------------------------------------------------------------------------
# Manual registration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ManualResult(Outcome):
    """Result of registering a moving scan onto a reference scan from targets, then ICP (the
    shared :class:`~forestreg.engine.core.outcome.Outcome` shape; ``timings`` in ``*_s`` keys).

    ``status`` is "ok" or "failed"; a failed result has ``matrix = None`` and a ``reason``.
    ``matrix`` maps moving file coordinates to reference file coordinates; ``target_fit.matrix``
    is the target fit ICP started from (same frames). ``icp_correction_m`` / ``_deg`` say how far
    ICP moved the target fit.
    """

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    target_fit: Optional[TargetFit]
    icp: Optional[IcpResult]
    timings: dict[str, float]
    reference_name: str
    moving_name: str
    icp_correction_m: Optional[float] = None
    icp_correction_deg: Optional[float] = None
    suspects: list[str] = field(default_factory=list)

    method = "manual (targets + ICP)"
    convention = "p_reference = matrix @ p_moving (file coordinates, homogeneous column vectors)"

    def evidence(self) -> dict[str, Any]:
        """The target fit (count, RMS, worst target), suspects, and how far ICP moved it."""
        fit = self.target_fit
        return {
            "targets": None if fit is None else len(fit.target_ids),
            "target_rms_m": None if fit is None else fit.rmse_m,
            "worst_target": None if fit is None else fit.worst_id,
            "suspect_targets": list(self.suspects),
            "icp_std_m": None if self.icp is None else self.icp.std_m,
            "icp_fitness": None if self.icp is None else self.icp.fitness,
            "icp_correction_m": self.icp_correction_m,
            "icp_correction_deg": self.icp_correction_deg,
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary: the shared outcome keys, then the manual-specific figures."""
        return {
            **self.outcome_dict(),
            "reference": self.reference_name,
            "moving": self.moving_name,
            "target_fit": None if self.target_fit is None else self.target_fit.to_dict(),
            "suspect_targets": list(self.suspects),
            "icp": None if self.icp is None else self.icp.to_dict(),
            "icp_correction_m": self.icp_correction_m,
            "icp_correction_deg": self.icp_correction_deg,
        }


def register_manual(
    reference: Scan,
    moving: Scan,
    reference_targets: Mapping[str, Any],
    moving_targets: Mapping[str, Any],
    params: Optional[RegistrationParams] = None,
    *,
    progress: Optional[ProgressCallback] = None,
    cancel: Optional[CancelToken] = None,
) -> ManualResult:
    """Register ``moving`` onto ``reference`` from shared targets, then the same ICP as
    :func:`~forestreg.engine.tls.pair.register` (paper sec. 2.7, the manual method).

    Parameters
    ----------
    reference_targets, moving_targets : ``{id: xyz}`` in each scan's file coordinates.
    params : ICP settings (``icp``, ``icp_min_fitness``, ``icp_max_correction_m``), ``max_range_m``, levelling and the limits of the target
        fit (``manual_*``); default the paper's.

    Returns
    -------
    ManualResult
        ``"failed"`` (matrix None, with the reason) when fewer than 3 targets are shared or they
        lie within ``params.manual_min_target_spread_m`` of one line, when the target fit's RMS
        residual exceeds ``params.manual_max_target_rmse_m`` (the reason names the suspect
        targets), when ICP moves the fit by more than ``params.icp_max_correction_m`` or turns it
        by more than ``params.manual_max_icp_rotation_deg``, or when ICP's fitness is below
        ``params.icp_min_fitness`` (as in ``register``).

    Malformed target coordinates raise :class:`TargetError`.
    """
    params = params or RegistrationParams()
    step = Progress(progress, cancel=cancel)
    timings = StepTimer()
    base = dict(reference_name=reference.name, moving_name=moving.name, timings=timings)
    log.info("manual registration of %s onto %s", moving.name, reference.name)

    step(0.0, "fitting targets")
    t0 = time.perf_counter()
    ref_t = _as_targets(reference_targets, f"{reference.name}:")
    mov_t = _as_targets(moving_targets, f"{moving.name}:")
    try:
        fit = fit_to_targets(ref_t, mov_t, min_spread_m=params.manual_min_target_spread_m)
    except TargetError as exc:
        timings.add("target_fit", time.perf_counter() - t0)
        return _failed(str(exc), base)
    if fit.rmse_m > params.manual_max_target_rmse_m:
        outliers = _consensus_outliers(ref_t, mov_t, params.manual_max_target_rmse_m, params.manual_min_target_spread_m)
        suspects = outliers or []
        timings.add("target_fit", time.perf_counter() - t0)
        worst = suspects[0] if suspects else fit.worst_id
        detail = ", ".join(
            f"{t} {r:.2f} m" for t, r in sorted(zip(fit.target_ids, fit.residuals_m), key=lambda x: -x[1])
        )
        if suspects:
            agree = len(fit.target_ids) - len(suspects)
            why = f"target(s) {', '.join(suspects)} disagree with the other {agree} - ids mixed up or wrongly picked"
        elif outliers is None and len(fit.target_ids) < 4:
            why = f"with only {len(fit.target_ids)} targets which one is wrong cannot be told - check them all"
        elif outliers is None:
            why = "no 3 of the targets agree with each other, so which ids are wrong cannot be told - check them all"
        else:
            why = "the misfit is spread over all targets - check the target coordinates (units, scan names)"
        return _failed(
            f"the targets do not fit: RMS residual {fit.rmse_m:.3f} m over {len(fit.target_ids)} targets "
            f"(limit {params.manual_max_target_rmse_m:.2f} m; residuals {detail}). Worst target: {worst}; {why}",
            base,
            target_fit=fit,
            suspects=suspects,
        )
    timings.add("target_fit", time.perf_counter() - t0)
    log.info("target fit: %d targets, RMS %.1f mm", len(fit.target_ids), 1000 * fit.rmse_m)

    timed = timings.run

    step(0.05, "preparing reference scan")
    ref_prep = timed("prepare_reference", prepare_scan, reference.points, reference.scanner_position, params)
    step(0.3, "preparing moving scan")
    mov_prep = timed("prepare_moving", prepare_scan, moving.points, moving.scanner_position, params)
    step(0.55, "ICP")
    coarse_lsf = file_to_lsf_matrix(reference, moving, ref_prep, mov_prep, fit.matrix)
    fine = timed("icp", fine_registration, ref_prep, mov_prep, coarse_lsf, params)
    step(0.95, "checking ICP")
    correction = np.linalg.inv(coarse_lsf) @ fine.matrix
    moved_m = float(np.linalg.norm(correction[:3, 3]))
    turned = rotation_angle_deg(correction[:3, :3])
    common = dict(base, target_fit=fit, icp=fine, icp_correction_m=moved_m, icp_correction_deg=turned)
    if moved_m > params.icp_max_correction_m or turned > params.manual_max_icp_rotation_deg:
        return _failed(
            f"ICP moved the target fit by {moved_m:.2f} m and {turned:.1f} deg (limits {params.icp_max_correction_m:.2f} m, "
            f"{params.manual_max_icp_rotation_deg:g} deg): the targets and the point clouds disagree - check the target coordinates",
            common,
        )
    if fine.fitness < params.icp_min_fitness:
        return _failed(
            f"ICP fitness {fine.fitness:.2f} is below {params.icp_min_fitness:.2f}: the scans hardly overlap where the targets put them",
            common,
        )
    matrix = lsf_to_file_matrix(reference, moving, ref_prep, mov_prep, fine.matrix)
    step(1.0, "done")
    log.info(
        "ok: target RMS %.1f mm, ICP moved it %.1f mm / %.3f deg, ICP std %.1f mm",
        1000 * fit.rmse_m,
        1000 * moved_m,
        turned,
        1000 * fine.std_m,
    )
    return ManualResult(status="ok", reason="", matrix=matrix, **common)


def _failed(reason: str, common: dict[str, Any], **extra: Any) -> ManualResult:
    log.warning("manual registration failed: %s", reason)
    fields = dict(common, **extra)
    fields.setdefault("target_fit", None)
    fields.setdefault("icp", None)
    return ManualResult(status="failed", reason=reason, matrix=None, **fields)


# --------------------------------------------------------------------------------------------
# Reflector detection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectedTarget:
    """A reflector found in a scan.

    Attributes
    ----------
    centre : (3,) estimated centre of the reflector in the scan's file coordinates, metres.
    points : number of bright returns on it.
    mean_intensity : their mean intensity (the file's scale).
    radius_m : estimated radius of the reflector (or the given one), metres.
    score : confidence, larger is better (see :func:`detect_reflectors`).
    """

    centre: np.ndarray
    points: int
    mean_intensity: float
    radius_m: float
    score: float


#: How far the visible surface's centroid lies in front of the centre, in radii, per shape:
#: a cylinder seen side-on, sampled evenly across its width, has its visible half-circle's mean
#: depth at pi/4 r; a sphere sampled evenly over its projected disc at 2/3 r; a flat (disc,
#: sticker) target's centre is on its surface.
CENTRE_DEPTH_FACTOR = {"cylinder": math.pi / 4.0, "sphere": 2.0 / 3.0, "flat": 0.0}


def detect_reflectors(
    scan: Scan,
    *,
    max_size_m: float = 0.3,
    min_points: int = 3,
    intensity_quantile: float = 0.999,
    bulk_factor: float = 1.75,
    intensity_threshold: Optional[float] = None,
    link_m: float = 0.15,
    shape: str = "cylinder",
    target_radius_m: Optional[float] = None,
    max_candidates: int = 200_000,
) -> list[DetectedTarget]:
    """Find high-reflectance targets in a scan from its intensity.

    1. Bright returns: intensity at least ``threshold = max(q(intensity_quantile),
       median + bulk_factor * (q(0.99) - median))`` - well above the bulk's own upper tail, so
       the threshold follows the intensity scale of the file (16-bit counts, dB reflectance, ...),
       and never below the ``intensity_quantile`` (reflectors are a tiny fraction of a scan; the
       estimate holds while bright objects make up well under 0.1 % of the points).
       ``intensity_threshold`` overrides it (see :func:`reflector_threshold`). At most
       ``max_candidates`` brightest points are used. On the simulator's scans (retro-reflectors
       45 000-62 000, anything else below ~36 000) the default lands at 39 000-44 000.
    2. Clusters: bright points linked when closer than ``link_m`` (3D, connected components).
    3. Kept: clusters of at least ``min_points`` points spanning at most ``max_size_m`` (a road
       sign or a car's tail lights are bigger; single glints are fewer).
    4. Centre: a cylinder or sphere reflector is seen on its near side only, so the centroid of
       its returns is moved away from the scanner along the ray through it by
       ``CENTRE_DEPTH_FACTOR[shape] * r`` (pi/4 r for a cylinder, 2/3 r for a sphere, 0 for a flat
       target). ``r`` is ``target_radius_m`` when known, else estimated from the spread of the
       returns across the ray: returns spread evenly over a width ``2r`` have a standard
       deviation of ``r / sqrt(3)``, so ``r = sqrt(3) * std`` along the wider across-ray axis
       (noisy with very few returns: give the radius when it is known).
    5. Score: ``sqrt(points) * (mean intensity - median) / (threshold - median)``; the result is
       sorted by score, best first.

    Raises
    ------
    TargetError
        The scan has no intensity, or its intensity is constant.
    """
    if shape not in CENTRE_DEPTH_FACTOR:
        raise TargetError(f"unknown target shape {shape!r}; use one of {', '.join(CENTRE_DEPTH_FACTOR)}")
    if scan.intensity is None:
        raise TargetError(
            f"{scan.name}: the scan has no intensity; reflectors cannot be found - pick the targets by hand"
        )
    inten = np.asarray(scan.intensity, dtype=np.float64)
    finite = np.isfinite(inten)
    if finite.sum() < 10 or np.ptp(inten[finite]) <= 0.0:
        raise TargetError(
            f"{scan.name}: the scan has no intensity variation (all values equal); reflectors cannot be found"
        )
    median, threshold = _threshold(inten[finite], intensity_quantile, bulk_factor)
    if intensity_threshold is not None:
        threshold = float(intensity_threshold)
    bright = np.flatnonzero(finite & (inten >= threshold))
    if len(bright) > max_candidates:
        bright = bright[np.argsort(-inten[bright], kind="stable")[:max_candidates]]
        log.warning("%s: more than %d bright returns; only the brightest used", scan.name, max_candidates)
    if len(bright) < min_points:
        return []
    pts = scan.points[bright]
    labels = connected_clusters(pts, link_m)
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    contrast_unit = max(threshold - median, 1e-12)
    found: list[DetectedTarget] = []
    for members in np.split(order, bounds):
        if len(members) < min_points:
            continue
        cp = pts[members]
        size = float(np.linalg.norm(cp.max(axis=0) - cp.min(axis=0)))
        if size > max_size_m:
            continue
        centroid = cp.mean(axis=0)
        ray = centroid - scan.scanner_position
        dist = float(np.linalg.norm(ray))
        ray = ray / dist if dist > 0 else np.array([0.0, 0.0, 1.0])
        radius = target_radius_m if target_radius_m is not None else _across_ray_radius(cp, ray, max_size_m)
        centre_local = centroid + CENTRE_DEPTH_FACTOR[shape] * radius * ray
        mean_i = float(inten[bright[members]].mean())
        score = math.sqrt(len(members)) * (mean_i - median) / contrast_unit
        found.append(
            DetectedTarget(
                centre=centre_local + scan.origin_shift,
                points=int(len(members)),
                mean_intensity=mean_i,
                radius_m=float(radius),
                score=float(score),
            )
        )
    found.sort(key=lambda d: -d.score)
    return found


def reflector_threshold(scan: Scan, *, intensity_quantile: float = 0.999, bulk_factor: float = 1.75) -> float:
    """The intensity above which :func:`detect_reflectors` takes a return to be on a reflector
    (same defaults); for display, or to tune ``intensity_threshold``."""
    if scan.intensity is None:
        raise TargetError(f"{scan.name}: the scan has no intensity")
    inten = np.asarray(scan.intensity, dtype=np.float64)
    inten = inten[np.isfinite(inten)]
    if len(inten) < 10:
        raise TargetError(f"{scan.name}: the scan has no usable intensity")
    return _threshold(inten, intensity_quantile, bulk_factor)[1]


def _threshold(values: np.ndarray, quantile: float, bulk_factor: float) -> tuple[float, float]:
    """(median, threshold) of finite intensities (a regular subsample of at most 2 M values)."""
    if len(values) > 2_000_000:
        values = values[:: int(math.ceil(len(values) / 2_000_000))]
    median, q99, qhi = np.quantile(values, [0.5, 0.99, quantile])
    return float(median), float(max(qhi, median + bulk_factor * (q99 - median)))


def _across_ray_radius(points: np.ndarray, ray: np.ndarray, max_size_m: float) -> float:
    """Radius of a reflector from the spread of its returns across the ray (see
    :func:`detect_reflectors`), clipped to [5 mm, max_size_m / 2]."""
    c = points - points.mean(axis=0)
    across = c - np.outer(c @ ray, ray)
    ev = np.linalg.eigvalsh(across.T @ across / len(points))
    r = math.sqrt(3.0 * max(float(ev[-1]), 0.0))
    return float(min(max(r, 0.005), max_size_m / 2.0))


def match_detected_to_known(
    detected: Sequence[DetectedTarget] | Sequence[Any],
    known: Mapping[str, Any],
    max_distance_m: float,
) -> Targets:
    """Name detections after known (or approximate) target positions of the same scan (file
    coordinates): a one-to-one assignment minimising the total distance, pairs farther than
    ``max_distance_m`` left out. Returns ``{id: detected centre}`` for the named detections, in
    the order of ``known``. ``detected`` may also hold plain (3,) centres.
    """
    from scipy.optimize import linear_sum_assignment

    ids = list(known)
    if not ids or not len(detected):
        return {}
    kn = np.array([np.asarray(known[i], dtype=np.float64).reshape(3) for i in ids])
    det = np.array([np.asarray(getattr(d, "centre", d), dtype=np.float64).reshape(3) for d in detected])
    dist = np.linalg.norm(kn[:, None, :] - det[None, :, :], axis=2)
    big = 1e6 + dist.max()
    cost = np.where(dist <= max_distance_m, dist, big)
    rows, cols = linear_sum_assignment(cost)
    chosen = {int(r): int(c) for r, c in zip(rows, cols) if dist[r, c] <= max_distance_m}
    return {str(ids[r]): det[chosen[r]].copy() for r in range(len(ids)) if r in chosen}


# --------------------------------------------------------------------------------------------
# Accuracy from targets (paper table 5)
# --------------------------------------------------------------------------------------------


def target_residuals(
    targets_by_scan: Mapping[str, Mapping[str, Any]], poses: Mapping[str, Optional[np.ndarray]]
) -> dict[str, Any]:
    """The paper's per-plot accuracy figure (table 5): with every scan in the project frame, the
    mean distance between the centres of one target seen from different scans.

    Parameters
    ----------
    targets_by_scan : ``{scan: {target: xyz}}`` in each scan's file coordinates.
    poses : ``{scan: 4x4}`` mapping that scan's file coordinates into the project frame; scans
        without a pose (missing or None) are skipped.

    Returns
    -------
    dict
        ``{"per_target": {id: {"scans": [...], "mean_distance_m", "max_distance_m"}},
        "mean_m": mean of the per-target means (None without any target seen twice),
        "targets": number of targets seen in >= 2 posed scans, "skipped_scans": [...]}``.
    """
    seen: dict[str, list[tuple[str, np.ndarray]]] = {}
    skipped = []
    for scan, targets in targets_by_scan.items():
        pose = poses.get(scan)
        if pose is None:
            skipped.append(scan)
            continue
        m = np.asarray(pose, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise TargetError(f"the pose of scan {scan!r} must be a finite 4x4 matrix")
        for tid, xyz in _as_targets(targets, f"{scan}:").items():
            seen.setdefault(tid, []).append((scan, apply(m, xyz[None, :])[0]))
    per_target: dict[str, dict[str, Any]] = {}
    for tid, obs in seen.items():
        if len(obs) < 2:
            continue
        pts = np.array([p for _, p in obs])
        d = [float(np.linalg.norm(pts[i] - pts[j])) for i, j in itertools.combinations(range(len(pts)), 2)]
        per_target[tid] = {
            "scans": [s for s, _ in obs],
            "mean_distance_m": float(np.mean(d)),
            "max_distance_m": float(np.max(d)),
        }
    means = [v["mean_distance_m"] for v in per_target.values()]
    return {
        "per_target": per_target,
        "mean_m": float(np.mean(means)) if means else None,
        "targets": len(per_target),
        "skipped_scans": skipped,
    }
