"""Comparison: a plot registered automatically (trunk shadows) and from reflector targets, side by
side (the paper's tables 4 and 5; ``forestreg compare``).

:func:`compare_plot` registers both ways (:func:`forestreg.engine.tls.compare.compare_auto_manual`)
and writes the folder (``comparison.json``/``.csv``, ``project.json``, ``poses.json``,
``report.html``) as one transaction.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

from .common import RunOutcome, with_cancel

log = logging.getLogger("forestreg")


@dataclass(frozen=True)
class SideResult:
    """One registration of a pair (automatic or from targets): status, reason, ICP std (m),
    matched VOPs (automatic) or targets used (manual), and the trunk shadows (VOPs) found in the
    reference and the moving scan (automatic)."""

    status: str
    reason: str = ""
    icp_std_m: Optional[float] = None
    matched: Optional[int] = None
    targets: Optional[int] = None
    reference_vops: Optional[int] = None
    moving_vops: Optional[int] = None

    @classmethod
    def of(cls, d) -> "SideResult":
        d = d if isinstance(d, Mapping) else {}
        return cls(
            str(d.get("status") or "failed"),
            str(d.get("reason") or ""),
            d.get("icp_std_m"),
            d.get("matched"),
            d.get("targets"),
            d.get("reference_vops"),
            d.get("moving_vops"),
        )

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class PairComparison:
    """A pair registered both ways, and how far apart the two matrices are."""

    moving: str
    reference: str
    auto: SideResult
    manual: SideResult
    rotation_difference_deg: Optional[float]
    translation_difference_m: Optional[float]

    @classmethod
    def of(cls, d: Mapping) -> "PairComparison":
        return cls(
            str(d.get("moving")),
            str(d.get("reference")),
            SideResult.of(d.get("auto")),
            SideResult.of(d.get("manual")),
            d.get("rotation_difference_deg"),
            d.get("translation_difference_m"),
        )


@dataclass(frozen=True)
class ComparisonFigures:
    """A comparison (what :func:`compare_in_memory` returns, or ``comparison.json``), typed: the
    pairs, the average target distance residual of each way (m) with its note, and each target's
    residual (target id -> m) of each way."""

    pairs: tuple = ()
    auto_target_residual_m: Optional[float] = None
    manual_target_residual_m: Optional[float] = None
    target_residual_note: str = ""
    auto_targets: dict = field(default_factory=dict)
    manual_targets: dict = field(default_factory=dict)

    @classmethod
    def of(cls, d: Mapping) -> "ComparisonFigures":
        targets = d.get("targets") if isinstance(d.get("targets"), Mapping) else {}
        return cls(
            tuple(PairComparison.of(p) for p in d.get("pairs") or [] if isinstance(p, Mapping)),
            d.get("auto_target_residual_m"),
            d.get("manual_target_residual_m"),
            str(d.get("target_residual_note") or ""),
            dict(targets.get("auto") or {}),
            dict(targets.get("manual") or {}),
        )


@dataclass(frozen=True, eq=False)
class ComparisonOutcome(RunOutcome):
    """The comparison of a plot: ``pairs`` (:class:`PairComparison`), the average target distance
    residual of each way (m) and its note; ``json_path`` the comparison written. Failed when a
    registration failed (the reasons in ``failed``)."""

    method = "auto (trunk shadows) against targets"
    pairs: tuple = ()
    auto_target_residual_m: Optional[float] = None
    manual_target_residual_m: Optional[float] = None
    target_residual_note: str = ""
    failed: tuple = ()
    json_path: Optional[Path] = None
    report: Optional[Path] = None


def compare_plot(project, out, *, inputs: Sequence = (), progress=None, cancel=None) -> ComparisonOutcome:
    """Register ``project`` (whose scans carry targets) both ways and write the folder ``out``."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.core.errors import UsageError
    from ..engine.io.results import write_comparison
    from ..engine.tls.compare import compare_auto_manual
    from ..engine.tls.plot import ScanCache
    from .plot import write_poses

    out = check_output_folder(out, "compare", inputs=list(inputs))
    with_targets = [s.name for s in project.scans if s.targets]
    if len(with_targets) < 2:
        raise UsageError(
            "compare needs targets in at least two scans (--targets TARGETS.csv with scan,target,x,y,z; "
            f"scans with targets: {', '.join(with_targets) or 'none'})"
        )
    scans = ScanCache(project)
    comparison = compare_auto_manual(project, scans=scans, progress=with_cancel(progress, cancel))
    drawn = False
    with output_folder(out, "compare") as tmp:
        project.save(tmp / "project.json")
        write_poses(project, tmp)
        json_path, _ = write_comparison(comparison, tmp)
        try:
            from ..engine.report.plot_report import write_plot_report

            write_plot_report(project, tmp / "report.html", scans=scans, comparison=comparison)
            drawn = (tmp / "report.html").exists()
        except Exception as exc:  # a report must never lose the result
            log.warning("could not write the report: %s", exc)
    # the project file was saved inside the temporary folder: point it at its final place
    project.path = out / "project.json"
    figures = ComparisonFigures.of(comparison)
    pairs = figures.pairs
    failed = tuple(
        f"{p.moving} -> {p.reference} {name}: {side.reason or 'failed'}"
        for p in pairs
        for name, side in (("auto", p.auto), ("manual", p.manual))
        if not side.ok
    )
    return ComparisonOutcome(
        status="failed" if failed else "ok",
        reason="; ".join(failed),
        out=out,
        summary=comparison,
        result=comparison,
        pairs=pairs,
        auto_target_residual_m=figures.auto_target_residual_m,
        manual_target_residual_m=figures.manual_target_residual_m,
        target_residual_note=figures.target_residual_note,
        failed=failed,
        json_path=out / Path(json_path).name,
        report=out / "report.html" if drawn else None,
    )


def comparison_project(scans: Sequence, params, **marks: Any):
    """The project of a comparison: :func:`forestreg.app.plot.new_project`."""
    from .plot import new_project

    return new_project(scans, params, **marks)


def compare_in_memory(project, *, scans=None, progress=None, cancel=None) -> dict:
    """Register ``project`` automatically and from its targets, nothing written (the desktop's
    comparison): the comparison as :func:`~forestreg.engine.tls.compare.compare_auto_manual`
    returns it."""
    from ..engine.tls.compare import compare_auto_manual

    return compare_auto_manual(project, scans=scans, progress=progress, cancel=cancel)
