"""Whole surveys: every useful pair, a pose graph weighted by each pair's evidence, inconsistent
links found and dropped, and the uncertainty and quality of every pose without ground truth.

Steps (:func:`register_survey`):

1. the paper's plot run (:func:`~forestreg.engine.tls.plot.register_project`): every scan to the
   centre, failures retried against the registered scans;
2. every further pair whose scanners stand within ``max_distance_m`` (or all pairs) is registered
   as an extra link; where scans are not yet placed their prior poses (E57/SOP poses, a shared
   georeferenced frame) say which pairs are near;
3. links are checked against priors (a link that puts a scan farther from its prior than the prior's
   tolerance is dropped: priors limit, they are never trusted blindly) and against each other:
   every triangle of links must close within its stated uncertainty; a link whose triangles all
   fail while it has others' support is dropped;
4. a pose graph (robust least squares over all kept links, each weighted by its stated 1-sigma
   uncertainty; the frame scan and any ``fixed`` scans held) gives the poses; a scan whose centre
   link failed is placed through its neighbours;
5. per scan: uncertainty (propagated along the most certain chain of links, inflated where the
   loop closures disagree more than stated) and quality (links, residuals, ambiguity, ICP).

Frames: poses map each scan's file coordinates into the frame scan's file coordinates (see
:mod:`~forestreg.engine.tls.project`).
"""

from __future__ import annotations

import itertools
import logging
from typing import Any, Callable, Optional, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..core.progress import CancelToken, Progress, ProgressCallback
from ..core.transform import rigid_errors
from .params import SurveyParams
from .plot import LinkQueue, PlotOutcome, ScanCache, _run_link, default_links, informative_priors, register_project
from .project import Link, Project
from .uncertainty import propagate_uncertainty

log = logging.getLogger("forestreg")

__all__ = ["SurveyParams", "register_survey", "solve_pose_graph", "inconsistent_links"]


def _link_sigma(link: Link) -> tuple[float, float]:
    """A link's stated 1-sigma (translation m, rotation deg); manual/old links get a cautious default."""
    u = (link.result if link.result is not None else {}).get("uncertainty") or {}
    t, r = u.get("translation_m"), u.get("rotation_deg")
    if t is None or r is None:
        return 0.05, 0.1
    return float(t), float(r)


def _scanner_file(scans: ScanCache, name: str) -> np.ndarray:
    return np.asarray(scans.frame(name).scanner_position_file, dtype=float)


def _usable(scans: ScanCache, name: str) -> bool:
    """Whether the scan can be read and has a scanner position (its links report why not)."""
    from ..core.errors import ScanDataError, ScanReadError

    try:
        scans.frame(name)
        return True
    except (ScanReadError, ScanDataError):
        return False


def _prior_positions(
    project: Project, scans: ScanCache, poses: dict[str, Optional[np.ndarray]]
) -> dict[str, np.ndarray]:
    """Scanner positions in the frame scan's file coordinates: from the registered poses, else from
    prior poses (relative to the frame scan's prior), else the file coordinates themselves when the
    files share a georeferenced frame (large coordinates)."""
    frame = project.centre
    out: dict[str, np.ndarray] = {}
    frame_prior = project.scan(frame).prior_pose
    if not _usable(scans, frame):
        return out
    for s in project.scans:
        if not _usable(scans, s.name):
            continue
        pos = _scanner_file(scans, s.name)
        pose = poses.get(s.name)
        if pose is not None:
            out[s.name] = pose[:3, :3] @ pos + pose[:3, 3]
        elif s.prior_pose is not None and frame_prior is not None and informative_priors(project):
            m = np.linalg.inv(frame_prior) @ s.prior_pose
            out[s.name] = m[:3, :3] @ pos + m[:3, 3]
        elif _georeferenced(scans, s.name) and _georeferenced(scans, frame):
            out[s.name] = pos
    return out


def _georeferenced(scans: ScanCache, name: str) -> bool:
    return bool(np.abs(scans.frame(name).origin_shift).max() > 0.0)


def _prior_relative(project: Project, scans: ScanCache, moving: str, reference: str) -> Optional[np.ndarray]:
    """The prior moving -> reference file matrix, where both scans have priors."""
    a, b = project.scan(moving).prior_pose, project.scan(reference).prior_pose
    if a is not None and b is not None and informative_priors(project):
        return np.linalg.inv(b) @ a
    if _georeferenced(scans, moving) and _georeferenced(scans, reference):
        return np.eye(4)
    return None


def _heading_deg(m: np.ndarray) -> float:
    """Rotation about the vertical of a 4x4 (degrees)."""
    return float(np.degrees(np.arctan2(m[1, 0], m[0, 0])))


def _prior_conflict(project: Project, scans: ScanCache, link: Link, params: SurveyParams) -> str:
    prior = _prior_relative(project, scans, link.moving, link.reference)
    if prior is None or link.matrix is None:
        return ""
    pos = _scanner_file(scans, link.moving)
    moved = link.matrix[:3, :3] @ pos + link.matrix[:3, 3]
    expected = prior[:3, :3] @ pos + prior[:3, 3]
    off = float(np.linalg.norm(moved[:2] - expected[:2]))
    turn = abs((_heading_deg(link.matrix) - _heading_deg(prior) + 180.0) % 360.0 - 180.0)
    # both scans' priors may be off: twice the position tolerance, plus the reference's heading
    # error swinging the moving scanner about the reference scanner (lever arm = their distance)
    ref_pos = _scanner_file(scans, link.reference)
    lever = float(np.linalg.norm(expected[:2] - ref_pos[:2]))
    allowed_m = 2.0 * params.prior_position_tolerance_m + 2.0 * lever * np.sin(
        np.radians(min(params.prior_heading_tolerance_deg, 90.0)) / 1.0
    )
    allowed_deg = min(180.0, 2.0 * params.prior_heading_tolerance_deg)
    if off > allowed_m or turn > allowed_deg:
        return (
            f"puts the scanner {off:.1f} m and {turn:.0f} deg from where the prior poses put it "
            f"(allowed {allowed_m:.1f} m, {allowed_deg:.0f} deg for priors within {params.prior_position_tolerance_m:g} m, "
            f"{params.prior_heading_tolerance_deg:g} deg)"
        )
    return ""


def _error(link_matrix: np.ndarray, predicted: np.ndarray, at: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation at the moving scanner ``at`` (m) between two matrices."""
    rot, _ = rigid_errors(link_matrix, predicted)
    d = (link_matrix[:3, :3] @ at + link_matrix[:3, 3]) - (predicted[:3, :3] @ at + predicted[:3, 3])
    return rot, float(np.linalg.norm(d))


def inconsistent_links(
    links: Sequence[Link],
    scanner: dict[str, np.ndarray],
    closure_sigmas: float,
    *,
    min_closure_m: float = 0.03,
    min_closure_deg: float = 0.1,
) -> tuple[list[Link], list[dict[str, Any]]]:
    """Links whose triangles all fail to close while at least one closes elsewhere in the graph.

    Every triangle ``a -> b -> c -> a`` of links is composed; it closes when the rotation and the
    translation at a scanner stay within ``closure_sigmas`` times the combined stated sigmas (at
    least ``min_closure_m`` and ``min_closure_deg``). Returns (the links to drop, one row per triangle)."""
    by_pair: dict[frozenset, Link] = {}
    for link in links:
        by_pair.setdefault(frozenset((link.moving, link.reference)), link)

    def matrix(a: str, b: str) -> Optional[np.ndarray]:  # b-file -> a-file
        link = by_pair.get(frozenset((a, b)))
        if link is None:
            return None
        return link.matrix if link.reference == a else np.linalg.inv(link.matrix)

    names = sorted({n for link in links for n in (link.moving, link.reference)})
    rows, passed, failed = [], {}, {}
    for a, b, c in itertools.combinations(names, 3):
        m_ab, m_bc, m_ca = matrix(a, b), matrix(b, c), matrix(c, a)
        if m_ab is None or m_bc is None or m_ca is None:
            continue
        loop = m_ab @ m_bc @ m_ca  # a-file -> a-file: identity when consistent
        rot, trans = _error(loop, np.eye(4), scanner[a])
        trio = [by_pair[frozenset(p)] for p in ((a, b), (b, c), (c, a))]
        sig_t = np.sqrt(sum(_link_sigma(x)[0] ** 2 for x in trio))
        sig_r = np.sqrt(sum(_link_sigma(x)[1] ** 2 for x in trio))
        ok = trans <= max(closure_sigmas * sig_t, min_closure_m) and rot <= max(closure_sigmas * sig_r, min_closure_deg)
        rows.append({"scans": [a, b, c], "rotation_deg": rot, "translation_m": trans, "closes": bool(ok)})
        for x in trio:
            key = id(x)
            (passed if ok else failed)[key] = (passed if ok else failed).get(key, 0) + 1
    drop = [x for x in links if failed.get(id(x), 0) > 0 and passed.get(id(x), 0) == 0]
    # a link that fails every triangle it is in, when every other link of those triangles also
    # closes a triangle elsewhere, is the culprit; links failing only with the culprit are kept
    culprits = []
    for x in drop:
        partners_ok = True
        for row in rows:
            if row["closes"] or x.moving not in row["scans"] or x.reference not in row["scans"]:
                continue
            others = [
                by_pair[frozenset(p)]
                for p in itertools.combinations(row["scans"], 2)
                if frozenset(p) != frozenset((x.moving, x.reference))
            ]
            partners_ok &= all(passed.get(id(o), 0) > 0 for o in others)
        if partners_ok:
            culprits.append(x)
    if not culprits and drop:
        # the loops cannot single the culprit out (e.g. one lone triangle): the link with the
        # weakest evidence (largest stated uncertainty) goes, reported as such
        culprits = [
            max(
                drop,
                key=lambda x: (_link_sigma(x)[0], -((x.result if x.result is not None else {}).get("matched") or 0)),
            )
        ]
        rows.append(
            {
                "note": f"loops cannot single out the wrong link; the weakest ({culprits[0].moving} -> {culprits[0].reference}) is dropped"
            }
        )
    return culprits, rows


def solve_pose_graph(
    frame: str,
    links: Sequence[Link],
    initial: dict[str, np.ndarray],
    scanner: dict[str, np.ndarray],
    fixed: Optional[dict[str, np.ndarray]] = None,
) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """Poses (file -> frame file, 4x4) minimising every link's disagreement over its stated sigma.

    Parameters: ``initial`` poses of every scan to solve (e.g. a spanning tree of the links),
    ``scanner`` each scan's scanner position in its file coordinates (where translations are
    compared), ``fixed`` poses held (the frame scan is always held at identity). Residuals are
    rotation vector / sigma_r and the displacement of the moving scanner / sigma_t; soft-L1 loss.
    Returns (poses, per-link residual rows).
    """
    held = {frame: np.eye(4), **(fixed or {})}
    free = [n for n in initial if n not in held]
    centre = {n: np.asarray(initial[n][:3, 3], dtype=float) for n in initial}
    index = {n: k for k, n in enumerate(free)}

    def unpack(x: np.ndarray) -> dict[str, np.ndarray]:
        poses = dict(held)
        for n, k in index.items():
            m = np.eye(4)
            m[:3, :3] = Rotation.from_rotvec(x[6 * k : 6 * k + 3]).as_matrix() @ initial[n][:3, :3]
            m[:3, 3] = centre[n] + x[6 * k + 3 : 6 * k + 6]
            poses[n] = m
        return poses

    usable = [link for link in links if link.moving in initial and link.reference in initial]

    def residuals(x: np.ndarray) -> np.ndarray:
        poses = unpack(x)
        out = []
        for link in usable:
            sig_t, sig_r = _link_sigma(link)
            predicted = np.linalg.inv(poses[link.reference]) @ poses[link.moving]
            delta = np.linalg.inv(link.matrix) @ predicted
            rv = Rotation.from_matrix(delta[:3, :3]).as_rotvec()
            s = scanner[link.moving]
            d = (predicted[:3, :3] @ s + predicted[:3, 3]) - (link.matrix[:3, :3] @ s + link.matrix[:3, 3])
            out.append(np.degrees(rv) / sig_r)
            out.append(d / sig_t)
        return np.concatenate(out) if out else np.zeros(1)

    if free and usable:
        sol = least_squares(residuals, np.zeros(6 * len(free)), loss="soft_l1", f_scale=3.0, x_scale="jac")
        poses = unpack(sol.x)
    else:
        poses = unpack(np.zeros(6 * len(free)))
    rows = []
    for link in usable:
        predicted = np.linalg.inv(poses[link.reference]) @ poses[link.moving]
        rot, trans = _error(link.matrix, predicted, scanner[link.moving])
        sig_t, sig_r = _link_sigma(link)
        rows.append(
            {
                "moving": link.moving,
                "reference": link.reference,
                "rotation_deg": rot,
                "translation_m": trans,
                "normalised": max(rot / sig_r, trans / sig_t),
            }
        )
    return poses, rows


def _spanning_poses(frame: str, links: Sequence[Link], fixed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Initial poses: breadth-first from the frame (and fixed scans) along the most certain links."""
    poses = {frame: np.eye(4), **fixed}
    ordered = sorted(links, key=lambda x: _link_sigma(x)[0])
    grown = True
    while grown:
        grown = False
        for link in ordered:
            if link.reference in poses and link.moving not in poses:
                poses[link.moving] = poses[link.reference] @ link.matrix
                grown = True
            elif link.moving in poses and link.reference not in poses:
                poses[link.reference] = poses[link.moving] @ np.linalg.inv(link.matrix)
                grown = True
    return poses


def _register_two_at_a_time(
    project: Project,
    pending: list[Link],
    scans: ScanCache,
    step: Progress,
    cancel: Optional[CancelToken],
    after: Optional[Callable[[], None]],
) -> None:
    """Register the further pairs ``pending`` two at a time (threads: a link's coarse matching and
    ICP keep about one core busy), for plots of :func:`~forestreg.engine.tls.plot.small_scans`
    whose scans the links to the centre left prepared (all of them kept), on a
    :class:`~forestreg.engine.tls.plot.LinkQueue` served by this thread and one more. The
    scans' points are let go first (:meth:`~forestreg.engine.tls.plot.ScanCache.let_go_of_points`:
    the links need only the preparations; two links' work takes about their room). ``after`` is
    called and the progress advanced as each link ends; results are those of the same links run
    one after the other."""
    # the links run on the kept preparations: the scans' points make room for two links' work
    scans.let_go_of_points()
    queue = LinkQueue(project, pending, scans, cancel)
    try:
        queue.finish(step, after=after)
    except BaseException:
        queue.close()
        raise


def register_survey(
    project: Project,
    params: Optional[SurveyParams] = None,
    *,
    scans: Optional[ScanCache] = None,
    rerun: bool = False,
    progress: Optional[ProgressCallback] = None,
    cancel: Optional[CancelToken] = None,
    on_link_done: Optional[Callable[[Project], None]] = None,
) -> PlotOutcome:
    """Register a whole survey (see the module docstring). The solution (poses, per-link rows,
    dropped links with reasons, per-scan uncertainty and quality) is stored in
    ``project.adjustment`` (``method: "survey"``), which :meth:`Project.poses` returns.

    ``on_link_done(project)`` is called after each finished link (see
    :func:`~forestreg.engine.tls.plot.register_project`); this function writes no file."""
    params = params or SurveyParams()
    after = None if on_link_done is None else (lambda: on_link_done(project))
    scans = scans or ScanCache(project)
    step = Progress(progress, cancel=cancel)
    # the links to the centre take the first part of the progress, the further pairs the rest
    # (about as many again for "all" pairs)
    share = 1.0 if params.pairs == "centre" else 0.5
    names = [s.name for s in project.scans]
    beside = None
    if params.pairs == "all" and len(names) > 2 and scans.small:
        # every pair is known before the links to the centre run: those whose scans are prepared
        # are registered beside them, by the thread that prepares the scans ahead
        default_links(project)
        scans.keep_prepared_points = False  # the links run on the preparations: room for two at once
        linked = {frozenset((link.moving, link.reference)) for link in project.links}
        beside = LinkQueue(
            project,
            [
                Link(moving=b, reference=a, extra=True)
                for a, b in itertools.combinations(names, 2)
                if frozenset((a, b)) not in linked
            ],
            scans,
            cancel,
        )
    try:
        outcome = register_project(
            project,
            rerun=rerun,
            progress=step.sub(0.0, share),
            cancel=cancel,
            scans=scans,
            beside=beside,
            on_link_done=on_link_done,
        )
    except BaseException:
        if beside is not None:
            beside.close()
        raise
    frame = project.centre
    if params.pairs != "centre":
        positions = _prior_positions(project, scans, project.chained_poses())
        linked = {frozenset((link.moving, link.reference)) for link in project.links}
        early = {
            frozenset((link.moving, link.reference)): link for link in (beside.links if beside is not None else [])
        }
        added: list[Link] = []
        for a, b in itertools.combinations(names, 2):
            if frozenset((a, b)) in linked:
                continue
            if params.pairs == "within":
                if a not in positions or b not in positions:
                    continue
                if np.linalg.norm(positions[a][:2] - positions[b][:2]) > params.max_distance_m:
                    continue
            if frozenset((a, b)) in early:  # registered (or under way) beside the links to the centre
                added.append(early.pop(frozenset((a, b))))
                project.links.append(added[-1])
            else:
                added.append(project.add_link(b, a))
        for link in early.values():  # a retried link now joins these scans
            beside.discard(link)
        pending = [
            link for link in project.links if link.extra and (link.result is None or any(link is x for x in added))
        ]
        if pending:
            log.info("registering %d further pairs", len(pending))
        if beside is not None:
            scans.let_go_of_points()  # the links run on the kept preparations: room for two at once
            try:
                beside.finish(step.sub(share, 1.0), after=after)
            except BaseException:
                beside.close()
                raise
        elif (
            len(pending) > 1
            and scans.small
            and all(
                scans.is_prepared(name, link.params(project.params))
                for link in pending
                for name in (link.reference, link.moving)
            )
        ):
            _register_two_at_a_time(project, pending, scans, step.sub(share, 1.0), cancel, after)
        for k, link in enumerate(pending):
            if link.result is not None:
                continue
            sub = step.sub(share + (1 - share) * k / len(pending), share + (1 - share) * (k + 1) / len(pending))
            sub(0.0, f"registering further pair {k + 1} of {len(pending)}: {link.moving} onto {link.reference}")
            link.result = _run_link(project, link, scans, sub, cancel)
            if after is not None:
                after()
        scans.prepared.release(("icp_reference",))  # the links are done: their ICP search structures go
        step(1.0, "done")
    scanner = {s.name: _scanner_file(scans, s.name) for s in project.scans if _usable(scans, s.name)}
    if frame not in scanner:  # the centre scan itself is unusable: nothing can be placed
        for s in project.scans:
            outcome.scans[s.name] = "failed"
            outcome.reasons.setdefault(s.name, f"the centre scan {frame} cannot be used")
        project.adjustment = None
        return outcome
    ok_links = [
        link
        for link in project.links
        if link.ok and link.matrix is not None and link.moving in scanner and link.reference in scanner
    ]
    dropped: list[dict[str, Any]] = []
    kept = []
    for link in ok_links:
        why = _prior_conflict(project, scans, link, params)
        if why:
            dropped.append(
                {
                    "moving": link.moving,
                    "reference": link.reference,
                    "reason": f"inconsistent with the prior poses: {why}",
                }
            )
            log.warning("dropping link %s -> %s: %s", link.moving, link.reference, why)
        else:
            kept.append(link)
    triangles: list[dict[str, Any]] = []
    while True:
        culprits, triangles = inconsistent_links(
            kept,
            scanner,
            params.closure_sigmas,
            min_closure_m=params.min_closure_m,
            min_closure_deg=params.min_closure_deg,
        )
        if not culprits:
            break
        worst = max(culprits, key=lambda x: _link_sigma(x)[0])
        kept.remove(worst)
        note = next((r["note"] for r in triangles if "note" in r), "")
        reason = note or "its loops do not close while the other links' loops do: inconsistent with the rest"
        dropped.append({"moving": worst.moving, "reference": worst.reference, "reason": reason})
        log.warning("dropping link %s -> %s: inconsistent with the other links", worst.moving, worst.reference)
    fixed = {}
    frame_prior = project.scan(frame).prior_pose
    for name in params.fixed:
        prior = project.scan(name).prior_pose
        if name != frame and prior is not None and frame_prior is not None:
            fixed[name] = np.linalg.inv(frame_prior) @ prior
        elif name != frame and _usable(scans, name) and _georeferenced(scans, name) and _georeferenced(scans, frame):
            fixed[name] = np.eye(4)
        elif name != frame:
            log.warning("%s cannot be held fixed: it has no prior pose (give --prior-poses)", name)
    initial = _spanning_poses(frame, kept, fixed)
    poses, rows = solve_pose_graph(frame, kept, initial, scanner, fixed)
    before = {}  # each link against the spanning-tree poses the adjustment started from
    for link in kept:
        if link.moving in initial and link.reference in initial:
            rot, trans = _error(
                link.matrix, np.linalg.inv(initial[link.reference]) @ initial[link.moving], scanner[link.moving]
            )
            before[(link.moving, link.reference)] = {"rotation_deg": rot, "translation_m": trans}
    # loops that disagree more than the links state: inflate every stated sigma by the excess
    dof = max(6 * len(rows) - 6 * max(len(poses) - 1 - len(fixed), 0), 0)
    chi2 = sum(min(r["normalised"], 10.0) ** 2 for r in rows) * 3.0  # ~ 3 components per block
    inflation = float(np.sqrt(chi2 / dof)) if dof > 0 else 1.0
    inflation = max(1.0, inflation)
    positions = {n: p[:3, :3] @ scanner[n] + p[:3, 3] for n, p in poses.items() if n in scanner}
    link_sigmas = [
        {
            "moving": x.moving,
            "reference": x.reference,
            "translation_m": _link_sigma(x)[0] * inflation,
            "rotation_deg": _link_sigma(x)[1] * inflation,
        }
        for x in kept
    ]
    uncertainty = propagate_uncertainty(frame, positions, link_sigmas)
    for name in fixed:
        uncertainty[name] = {"translation_m": 0.0, "rotation_deg": 0.0, "fixed": True}
    quality = _quality(project, kept, rows, dropped)
    all_poses: dict[str, Optional[list]] = {
        s.name: (poses[s.name].tolist() if s.name in poses else None) for s in project.scans
    }
    for s in project.scans:
        if s.name in poses and outcome.scans.get(s.name) == "failed":
            outcome.scans[s.name] = "ok"
            outcome.reasons.pop(s.name, None)
            log.info("%s placed through its neighbours", s.name)
        elif s.name not in poses and outcome.scans.get(s.name) in ("ok", "centre") and s.name != frame:
            outcome.scans[s.name] = "failed"
            outcome.reasons[s.name] = "no consistent link connects it to the others"
    project.adjustment = {
        "method": "survey",
        "poses": all_poses,
        "links": [
            {
                "moving": r["moving"],
                "reference": r["reference"],
                "before": before.get((r["moving"], r["reference"]), {}),
                "after": {"rotation_deg": r["rotation_deg"], "translation_m": r["translation_m"]},
                "normalised_residual": r["normalised"],
            }
            for r in rows
        ],
        "dropped": dropped,
        "triangles": triangles,
        "uncertainty": {k: v for k, v in uncertainty.items() if k in poses},
        "uncertainty_inflation": inflation,
        "quality": quality,
        "pairs": params.pairs,
    }
    return outcome


def _quality(
    project: Project, kept: Sequence[Link], rows: Sequence[dict[str, Any]], dropped: Sequence[dict[str, Any]]
) -> dict[str, Any]:
    """Per scan, from its links: how many, worst residual after the adjustment, matched trunks,
    ambiguity (second best / best matched VOPs), ICP spread and fitness, free space."""
    residual = {(r["moving"], r["reference"]): r for r in rows}
    out: dict[str, Any] = {}
    for s in project.scans:
        mine = [x for x in kept if s.name in (x.moving, x.reference)]
        items = []
        for x in mine:
            res = x.result if x.result is not None else {}
            icp = res.get("icp") or {}
            r = residual.get((x.moving, x.reference), {})
            matched = res.get("matched") or 0
            items.append(
                {
                    "other": x.reference if x.moving == s.name else x.moving,
                    "matched_vops": matched,
                    "ambiguity": None if not matched else (res.get("second_matched") or 0) / matched,
                    "vop_residual_m": res.get("vop_residual_m"),
                    "icp_std_m": icp.get("std_m"),
                    "icp_fitness": icp.get("fitness"),
                    "free_space_violation": res.get("free_space_violation"),
                    "terrain_median_m": (res.get("quality") or {}).get("terrain_median_m"),
                    "terrain_cells": (res.get("quality") or {}).get("terrain_cells"),
                    "residual_m": r.get("translation_m"),
                    "residual_deg": r.get("rotation_deg"),
                }
            )
        out[s.name] = {
            "links": len(mine),
            "dropped_links": sum(s.name in (d["moving"], d["reference"]) for d in dropped),
            "max_residual_m": max((i["residual_m"] for i in items if i["residual_m"] is not None), default=None),
            "max_residual_deg": max((i["residual_deg"] for i in items if i["residual_deg"] is not None), default=None),
            "terrain_median_m": max(
                (i["terrain_median_m"] for i in items if i["terrain_median_m"] is not None), default=None
            ),
            "min_matched_vops": min((i["matched_vops"] for i in items), default=None),
            "max_ambiguity": max((i["ambiguity"] for i in items if i["ambiguity"] is not None), default=None),
            "per_link": items,
        }
    return out


def read_positions_csv(path: str) -> dict[str, tuple[float, float, float]]:
    """Scanner positions from a CSV ``scan,x,y,z`` (file coordinates of each scan, metres; a header
    line is allowed). Raises :class:`~forestreg.engine.core.errors.ParameterError` on bad rows."""
    import csv

    from ..core.errors import ParameterError
    from ..io.base import read_text_lines

    _, lines = read_text_lines(path, ParameterError, "positions CSV")
    out: dict[str, tuple[float, float, float]] = {}
    for k, line in lines:
        row = next(csv.reader([line]))
        if not "".join(row).strip():
            continue
        if len(row) < 4:
            raise ParameterError(f"positions CSV {path}, line {k}: expected scan,x,y,z, got {','.join(row)!r}")
        try:
            xyz = tuple(float(v) for v in row[1:4])
        except ValueError:
            if k == lines[0][0]:
                continue  # header
            raise ParameterError(
                f"positions CSV {path}, line {k}: x,y,z must be numbers, got {','.join(row[1:4])!r}"
            ) from None
        if not np.isfinite(xyz).all():
            raise ParameterError(f"positions CSV {path}, line {k}: x,y,z must be finite")
        out[row[0].strip()] = xyz  # type: ignore[assignment]
    if not out:
        raise ParameterError(f"positions CSV {path}: no rows scan,x,y,z")
    return out


def read_prior_poses(path: str) -> dict[str, np.ndarray]:
    """Prior poses (each scan's file coordinates -> a common frame, 4x4) from a ``poses.json``
    (``{"scans": {name: {"matrix": 4x4}}}``), a JSON ``{name: 4x4}``, or a CSV
    ``scan,x,y,z[,heading_deg]`` (a GNSS position and compass heading of a scanner-centred file:
    the pose turns by the heading about the vertical, then moves to x,y,z)."""
    import json
    from pathlib import Path

    from ..core.errors import ParameterError
    from ..core.transform import matrix_from_yaw

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ParameterError(f"prior poses {path}: {exc.strerror or exc}") from exc
    out: dict[str, np.ndarray] = {}
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ParameterError(f"prior poses {path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
        items = data.get("scans", data) if isinstance(data, dict) else {}
        for name, value in items.items():
            m = value.get("matrix") if isinstance(value, dict) else value
            if m is None:
                continue
            arr = np.asarray(m, dtype=float) if isinstance(m, list) else None
            if (
                arr is None
                or arr.shape != (4, 4)
                or not np.isfinite(arr).all()
                or abs(np.linalg.det(arr[:3, :3]) - 1.0) > 1e-3
            ):
                raise ParameterError(f"prior poses {path}: {name}: a pose must be a rigid 4x4 matrix")
            out[str(name)] = arr
    else:
        import csv

        for k, row in enumerate(csv.reader(text.splitlines()), start=1):
            if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
                continue
            try:
                values = [float(v) for v in row[1:5]]
            except ValueError:
                if k == 1:
                    continue
                raise ParameterError(
                    f"prior poses {path}, line {k}: expected scan,x,y,z[,heading_deg] numbers"
                ) from None
            if len(values) < 3 or not np.isfinite(values).all():
                raise ParameterError(f"prior poses {path}, line {k}: expected scan,x,y,z[,heading_deg]")
            heading = values[3] if len(values) > 3 else 0.0
            out[row[0].strip()] = matrix_from_yaw(heading, np.array(values[:3]))
    if not out:
        raise ParameterError(f"prior poses {path}: no poses found")
    return out


def parse_pairs(text: str) -> tuple[str, float]:
    """``all`` | ``centre`` | ``within:D`` (D metres) -> (pairs, max_distance_m)."""
    from ..core.errors import ParameterError

    t = text.strip().lower()
    if t in ("all", "centre", "center"):
        return ("centre" if t == "center" else t), SurveyParams().max_distance_m
    if t.startswith("within:"):
        try:
            d = float(t.split(":", 1)[1])
        except ValueError:
            d = float("nan")
        if not np.isfinite(d) or d <= 0:
            raise ParameterError(f"--pairs {text}: the distance must be a positive number of metres")
        return "within", d
    raise ParameterError(f"--pairs {text}: expected all, centre or within:D (metres)")
