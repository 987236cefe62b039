"""Trees on a stand grown another way than the plots the height rules were chosen on.

:mod:`forestreg.engine.simulate.branched_stand` grows every tree as a branching skeleton with
leaves on its twigs (no crown shape is filled), dominant broadleaves and narrow-crowned trees with
suppressed trees under their crowns, scanned four times full-dome. Seed 615 is one of the
benchmark's held-out branched stands (``python -m benchmarks.trees_compare --branched``)."""

from __future__ import annotations

import functools
import math

import numpy as np

from forestreg.engine.simulate.branched_stand import branched_stand, scan_branched_stand
from forestreg.engine.trees.inventory import TreeParams, measure_trees


@functools.lru_cache(maxsize=None)
def _stand(seed: int):
    """(stand, points, each point's tree id, true heights, inventory without cylinder models)."""
    stand = branched_stand(seed)
    points, ids, heights = scan_branched_stand(stand)
    return stand, points, ids, heights, measure_trees(points, TreeParams(cylinder_models=False))


def test_a_branched_stand_has_suppressed_trees_under_dominant_crowns_and_true_tops():
    """The stand: 20-30 trees of at least 10 cm within 11 m, a quarter or more of them suppressed
    (their tops 5-16 m, under a dominant's crown); a tree's true height is the top of its own
    mesh, and the scans reach within 0.3 m of it for most trees."""
    stand, points, ids, heights, _ = _stand(615)
    inside = [t for t in stand.trees if math.hypot(t.x, t.y) < 11.0 and t.dbh_m >= 0.1]
    assert 20 <= len(inside) <= 30
    suppressed = [t for t in inside if t.suppressed]
    assert len(suppressed) >= 0.25 * len(inside)
    assert all(5.0 <= heights[t.id] <= 16.0 for t in suppressed)
    assert all(heights[t.id] >= t.wood.height_m - 1e-6 for t in inside)
    seen = [t for t in inside if np.any((ids == t.id) & (points[:, 2] - t.ground_z > heights[t.id] - 0.3))]
    assert len(seen) >= 0.8 * len(inside)


def test_trees_on_a_branched_stand_not_tuned_on():
    """Seed 615 (held out): every tree found, no false stem, DBH within 3 % rRMSE (measured
    1.1 %; one stem occluded at breast height has none); at least 15 heights unflagged (measured
    16), each within 10 % of the truth (measured within 1 %). No tree's highest point stands more
    than 10 % over its true top (measured 5 %): the small trees under a thicker neighbour's crown
    whose segments reached that crown across an empty band (up to +79 % without the cut) end at
    the band. Every tree's height within 7 % rRMSE (measured 5.3 %; Sylva 9.1 % on this stand),
    every suppressed tree's within 10 % (measured 5.5 %: a top under or touching the crown over it
    keeps its points' height, flagged, where the curve of free-grown trees stood it up to 66 % too
    tall), and each height more than 25 % off is flagged."""
    stand, _, _, heights, inv = _stand(615)
    inside = [t for t in stand.trees if math.hypot(t.x, t.y) < 11.0 and t.dbh_m >= 0.1]
    xy = np.array([(r.stem.x, r.stem.y) for r in inv.trees])
    pairs = []
    for t in inside:
        d = np.hypot(*(xy - (t.x, t.y)).T)
        assert d.min() < 0.5, f"tree {t.id} not found"
        pairs.append((inv.trees[int(np.argmin(d))], t))
    true_xy = np.array([(t.x, t.y) for t in stand.trees])
    false = [
        r.tree_id
        for r in inv.trees
        if math.hypot(r.stem.x, r.stem.y) < 11.0 and np.hypot(*(true_xy - (r.stem.x, r.stem.y)).T).min() > 0.5
    ]
    assert not false
    dbh = np.array([(r.dbh_m, t.dbh_m) for r, t in pairs if math.isfinite(r.dbh_m)])
    assert len(dbh) >= len(pairs) - 1  # a stem occluded at breast height has no DBH (flagged)
    assert math.sqrt(np.mean((dbh[:, 0] - dbh[:, 1]) ** 2)) / dbh[:, 1].mean() <= 0.03
    err = {t.id: r.height_m / heights[t.id] - 1.0 for r, t in pairs}
    low = {t.id: r.quality["height"].endswith(("low", "none")) for r, t in pairs}
    unflagged = [e for k, e in err.items() if not low[k]]
    assert len(unflagged) >= 15
    assert max(r.crown.height_m / heights[t.id] - 1.0 for r, t in pairs) <= 0.10
    h = np.array([(r.height_m, heights[t.id]) for r, t in pairs])
    assert math.sqrt(np.mean((h[:, 0] - h[:, 1]) ** 2)) / h[:, 1].mean() <= 0.07
    assert max(abs(err[t.id]) for _, t in pairs if t.suppressed) <= 0.10
    assert max(abs(e) for e in unflagged) <= 0.10
    assert all(low[k] for k, e in err.items() if abs(e) > 0.25)
