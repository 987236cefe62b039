"""Automatic (trunk shadows) vs manual (targets) registration of the same plot: the paper's
evaluation (sec. 2.7, tables 4 and 5).

For the same links, both routes end with the same ICP. Compared are, per pair, the ICP standard
deviation and the matched VOPs, and how far apart the two results are (rotation in degrees, and
the displacement of the moving scanner in metres); per plot, the average distance between the
centres of the same target seen from different scans once every scan is in the centre frame.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import numpy as np

from ..core.progress import CancelToken, Progress, ProgressCallback
from ..core.transform import rotation_angle_deg
from .manual import register_manual, target_residuals
from .plot import ScanCache, register_project
from .project import Project


def compare_auto_manual(
    project: Project,
    *,
    scans: Optional[ScanCache] = None,
    progress: Optional[ProgressCallback] = None,
    cancel: Optional[CancelToken] = None,
    on_link_done: Optional[Callable[[Project], None]] = None,
) -> dict[str, Any]:
    """Register the project automatically (its links, with retries), then register the same links
    manually from the scans' targets, and compare (the structure is documented in the README and
    read by :func:`~forestreg.engine.report.plot_report.write_plot_report`).

    The project keeps the automatic result; the manual poses are in ``["manual_poses"]``.
    ``on_link_done(project)`` is called after each finished automatic link (see
    :func:`~forestreg.engine.tls.plot.register_project`); nothing is written here.
    """
    scans = scans or ScanCache(project)
    step = Progress(progress, cancel=cancel)
    register_project(project, scans=scans, progress=step.sub(0.0, 0.6), cancel=cancel, on_link_done=on_link_done)
    auto_poses = project.poses()
    placing = [project.link_of(s.name) for s in project.scans if s.name != project.centre]
    manual_links: dict[str, np.ndarray] = {}
    pairs = []
    for k, link in enumerate(placing):
        sub = step.sub(0.6 + 0.4 * k / max(len(placing), 1), 0.6 + 0.4 * (k + 1) / max(len(placing), 1))
        reference, moving = scans(link.reference), scans(link.moving)
        manual = register_manual(
            reference,
            moving,
            project.scan(link.reference).targets,
            project.scan(link.moving).targets,
            link.params(project.params),
            progress=sub,
            cancel=cancel,
        )
        if manual.ok:
            manual_links[link.moving] = manual.matrix
        auto = link.result if link.result is not None else {}
        row: dict[str, Any] = {
            "moving": link.moving,
            "reference": link.reference,
            "auto": {
                "status": auto.get("status", "not run"),
                "reason": auto.get("reason", ""),
                "matched": auto.get("matched"),
                "icp_std_m": (auto.get("icp") or {}).get("std_m"),
                "reference_vops": auto.get("reference_vops"),
                "moving_vops": auto.get("moving_vops"),
            },
            "manual": {
                "status": manual.status,
                "reason": manual.reason,
                "icp_std_m": None if manual.icp is None else manual.icp.std_m,
                "targets": None if manual.target_fit is None else len(manual.target_fit.target_ids),
            },
            "rotation_difference_deg": None,
            "translation_difference_m": None,
        }
        if link.ok and manual.ok:
            diff = np.linalg.inv(manual.matrix) @ link.matrix
            row["rotation_difference_deg"] = rotation_angle_deg(diff[:3, :3])
            scanner = np.append(moving.scanner_position_file, 1.0)
            row["translation_difference_m"] = float(
                np.linalg.norm((link.matrix @ scanner - manual.matrix @ scanner)[:3])
            )
        pairs.append(row)
    manual_poses = _compose(project, manual_links)
    # target ids are known to name the same targets across scans only where the target fit of a
    # pair succeeded (it checks the ids); elsewhere a "residual" would compare unrelated targets
    trusted = {project.centre, *manual_links}
    targets = {s.name: s.targets for s in project.scans if s.targets and s.name in trusted}
    auto_res = target_residuals(targets, auto_poses)
    manual_res = target_residuals(targets, manual_poses)
    note = ""
    if auto_res.get("mean_m") is None:
        reasons = sorted(
            {p["manual"]["reason"] for p in pairs if p["manual"]["status"] != "ok" and p["manual"]["reason"]}
        )
        note = "no target is seen, under the same id, by two scans whose targets were fitted" + (
            f" ({'; '.join(reasons)})" if reasons else ""
        )
    step(1.0, "done")
    return {
        "frame": project.centre,
        "pairs": pairs,
        "auto_target_residual_m": auto_res.get("mean_m"),
        "manual_target_residual_m": manual_res.get("mean_m"),
        "target_residual_note": note,
        "targets": {
            "auto": {k: v["mean_distance_m"] for k, v in auto_res.get("per_target", {}).items()},
            "manual": {k: v["mean_distance_m"] for k, v in manual_res.get("per_target", {}).items()},
        },
        "auto_poses": {k: None if v is None else v.tolist() for k, v in auto_poses.items()},
        "manual_poses": {k: None if v is None else v.tolist() for k, v in manual_poses.items()},
    }


def _compose(project: Project, link_matrices: dict[str, np.ndarray]) -> dict[str, Optional[np.ndarray]]:
    """Poses from the manual link matrices, composed along the project's links."""
    poses: dict[str, Optional[np.ndarray]] = {s.name: None for s in project.scans}
    poses[project.centre] = np.eye(4)
    for _ in range(len(project.scans)):
        for s in project.scans:
            link = project.link_of(s.name)
            if (
                poses[s.name] is None
                and link is not None
                and s.name in link_matrices
                and poses.get(link.reference) is not None
            ):
                poses[s.name] = poses[link.reference] @ link_matrices[s.name]
    return poses
