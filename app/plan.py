"""Where to scan next (``forestreg plan``): from the placed scans of a plot project, the stems seen
by two or more scans, the stem and ground area not seen yet within the plot, the strength of the
links, and the next one to three scanner positions that would link to a placed scan and see the
most stem area not seen yet (:mod:`forestreg.engine.tls.plan`); written to ``plan.json`` and,
beside it, ``plan.gpkg`` (the suggestions as the ``next_scans`` point layer of
:func:`~forestreg.app.layers.plan_layers`, styled for QGIS as numbered markers).

Positions are in the plan frame: the centre scan's file coordinates (x, y), metres. The layer has
the plot's CRS when one is known (:func:`plan_crs`), local coordinates otherwise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from .common import RunOutcome
from .saved import count_or_none, finite_or_none, mapping_or_empty

PLAN_FILE = "plan.json"
PLAN_FORMAT = "forestreg-plan"
#: The suffix of the plan's GeoPackage, written beside the plan file (``plan.json`` -> ``plan.gpkg``).
PLAN_LAYERS_SUFFIX = ".gpkg"


@dataclass(frozen=True)
class LinkStrength:
    """How firmly a placed scan hangs on its reference: trunk shadows matched and still coinciding
    after ICP, the ambiguity (the best other solution's matches over the best's), the pair's
    1-sigma uncertainty (m, deg) and a word: "strong" (at least twice ``min_shared_stems`` trunk
    shadows matched), "fair" (at least ``min_shared_stems``) or "weak" (fewer: a scan between the
    two would make it firmer)."""

    moving: str
    reference: str
    matched: Optional[int]
    confirmed: Optional[int]
    ambiguity: Optional[float]
    translation_m: Optional[float]
    rotation_deg: Optional[float]
    strength: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "moving": self.moving,
            "reference": self.reference,
            "matched": self.matched,
            "confirmed": self.confirmed,
            "ambiguity": self.ambiguity,
            "translation_m": self.translation_m,
            "rotation_deg": self.rotation_deg,
            "strength": self.strength,
        }


@dataclass(frozen=True, eq=False)
class PlanRun(RunOutcome):
    """A plan: ``plan`` the engine's :class:`~forestreg.engine.tls.plan.ScanPlan`, ``links`` the
    :class:`LinkStrength` of each placed scan's link, ``out`` the ``plan.json`` written, ``layers``
    the ``plan.gpkg`` beside it, ``crs`` the layer's :class:`~forestreg.engine.io.crs.Crs` (None:
    local coordinates). Failed (with the reason) when no position within the plot would link."""

    plan: Any = None
    links: tuple = ()
    frame: Optional[str] = None
    layers: Optional[Path] = None
    crs: Any = None


def link_strengths(project, min_shared: int) -> tuple[LinkStrength, ...]:
    """The :class:`LinkStrength` of every successful link of ``project``."""
    rows = []
    for link in project.links:
        if not link.ok:
            continue
        r = link.result
        quality, u = mapping_or_empty(r.get("quality")), mapping_or_empty(r.get("uncertainty"))
        matched = count_or_none(r.get("matched"))
        word = (
            ""
            if matched is None
            else ("strong" if matched >= 2 * min_shared else "fair" if matched >= min_shared else "weak")
        )
        rows.append(
            LinkStrength(
                link.moving,
                link.reference,
                matched,
                count_or_none(quality.get("confirmed_vops")),
                finite_or_none(quality.get("ambiguity")),
                finite_or_none(u.get("translation_m")),
                finite_or_none(u.get("rotation_deg")),
                word or "manual",
            )
        )
    return tuple(rows)


def project_of(source) -> Path:
    """The project file of ``source``: a ``project.json`` (or another project file) or a plot
    folder holding one. A missing one is bad input (:class:`~forestreg.engine.core.errors.UsageError`)."""
    from ..engine.core.errors import UsageError

    p = Path(source).expanduser()
    if p.is_dir():
        p = p / "project.json"
        if not p.is_file():
            raise UsageError(f"{source}: holds no project.json (give a plot folder or a project file)")
    elif not p.is_file():
        raise UsageError(f"{source}: no such project file or plot folder")
    return p


def plan_next(source, *, n: int = 1, params=None, out=None, scans=None, progress=None) -> PlanRun:
    """Plan the next ``n`` (1 to 3) scans of the plot project ``source`` (a project file or a plot
    folder) with the :class:`~forestreg.engine.tls.params.PlanParams` ``params`` and write
    ``plan.json`` (``out``, default beside the project file) and ``plan.gpkg`` beside it (the same
    name, suffix ``.gpkg``). Both are written to temporary files first and renamed into place
    together, the GeoPackage first: each is whole or absent, and nothing is replaced when either
    cannot be written. ``scans``: a :class:`~forestreg.engine.tls.plot.ScanCache` of the project
    holding its preparations."""
    from ..engine.core.atomic import atomic_path
    from ..engine.core.errors import UsageError
    from ..engine.core.jsonable import to_jsonable
    from ..engine.io.gpkg import write_geopackage
    from ..engine.tls.params import PlanParams
    from ..engine.tls.plot import ScanCache
    from ..engine.tls.project import Project
    from .layers import plan_layers

    if not 1 <= int(n) <= 3:
        raise UsageError(f"--n must be 1, 2 or 3, got {n}")
    params = params or PlanParams()
    path = project_of(source)
    target = Path(out) if out is not None else path.parent / PLAN_FILE
    if target.suffix.lower() != ".json" or target.is_dir():
        raise UsageError(f"{target}: the plan is written to a .json file")
    layers = target.with_suffix(PLAN_LAYERS_SUFFIX)
    project = Project.load(path)
    scans = scans if scans is not None else ScanCache(project, with_intensity=False)
    plan, links = plan_project(project, n=n, params=params, scans=scans, progress=progress, source=path)
    report = progress or (lambda f, m: None)
    crs = plan_crs(path, project, scans)
    doc = plan_document(plan, links, project.centre, params)
    with (
        atomic_path(target) as tmp_plan,
        atomic_path(layers) as tmp_layers,
    ):  # renamed inner first: plan.gpkg, then plan.json
        write_geopackage(tmp_layers, plan_layers(plan), crs)
        tmp_plan.write_text(json.dumps(to_jsonable(doc, nan_as_null=True), indent=1) + "\n", encoding="utf-8")
    report(1.0, "done")
    return PlanRun(
        status="ok" if plan.suggestions else "failed",
        reason=plan.reason,
        out=target,
        plan=plan,
        links=links,
        frame=project.centre,
        layers=layers,
        crs=crs,
    )


def plan_crs(project_file, project, scans=None):
    """The CRS of a plan's layer (:class:`~forestreg.engine.io.crs.Crs`, None when none is known):
    that of the plot folder's ``layers.gpkg`` beside ``project_file`` (what ``forestreg plot``
    wrote, its ``--crs`` included), else the centre scan's as its file declares it."""
    from ..engine.io.gpkg import read_crs
    from .layers import LAYERS_FILE
    from .plot import plot_crs

    beside = Path(project_file).parent / LAYERS_FILE
    if beside.is_file():
        found = read_crs(beside)
        if found is not None:
            return found
    return plot_crs(project, scans).crs


def plan_project(project, *, n: int = 1, params=None, scans=None, progress=None, source=None) -> tuple:
    """The plan of the next ``n`` scans of the ``project`` in memory (as :func:`plan_next` makes
    it, nothing written) and the strength of its links: ``(plan, links)``."""
    from ..engine.core.errors import DataError
    from ..engine.tls.params import PlanParams
    from ..engine.tls.plan import placed_links, placed_views, plan_scans
    from ..engine.tls.plot import ScanCache

    params = params or PlanParams()
    poses = project.poses()
    placed = [s.name for s in project.scans if poses.get(s.name) is not None]
    if not placed:
        raise DataError(f"{source or project.name}: no scan of the project is placed yet (register the plot first)")
    report = progress or (lambda f, m: None)
    report(0.0, f"reading the {len(placed)} placed scans")
    scans = scans if scans is not None else ScanCache(project, with_intensity=False)
    views = placed_views(project, scans, cell_m=params.ground_cell_m)
    report(0.7, "planning the next scans")
    plan = plan_scans(views, params, project.params, n=int(n), links=placed_links(project))
    return plan, link_strengths(project, params.min_shared_stems)


def plan_document(plan, links, frame: Optional[str], params) -> dict[str, Any]:
    """The body of ``plan.json``."""
    return {
        "format": PLAN_FORMAT,
        "version": 1,
        "frame": frame,
        "convention": "positions (x, y[, z]) in the centre scan's file coordinates, metres, seen from above",
        "plot": {"centre": list(plan.centre), "radius_m": plan.radius_m},
        "scanners": {name: list(xyz) for name, xyz in plan.scanners.items()},
        "stems": {
            "mapped": plan.stems,
            "seen_by_two_or_more": plan.stems_seen_twice,
            "area_seen_m2": plan.stem_area_seen_m2,
            "area_not_seen_m2": plan.stem_area_unseen_m2,
            "band_m": params.stem_band_m,
        },
        "ground": {"seen_m2": plan.ground_seen_m2, "not_seen_m2": plan.ground_unseen_m2},
        "links": [link.to_dict() for link in links],
        "candidates": {
            "tried": plan.candidates,
            "linking": plan.linking,
            "min_shared_stems": params.min_shared_stems,
            "shared_falloff_m": plan.falloff_m if plan.falloff_m != float("inf") else None,
        },
        "suggestions": [
            {
                "rank": k + 1,
                "x": s.x,
                "y": s.y,
                "links_to": s.links_to,
                "shared_stems": s.shared_stems,
                "vop_radius_m": s.radius_m,
                "distance_m": s.distance_m,
                "new_stem_area_m2": s.new_stem_area_m2,
                "new_view_m2": s.new_view_m2,
                "expected_stem_area_m2": s.expected_stem_area_m2,
                "reason": s.reason,
            }
            for k, s in enumerate(plan.suggestions)
        ],
        "reason": plan.reason or None,
    }


__all__ = [
    "LinkStrength",
    "PLAN_FILE",
    "PLAN_LAYERS_SUFFIX",
    "PlanRun",
    "link_strengths",
    "plan_crs",
    "plan_document",
    "plan_next",
    "project_of",
]
