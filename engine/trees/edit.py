"""Corrections of a tree inventory by hand (the desktop's correction loop): merge two trees, split
one, delete a false stem, add a missed stem at a clicked position, and measure the DBH at another
height (a buttressed stem). Each edit is a pure function of a
:class:`~forestreg.engine.trees.inventory.TreeInventory` and the cloud's points that returns a new
inventory in which only the edited trees were measured again (with the same step functions as
:func:`~forestreg.engine.trees.inventory.measure_trees`); the others are untouched.

Edits are described by :class:`TreeEdit` records (JSON-friendly: :meth:`TreeEdit.to_dict`), so a
list of them can be kept in a project or next to ``trees.csv`` (``edits.json``, which also records
the content hash of the cloud they were made on) and replayed on the same cloud with
:func:`apply_edits` (another cloud is refused, also one with the same number of points).
:func:`forestreg.app.trees.save_edited` writes the edited inventory like ``forestreg trees`` does,
with an ``edited`` column naming each tree's edits.

Frame: the inventory's local frame (the points given to ``measure_trees``; metres, z up). A
clicked position from a file-coordinate view is converted by subtracting ``origin_shift``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import ParameterError, ScanDataError
from .consistency import stem_curve_wood
from .crown import CrownMeasurement, measure_crown
from .inventory import TreeInventory, TreeParams, TreeRecord, ground_near_stems, tree_record
from .segmentation import tree_completeness
from .stems import Stem, detect_stems, measure_dbh, stem_curve

__all__ = [
    "EDIT_KINDS",
    "TreeEdit",
    "TreeEdits",
    "add_stem",
    "apply_edit",
    "apply_edits",
    "cloud_digest",
    "dbh_at_height",
    "delete_tree",
    "measure_tree",
    "edit_notes",
    "merge_trees",
    "read_edits",
    "split_tree",
]

EDIT_KINDS = ("delete", "merge", "split", "add", "dbh_height")


@dataclass(frozen=True)
class TreeEdit:
    """One correction. ``kind`` one of :data:`EDIT_KINDS`; ``trees`` the tree ids it acts on
    (merge: the kept tree first); ``xy`` a position (local frame, m) for add / split;
    ``height_m`` the DBH height (m above the stem base) for dbh_height."""

    kind: str
    trees: tuple[int, ...] = ()
    xy: Optional[tuple[float, float]] = None
    height_m: Optional[float] = None

    def __post_init__(self) -> None:
        if self.kind not in EDIT_KINDS:
            raise ParameterError(f"unknown tree edit '{self.kind}' (one of {', '.join(EDIT_KINDS)})")
        for name in ("trees", "xy"):  # a list from a caller is taken as the tuple it stands for
            if isinstance(getattr(self, name), list):
                object.__setattr__(self, name, tuple(getattr(self, name)))
        if not isinstance(self.trees, tuple) or not all(_is_id(t) for t in self.trees):
            raise ParameterError(
                f"a {self.kind} edit: trees must be a list of tree ids (whole numbers), not {self.trees!r}"
            )
        wanted = {"delete": 1, "merge": 2, "split": 1, "add": 0, "dbh_height": 1}[self.kind]
        if len(self.trees) != wanted:
            count = {0: "no tree", 1: "one tree", 2: "two trees"}[wanted]
            raise ParameterError(f"a {self.kind} needs {count}, not {len(self.trees)}")
        if self.xy is not None and not (
            isinstance(self.xy, tuple) and len(self.xy) == 2 and all(_is_number(v) for v in self.xy)
        ):
            raise ParameterError(
                f"a {self.kind} edit: the position must be two finite numbers (x, y in m), not {self.xy!r}"
            )
        if self.kind in ("split", "add") and self.xy is None:
            raise ParameterError(f"a {self.kind} needs a position (x, y in m)")
        if self.height_m is not None and not _is_number(self.height_m):
            raise ParameterError(f"a {self.kind} edit: the height must be a finite number (m), not {self.height_m!r}")
        if self.kind == "dbh_height" and self.height_m is None:
            raise ParameterError("a dbh_height needs a height (m)")

    def describe(self) -> str:
        """A short note for trees.csv and the report."""
        if self.kind == "delete":
            return "deleted"
        if self.kind == "merge":
            return f"merged with tree {', '.join(str(t) for t in self.trees[1:])}"
        if self.kind == "split":
            return f"split (tree {self.trees[0]} was two)" if self.trees else "split"
        if self.kind == "add":
            return "stem added by hand"
        return f"DBH measured at {self.height_m:.2f} m"

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "trees": list(self.trees),
            "xy": None if self.xy is None else list(self.xy),
            "height_m": self.height_m,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TreeEdit":
        """An edit from its JSON form; ParameterError naming what is wrong (values are taken as
        they are, never converted: ``"12"`` is not a list of tree ids)."""
        if not isinstance(d, Mapping):
            raise ParameterError(f"not a tree edit: {d!r} (an edit is an object with kind, trees, xy, height_m)")
        unknown = sorted(set(d) - {"kind", "trees", "xy", "height_m"})
        if unknown:
            raise ParameterError(f"not a tree edit: unknown field(s) {', '.join(map(str, unknown))}")
        if not isinstance(d.get("kind"), str):
            raise ParameterError(f"not a tree edit: kind must be one of {', '.join(EDIT_KINDS)}, not {d.get('kind')!r}")
        trees, xy = d.get("trees", []), d.get("xy")
        if trees is None:
            trees = []
        if not isinstance(trees, list):
            raise ParameterError(f"a {d['kind']} edit: trees must be a list of tree ids (whole numbers), not {trees!r}")
        if xy is not None and not isinstance(xy, list):
            raise ParameterError(f"a {d['kind']} edit: the position must be two finite numbers (x, y in m), not {xy!r}")
        return cls(kind=d["kind"], trees=tuple(trees), xy=None if xy is None else tuple(xy), height_m=d.get("height_m"))


def _is_id(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_number(v: Any) -> bool:
    return (
        isinstance(v, (int, float, np.integer, np.floating))
        and not isinstance(v, (bool, np.bool_))
        and math.isfinite(v)
    )


class TreeEdits(list):
    """The edits of an ``edits.json`` (a list of :class:`TreeEdit`) with ``cloud``: the content
    hash of the cloud they were made on (:func:`cloud_digest`), None in files that lack it."""

    cloud: Optional[str] = None


def cloud_digest(points: np.ndarray) -> str:
    """The content hash of a cloud (SHA-256 of its x, y, z as float64, in order): edits replay
    only on the cloud with this hash."""
    import hashlib

    p = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64)
    return hashlib.sha256(p.tobytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# measuring one tree
# --------------------------------------------------------------------------------------------


def _tree_indices(inventory: TreeInventory, tree_id: int) -> np.ndarray:
    return np.flatnonzero(inventory.labels == tree_id)


def measure_tree(
    points: np.ndarray,
    inventory: TreeInventory,
    stem: Stem,
    indices: np.ndarray,
    params: TreeParams = TreeParams(),
    *,
    breast_height_m: Optional[float] = None,
    search_tree: Optional[cKDTree] = None,
) -> TreeRecord:
    """Measure one tree from its points (``indices`` into ``points``) and its stem: DBH (at
    ``breast_height_m`` along the stem if given, else the parameters'), stem curve, crown,
    completeness flags and cylinder model, with the step functions ``measure_trees`` uses."""
    p = points
    heights = inventory.heights
    base_params = (
        params.noisy_stems.apply(params.stems) if getattr(inventory, "method", "fine") == "noisy" else params.stems
    )
    stem_params = (
        base_params
        if breast_height_m is None
        else dataclasses.replace(base_params, breast_height_m=float(breast_height_m))
    )
    index = search_tree if search_tree is not None else cKDTree(p)
    dbh = measure_dbh(p, heights, stem, stem_params, search_tree=index)
    curve = stem_curve(p, heights, stem, base_params, search_tree=index)
    labels = np.zeros(len(p), dtype=inventory.labels.dtype)
    labels[indices] = stem.id
    complete = tree_completeness(p, heights, labels, [stem], params.completeness, {stem.id: dbh})
    try:
        crown = measure_crown(p[indices], heights[indices], stem, params.crown)
    except ScanDataError as exc:
        nan = math.nan
        crown = CrownMeasurement(
            tree_id=stem.id,
            x=stem.x,
            y=stem.y,
            height_m=nan,
            crown_base_m=nan,
            crown_width_ew_m=nan,
            crown_width_ns_m=nan,
            crown_area_m2=nan,
            crown_diameter_m=nan,
            crown_length_m=nan,
            crown_volume_m3=nan,
            n_points=int(len(indices)),
            top=(nan, nan, nan),
            ok=False,
            reasons=(str(exc),),
        )
    wood = inventory.wood_probability.copy() if len(inventory.wood_probability) == len(p) else np.zeros(len(p))
    wood[stem_curve_wood(p, index, stem, curve, max(2.0 * stem_params.inlier_tolerance_m, 0.03))] = 1.0
    ground = np.asarray(inventory.ground, dtype=bool)
    no_ground = not ground.any()
    return tree_record(
        p,
        stem,
        np.asarray(indices),
        dbh,
        curve,
        crown,
        wood,
        complete[0].reasons if complete else (),
        params,
        stem_params=stem_params,
        method=getattr(inventory, "method", "fine"),
        no_ground=no_ground,
        ground_near=ground_near_stems(p, ground, [stem], params.ground_near_stem_m).get(stem.id),
        height_curve=getattr(inventory, "height_curve", None),
    )


def _replace(inventory: TreeInventory, records: Sequence[TreeRecord], labels: np.ndarray) -> TreeInventory:
    ordered = sorted(records, key=lambda r: r.tree_id)
    return dataclasses.replace(inventory, trees=list(ordered), labels=labels)


def _record(inventory: TreeInventory, tree_id: int) -> TreeRecord:
    for r in inventory.trees:
        if r.tree_id == tree_id:
            return r
    raise ParameterError(f"there is no tree {tree_id}")


def _stem_near(
    points: np.ndarray, inventory: TreeInventory, xy: Sequence[float], params: TreeParams, exclude: Iterable[Stem] = ()
) -> Stem:
    """The stem nearest ``xy`` found by the stem detector in the points within
    ``params.stem_search_radius_m`` of it (stems in ``exclude`` are not taken); ScanDataError if none."""
    c = np.asarray(xy, dtype=np.float64)[:2]
    near = np.flatnonzero(np.hypot(points[:, 0] - c[0], points[:, 1] - c[1]) <= params.stem_search_radius_m)
    if len(near) < 30:
        raise ScanDataError(
            f"too few points within {params.stem_search_radius_m:g} m of ({c[0]:.2f}, {c[1]:.2f}) to find a stem"
        )
    found = detect_stems(points[near], inventory.heights[near], params.stems)
    taken = [s for s in exclude]
    found = [s for s in found if all(math.hypot(s.x - t.x, s.y - t.y) > max(s.radius_m, t.radius_m) for t in taken)]
    if not found:
        raise ScanDataError(f"no stem found within {params.stem_search_radius_m:g} m of ({c[0]:.2f}, {c[1]:.2f})")
    best = min(found, key=lambda s: math.hypot(s.x - c[0], s.y - c[1]))
    return dataclasses.replace(best, point_indices=near[best.point_indices])


def _next_id(inventory: TreeInventory) -> int:
    return max([r.tree_id for r in inventory.trees] + [int(inventory.labels.max()) if len(inventory.labels) else 0]) + 1


# --------------------------------------------------------------------------------------------
# the edits
# --------------------------------------------------------------------------------------------


def delete_tree(inventory: TreeInventory, tree_id: int) -> TreeInventory:
    """Remove a false stem: its record goes, its points become unassigned (label 0)."""
    _record(inventory, tree_id)
    labels = inventory.labels.copy()
    labels[labels == tree_id] = 0
    return _replace(inventory, [r for r in inventory.trees if r.tree_id != tree_id], labels)


def merge_trees(
    points: np.ndarray, inventory: TreeInventory, keep: int, other: int, params: TreeParams = TreeParams()
) -> TreeInventory:
    """One tree taken as two: ``other``'s points join ``keep`` (whose stem stays) and the merged
    tree is measured again; ``other`` is removed."""
    if keep == other:
        raise ParameterError("cannot merge a tree with itself")
    a = _record(inventory, keep)
    _record(inventory, other)
    labels = inventory.labels.copy()
    labels[labels == other] = keep
    merged = measure_tree(
        points, dataclasses.replace(inventory, labels=labels), a.stem, np.flatnonzero(labels == keep), params
    )
    rest = [r for r in inventory.trees if r.tree_id not in (keep, other)]
    return _replace(inventory, rest + [merged], labels)


def split_tree(
    points: np.ndarray, inventory: TreeInventory, tree_id: int, xy: Sequence[float], params: TreeParams = TreeParams()
) -> TreeInventory:
    """Two trees taken as one: a second stem is detected near ``xy``; the tree's points go to the
    nearer of the two stem axes (horizontally, at each point's height), both are measured again;
    the new tree gets the next free id."""
    a = _record(inventory, tree_id)
    stem_b = _stem_near(points, inventory, xy, params, exclude=[a.stem])
    new_id = _next_id(inventory)
    stem_b = dataclasses.replace(stem_b, id=new_id)
    idx = _tree_indices(inventory, tree_id)
    pts = points[idx]

    def axis_distance(stem: Stem) -> np.ndarray:
        s = (pts[:, 2] - stem.base[2]) / max(float(stem.axis[2]), 1e-6)
        on_axis = stem.base[None, :] + s[:, None] * stem.axis[None, :]
        return np.hypot(pts[:, 0] - on_axis[:, 0], pts[:, 1] - on_axis[:, 1])

    to_b = axis_distance(stem_b) < axis_distance(a.stem)
    labels = inventory.labels.copy()
    labels[idx[to_b]] = new_id
    inv = dataclasses.replace(inventory, labels=labels)
    index = cKDTree(points)
    rec_a = measure_tree(points, inv, a.stem, idx[~to_b], params, search_tree=index)
    rec_b = measure_tree(points, inv, stem_b, idx[to_b], params, search_tree=index)
    rest = [r for r in inventory.trees if r.tree_id != tree_id]
    return _replace(inventory, rest + [rec_a, rec_b], labels)


def add_stem(
    points: np.ndarray, inventory: TreeInventory, xy: Sequence[float], params: TreeParams = TreeParams()
) -> TreeInventory:
    """A missed stem: detected near ``xy``. It takes the points within 1.5 m of it horizontally
    (above the ground clearance) that are unassigned or nearer to it than to their own stem; it
    and the trees it took points from are measured again. The new tree gets the next free id."""
    stem = _stem_near(points, inventory, xy, params, exclude=[r.stem for r in inventory.trees])
    new_id = _next_id(inventory)
    stem = dataclasses.replace(stem, id=new_id)
    d_new = np.hypot(points[:, 0] - stem.x, points[:, 1] - stem.y)
    candidates = np.flatnonzero((d_new <= 1.5) & (inventory.heights > params.segmentation.ground_clearance_m))
    stems = {r.tree_id: r.stem for r in inventory.trees}
    take = []
    for i in candidates:
        own = int(inventory.labels[i])
        if own == 0 or own not in stems:
            take.append(i)
        elif d_new[i] < math.hypot(points[i, 0] - stems[own].x, points[i, 1] - stems[own].y):
            take.append(i)
    take_idx = np.asarray(take, dtype=np.int64)
    touched = sorted({int(v) for v in inventory.labels[take_idx] if int(v) in stems})
    labels = inventory.labels.copy()
    labels[take_idx] = new_id
    inv = dataclasses.replace(inventory, labels=labels)
    index = cKDTree(points)
    new = [measure_tree(points, inv, stem, take_idx, params, search_tree=index)]
    for tid in touched:
        new.append(measure_tree(points, inv, stems[tid], np.flatnonzero(labels == tid), params, search_tree=index))
    rest = [r for r in inventory.trees if r.tree_id not in touched]
    return _replace(inventory, rest + new, labels)


def dbh_at_height(
    points: np.ndarray, inventory: TreeInventory, tree_id: int, height_m: float, params: TreeParams = TreeParams()
) -> TreeInventory:
    """Measure the tree's DBH at ``height_m`` along its stem (above a buttress) instead of the
    breast height; the rest of the tree is measured again as well (same points)."""
    lo, hi = 0.3, 5.0
    if not (lo <= float(height_m) <= hi):
        raise ParameterError(f"the DBH height must be between {lo:g} and {hi:g} m (got {height_m:g})")
    a = _record(inventory, tree_id)
    rec = measure_tree(points, inventory, a.stem, _tree_indices(inventory, tree_id), params, breast_height_m=height_m)
    return _replace(inventory, [r for r in inventory.trees if r.tree_id != tree_id] + [rec], inventory.labels)


def apply_edit(
    points: np.ndarray, inventory: TreeInventory, edit: TreeEdit, params: TreeParams = TreeParams()
) -> TreeInventory:
    """Apply one :class:`TreeEdit`."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) != len(inventory.labels):
        raise ParameterError("the points are not the ones the inventory was measured on")
    t = edit.trees
    if edit.kind == "delete":
        return delete_tree(inventory, t[0])
    if edit.kind == "merge":
        if len(t) != 2:
            raise ParameterError("a merge needs two trees")
        return merge_trees(p, inventory, t[0], t[1], params)
    if edit.kind == "split":
        if edit.xy is None or not t:
            raise ParameterError("a split needs a tree and a position")
        return split_tree(p, inventory, t[0], edit.xy, params)
    if edit.kind == "add":
        if edit.xy is None:
            raise ParameterError("adding a stem needs a position")
        return add_stem(p, inventory, edit.xy, params)
    if edit.height_m is None or not t:
        raise ParameterError("a DBH height edit needs a tree and a height")
    return dbh_at_height(p, inventory, t[0], edit.height_m, params)


def apply_edits(
    points: np.ndarray, inventory: TreeInventory, edits: Iterable[TreeEdit], params: TreeParams = TreeParams()
) -> TreeInventory:
    """Replay edits in order (e.g. those read from ``edits.json`` on the same cloud). Edits read
    from a file that records its cloud's hash (:class:`TreeEdits`) are refused on another cloud."""
    recorded = getattr(edits, "cloud", None)
    if recorded is not None and cloud_digest(points) != recorded:
        raise ParameterError(
            "these tree edits were made on another cloud (its content differs; the same number of "
            "points is not enough): open the cloud they were made on"
        )
    for e in edits:
        inventory = apply_edit(points, inventory, e, params)
    return inventory


def edit_notes(before: TreeInventory, edits: Sequence[tuple[TreeEdit, TreeInventory]]) -> dict[int, str]:
    """Tree id -> "; "-joined notes of the edits that changed it (trees that no longer exist
    are left out). ``edits``: each edit with the inventory it produced, in order."""
    notes: dict[int, list[str]] = {}
    prev = before
    for edit, after in edits:
        old = {r.tree_id: r for r in prev.trees}
        for r in after.trees:
            if old.get(r.tree_id) is not r:
                notes.setdefault(r.tree_id, []).append(edit.describe())
        prev = after
    alive = {r.tree_id for r in prev.trees}
    return {k: "; ".join(dict.fromkeys(v)) for k, v in notes.items() if k in alive}


def read_edits(path: str | Path) -> TreeEdits:
    """The edits of an ``edits.json`` with the hash of their cloud; ParameterError naming what is
    wrong if it is not one."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ParameterError(f"cannot read the tree edits {path}: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != "forestreg-tree-edits":
        raise ParameterError(f"{path} is not a forestreg tree edits file")
    items = data.get("edits", [])
    if not isinstance(items, list):
        raise ParameterError(f"{path}: edits must be a list of edits, not {items!r}")
    edits = TreeEdits()
    for k, item in enumerate(items):
        try:
            edits.append(TreeEdit.from_dict(item))
        except ParameterError as exc:
            raise ParameterError(f"{path}: edit {k + 1}: {exc}") from None
    cloud = data.get("cloud")
    if cloud is not None:
        if not isinstance(cloud, dict) or not isinstance(cloud.get("sha256"), str):
            raise ParameterError(f"{path}: cloud must be an object with the cloud's sha256")
        edits.cloud = cloud["sha256"]
    return edits
