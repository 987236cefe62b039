"""Marker-free pair registration (System A): the pipeline from two scans to a :class:`PairResult`.

Steps: reduce -> level -> ground -> slice -> VOPs -> horizontal coarse match ->
vertical offset from the ground overlap -> ICP -> evidence. Each step is a function of
``engine.occlusion`` / ``engine.match``; this module only composes them, times them and decides,
from the evidence, whether the result can be trusted.

Frames: ``PairResult.matrix`` maps the moving scan's *file coordinates* to the reference scan's
file coordinates: ``p_reference = matrix @ p_moving`` (homogeneous column vectors).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence

import numpy as np

from ..core.outcome import Outcome, StepTimer
from ..core.progress import CancelToken, Progress, ProgressCallback
from ..core.scan import Scan, ScanSource
from ..core.transform import apply as apply_transform
from ..core.transform import rigid_errors, rotation_angle_deg, rotation_from_vector
from ..core.uncertainty import (
    Alternative,
    WeakDirection,
    alternative_weight,
    icp_covariance_at,
    judge,
    repeat_shift,
    weak_directions,
    with_alternatives,
)
from ..geometry.icp import IcpReference, IcpResult, icp
from ..geometry.nearest import PlaneNearest
from ..geometry.voxel import voxel_grid

# the coarse matcher's compiled bounds, imported with the pair (the matcher imports them at its
# first match): a process that loads a pair's kernels in the background while the scans are read
# and prepared (:func:`~forestreg.engine.core.jit.preload`) loads these with them
from . import coarse_kernels  # noqa: F401
from .coarse import CoarseMatch, match_vops
from .evidence import mutual_free_space_violation
from .params import RegistrationParams, ScannerPositionParams
from .prepare import (
    PreparedScan,
    PreparedScans,
    SliceLayer,
    centre_scan,
    derived,
    extract_vops,
    icp_grid_voxel,
    prepare_centred,
    slice_layers,
)
from .scanner_position import locate_scanner
from .uncertainty import pair_uncertainty
from .vop import VisualOcclusionPoints

log = logging.getLogger("forestreg")

#: Scans of more points than this are prepared one at a time (a pair of two such scans one after
#: the other).
SEQUENTIAL_PREPARE_POINTS = 15_000_000


@dataclass(frozen=True)
class CoarseAttempt:
    """The coarse match at one VOP radius, with the evidence the decision is made from."""

    radius_m: float
    reference_vops: VisualOcclusionPoints
    moving_vops: VisualOcclusionPoints
    match: Optional[CoarseMatch]
    problem: str = ""
    slice_offsets_m: tuple[float, ...] = (0.0,)
    reference_layers: list[SliceLayer] = field(default_factory=list, repr=False)
    moving_layers: list[SliceLayer] = field(default_factory=list, repr=False)

    @property
    def matched(self) -> int:
        return 0 if self.match is None else self.match.matched

    @property
    def margin(self) -> int:
        if self.match is None:
            return 0
        return self.match.matched - (self.match.second_matched or 0)

    def summary(self) -> dict[str, Any]:
        m = self.match
        return {
            "vop_radius_m": self.radius_m,
            "slice_offsets_m": list(self.slice_offsets_m),
            "reference_vops": len(self.reference_vops),
            "moving_vops": len(self.moving_vops),
            "matched": self.matched,
            "second_matched": None if m is None else m.second_matched,
            "score_m": None if m is None else m.score,
            "second_score_m": None if m is None else m.second_score,
            "problem": self.problem,
        }


@dataclass(frozen=True)
class PairDetails:
    """What the pipeline saw, for figures and the GUI (levelled scanner frames, metres)."""

    reference: PreparedScan
    moving: PreparedScan
    reference_layers: list[SliceLayer]
    moving_layers: list[SliceLayer]
    attempts: list[CoarseAttempt]
    chosen: Optional[CoarseAttempt]
    lsf_matrix: Optional[np.ndarray]
    coarse_lsf_matrix: Optional[np.ndarray]


@dataclass(frozen=True)
class PairResult(Outcome):
    """Result of registering a moving scan onto a reference scan (the shared
    :class:`~forestreg.engine.core.outcome.Outcome` shape).

    ``status`` is "ok" or "failed"; a failed result has ``matrix = None`` and a ``reason``.
    ``matrix`` maps moving file coordinates to reference file coordinates; ``coarse_matrix`` is
    the coarse (VOP + ground) solution ICP started from, in the same frames. ``timings`` are
    seconds per step (``*_s`` keys).
    """

    method = "auto (trunk shadows + ICP)"
    convention = "p_reference = matrix @ p_moving (file coordinates, homogeneous column vectors)"

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    coarse_matrix: Optional[np.ndarray]
    reference_name: str
    moving_name: str
    reference_vops: int
    moving_vops: int
    matched: int
    second_matched: Optional[int]
    score_m: Optional[float]
    second_score_m: Optional[float]
    vop_radius_m: Optional[float]
    vop_residual_m: Optional[float]
    vertical_offset_m: Optional[float]
    reference_tilt_deg: float
    moving_tilt_deg: float
    icp: Optional[IcpResult]
    timings: dict[str, float]
    params: RegistrationParams
    free_space_violation: Optional[float] = None
    attempts: list[dict[str, Any]] = field(default_factory=list)
    ambiguity_resolved: str = ""
    uncertainty: Optional[dict[str, Any]] = None
    quality: Optional[dict[str, Any]] = None
    details: Optional[PairDetails] = field(default=None, repr=False, compare=False)

    @property
    def score_gap_m(self) -> Optional[float]:
        """Overlap-distance gap between the best and the next distinct coarse solution, metres."""
        if self.score_m is None or self.second_score_m is None:
            return None
        return self.second_score_m - self.score_m

    def evidence(self) -> dict[str, Any]:
        """Matched trunk shadows and the margin over the next solution, the fine fit, the
        free-space check, and the calibrated standard errors when computed."""
        return {
            "matched": self.matched,
            "second_matched": self.second_matched,
            "score_gap_m": self.score_gap_m,
            "vop_residual_m": self.vop_residual_m,
            "icp_std_m": None if self.icp is None else self.icp.std_m,
            "icp_fitness": None if self.icp is None else self.icp.fitness,
            "free_space_violation": self.free_space_violation,
            "standard_errors": None
            if not self.uncertainty
            else {k: self.uncertainty.get(k) for k in ("rotation_deg", "translation_m") if k in self.uncertainty},
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (what ``result.json`` holds): the shared outcome keys, then the
        pair-specific figures."""
        return {
            **self.outcome_dict(),
            "coarse_matrix": None if self.coarse_matrix is None else self.coarse_matrix.tolist(),
            "reference": self.reference_name,
            "moving": self.moving_name,
            "reference_vops": self.reference_vops,
            "moving_vops": self.moving_vops,
            "matched": self.matched,
            "second_matched": self.second_matched,
            "score_m": self.score_m,
            "second_score_m": self.second_score_m,
            "score_gap_m": self.score_gap_m,
            "vop_radius_m": self.vop_radius_m,
            "vop_residual_m": self.vop_residual_m,
            "vertical_offset_m": self.vertical_offset_m,
            "reference_tilt_deg": self.reference_tilt_deg,
            "moving_tilt_deg": self.moving_tilt_deg,
            "icp": None if self.icp is None else self.icp.to_dict(),
            "free_space_violation": self.free_space_violation,
            "attempts": list(self.attempts),
            "ambiguity_resolved": self.ambiguity_resolved,
            "uncertainty": self.uncertainty,
            "quality": self.quality,
            "parameters": self.params.to_dict(),
        }


def _checked_up(up: Optional[np.ndarray], what: str) -> Optional[np.ndarray]:
    """A given vertical as a unit (3,) vector; ParameterError unless finite and non-zero."""
    if up is None:
        return None
    from ..core.errors import ParameterError

    v = np.asarray(up, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-9:
        raise ParameterError(f"{what} must be a finite non-zero direction (3 numbers), got {up!r}")
    return v / np.linalg.norm(v)


def register(
    reference: ScanSource,
    moving: ScanSource,
    params: Optional[RegistrationParams] = None,
    *,
    progress: Optional[ProgressCallback] = None,
    cancel: Optional[CancelToken] = None,
    reference_up: Optional[np.ndarray] = None,
    moving_up: Optional[np.ndarray] = None,
    prior: Optional[np.ndarray] = None,
    prior_tolerance: tuple[float, float] = (12.0, 70.0),
    prepared: Optional[PreparedScans] = None,
    scanner_params: Optional[ScannerPositionParams] = None,
) -> PairResult:
    """Register ``moving`` onto ``reference`` from trunk shadows, then ICP.

    Parameters
    ----------
    reference, moving : the two scans (each in its own frame, scanner position known), or
        functions without arguments that read them (e.g. ``lambda: read_scan(path)``): the scans
        are then read one after the other in worker threads, each prepared as soon as it is read
        (while the other is read), and only the prepared scans stay in memory.
    params : settings; default the paper's table 2 with an automatic ``D_r``.
    scanner_params : settings of the scanner-position estimate of a scan that does not say where
        its scanner stood (:func:`~.scanner_position.locate_scanner`).
    progress : optional ``progress(fraction, message)`` callback.
    cancel : optional token; cancelling raises :class:`~forestreg.engine.core.errors.Cancelled`.
    reference_up, moving_up : optional known vertical directions in each scan's local frame
        (from an inclination sensor); default estimated when ``params.level_tilted``.
    prior : optional rough moving-file -> reference-file matrix (GNSS/compass placement, E57/SOP
        poses); used only to decide between two coarse solutions that pass every check, the one
        within ``prior_tolerance`` (metres at the moving scanner, degrees of heading) of it winning.
        Never trusted on its own: a result is always judged by its own evidence.
    prepared : optional cache of prepared scans shared by several calls (the links of a plot):
        each scan is prepared, sliced and searched for VOPs once.

    Returns
    -------
    PairResult
        ``status == "ok"`` with the matrix and its evidence, or ``"failed"`` with the reason.
    """
    params = params or RegistrationParams()
    reference_up, moving_up = _checked_up(reference_up, "reference_up"), _checked_up(moving_up, "moving_up")
    step = Progress(progress, cancel=cancel)
    timings = StepTimer()
    timed = timings.run

    reading, preparing_large = threading.Lock(), threading.Lock()

    def load(source: ScanSource, role: str) -> Scan:
        # a scan given as a reader is read here, in a worker thread, so that one scan is read
        # while the other is prepared (one read at a time: the reader decompresses on every core,
        # and the two scans' reading peaks do not meet); scans exported in project/UTM
        # coordinates carry no scanner position: it is found from the data
        if callable(source):
            with reading:
                source = timed(f"read_{role}", source)
        return locate_scanner(source, scanner_params)

    def prepare(held: list, up: Optional[np.ndarray]) -> PreparedScan:
        # ``held``: the scan, in the only reference to it, taken out here; two large scans (a plot
        # of 30 M-point scans) are prepared one after the other, so that the two preparations'
        # working arrays (~1 GB each) are not held at once (their ICP grids made within too)
        if len(held[0]) > SEQUENTIAL_PREPARE_POINTS:
            with preparing_large:
                return _prepare(held, up, with_icp_grid=True)
        return _prepare(held, up, with_icp_grid=False)

    def _prepare(held: list, up: Optional[np.ndarray], *, with_icp_grid: bool) -> PreparedScan:
        scan = held.pop()
        if prepared is not None:
            return prepared.get(scan, params, up)
        # the scan's own points go once centred (float32): they are not held through the
        # levelling and the grids, while the other scan is read or prepared beside
        centred, position = centre_scan(scan.points, scan.scanner_position, params, up=up), scan.scanner_position
        del scan
        return prepare_centred(centred, position, params, up=up, with_icp_grid=with_icp_grid)

    def read_and_prepare(source: ScanSource, role: str) -> Optional[PreparedScan]:
        # one thread a scan: it is read (one read at a time) and prepared as soon as it is read;
        # only this frame holds the scan's points, handed on to the preparation that lets go of them
        try:
            scan = load(source, role)
            scans[role] = scan.without_points()
        except BaseException as exc:
            failed.append((role, exc))
            raise
        finally:
            read[role].set()
            del source
        if failed:  # the other scan could not be read: the run ends, no preparation is spent
            return None
        held = [scan]
        del scan
        prepared_scan = timed(f"prepare_{role}", prepare, held, ups[role])
        # the ICP grid (a sort of the scan's points) is made in a thread of its own beside the
        # slicing and the VOPs, which do not use it: the last scan's preparation, which nothing
        # else runs beside, is shorter by as much (a large scan's is made with it, see above)
        grid = None
        if prepared_scan.icp_grid is None and _pair_threads() < 2:  # one core: nothing to run beside
            prepared_scan = dataclasses.replace(
                prepared_scan, icp_grid=voxel_grid(prepared_scan.points, icp_grid_voxel(params))
            )
        elif prepared_scan.icp_grid is None:
            grid = ThreadPoolExecutor(1, thread_name_prefix="forestreg-icp-grid")
            grid_job = grid.submit(voxel_grid, prepared_scan.points, icp_grid_voxel(params))
            grid.shutdown(wait=False)
        if not failed:  # the other scan could be read: its VOPs will be matched with these
            scan_vops(prepared_scan, params, timed)
        if grid is not None:
            prepared_scan = dataclasses.replace(prepared_scan, icp_grid=grid_job.result())
        return prepared_scan

    # the two scans are read and prepared in two threads (mostly compiled or numpy code, which
    # releases the GIL). A file that cannot be read ends the run here, before any progress is shown.
    ups = {"reference": reference_up, "moving": moving_up}
    scans: dict[str, Scan] = {}
    read = {role: threading.Event() for role in ("reference", "moving")}
    failed: list[tuple[str, BaseException]] = []
    with ThreadPoolExecutor(max_workers=_pair_threads()) as pool:
        jobs = {
            "reference": pool.submit(read_and_prepare, reference, "reference"),
            "moving": pool.submit(read_and_prepare, moving, "moving"),
        }
        del reference, moving
        for role in ("reference", "moving"):
            read[role].wait()
        if failed:  # the reference's error first when both fail, whichever thread failed first
            raise dict(failed).get("reference", failed[0][1])
        step(0.0, "preparing both scans")
        (reference, ref_prep), (moving, mov_prep) = (
            (scans[role], jobs[role].result()) for role in ("reference", "moving")
        )
    log.info("registering %s onto %s", moving.name, reference.name)
    for name, prep in ((reference.name, ref_prep), (moving.name, mov_prep)):
        log.info(
            "%s: %d points within %.0f m, tilt %.2f deg%s, scanner %.2f m above ground",
            name,
            len(prep.points),
            params.max_range_m,
            prep.tilt_deg,
            " (levelled)" if prep.levelled else "",
            prep.scanner_height_m,
        )
    step(0.3, "slicing")
    attempts = _coarse_attempts(ref_prep, mov_prep, params, timed, step.sub(0.3, 0.5))
    if params.fallback_slice_offsets_m and all(a.matched < params.min_matched for a in attempts):
        wider = params.replace(slice_offsets_m=tuple(params.slice_offsets_m) + tuple(params.fallback_slice_offsets_m))
        log.info(
            "no confident match at dh %s: adding slice layers at dh %s",
            params.slice_offsets_m,
            params.fallback_slice_offsets_m,
        )
        attempts += _coarse_attempts(ref_prep, mov_prep, wider, timed, step.sub(0.5, 0.6))
    chosen = _choose_attempt(attempts)
    base = dict(
        reference_name=reference.name,
        moving_name=moving.name,
        reference_tilt_deg=ref_prep.tilt_deg,
        moving_tilt_deg=mov_prep.tilt_deg,
        timings=timings,
        params=params,
        attempts=[a.summary() for a in attempts],
    )
    details = dict(
        reference=ref_prep,
        moving=mov_prep,
        reference_layers=chosen.reference_layers,
        moving_layers=chosen.moving_layers,
        attempts=attempts,
        chosen=chosen,
    )
    ambiguous = (
        chosen.problem.startswith("ambiguous")
        and chosen.match is not None
        and chosen.match.second_translation is not None
    )
    if chosen.problem and not ambiguous:
        return _failed(chosen.problem, chosen, base, PairDetails(**details, lsf_matrix=None, coarse_lsf_matrix=None))
    if not ambiguous:
        result = _finish(reference, moving, ref_prep, mov_prep, chosen, base, details, params, timed, step)
        if not result.ok:
            return result
        return _count_alternative(
            result,
            chosen,
            moving,
            params,
            lambda candidate: _finish(
                reference,
                moving,
                ref_prep,
                mov_prep,
                candidate,
                base,
                dict(details, chosen=candidate),
                params,
                timed,
                Progress(None, cancel=cancel),
                alternative=True,
            ),
        )
    # Two coarse solutions are nearly as good: let evidence the VOP score did not use decide (the
    # ground overlap, ICP, the VOPs confirmed after ICP, free space). Only when exactly one of them
    # passes every check is it taken; otherwise the pair stays ambiguous and fails.
    log.info("%s - checking both solutions with ICP and free-space evidence", chosen.problem)

    def checking(candidate: CoarseAttempt) -> PairResult:
        return _finish(
            reference,
            moving,
            ref_prep,
            mov_prep,
            candidate,
            base,
            dict(details, chosen=candidate),
            params,
            timed,
            Progress(None, cancel=cancel),
            alternative=True,
        )

    outcomes = []
    for candidate in (dataclasses.replace(chosen, problem=""), _second_candidate(chosen, params.match_distance_m)):
        outcomes.append(
            _finish(
                reference,
                moving,
                ref_prep,
                mov_prep,
                candidate,
                base,
                dict(details, chosen=candidate),
                params,
                timed,
                Progress(None, cancel=cancel),
            )
        )
    passed = [r for r in outcomes if r.ok]
    if len(passed) == 1 and passed[0].matched >= params.min_matched:
        other = outcomes[1] if passed[0] is outcomes[0] else outcomes[0]
        note = f"{chosen.problem}; resolved: the other solution fails its checks ({other.reason})"
        log.info("ambiguity resolved by ICP/free-space evidence")
        excluded = _alternative(passed[0], other, moving, params, f"excluded: it fails its checks ({other.reason})")
        return _count_alternative(
            dataclasses.replace(passed[0], ambiguity_resolved=note),
            passed[0].details.chosen,
            moving,
            params,
            checking,
            known=[excluded],
        )
    if len(passed) == 2:
        rot, trans = rigid_errors(passed[0].matrix, passed[1].matrix)
        if rot < 0.2 and trans < 0.05:  # ICP took both to the same place: not two solutions
            same = _alternative(passed[0], passed[1], moving, params, "the same pose after ICP")
            return _count_alternative(
                dataclasses.replace(
                    passed[0],
                    ambiguity_resolved=f"{chosen.problem}; resolved: ICP takes both solutions to the same pose",
                ),
                passed[0].details.chosen,
                moving,
                params,
                checking,
                known=[same],
            )
        if prior is not None:
            near = [r for r in passed if _within_prior(r.matrix, prior, moving, prior_tolerance)]
            if len(near) == 1:
                other = passed[1] if near[0] is passed[0] else passed[0]
                excluded = _alternative(near[0], other, moving, params, "excluded: it disagrees with the prior pose")
                return _count_alternative(
                    dataclasses.replace(
                        near[0],
                        ambiguity_resolved=f"{chosen.problem}; resolved: only this solution agrees with the prior pose",
                    ),
                    near[0].details.chosen,
                    moving,
                    params,
                    checking,
                    known=[excluded],
                )
    why = "both pass every check" if len(passed) == 2 else "neither passes every check"
    return _failed(
        f"{chosen.problem}; ICP and free-space evidence cannot decide ({why})",
        chosen,
        base,
        PairDetails(**details, lsf_matrix=None, coarse_lsf_matrix=None),
    )


def _within_prior(matrix: np.ndarray, prior: np.ndarray, moving: Scan, tolerance: tuple[float, float]) -> bool:
    """Whether a file -> file matrix puts the moving scanner within ``tolerance`` (m, deg of
    heading) of where the prior matrix puts it."""
    s = moving.scanner_position_file
    off = float(np.linalg.norm((matrix[:3, :3] @ s + matrix[:3, 3] - prior[:3, :3] @ s - prior[:3, 3])[:2]))
    turn = np.degrees(np.arctan2(matrix[1, 0], matrix[0, 0]) - np.arctan2(prior[1, 0], prior[0, 0]))
    turn = abs((turn + 180.0) % 360.0 - 180.0)
    return off <= tolerance[0] and turn <= tolerance[1]


def _second_candidate(attempt: CoarseAttempt, match_distance_m: float) -> CoarseAttempt:
    """The attempt with its best distinct coarse solution in place of the best one (matched VOP
    pairs recomputed: each moving VOP with its nearest reference VOP within ``match_distance_m``)."""
    m = attempt.match
    theta = np.deg2rad(m.second_rotation_deg)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    moved = attempt.moving_vops.xy @ rot.T + np.asarray(m.second_translation)
    d, idx = PlaneNearest(attempt.reference_vops.xy, match_distance_m).query(moved)
    hit = np.flatnonzero(d < match_distance_m)
    pairs = np.column_stack([idx[hit], hit]).astype(np.int64).reshape(-1, 2)
    second = dataclasses.replace(
        m,
        rotation_deg=m.second_rotation_deg,
        translation=np.asarray(m.second_translation),
        score=m.second_score,
        matched=int(len(pairs)),
        matched_pairs=pairs,
        second_score=m.score,
        second_matched=m.matched,
        second_rotation_deg=m.rotation_deg,
        second_translation=m.translation,
    )
    return dataclasses.replace(attempt, match=second, problem="")


def _finish(
    reference: Scan,
    moving: Scan,
    ref_prep: PreparedScan,
    mov_prep: PreparedScan,
    chosen: CoarseAttempt,
    base: dict[str, Any],
    details: dict[str, Any],
    params: RegistrationParams,
    timed,
    step,
    *,
    alternative: bool = False,
) -> PairResult:
    """From a confident coarse VOP match to the result: vertical offset, ICP, evidence checks.
    ``alternative``: the solution is an alternative being checked, excluded only by evidence
    against it (ICP running away, its trunks not coinciding, free space, no overlap), not for
    having fewer trunks than a result needs (a shift along a row loses the ones at its ends)."""
    step(0.6, "vertical alignment")
    coarse = timed(
        "vertical",
        vertical_alignment,
        ref_prep,
        mov_prep,
        chosen.match.matrix(),
        fit_tilt=ref_prep.levelled or mov_prep.levelled,
    )
    if coarse is None:
        return _failed(
            "the two scans share no ground where the match puts them: no vertical offset",
            chosen,
            base,
            PairDetails(**details, lsf_matrix=None, coarse_lsf_matrix=None),
        )
    dz = float(coarse[2, 3])

    step(0.65, "ICP")
    fine = timed("icp", fine_registration, ref_prep, mov_prep, coarse, params)
    step(0.95, "checking evidence")
    correction = np.linalg.inv(coarse) @ fine.matrix
    moved_m = float(np.linalg.norm(correction[:3, 3]))
    turned = rotation_angle_deg(correction[:3, :3])
    vop_residual, confirmed = _vop_confirmation(chosen, fine.matrix, params.match_distance_m)
    full_details = PairDetails(**details, lsf_matrix=fine.matrix, coarse_lsf_matrix=coarse)
    common = dict(base, icp=fine)
    if moved_m > params.icp_max_correction_m or turned > 5.0:
        return _failed(
            f"ICP moved the coarse solution by {moved_m:.2f} m and {turned:.1f} deg: the coarse match is not trustworthy",
            chosen,
            common,
            full_details,
        )
    needed = max(2 if alternative else params.min_matched, int(np.ceil(0.5 * chosen.matched)))
    if confirmed < needed:
        return _failed(
            f"after ICP only {confirmed} of the {chosen.matched} matched VOPs still coincide within "
            f"{0.75 * params.match_distance_m:.2f} m (need {needed}): the VOP match was chance, not the same trunks",
            chosen,
            common,
            full_details,
        )
    violation, tested = mutual_free_space_violation(
        ref_prep, mov_prep, chosen.reference_layers, chosen.moving_layers, fine.matrix, params
    )
    if tested >= 100 and violation > params.max_free_space_violation:
        return _failed(
            f"{100 * violation:.0f} % of one scan's trunk-slice points stand where the other scanner saw empty space "
            f"(allowed {100 * params.max_free_space_violation:.0f} %): the scans do not fit together there - wrong match",
            chosen,
            dict(common, free_space_violation=violation),
            full_details,
        )
    common["free_space_violation"] = None if tested < 100 else violation
    if fine.fitness < params.icp_min_fitness:
        return _failed(
            f"ICP fitness {fine.fitness:.2f} is below {params.icp_min_fitness:.2f}: the scans hardly overlap where the match puts them",
            chosen,
            common,
            full_details,
        )
    matrix = lsf_to_file_matrix(reference, moving, ref_prep, mov_prep, fine.matrix)
    coarse_matrix = lsf_to_file_matrix(reference, moving, ref_prep, mov_prep, coarse)
    uncertainty = _pair_uncertainty(chosen, fine, params, _lsf_to_file_rotation(reference, ref_prep))
    quality = {
        **terrain_agreement(ref_prep, mov_prep, fine.matrix),
        "ambiguity": (chosen.match.second_matched or 0) / max(chosen.matched, 1),
        "confirmed_vops": confirmed,
        "icp_std_m": fine.std_m,
        "icp_fitness": fine.fitness,
    }
    step(1.0, "done")
    log.info(
        "ok: %d matched VOPs, ICP std %.1f mm, fitness %.2f (%.1f s)",
        chosen.matched,
        1000 * fine.std_m,
        fine.fitness,
        base["timings"].get("total_s", sum(base["timings"].values())),
    )
    return PairResult(
        status="ok",
        reason="",
        matrix=matrix,
        coarse_matrix=coarse_matrix,
        reference_vops=len(chosen.reference_vops),
        moving_vops=len(chosen.moving_vops),
        matched=chosen.matched,
        second_matched=chosen.match.second_matched,
        score_m=chosen.match.score,
        second_score_m=chosen.match.second_score,
        vop_radius_m=chosen.radius_m,
        vop_residual_m=vop_residual,
        vertical_offset_m=dz,
        details=full_details,
        uncertainty=uncertainty,
        quality=quality,
        **common,
    )


def _coarse_attempts(
    ref_prep: PreparedScan, mov_prep: PreparedScan, params: RegistrationParams, timed, step: Progress
) -> list[CoarseAttempt]:
    """Slice both scans at ``params.slice_offsets_m`` and match their VOPs at ``params``'s VOP
    radius, or at each automatic radius."""
    ref_layers = timed("slice", derived, ref_prep, ("layers", params), lambda: slice_layers(ref_prep, params))
    mov_layers = timed("slice", derived, mov_prep, ("layers", params), lambda: slice_layers(mov_prep, params))
    radii = vop_radii(params)
    step(0.0, f"visual occlusion points within {', '.join(f'{r:.0f}' for r in radii)} m")
    # every (scan, radius) extraction is independent and mostly compiled-kernel and numpy work (which
    # releases the GIL): two at a time
    jobs = [
        (prep, layers, radius) for radius in radii for prep, layers in ((ref_prep, ref_layers), (mov_prep, mov_layers))
    ]

    def vops(job: tuple) -> VisualOcclusionPoints:
        prep, layers, radius = job
        return derived(prep, ("vops", params, radius), lambda: extract_vops(layers, params, radius))

    with ThreadPoolExecutor(max_workers=_pair_threads()) as pool:
        found = timed("vops", lambda: list(pool.map(vops, jobs)))
        step(0.5, f"matching the visual occlusion points within {', '.join(f'{r:.0f}' for r in radii)} m")
        # the radii are matched independently (compiled kernels, without the GIL): two at a time
        matched = timed(
            "coarse",
            lambda: list(
                pool.map(lambda k: _coarse_attempt(found[2 * k], found[2 * k + 1], radii[k], params), range(len(radii)))
            ),
        )
    attempts = []
    for k, radius in enumerate(radii):
        ref_vops, mov_vops = found[2 * k], found[2 * k + 1]
        attempt = dataclasses.replace(
            matched[k],
            slice_offsets_m=tuple(params.slice_offsets_m),
            reference_layers=ref_layers,
            moving_layers=mov_layers,
        )
        log.info(
            "D_r %.0f m, dh %s: %d / %d VOPs, %d matched (next distinct: %s)%s",
            radius,
            params.slice_offsets_m,
            len(ref_vops),
            len(mov_vops),
            attempt.matched,
            None if attempt.match is None else attempt.match.second_matched,
            f" - {attempt.problem}" if attempt.problem else "",
        )
        attempts.append(attempt)
    return attempts


def vop_radii(params: RegistrationParams) -> tuple[float, ...]:
    """The VOP radii ``D_r`` (metres) a pair is matched at: ``params.vop_radius_m``, or each
    automatic radius within the scans' reach."""
    if params.vop_radius_m is not None:
        return (params.vop_radius_m,)
    return tuple(r for r in params.auto_vop_radii_m if r <= params.max_range_m - 3.0)


def scan_vops(prepared: PreparedScan, params: RegistrationParams, timed: Callable[..., Any]) -> None:
    """Make a prepared scan's slice layers and its VOPs at every radius of :func:`vop_radii` (kept
    in ``prepared.derived``, where :func:`_coarse_attempts` finds them). :func:`register` calls
    this in the thread that prepared the scan, as soon as it is prepared: the first scan's VOPs
    are found while the second is still being read or prepared, not after both. ``timed``:
    the run's :meth:`~forestreg.engine.core.outcome.StepTimer.run`."""
    layers = timed("slice", derived, prepared, ("layers", params), lambda: slice_layers(prepared, params))

    def vops(radius: float) -> None:
        derived(prepared, ("vops", params, radius), lambda: extract_vops(layers, params, radius))

    # the radii two at a time (mostly compiled-kernel and numpy work, which releases the GIL): the
    # second scan's VOPs are the only ones left when it is prepared
    with ThreadPoolExecutor(max_workers=_pair_threads(), thread_name_prefix="forestreg-vops") as pool:
        timed("vops", lambda: list(pool.map(vops, vop_radii(params))))


def _pair_threads() -> int:
    """Threads a pair runs its two scans' work in: two, or one when the process may use one core
    (:func:`~forestreg.engine.core.jit.worker_count`, e.g. a batch's ``--threads 1``); the
    results are the same either way."""
    from ..core.jit import worker_count

    return min(2, worker_count())


def _coarse_attempt(
    ref_vops: VisualOcclusionPoints, mov_vops: VisualOcclusionPoints, radius: float, params: RegistrationParams
) -> CoarseAttempt:
    """Match the VOPs of one radius and judge the evidence."""
    if len(ref_vops) < params.min_vops or len(mov_vops) < params.min_vops:
        return CoarseAttempt(
            radius,
            ref_vops,
            mov_vops,
            None,
            f"too few visual occlusion points within {radius:.0f} m (reference {len(ref_vops)}, moving {len(mov_vops)}; "
            f"need {params.min_vops}): no trunks visible in the slice - not a forest scan, or try other slice heights (--dh)",
        )
    match = match_vops(
        ref_vops.xy,
        mov_vops.xy,
        angle_step_deg=params.angular_step_deg,
        match_distance_m=params.match_distance_m,
        distinct_rotation_deg=params.distinct.rotation_deg,
        distinct_translation_m=params.distinct.translation_m,
    )
    problem = ""
    second = match.second_matched or 0
    need = params.margin.needed(match.matched)
    if match.matched < params.min_matched:
        problem = f"only {match.matched} VOPs match (need {params.min_matched}): the scans share too few trunks - scans too far apart, or D_r too small"
    elif match.matched - second < need:
        problem = (
            f"ambiguous: the best solution matches {match.matched} VOPs and a different one {second} "
            f"(need a margin of {need}) - regular planting or too few common trunks"
        )
    return CoarseAttempt(radius, ref_vops, mov_vops, match, problem)


def _choose_attempt(attempts: list[CoarseAttempt]) -> CoarseAttempt:
    """The attempt with the strongest evidence: confident ones first, then the largest margin
    over the next distinct solution, then the most matched VOPs."""
    return max(attempts, key=lambda a: (not a.problem, a.margin, a.matched, -a.radius_m))


def fine_registration(
    reference: PreparedScan, moving: PreparedScan, coarse_lsf: np.ndarray, params: RegistrationParams
) -> IcpResult:
    """ICP (paper sec. 2.6) from a coarse moving-LSF -> reference-LSF matrix, on the points the two
    scans can share (see :func:`overlap_region`)."""
    if reference.icp_grid is not None and moving.icp_grid is not None:
        # the grids made while preparing: the moving scan's voxel centroids that the reference
        # scanner can see; the whole reference (correspondences lie within the last stage's
        # distance of the moving points, so the reference's overlap is found by the search)
        centroids = moving.icp_grid.centroids
        reference_scanner = np.linalg.inv(coarse_lsf)[:2, 3]
        near = (centroids[:, 0] - reference_scanner[0]) ** 2 + (
            centroids[:, 1] - reference_scanner[1]
        ) ** 2 <= params.max_range_m**2
        return icp(
            _icp_reference(reference),
            centroids[near],
            coarse_lsf,
            moving_voxel_m=moving.icp_grid.voxel_m,
            **params.icp.keywords(),
        )
    ref_overlap, mov_overlap = overlap_region(reference.points, moving.points, coarse_lsf, params.max_range_m)
    return icp(ref_overlap, mov_overlap, coarse_lsf, **params.icp.keywords())


def _icp_reference(prepared: PreparedScan) -> IcpReference:
    """The prepared scan as an ICP reference on its grid (kept in ``prepared.derived`` under
    ``("icp_reference",)``, so the two solutions of an ambiguous match share it; a plot lets it go
    after each link, see :meth:`~forestreg.engine.tls.prepare.PreparedScans.release`). Built when
    ICP starts, not while the other scan is prepared: that overlap raised the peak memory by
    ~50 MB for no time saved."""
    return derived(prepared, ("icp_reference",), lambda: IcpReference(prepared.points, prepared.icp_grid))


def overlap_region(
    reference: np.ndarray, moving: np.ndarray, moving_to_reference: np.ndarray, reach_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The points each scan could share with the other: reference points within ``reach_m``
    (horizontally) of the moving scanner and moving points within ``reach_m`` of the reference
    scanner, under the transform ``moving_to_reference`` (levelled scanner frames, metres)."""
    moving_scanner = moving_to_reference[:2, 3]
    reference_scanner = np.linalg.inv(moving_to_reference)[:2, 3]
    ref_keep = np.sum((reference[:, :2] - moving_scanner) ** 2, axis=1) <= reach_m**2
    mov_keep = np.sum((moving[:, :2] - reference_scanner) ** 2, axis=1) <= reach_m**2
    return reference[ref_keep], moving[mov_keep]


def vertical_alignment(
    reference: PreparedScan, moving: PreparedScan, horizontal: np.ndarray, *, fit_tilt: bool
) -> Optional[np.ndarray]:
    """The vertical part of the coarse registration from the two ground grids.

    ``horizontal`` (3x3, moving LSF xy -> reference LSF xy) places the moving ground cells over
    the reference's; the height differences over the cells both measured give the Z offset (their
    median) and, with ``fit_tilt``, the residual tilt of a scan levelled from its own data (a
    plane fitted to the differences, outliers dropped). Returns the 4x4 coarse matrix (moving LSF
    -> reference LSF), or None when the scans share fewer than 10 ground cells.
    """
    g = moving.ground
    ix, iy = np.nonzero(g.measured)
    centres = np.column_stack([g.origin + (np.column_stack([ix, iy]) + 0.5) * g.cell_m, g.heights[ix, iy]])
    matrix = np.eye(4)
    matrix[:2, :2] = horizontal[:2, :2]
    matrix[:2, 3] = horizontal[:2, 2]
    for _ in range(3 if fit_tilt else 1):
        moved = apply_transform(matrix, centres)
        both = reference.ground.measured_at(moved[:, :2])
        if both.sum() < 10:
            return None
        diff = reference.ground.height_at(moved[both, :2]) - moved[both, 2]
        if not fit_tilt:
            matrix[2, 3] += float(np.median(diff))
            break
        xy = moved[both, :2]
        keep = np.abs(diff - np.median(diff)) <= max(0.15, 3.0 * 1.4826 * np.median(np.abs(diff - np.median(diff))))
        design = np.column_stack([xy[keep], np.ones(keep.sum())])
        (a, b, c), *_ = np.linalg.lstsq(design, diff[keep], rcond=None)
        correction = np.eye(4)
        correction[:3, :3] = rotation_from_vector(np.array([b, -a, 0.0]))
        correction[2, 3] = c
        matrix = correction @ matrix
    return matrix


def _vop_confirmation(
    attempt: CoarseAttempt, lsf_matrix: np.ndarray, match_distance_m: float
) -> tuple[Optional[float], int]:
    """Check the coarse VOP match against the ICP result, which does not depend on it: the mean
    horizontal distance (m) between the matched VOPs after the final transform, and how many of
    them still coincide within 0.75 ``D_t`` (the same trunks do; chance matches scatter)."""
    if attempt.match is None or attempt.match.matched == 0:
        return None, 0
    pairs = attempt.match.matched_pairs
    moved = attempt.moving_vops.xy[pairs[:, 1]] @ lsf_matrix[:2, :2].T + lsf_matrix[:2, 3]
    d = np.hypot(*(moved - attempt.reference_vops.xy[pairs[:, 0]]).T)
    return float(np.mean(d)), int(np.sum(d < 0.75 * match_distance_m))


def terrain_agreement(reference: PreparedScan, moving: PreparedScan, lsf_matrix: np.ndarray) -> dict[str, Any]:
    """How well the two ground models agree under a moving-LSF -> reference-LSF matrix: the median
    and the 90th percentile of the absolute height differences (m) over the ground cells both
    measured, and their count. Needs no ground truth."""
    g = moving.ground
    ix, iy = np.nonzero(g.measured)
    centres = np.column_stack([g.origin + (np.column_stack([ix, iy]) + 0.5) * g.cell_m, g.heights[ix, iy]])
    moved = apply_transform(lsf_matrix, centres)
    both = reference.ground.measured_at(moved[:, :2])
    if both.sum() < 10:
        return {"terrain_cells": int(both.sum()), "terrain_median_m": None, "terrain_p90_m": None}
    diff = np.abs(reference.ground.height_at(moved[both, :2]) - moved[both, 2])
    return {
        "terrain_cells": int(both.sum()),
        "terrain_median_m": float(np.median(diff)),
        "terrain_p90_m": float(np.percentile(diff, 90)),
    }


def _pair_uncertainty(
    attempt: CoarseAttempt, fine: IcpResult, params: RegistrationParams, to_file: Optional[np.ndarray] = None
) -> dict[str, Any]:
    """1-sigma uncertainty of the result at the moving scanner: the ICP's precision from its
    normal matrix, the matched trunks that still coincide after ICP (within 0.75
    ``match_distance_m``; :func:`~forestreg.engine.tls.uncertainty.pair_uncertainty`) as the
    independent evidence, and the directions the surfaces cannot pin (see
    :func:`combine_with_fit`). ``to_file``: the rotation from the reference's levelled frame to its
    file frame (the weak directions are stated in the file frame)."""
    pairs = attempt.match.matched_pairs
    lsf = fine.matrix
    moved = attempt.moving_vops.xy[pairs[:, 1]] @ lsf[:2, :2].T + lsf[:2, 3]
    ref = attempt.reference_vops.xy[pairs[:, 0]]
    keep = np.hypot(*(moved - ref).T) < 0.75 * params.match_distance_m
    trunks = pair_uncertainty(
        ref[keep],
        moved[keep],
        lsf[:2, 3],
        icp_std_m=fine.std_m,
        floor_m=params.min_uncertainty_m,
        floor_deg=params.min_uncertainty_deg,
    )
    return combine_with_fit(trunks, fine, lsf[:3, 3], params, np.eye(3) if to_file is None else to_file)


def _lsf_to_file_rotation(scan: Scan, prepared: PreparedScan) -> np.ndarray:
    """3x3 rotation from a prepared scan's levelled frame to its file frame."""
    return (scan.local_to_file_matrix() @ np.linalg.inv(prepared.local_to_lsf))[:3, :3]


def _alternative(
    result: PairResult,
    other: PairResult,
    moving: Scan,
    params: RegistrationParams,
    status: str,
    lead: Optional[float] = None,
) -> Alternative:
    """The distinct solution ``other`` as the chosen ``result``'s uncertainty counts it: its weight
    from the matched VOPs it trails by (0 unless ``status`` is "counted"), where it puts the
    moving scanner against the chosen matrix (m, deg), from its ICP result when it has one, else
    from its coarse VOP solution. ``lead``: the matches it trails by (default the difference of
    the two results' matched VOPs)."""
    s = moving.scanner_position_file
    if other.matrix is not None:
        here = result.matrix[:3, :3] @ s + result.matrix[:3, 3]
        there = other.matrix[:3, :3] @ s + other.matrix[:3, 3]
        offset = there - here
        turn = rotation_angle_deg(result.matrix[:3, :3].T @ other.matrix[:3, :3])
    else:
        offset, turn = np.zeros(3), 0.0
        if (
            other.details is not None
            and other.details.chosen is not None
            and other.details.chosen.match is not None
            and result.details is not None
            and result.details.chosen is not None
            and result.details.chosen.match is not None
        ):
            a, b = result.details.chosen.match, other.details.chosen.match
            offset = np.append(np.asarray(b.translation, dtype=float) - np.asarray(a.translation, dtype=float), 0.0)
            turn = abs((float(b.rotation_deg) - float(a.rotation_deg) + 180.0) % 360.0 - 180.0)
    lead = result.matched - other.matched if lead is None else lead
    weight = alternative_weight(lead, params.uncertainty) if status == "counted" else 0.0
    direction = (
        float(np.degrees(np.arctan2(offset[1], offset[0])) % 360.0) if np.hypot(offset[0], offset[1]) > 1e-6 else None
    )
    return Alternative(
        weight=weight,
        offset_m=float(np.linalg.norm(offset)),
        offset_deg=float(turn),
        support=float(other.matched),
        chosen_support=float(result.matched),
        status=status,
        direction_deg=direction,
    )


def _count_alternative(
    result: PairResult,
    chosen: CoarseAttempt,
    moving: Scan,
    params: RegistrationParams,
    finish: Callable[[CoarseAttempt], PairResult],
    known: Sequence[Alternative] = (),
) -> PairResult:
    """The chosen solution's result with its alternatives counted: the best distinct coarse
    solution (when likely enough to matter by its lead,
    :attr:`~forestreg.engine.core.uncertainty.UncertaintyParams.min_alternative_weight`, or close in
    matches, ``second_share``), and the chosen one shifted by the step under which its matched
    trunks repeat themselves (:func:`trunk_repeat`; rows of posts, a planted grid). Each is refined
    and checked like the chosen one: one that fails its checks, whose surfaces overlap far less
    (``min_fitness_ratio``), or that ICP takes to the same pose, is excluded; one that passes every
    check is counted, at least ``passing_weight`` likely (a tie when it overlaps far more),
    widening the stated uncertainty (and refusing the result when that exceeds the limits).
    ``known``: alternatives already weighed (the best distinct solution of an ambiguous match,
    checked before): the best distinct coarse solution is then not checked again."""
    up = params.uncertainty
    m = chosen.match
    candidates: list[tuple[CoarseAttempt, float, str]] = []
    if not known and m is not None and m.second_translation is not None and m.second_matched:
        lead = chosen.matched - int(m.second_matched)
        if (
            alternative_weight(lead, up) >= up.min_alternative_weight
            or m.second_matched >= up.second_share * chosen.matched
        ):
            candidates.append((_second_candidate(chosen, params.match_distance_m), lead, ""))
    # the shifts under which the trunks repeat: the matched ones and all those of the reference
    # scan (a row of posts beyond the matched ones), at least ``repeat_share`` of them; and the
    # matched ones along a motion the surfaces leave free (there the trunks alone pin the result:
    # three in a row repeating is enough)
    weak = (
        [
            np.asarray(w.vector[:2])
            for w in weak_directions(result.icp.information, up)
            if w.kind == "translation" and w.azimuth_deg is not None
        ]
        if result.icp is not None
        else []
    )
    seen: list[np.ndarray] = []
    rules = [(None, 4.0, False), (None, 3.0, True)] + [(u, 3.0, False) for u in weak]
    for along, least, everyone in rules:
        repeat = trunk_repeat(chosen, params, along=along, all_vops=everyone)
        if repeat is None:
            continue
        translation, repeated, of = repeat
        if repeated < max(least, up.repeat_share * of if along is None else 0.0) or any(
            np.hypot(*(translation - t)) < params.distinct.translation_m for t in seen
        ):
            continue
        seen.append(translation)
        which = "trunk shadows of the reference scan" if everyone else "matched trunks"
        pattern = (
            f"{repeated} of the {of} {which} repeat themselves {float(np.hypot(*translation)):.2f} m along "
            f"{np.degrees(np.arctan2(translation[1], translation[0])) % 180.0:.0f} deg"
            + (", where the surfaces do not pin it" if along is not None else "")
            + ": regular rows (posts, columns, a planted grid)"
        )
        candidates.append(
            (_moved_candidate(chosen, 0.0, translation, params.match_distance_m), chosen.matched - repeated, pattern)
        )
    alternatives = list(known)
    for candidate, lead, pattern in candidates:
        log.info(
            "a distinct solution (%s) is refined and checked too",
            pattern or f"{candidate.matched} VOPs against {chosen.matched}",
        )
        _checking.alternative = True
        try:
            other = finish(candidate)
        finally:
            _checking.alternative = False
        fitness, other_fitness = result.icp.fitness, (other.icp.fitness if other.icp is not None else 0.0)
        if not other.ok:
            status = f"excluded: it fails its checks ({other.reason})"
        elif other_fitness < up.min_fitness_ratio * fitness:
            status = f"excluded: the surfaces overlap far less under it (ICP fitness {other_fitness:.2f} against {fitness:.2f})"
        else:
            rot, trans = rigid_errors(result.matrix, other.matrix)
            status = "the same pose after ICP" if rot < 0.2 and trans < 0.05 else "counted"
        alternative = _alternative(result, other, moving, params, status, lead=lead)
        if status == "counted":
            floor = 0.5 if fitness < up.min_fitness_ratio * other_fitness else up.passing_weight
            alternative = dataclasses.replace(alternative, weight=max(alternative.weight, floor))
        alternatives.append(dataclasses.replace(alternative, pattern=pattern))
    return _settle(result, alternatives, params)


def trunk_repeat(
    attempt: CoarseAttempt, params: RegistrationParams, *, along: Optional[np.ndarray] = None, all_vops: bool = False
) -> Optional[tuple[np.ndarray, int, int]]:
    """The shift under which a coarse solution's matched reference trunks (VOPs) best repeat
    themselves (:func:`~forestreg.engine.core.uncertainty.repeat_shift` at ``match_distance_m``,
    shifts of at least ``distinct.translation_m``; reference levelled frame, m); None with fewer
    than 4 matched trunks. ``along``: only shifts near this horizontal direction. ``all_vops``:
    every reference VOP, not only the matched ones."""
    if attempt.match is None or attempt.matched < 4:
        return None
    xy = (
        attempt.reference_vops.xy
        if all_vops
        else attempt.reference_vops.xy[np.unique(attempt.match.matched_pairs[:, 0])]
    )
    return repeat_shift(
        xy, params.match_distance_m, params.distinct.translation_m, along=along, limit=45 if all_vops else 60
    )


def _moved_candidate(
    attempt: CoarseAttempt, rotation_deg: float, translation: np.ndarray, match_distance_m: float
) -> CoarseAttempt:
    """The attempt with its coarse solution followed by a motion of the reference frame (rotation
    deg, translation m): the solution where a repeating pattern puts the moving scan next."""
    m = attempt.match
    theta = np.deg2rad(rotation_deg)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    moved = dataclasses.replace(
        m,
        second_rotation_deg=float(m.rotation_deg) + float(rotation_deg),
        second_translation=rot @ np.asarray(m.translation, dtype=float) + np.asarray(translation, dtype=float),
        second_score=m.score,
        second_matched=m.matched,
    )
    return _second_candidate(dataclasses.replace(attempt, match=moved), match_distance_m)


def _settle(result: PairResult, alternatives: Sequence[Alternative], params: RegistrationParams) -> PairResult:
    """The result with its alternatives in its uncertainty (widened by the counted ones), refused
    when the stated uncertainty exceeds the limits of ``params.uncertainty``."""
    u = dict(result.uncertainty or {})
    u["alternatives"] = [a.to_dict() for a in alternatives]
    t, r = u.get("translation_m"), u.get("rotation_deg")
    if t is not None and r is not None:
        u["translation_m"], u["rotation_deg"] = with_alternatives(t, r, alternatives)
        if any(a.status == "counted" and a.weight > 0 for a in alternatives):
            u["without_alternatives"] = {"translation_m": t, "rotation_deg": r}
    weak = [WeakDirection.from_dict(w) for w in u.get("weak_directions", [])]
    reason = judge(
        u.get("translation_m"), u.get("rotation_deg"), params.uncertainty, weak=weak, alternatives=alternatives
    )
    if not reason:
        return dataclasses.replace(result, uncertainty=u)
    log.warning("registration refused: %s", reason)
    return dataclasses.replace(result, status="failed", reason=reason, matrix=None, coarse_matrix=None, uncertainty=u)


def combine_with_fit(
    trunks: dict[str, Any], fine: IcpResult, at: np.ndarray, params: RegistrationParams, to_file: np.ndarray = np.eye(3)
) -> dict[str, Any]:
    """The stated 1-sigma uncertainty at ``at`` (the moving scanner in the reference's levelled
    frame) from the ICP's normal matrix and the trunks' figures (``trunks``, from
    :func:`~forestreg.engine.tls.uncertainty.pair_uncertainty`).

    Along the motions the surfaces pin, the ICP's precision
    (:func:`~forestreg.engine.core.uncertainty.icp_covariance_at`) plus
    :attr:`~forestreg.engine.core.uncertainty.UncertaintyParams.evidence_share` of the trunks'
    correction and bootstrap (the trunks check the fit; a fit they disagree with is less certain);
    along a weak motion (:func:`~forestreg.engine.core.uncertainty.weak_directions`) the trunks
    alone. Without a usable normal matrix, or with fewer than 3 trunks, the trunks' figures as
    they are. Adds ``weak_directions`` (stated in the file frame by ``to_file``), ``fit_m`` /
    ``fit_deg`` (the ICP's own precision) and ``trunks_m`` / ``trunks_deg`` (the trunks' figures).
    """
    u = dict(trunks)
    info = getattr(fine, "information", None)
    if info is None or u.get("translation_m") is None or not np.all(np.isfinite(info)) or not np.isfinite(fine.std_m):
        u["weak_directions"] = []
        return u
    up = params.uncertainty
    weak = weak_directions(info, up)
    extra = np.zeros((6, 6))
    d = np.asarray(u["correction_vector_m"], dtype=float)
    boot = np.asarray(u["bootstrap_cov_m2"], dtype=float)
    trunk_cov = np.outer(d, d) + np.where(np.isfinite(boot), boot, 1e6)
    heading_var = np.radians(float(u["correction_deg"])) ** 2 + np.radians(float(u["bootstrap_deg"])) ** 2
    at = np.asarray(at, dtype=float)
    for w in weak:  # the trunks' own constraint along a motion the surfaces leave free
        v = np.asarray(w.vector, dtype=float)
        if w.kind == "translation":
            h = v[:2]
            var = float(h @ trunk_cov @ h) + 1e-12 if np.hypot(*h) > 0.5 else 1e6
            g = np.concatenate([np.cross(at, v), v])  # the moving scanner's position along v
        else:  # the trunks pin a heading; a tilt only the surfaces can
            var = heading_var + 1e-12 if abs(v[2]) > 0.9 else 1e6
            g = np.concatenate([v, np.zeros(3)])
        extra += np.outer(g, g) / var
    pos_cov, rot_cov = icp_covariance_at(
        info, float(fine.std_m), at, up.independent_patches, up.rotation_patches, extra
    )
    weak_h = [
        np.asarray(w.vector[:2]) / max(np.hypot(*w.vector[:2]), 1e-12)
        for w in weak
        if w.kind == "translation" and w.azimuth_deg is not None
    ]
    strong = np.eye(2)
    for h in weak_h:
        strong = strong - np.outer(h, h)
    share = up.evidence_share**2
    horizontal = pos_cov[:2, :2] + share * strong @ trunk_cov @ strong.T
    heading_weak = any(w.kind == "rotation" and abs(w.vector[2]) > 0.9 for w in weak)
    heading = rot_cov[2, 2] + (0.0 if heading_weak else share * heading_var)
    vertical = max(float(np.sqrt(max(pos_cov[2, 2], 0.0))), params.min_uncertainty_m)
    u.update(
        trunks_m=u["translation_m"],
        trunks_deg=u["rotation_deg"],
        fit_m=float(np.sqrt(max(np.trace(pos_cov), 0.0))),
        fit_deg=float(np.degrees(np.sqrt(max(np.trace(rot_cov), 0.0)))),
        horizontal_m=float(np.sqrt(max(np.trace(horizontal), 0.0))),
        vertical_m=vertical,
        heading_deg=float(np.degrees(np.sqrt(max(heading, 0.0)))),
        translation_m=max(params.min_uncertainty_m, float(np.sqrt(max(np.trace(horizontal), 0.0) + vertical**2))),
        rotation_deg=max(
            params.min_uncertainty_deg, float(np.degrees(np.sqrt(max(heading + rot_cov[0, 0] + rot_cov[1, 1], 0.0))))
        ),
        weak_directions=[_in_file_frame(w, to_file).to_dict() for w in weak],
        method=(
            "ICP normal matrix (the surfaces' precision) with the matched trunks after ICP as the check; "
            "along weak directions the trunks alone; distinct alternatives counted"
        ),
    )
    return u


def _in_file_frame(w: WeakDirection, to_file: np.ndarray) -> WeakDirection:
    """A weak direction with its vector turned from the levelled frame into the file frame."""
    v = np.asarray(to_file, dtype=float) @ np.asarray(w.vector, dtype=float)
    v = v / max(float(np.linalg.norm(v)), 1e-12)
    az = (
        None
        if w.kind == "rotation" or np.hypot(v[0], v[1]) < 0.5
        else float(np.degrees(np.arctan2(v[1], v[0])) % 180.0)
    )
    return WeakDirection(w.kind, tuple(float(x) for x in v), w.share, az)


def lsf_to_file_matrix(
    reference: Scan, moving: Scan, ref_prep: PreparedScan, mov_prep: PreparedScan, lsf_matrix: np.ndarray
) -> np.ndarray:
    """A moving-LSF -> reference-LSF matrix as a moving-file -> reference-file matrix (composes
    moving file -> local -> LSF -> reference LSF -> local -> file)."""
    file_to_local = np.linalg.inv(moving.local_to_file_matrix())
    return (
        reference.local_to_file_matrix()
        @ np.linalg.inv(ref_prep.local_to_lsf)
        @ lsf_matrix
        @ mov_prep.local_to_lsf
        @ file_to_local
    )


def file_to_lsf_matrix(
    reference: Scan, moving: Scan, ref_prep: PreparedScan, mov_prep: PreparedScan, file_matrix: np.ndarray
) -> np.ndarray:
    """The inverse of :func:`lsf_to_file_matrix`: a file -> file matrix in the levelled frames."""
    return (
        ref_prep.local_to_lsf
        @ np.linalg.inv(reference.local_to_file_matrix())
        @ file_matrix
        @ moving.local_to_file_matrix()
        @ np.linalg.inv(mov_prep.local_to_lsf)
    )


#: set in a thread while it checks an alternative solution: its failures are evidence, not news
_checking = threading.local()


def _failed(reason: str, attempt: CoarseAttempt, common: dict[str, Any], details: PairDetails) -> PairResult:
    (log.info if getattr(_checking, "alternative", False) else log.warning)("registration failed: %s", reason)
    m = attempt.match
    fields = dict(common)
    fields.setdefault("icp", None)
    return PairResult(
        status="failed",
        reason=reason,
        matrix=None,
        coarse_matrix=None,
        reference_vops=len(attempt.reference_vops),
        moving_vops=len(attempt.moving_vops),
        matched=attempt.matched,
        second_matched=None if m is None else m.second_matched,
        score_m=None if m is None else m.score,
        second_score_m=None if m is None else m.second_score,
        vop_radius_m=attempt.radius_m,
        vop_residual_m=None,
        vertical_offset_m=None,
        details=details,
        **fields,
    )
