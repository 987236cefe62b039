"""Tree edits by hand (engine/trees/edit.py): each edit changes only the trees it names, re-measures
them with the inventory's own steps, and the results agree with the simulator's truth."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

from forestreg.app.trees import save_edited
from forestreg.engine.core.errors import ParameterError, ScanDataError
from forestreg.engine.io.results import read_trees_dir
from forestreg.engine.trees import edit as E
from forestreg.engine.trees.inventory import TreeParams, measure_trees

PARAMS = TreeParams(cylinder_models=False)


@functools.lru_cache(maxsize=None)
def _case():
    from forestreg.engine.simulate import simulate_plot

    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.4, size_m=14.0)
    points = np.vstack([s.world_points() for s in plot.scans])
    return plot, points, measure_trees(points, PARAMS)


def _near(inv, x, y):
    d = [math.hypot(r.stem.x - x, r.stem.y - y) for r in inv.trees]
    k = int(np.argmin(d))
    return inv.trees[k] if d[k] < 0.3 else None


def _truth(plot, x, y):
    return min(plot.scene.trees, key=lambda t: math.hypot(t.x - x, t.y - y))


def _unchanged(before, after, ids):
    old = {r.tree_id: r for r in before.trees}
    return all(r is old[r.tree_id] for r in after.trees if r.tree_id not in ids)


def test_merge_then_split_restores_both_trees():
    plot, points, inv = _case()
    a, b = _near(inv, 1.93, 0.08), _near(inv, 2.69, 3.41)  # two true trees 3.4 m apart
    merged = E.merge_trees(points, inv, a.tree_id, b.tree_id, PARAMS)
    assert len(merged.trees) == len(inv.trees) - 1
    m = next(r for r in merged.trees if r.tree_id == a.tree_id)
    assert m.n_points == a.n_points + b.n_points
    assert not np.any(merged.labels == b.tree_id)
    assert _unchanged(inv, merged, {a.tree_id})
    split = E.split_tree(points, merged, a.tree_id, (b.stem.x + 0.2, b.stem.y - 0.1), PARAMS)
    assert len(split.trees) == len(inv.trees)
    new = max(split.trees, key=lambda r: r.tree_id)
    assert new.tree_id > max(r.tree_id for r in inv.trees)
    assert math.hypot(new.stem.x - b.stem.x, new.stem.y - b.stem.y) < 0.05
    for rec, orig in ((next(r for r in split.trees if r.tree_id == a.tree_id), a), (new, b)):
        truth = _truth(plot, orig.stem.x, orig.stem.y)
        assert abs(rec.dbh.dbh_m - truth.dbh_m) < 0.015, (rec.dbh.dbh_m, truth.dbh_m)
        assert abs(rec.n_points - orig.n_points) <= 0.05 * orig.n_points
    assert _unchanged(merged, split, {a.tree_id, new.tree_id})


def test_delete_and_add_a_stem_by_clicking_it():
    plot, points, inv = _case()
    rec = _near(inv, -3.59, 1.54)
    gone = E.delete_tree(inv, rec.tree_id)
    assert len(gone.trees) == len(inv.trees) - 1 and not np.any(gone.labels == rec.tree_id)
    assert _unchanged(inv, gone, set())
    back = E.add_stem(points, gone, (rec.stem.x + 0.25, rec.stem.y + 0.2), PARAMS)  # a click beside the stem
    new = max(back.trees, key=lambda r: r.tree_id)
    truth = _truth(plot, rec.stem.x, rec.stem.y)
    assert math.hypot(new.stem.x - truth.x, new.stem.y - truth.y) < 0.05
    assert abs(new.dbh.dbh_m - truth.dbh_m) < 0.015
    # a click on empty ground finds no stem: an honest error, nothing changed
    with pytest.raises(ScanDataError):
        E.add_stem(points, inv, (-5.5, -3.0), PARAMS)


def test_dbh_at_another_height_follows_the_taper():
    plot, points, inv = _case()
    rec = _near(inv, 6.18, 2.68)
    truth = _truth(plot, rec.stem.x, rec.stem.y)
    s, r = truth.profile()
    for h in (2.0, 2.5):
        edited = E.dbh_at_height(points, inv, rec.tree_id, h, PARAMS)
        got = next(x for x in edited.trees if x.tree_id == rec.tree_id)
        assert got.dbh.s_m == pytest.approx(h, abs=0.11)
        # a third to half of the section seen: within 4 % and within the stated 1-sigma
        err = abs(got.dbh.dbh_m - 2 * np.interp(h, s, r))
        assert err < 0.015 and err < got.dbh_sigma_m, (h, err, got.dbh_sigma_m)
        assert _unchanged(inv, edited, {rec.tree_id})
    with pytest.raises(ParameterError):
        E.dbh_at_height(points, inv, rec.tree_id, 9.0, PARAMS)


def test_edits_are_written_marked_and_replayed(tmp_path):
    plot, points, inv = _case()
    a, b = _near(inv, 1.93, 0.08), _near(inv, 2.69, 3.41)
    edits = [E.TreeEdit("merge", (a.tree_id, b.tree_id)), E.TreeEdit("dbh_height", (a.tree_id,), height_m=1.6)]
    steps, cur = [], inv
    for e in edits:
        cur = E.apply_edit(points, cur, e, PARAMS)
        steps.append((e, cur))
    notes = E.edit_notes(inv, steps)
    assert set(notes) == {a.tree_id} and "merged with tree" in notes[a.tree_id] and "1.60 m" in notes[a.tree_id]
    save_edited(tmp_path, cur, notes, edits, report=False)
    out = read_trees_dir(tmp_path)
    assert len(out.trees) == len(inv.trees) - 1
    marked = {t.tree_id: t.edited for t in out.trees if t.edited}
    assert marked == notes
    dbh = next(t for t in out.trees if t.tree_id == a.tree_id).get("dbh_m")
    assert dbh == pytest.approx(
        next(r for r in cur.trees if r.tree_id == a.tree_id).dbh_m, abs=1e-4
    )  # the reported DBH
    replayed = E.apply_edits(points, inv, E.read_edits(tmp_path / "edits.json"), PARAMS)
    assert [r.tree_id for r in replayed.trees] == [r.tree_id for r in cur.trees]
    assert json.loads((tmp_path / "edits.json").read_text())["edits"][0]["kind"] == "merge"
