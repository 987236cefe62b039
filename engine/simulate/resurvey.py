"""A later survey of the same simulated stand, with truth: the test bed of ``forestreg change``.

Between the two surveys (:func:`grow_scene`):

- every tree grows: DBH by ``dbh_growth_mm_per_year`` and height by ``height_growth_m_per_year``
  (each tree its own rate drawn from the ranges); crowns widen, their bases rise and their foliage
  changes (leaf area density times a factor drawn from ``crown_density_factor``: leaf-on/off);
- a share of the trees is removed: the ones nearest ``removal_centre`` (a harvest gap) or, with
  ``removal="scattered"``, trees drawn at random (windthrow, mortality);
- new trees grow in (``ingrowth_fraction`` of the stand): thin, short trees in free places.

:func:`simulate_resurvey` scans the stand before and after from different scanner positions,
merges each survey and gives the later one in another frame (a heading and a shift, as a survey
georeferenced differently or not at all). Truth: ``matrix`` (``p_before = matrix @ p_after``, the
registration to find) and each tree's fate (``persisting``, ``removed``, ``new``) with its DBH (tape
and area-equivalent diameters), ovality and height in each survey. Stems may be drawn with real
shapes (``stem_shapes="real"``: oval, bark relief, buttresses; a growing stem keeps its shape), and
each survey may take 1-8 scans (``scans_per_survey``, layouts of :func:`survey_positions`).

Frames: the BEFORE cloud is in the scene frame (plot centred on the origin, metres, z up); the
AFTER cloud is in its own frame, ``p_scene = matrix @ p_after``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..core.errors import ParameterError
from .scene import (
    BREAST_HEIGHT_M,
    CONIFER,
    STEM_SHAPES,
    ForestScene,
    Tree,
    make_scene,
    real_stem_shape,
    with_stem_shapes,
)

__all__ = ["ResurveyCase", "frame_matrix", "grow_scene", "simulate_resurvey", "survey_positions"]

#: Scanner positions of either survey when none are given (the plot of the default 30 m).
DEFAULT_BEFORE_POSITIONS = ((-6.0, -6.0), (6.0, -6.0), (-6.0, 6.0), (6.0, 6.0), (0.0, 0.0))
DEFAULT_AFTER_POSITIONS = ((0.0, -8.0), (8.0, 0.0), (0.0, 8.0), (-8.0, 0.0), (1.5, 1.5))

#: Most scans per survey :func:`survey_positions` lays out.
MAX_SCANS_PER_SURVEY = 8


def survey_positions(n: int, size_m: float, survey: str = "before") -> tuple[tuple[float, float], ...]:
    """``n`` (1-8) scanner positions (x, y; scene frame, m) of one survey of a ``size_m`` plot
    centred on the origin.

    Layouts (``L = size_m``): one scan stands at the centre (before) or at ``(0.05 L, 0.05 L)``
    (after); 2-4 scans stand evenly on a circle about the centre, of radius ``0.28 L`` before
    (the first at 45 deg) and ``0.27 L`` after (turned by half their spacing: the first at
    ``45 + 180 / n`` deg); 5-8 scans are one at the centre as for one scan and ``n - 1`` on the
    circle as for 2-4. The two surveys never share a position (at least ``0.05 L`` apart), and
    every position lies at least ``0.2 L`` inside the plot's edge.
    """
    if survey not in ("before", "after"):
        raise ParameterError(f"survey must be 'before' or 'after', got {survey!r}")
    n = int(n)
    if not 1 <= n <= MAX_SCANS_PER_SURVEY:
        raise ParameterError(f"scans per survey must be within 1-{MAX_SCANS_PER_SURVEY}, got {n}")
    size = float(size_m)
    after = survey == "after"
    centre = (0.05 * size, 0.05 * size) if after else (0.0, 0.0)
    if n == 1:
        return (centre,)
    m = n if n <= 4 else n - 1
    radius = (0.27 if after else 0.28) * size
    start = 45.0 + (180.0 / m if after else 0.0)
    ring = tuple(
        (radius * math.cos(math.radians(start + 360.0 * k / m)), radius * math.sin(math.radians(start + 360.0 * k / m)))
        for k in range(m)
    )
    return ring if n <= 4 else ring + (centre,)


def frame_matrix(heading_deg: float, shift_m: Sequence[float]) -> np.ndarray:
    """4x4 ``p_scene = M @ p_other``: a turn about z by ``heading_deg`` (counter-clockwise) and a
    shift (metres)."""
    a = math.radians(float(heading_deg))
    m = np.eye(4)
    m[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    m[:3, 3] = np.asarray(shift_m, dtype=float).reshape(3)
    return m


def grow_scene(
    scene: ForestScene,
    *,
    years: float = 6.0,
    seed: int = 0,
    dbh_growth_mm_per_year: tuple[float, float] = (2.5, 5.0),
    height_growth_m_per_year: tuple[float, float] = (0.2, 0.45),
    removed_fraction: float = 0.25,
    removal: str = "gap",
    removal_centre: Sequence[float] = (0.0, 0.0),
    ingrowth_fraction: float = 0.1,
    ingrowth_dbh_m: tuple[float, float] = (0.07, 0.11),
    crown_density_factor: tuple[float, float] = (0.6, 1.4),
    keep_clear: Sequence[Sequence[float]] = (),
) -> tuple[ForestScene, dict[str, Any]]:
    """The stand ``years`` later and each tree's fate.

    A growing tree keeps its place, lean and stem shape (ovality and its direction, buttress
    lobes, bark pattern: :class:`~.scene.Tree`); its ``dbh_m``, the tape (girth) diameter at
    1.3 m, grows by the drawn DBH growth with the shape's fractions unchanged. In a scene drawn
    with real stem shapes (``meta["stem_shapes"] == "real"``) new trees get real shapes too.

    Returns ``(after_scene, fates)``: ``fates["trees"]`` one entry per tree of either survey with
    ``id`` (new trees get ids above the stand's), ``status`` ("persisting", "removed", "new"),
    ``x``, ``y`` (breast-height axis point, scene frame), ``dbh_before_m``, ``dbh_after_m`` (tape
    diameters, m), ``area_dbh_before_m``, ``area_dbh_after_m`` (diameters of the circle of the
    section's area at 1.3 m, m), ``height_before_m``, ``height_after_m`` (None where the tree is
    absent) and ``ovality``. ``keep_clear``: (x, y) places (scanner positions) where no new tree
    grows.
    """
    if not 0.0 <= removed_fraction < 1.0:
        raise ParameterError(f"removed_fraction must be within [0, 1), got {removed_fraction}")
    if removal not in ("gap", "scattered"):
        raise ParameterError(f"removal must be 'gap' or 'scattered', got {removal!r}")
    rng = np.random.default_rng([int(seed), 35])
    trees = list(scene.trees)
    n = len(trees)
    n_removed = int(round(removed_fraction * n))
    xy = np.array([[t.x, t.y] for t in trees]).reshape(-1, 2)
    if removal == "gap":
        d = np.hypot(*(xy - np.asarray(removal_centre, dtype=float)).T)
        removed = set(np.argsort(d, kind="stable")[:n_removed].tolist())
    else:
        removed = set(rng.choice(n, n_removed, replace=False).tolist()) if n_removed else set()
    grown: list[Tree] = []
    fates: list[dict[str, Any]] = []
    for k, t in enumerate(trees):
        dd = years * rng.uniform(*dbh_growth_mm_per_year) / 1000.0
        dh = years * rng.uniform(*height_growth_m_per_year)
        bh = t.point_at_height(1.3)
        entry = {
            "id": t.id,
            "x": float(bh[0]),
            "y": float(bh[1]),
            "dbh_before_m": t.dbh_m,
            "height_before_m": t.height_m,
            "ovality": t.ovality,
            "area_dbh_before_m": t.area_diameter_m(BREAST_HEIGHT_M),
        }
        if k in removed:
            fates.append(
                {**entry, "status": "removed", "dbh_after_m": None, "height_after_m": None, "area_dbh_after_m": None}
            )
            continue
        g = dataclasses.replace(
            t,
            dbh_m=round(t.dbh_m + dd, 5),
            height_m=t.height_m + dh,
            crown_base_m=t.crown_base_m + 0.5 * dh,
            crown_radius_m=t.crown_radius_m * float(rng.uniform(1.0, 1.2)),
            leaf_area_density=t.leaf_area_density * float(rng.uniform(*crown_density_factor)),
        )
        grown.append(g)
        fates.append(
            {
                **entry,
                "status": "persisting",
                "dbh_after_m": g.dbh_m,
                "height_after_m": g.height_m,
                "area_dbh_after_m": g.area_diameter_m(BREAST_HEIGHT_M),
            }
        )
    # ingrowth: thin trees in free places (at least 1.5 m from any standing stem and 1.5 m from a scanner)
    xmin, xmax, ymin, ymax = scene.extent
    n_new = int(round(ingrowth_fraction * n))
    standing = [np.array([t.x, t.y]) for t in grown] + [np.asarray(p, dtype=float)[:2] for p in keep_clear]
    next_id = max((t.id for t in trees), default=0) + 1
    real_shapes = dict(scene.meta).get("stem_shapes") == "real"
    tries = 0
    while n_new > 0 and tries < 5000:
        tries += 1
        p = np.array([rng.uniform(xmin + 1.0, xmax - 1.0), rng.uniform(ymin + 1.0, ymax - 1.0)])
        if standing and min(float(np.hypot(*(p - s))) for s in standing) < 1.5:
            continue
        dbh = float(rng.uniform(*ingrowth_dbh_m))
        h = float(rng.uniform(5.0, 8.0))
        t = Tree(
            next_id,
            float(p[0]),
            float(p[1]),
            float(scene.ground_z(p[0], p[1])),
            dbh_m=round(dbh, 5),
            height_m=h,
            lean_deg=float(rng.uniform(0.0, 2.0)),
            lean_azimuth_deg=float(rng.uniform(0.0, 360.0)),
            crown_base_m=0.4 * h,
            crown_radius_m=0.8 + 2.0 * dbh,
            shape=CONIFER,
            n_branches=3,
            leaf_area_density=0.5,
        )
        if real_shapes:  # drawn from the tree's own stream: the other draws stay
            t = real_stem_shape(t, scene.seed, scene.preset)
        grown.append(t)
        standing.append(p)
        bh = t.point_at_height(1.3)
        fates.append(
            {
                "id": t.id,
                "status": "new",
                "x": float(bh[0]),
                "y": float(bh[1]),
                "dbh_before_m": None,
                "dbh_after_m": t.dbh_m,
                "height_before_m": None,
                "height_after_m": t.height_m,
                "ovality": t.ovality,
                "area_dbh_before_m": None,
                "area_dbh_after_m": t.area_diameter_m(BREAST_HEIGHT_M),
            }
        )
        next_id += 1
        n_new -= 1
    after = dataclasses.replace(scene, trees=tuple(grown), meta={**dict(scene.meta), "years_later": float(years)})
    return after, {"years": float(years), "removal": removal, "removed_fraction": removed_fraction, "trees": fates}


@dataclass(frozen=True, eq=False)
class ResurveyCase:
    """Two merged surveys of one stand and their truth.

    ``before`` (N, 3) scene frame; ``after`` (M, 3) in the later survey's frame; ``matrix`` the
    true ``p_before = matrix @ p_after``; ``truth`` the JSON-able truth (matrix, fates, positions);
    ``files`` the written clouds (``before.laz``, ``after.laz``, ``truth.json``) once
    :func:`~forestreg.engine.io.simulated.write_resurvey` wrote them.
    """

    before: np.ndarray
    after: np.ndarray
    matrix: np.ndarray
    truth: dict[str, Any]
    before_scene: ForestScene
    after_scene: ForestScene
    files: dict[str, Path] = field(default_factory=dict)

    def fates(self) -> list[dict[str, Any]]:
        return list(self.truth["fates"]["trees"])


def simulate_resurvey(
    preset: str = "planted_conifer",
    *,
    size_m: float = 30.0,
    seed: int = 0,
    before_positions: Optional[Sequence[Sequence[float]]] = None,
    after_positions: Optional[Sequence[Sequence[float]]] = None,
    after_heading_deg: float = 117.0,
    after_shift_m: Sequence[float] = (412.7, -238.4, 35.2),
    angular_step_deg: float = 0.3,
    scene: Optional[ForestScene] = None,
    stem_shapes: str = "round",
    scans_per_survey: Optional[int] = None,
    **growth: Any,
) -> ResurveyCase:
    """Scan a stand (``preset``, ``size_m``, ``seed``) from ``before_positions``, let it change
    (:func:`grow_scene` with ``growth``: ``years``, ``removed_fraction``, ...) and scan it again
    from ``after_positions``; the later survey is given in another frame
    (``p_scene = frame_matrix(after_heading_deg, after_shift_m) @ p_after``).

    Positions are (x, y) in the scene frame (m). Without them: ``scans_per_survey`` scans in each
    survey at the layouts of :func:`survey_positions` (different positions in the two surveys),
    or, without that too, :data:`DEFAULT_BEFORE_POSITIONS` and :data:`DEFAULT_AFTER_POSITIONS`
    (five scans each). ``stem_shapes`` ("round" or "real") is passed to
    :func:`~.scene.make_scene`; with a given ``scene``, "real" gives its trees real shapes
    (:func:`~.scene.with_stem_shapes`).

    Places within 1 m of any scanner position of either survey are cleared first (an operator
    sets up in a gap). ``truth["before_scan_points"]`` / ``["after_scan_points"]`` count the
    points of each scan, in the order of the positions. Nothing is written here
    (:func:`~forestreg.engine.io.simulated.write_resurvey` writes the case).
    """
    from .plot import simulate_plot

    if stem_shapes not in STEM_SHAPES:
        raise ParameterError(f"stem_shapes must be one of {', '.join(STEM_SHAPES)}, got {stem_shapes!r}")
    if scans_per_survey is not None:
        if before_positions is not None or after_positions is not None:
            raise ParameterError("give either scans_per_survey or the scanner positions, not both")
        before_positions = survey_positions(scans_per_survey, size_m, "before")
        after_positions = survey_positions(scans_per_survey, size_m, "after")
    before_positions = DEFAULT_BEFORE_POSITIONS if before_positions is None else before_positions
    after_positions = DEFAULT_AFTER_POSITIONS if after_positions is None else after_positions
    if scene is not None:
        base = with_stem_shapes(scene) if stem_shapes == "real" else scene
    else:
        base = make_scene(
            preset, seed=seed, size_m=size_m, **({"stem_shapes": stem_shapes} if stem_shapes != "round" else {})
        )
    every = [tuple(p) for p in before_positions] + [tuple(p) for p in after_positions]
    base = base.cleared(every, 1.0)
    growth.setdefault("keep_clear", every)
    after_scene, fates = grow_scene(base, seed=seed, **growth)
    before_plot = simulate_plot(
        preset, before_positions, scene=base, seed=seed, angular_step_deg=angular_step_deg, clearance_m=0.0
    )
    after_plot = simulate_plot(
        preset, after_positions, scene=after_scene, seed=seed + 1000, angular_step_deg=angular_step_deg, clearance_m=0.0
    )
    before = np.vstack([s.world_points() for s in before_plot.scans])
    frame = frame_matrix(after_heading_deg, after_shift_m)
    after_world = np.vstack([s.world_points() for s in after_plot.scans])
    after = (after_world - frame[:3, 3]) @ frame[:3, :3]  # p_after = inv(frame) @ p_scene
    truth = {
        "format": "forestreg-simulated-resurvey",
        "conventions": {
            "matrix": "p_before = matrix @ p_after (the registration to find)",
            "before": "scene frame: plot centred on the origin, metres, z up",
            "trees": "x, y: the stem axis at 1.3 m, BEFORE (scene) frame; dbh_*_m: tape (girth) "
            "diameters at 1.3 m; area_dbh_*_m: diameters of the circle of the section's area",
        },
        "preset": preset,
        "seed": int(seed),
        "size_m": float(size_m),
        "matrix": frame.tolist(),
        "stem_shapes": stem_shapes,
        "before_positions": [list(map(float, p)) for p in before_positions],
        "after_positions": [list(map(float, p)) for p in after_positions],
        "before_scan_points": [int(len(s.scan)) for s in before_plot.scans],
        "after_scan_points": [int(len(s.scan)) for s in after_plot.scans],
        "fates": fates,
    }
    return ResurveyCase(
        before=before, after=after, matrix=frame, truth=truth, before_scene=base, after_scene=after_scene
    )
