"""One outcome shape for pair, manual and co-registration results, and the typed link result."""

from __future__ import annotations

import json

import numpy as np
import pytest

from forestreg.engine.core.outcome import Outcome, OutcomeRecord, StepTimer, seconds_keys
from forestreg.engine.coreg.coregister import CoregistrationResult
from forestreg.engine.tls.manual import ManualResult
from forestreg.engine.tls.pair import PairResult
from forestreg.engine.tls.project import Link, LinkResult, Project

SHARED = ("method", "status", "reason", "matrix", "convention", "evidence", "timings")


def _rigid(deg: float = 10.0, t=(1.0, 2.0, 0.5)) -> np.ndarray:
    a = np.radians(deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[:3, 3] = t
    return m


def test_every_registration_result_is_an_outcome():
    for cls in (PairResult, ManualResult, CoregistrationResult):
        assert issubclass(cls, Outcome)
        assert cls.method and "matrix @" in cls.convention


def test_manual_result_dict_has_the_shared_keys_first_and_seconds():
    r = ManualResult(
        status="ok",
        reason="",
        matrix=_rigid(),
        target_fit=None,
        icp=None,
        timings={"target_fit_s": 0.5, "icp_s": 2.0},
        reference_name="a",
        moving_name="b",
    )
    d = r.to_dict()
    assert list(d)[: len(SHARED)] == list(SHARED)
    assert all(k.endswith("_s") for k in d["timings"]) and r.total_s == pytest.approx(2.5)
    assert d["evidence"]["targets"] is None and d["evidence"]["suspect_targets"] == []
    rec = r.record()
    assert rec.ok and np.allclose(rec.matrix, _rigid()) and rec.method == "manual (targets + ICP)"
    assert rec == json.loads(json.dumps(d)), "the record equals its JSON"


def test_coregistration_failure_dict_round_trips():
    r = CoregistrationResult(
        status="failed",
        reason="no canopy",
        matrix=None,
        local_matrix=None,
        keypoint_matrix=None,
        ground_keypoints=None,
        uav_keypoints=None,
        match=None,
        matched_after_icp=None,
        residuals_after_icp_m=None,
        icp=None,
        surface_correlation=float("nan"),
        alternative_correlation=float("nan"),
        timings={"terrain_s": 1.0},
    )
    d = r.to_dict()
    assert list(d)[2 : 2 + len(SHARED)] == list(SHARED)  # after format and version
    assert d["evidence"]["matched"] == 0
    rec = OutcomeRecord.from_dict(d)
    assert not rec.ok and rec.reason == "no canopy" and rec.matrix is None and rec.timings == {"terrain_s": 1.0}


def test_seconds_keys_and_step_timer():
    assert seconds_keys({"icp": 1, "read_s": 2.5, "junk": "x"}) == {"icp_s": 1.0, "read_s": 2.5}
    t = StepTimer()
    assert t.run("slice", sum, [1, 2]) == 3
    t.run("slice", sum, [3])
    t.add("icp_s", 0.25)
    assert set(t) == {"slice_s", "icp_s"} and t["icp_s"] == 0.25 and t["slice_s"] >= 0.0


@pytest.mark.parametrize(
    "bad, why",
    [
        (np.full((4, 4), np.nan), "finite"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "scale"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "mirror"),
        (None, "no matrix"),
        ([[1, 0], [0, 1]], "4x4"),
    ],
)
def test_an_ok_record_is_never_a_bad_matrix(bad, why):
    rec = OutcomeRecord.from_dict(
        {"status": "ok", "reason": "", "matrix": None if bad is None else np.asarray(bad).tolist()}
    )
    assert not rec.ok and rec.matrix is None and rec["matrix"] is None and "withheld" in rec.reason, why


def test_old_and_odd_records_are_read_safely():
    rec = OutcomeRecord.from_dict({"status": "maybe", "timings": {"icp": 3.0}})
    assert not rec.ok and "unknown status" in rec.reason and rec.timings == {"icp_s": 3.0}
    with pytest.raises(TypeError):
        OutcomeRecord.from_dict("ok")


def test_link_result_is_typed_and_a_mapping(tmp_path):
    link = Link("b.laz", "a.laz")
    link.result = {
        "status": "ok",
        "reason": "",
        "matrix": _rigid().tolist(),
        "matched": 7,
        "timings": {"icp": 1.0},
        "uncertainty": {"rotation_deg": 0.01},
    }
    assert isinstance(link.result, LinkResult) and link.ok
    assert link.result.matched == 7 == link.result["matched"] and link.result.get("nothing") is None
    assert link.result.uncertainty == {"rotation_deg": 0.01} and link.result.timings == {"icp_s": 1.0}
    assert np.allclose(link.matrix, _rigid())
    again = link.result.replace(retried=[{"reference": "c.laz"}])
    assert isinstance(again, LinkResult) and again["retried"] and "retried" not in link.result
    with pytest.raises(TypeError):
        link.result["matched"] = 8  # read-only

    link.result = {"status": "ok", "matrix": np.full((4, 4), np.nan).tolist()}
    assert not link.ok and link.matrix is None, "a NaN matrix is never an ok link"


def test_project_file_keeps_link_results(tmp_path):
    for name in ("a.laz", "b.laz"):
        (tmp_path / name).write_bytes(b"")
    p = Project(name="p")
    p.add_scan(tmp_path / "a.laz")
    p.add_scan(tmp_path / "b.laz")
    p.set_link("b.laz", "a.laz").result = {"status": "ok", "reason": "", "matrix": _rigid().tolist(), "matched": 5}
    path = p.save(tmp_path / "p.json")
    back = Project.load(path)
    r = back.link_of("b.laz").result
    assert isinstance(r, LinkResult) and r == p.link_of("b.laz").result and r.matched == 5
    saved = json.loads(path.read_text())["links"][0]["result"]
    assert saved["status"] == "ok" and saved["timings"] == {}
