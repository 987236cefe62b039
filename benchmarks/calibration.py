"""Calibration benchmark: does a pair registration's stated uncertainty cover the truth?

An "ok" is a promise: the matrix is right within its stated 1-sigma uncertainty
(``PairResult.uncertainty["translation_m"]`` at the moving scanner and ``["rotation_deg"]``). This
benchmark checks the promise on cases nobody tuned on: each run draws a seed (printed; ``--seed``
repeats a run) and from it a fresh set of pairs over every kind of scene, each with its own random
known transform (any heading, a few metres to tens of metres apart):

- the built scenes of the simulator (``corridor``, ``colonnade``, ``fence``, ``courtyard``,
  ``park``, ``campus``): walls, posts in rows at a regular spacing, few trees;
- ``plantation_rows``: trees on an exact grid in rows, the two scanners 30 m apart;
- ``forward``: a wheeled robot's forward-looking laser (180 deg, 0.7 m high, ranges up to 33 m; a
  quarter of them a 16-line laser), two scans 1-5 m apart along its way through a built scene or
  a forest;
- ``sector_300``: tripod scans that sweep a 300 deg sector only, in any scene;
- every forest preset of :data:`forestreg.engine.simulate.PRESETS` (``open_field``: a scene
  without trunks, to be refused);
- real clouds of ``../shared/data``: scans simulated from the merged plots ``LPine1_demo.laz`` and
  ``pine_plot.laz`` at chosen positions (:func:`~forestreg.engine.simulate.simulate_scan_from_cloud`),
  and the single real scan ``TLS_scan_scanner_at_origin.laz`` against a copy of itself moved by a
  known transform, the two cropped and thinned differently.

Every case is registered with :func:`forestreg.engine.tls.pair.register` and its ``status``,
``reason`` and ``uncertainty`` are compared with the truth: the rotation error (deg) and the
translation error at the moving scanner (m).

Report: for every "ok" the true error over the stated sigma (translation and rotation); of the
right answers (error at most 0.5 m and 2 deg) the share within 0.5, 1 and 2 sigma; every "ok"
beyond 3 sigma, listed (the broken promises); the "ok" that are wrong; the refusal rate per kind.

Run from the repository root::

    .venv/bin/python -m benchmarks.calibration                 # ~100 cases, a fresh seed
    .venv/bin/python -m benchmarks.calibration --quick         # one case per kind
    .venv/bin/python -m benchmarks.calibration --seed 1234 --cases 40 --kinds corridor forward
    .venv/bin/python -m benchmarks.calibration --json calibration.json

From code (tune on one set of seeds, report on another)::

    from benchmarks.calibration import make_cases, evaluate_case, summarise
    rows = [evaluate_case(c, params) for c in make_cases(seed=1, n=40)]
    print(summarise(rows)["overall"])
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import re
import secrets
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from forestreg.engine.core.scan import Scan
from forestreg.engine.simulate import (
    BUILT_PRESETS,
    PRESETS,
    make_scene,
    scanner_options,
    simulate_plot,
    simulate_scan_from_cloud,
    stand_positions,
)
from forestreg.engine.tls.pair import register
from forestreg.engine.tls.params import RegistrationParams

#: The real clouds (``../shared/data`` beside the repository).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

#: A right answer is within these of the truth; an "ok" beyond either is wrong.
WRONG_M = 0.5
WRONG_DEG = 2.0
#: Multiples of the stated sigma reported.
SIGMAS = (0.5, 1.0, 2.0)
#: The promise: no "ok" beyond this many sigmas.
PROMISE = 3.0

#: Angular step (deg) of the simulated scans and of the scans simulated from real clouds.
STEP_DEG = 0.25
REAL_STEP_DEG = 0.3

#: Scanner separation (m) per built scene (TLS on a tripod; along the scene's axis).
BUILT_SEPARATION_M = {
    "corridor": (1.5, 12.0),
    "colonnade": (2.0, 12.0),
    "fence": (2.0, 12.0),
    "courtyard": (5.0, 15.0),
    "park": (6.0, 16.0),
    "campus": (6.0, 16.0),
}
FOREST_SEPARATION_M = (5.0, 18.0)
PLANTATION_SEPARATION_M = 30.0

#: The kinds of cases, in report order, with what each holds.
KINDS: dict[str, str] = {
    **{k: f"built scene '{k}', tripod scans along it" for k in BUILT_PRESETS},
    "plantation_rows": "trees in exact rows, scanners 30 m apart",
    "forward": "robot's forward-looking laser (180 deg, 0.7 m, <= 33 m), 1-5 m steps",
    "sector_300": "tripod scans of a 300 deg sector, any scene",
    **{k: f"forest preset '{k}'" for k in PRESETS if k != "plantation_rows"},
    "real_lpine": "scans simulated from the real merged plot LPine1_demo.laz",
    "real_pine_plot": "scans simulated from the real merged plot pine_plot.laz",
    "real_tls_copy": "the real RIEGL scan against a moved, cropped, thinned copy",
}


@dataclass(frozen=True)
class Case:
    """One pair to register: what to simulate (or read) and the seed that makes it.

    ``spec`` is JSON-able and holds everything the pair is made from (scene, size, positions,
    headings, scanner, angular step; for a real cloud the file, the positions or the transform and
    the crops); the same case gives the same pair on any machine.
    """

    id: str
    kind: str
    seed: int
    scene: str
    spec: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.kind, "seed": self.seed, "scene": self.scene, "spec": self.spec}


@dataclass
class CasePair:
    """A case made: the two scans, the true moving -> reference matrix (file coordinates), the
    moving scanner in the moving file's coordinates (where the translation error is measured)."""

    reference: Scan
    moving: Scan
    truth: np.ndarray
    moving_scanner: np.ndarray
    simulate_s: float
    info: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------ the cases


def make_cases(seed: int, n: int, kinds: Optional[Sequence[str]] = None) -> list[Case]:
    """``n`` cases drawn from ``seed`` over ``kinds`` (default every kind of :data:`KINDS`).

    The kinds come in rounds, each round every kind once in a shuffled order, so that any ``n``
    covers the kinds evenly. Each case has its own seed drawn from ``seed``; its spec is made from
    that alone (the same ``seed`` and ``n`` give the same cases; a larger ``n`` extends them).
    """
    kinds = list(kinds) if kinds else list(KINDS)
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        raise ValueError(f"unknown case kind(s) {', '.join(unknown)}; kinds are {', '.join(KINDS)}")
    rng = np.random.default_rng([int(seed), 46])
    cases: list[Case] = []
    order: list[str] = []
    for i in range(int(n)):
        if not order:
            order = [kinds[k] for k in rng.permutation(len(kinds))]
        kind = order.pop(0)
        case_seed = int(rng.integers(0, 2**31 - 1))
        scene, spec = _spec(kind, case_seed)
        cases.append(Case(id=f"c{i + 1:03d}-{kind}", kind=kind, seed=case_seed, scene=scene, spec=spec))
    return cases


def _spec(kind: str, seed: int) -> tuple[str, dict[str, Any]]:
    rng = np.random.default_rng([seed, 7])
    if kind in BUILT_PRESETS:
        return kind, _built_spec(kind, seed, rng, "tls")
    if kind == "plantation_rows":
        return kind, _forest_spec(kind, seed, rng, "tls", separation=PLANTATION_SEPARATION_M, size=50.0)
    if kind in PRESETS:
        return kind, _forest_spec(kind, seed, rng, "tls")
    if kind == "forward":
        scanner = "robot_lines" if rng.uniform() < 0.25 else "robot_forward"
        scenes = ["corridor"] * 3 + [
            "colonnade",
            "fence",
            "courtyard",
            "park",
            "campus",
            "plantation_rows",
            "planted_conifer",
            "mixed_temperate",
            "sloped",
        ]
        scene = scenes[int(rng.integers(len(scenes)))]
        sep = float(rng.uniform(1.0, 5.0))
        if scene in BUILT_PRESETS:
            return scene, _built_spec(scene, seed, rng, scanner, separation=sep, forward=True)
        return scene, _forest_spec(scene, seed, rng, scanner, separation=sep, forward=True)
    if kind == "sector_300":
        scenes = list(BUILT_PRESETS) + [k for k in PRESETS if k != "open_field"]
        scene = scenes[int(rng.integers(len(scenes)))]
        if scene in BUILT_PRESETS:
            return scene, _built_spec(scene, seed, rng, "sector_300")
        sep = PLANTATION_SEPARATION_M if scene == "plantation_rows" else None
        return scene, _forest_spec(scene, seed, rng, "sector_300", separation=sep, size=50.0 if sep else None)
    if kind == "real_lpine":
        # ground mostly removed: the scanners stand 1.4 m above the stems' base level
        pos = _pair_in_box(rng, (1.0, 12.0, 0.0, 6.0), (3.0, 9.0))
        return "LPine1_demo.laz", {
            "file": "LPine1_demo.laz",
            "positions": [[*p, 1.4] for p in pos],
            "yaw_deg": _yaws(rng),
            "step_deg": REAL_STEP_DEG,
        }
    if kind == "real_pine_plot":
        pos = _pair_in_box(rng, (2.0, 8.0, 2.0, 8.0), (3.0, 6.0))
        return "pine_plot.laz", {
            "file": "pine_plot.laz",
            "positions": pos,
            "yaw_deg": _yaws(rng),
            "step_deg": REAL_STEP_DEG,
        }
    if kind == "real_tls_copy":
        dist = float(rng.uniform(3.0, 40.0))
        ang = float(rng.uniform(0.0, 2 * math.pi))
        spec = {
            "file": "TLS_scan_scanner_at_origin.laz",
            "yaw_deg": float(rng.uniform(0.0, 360.0)),
            "shift_m": [dist * math.cos(ang), dist * math.sin(ang), float(rng.uniform(-1.0, 1.0))],
            "crops": [_crop(rng), _crop(rng)],
            "moving_position_given": bool(rng.uniform() < 0.75),
        }
        return spec["file"], spec
    raise ValueError(f"unknown case kind {kind!r}")


def _yaws(rng: np.random.Generator) -> list[float]:
    return [float(rng.uniform(0.0, 360.0)), float(rng.uniform(0.0, 360.0))]


def _pair_in_box(
    rng: np.random.Generator, box: tuple[float, float, float, float], sep: tuple[float, float]
) -> list[list[float]]:
    x0, x1, y0, y1 = box
    for _ in range(1000):
        p = rng.uniform([x0, y0], [x1, y1])
        d = float(rng.uniform(*sep))
        a = float(rng.uniform(0.0, 2 * math.pi))
        q = p + d * np.array([math.cos(a), math.sin(a)])
        if x0 <= q[0] <= x1 and y0 <= q[1] <= y1:
            return [[float(p[0]), float(p[1])], [float(q[0]), float(q[1])]]
    raise ValueError("no pair of positions fits")  # pragma: no cover - the boxes are large enough


def _crop(rng: np.random.Generator) -> dict[str, Any]:
    """How one side of the real-scan pair is cut: a horizontal range limit or an azimuth sector
    removed, then a random thinning."""
    if rng.uniform() < 0.5:
        crop: dict[str, Any] = {"max_range_m": float(rng.uniform(11.0, 18.0))}
    else:
        crop = {"drop_sector_deg": [float(rng.uniform(0.0, 360.0)), float(rng.uniform(40.0, 100.0))]}
    crop["keep_fraction"] = float(rng.uniform(0.4, 0.9))
    crop["seed"] = int(rng.integers(0, 2**31 - 1))
    return crop


def _built_spec(
    preset: str,
    seed: int,
    rng: np.random.Generator,
    scanner: str,
    *,
    separation: Optional[float] = None,
    forward: bool = False,
) -> dict[str, Any]:
    size = 40.0 if preset == "courtyard" else 50.0
    scene = make_scene(preset, seed=seed, size_m=size)
    sep = float(separation if separation is not None else rng.uniform(*BUILT_SEPARATION_M[preset]))
    pos = stand_positions(scene, sep, rng, across_m=0.0 if forward else 1.0)
    axis = float(scene.meta["axis_deg"])
    if forward:  # the robot drives along the axis, either way, looking ahead
        heading = axis + (180.0 if rng.uniform() < 0.5 else 0.0)
        if heading != axis:
            pos = pos[::-1]
        yaws = [heading + float(rng.normal(0.0, 3.0)), heading + float(rng.normal(0.0, 3.0))]
    else:
        yaws = _yaws(rng)
    return {
        "size_m": size,
        "positions": pos.tolist(),
        "yaw_deg": yaws,
        "scanner": scanner,
        "step_deg": STEP_DEG,
        "separation_m": sep,
    }


def _forest_spec(
    preset: str,
    seed: int,
    rng: np.random.Generator,
    scanner: str,
    *,
    separation: Optional[float] = None,
    size: Optional[float] = None,
    forward: bool = False,
) -> dict[str, Any]:
    size = float(size if size is not None else 5.0 * int(rng.integers(8, 13)))  # 40-60 m
    sep = float(separation if separation is not None else rng.uniform(*FOREST_SEPARATION_M))
    half = size / 2.0 - 4.0
    for _ in range(1000):
        heading = float(rng.uniform(0.0, 360.0))
        d = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
        centre = rng.uniform(-3.0, 3.0, size=2)
        p, q = centre - d * sep / 2.0, centre + d * sep / 2.0
        if np.abs(p).max() < half and np.abs(q).max() < half:
            break
    yaws = [heading + float(rng.normal(0.0, 3.0)), heading + float(rng.normal(0.0, 3.0))] if forward else _yaws(rng)
    return {
        "size_m": size,
        "positions": [p.tolist(), q.tolist()],
        "yaw_deg": yaws,
        "scanner": scanner,
        "step_deg": STEP_DEG,
        "separation_m": sep,
    }


# --------------------------------------------------------------------------------- making a pair


@functools.lru_cache(maxsize=3)
def _real_cloud(name: str) -> Scan:
    from forestreg.engine.io import read_scan

    return read_scan(SHARED_DATA / name)


def simulate_case(case: Case) -> CasePair:
    """Make the two scans of ``case`` and their truth.

    Raises
    ------
    FileNotFoundError
        A real-cloud case whose file is not in ``../shared/data``.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    spec = case.spec
    if "file" in spec and not (SHARED_DATA / spec["file"]).is_file():
        raise FileNotFoundError(f"{SHARED_DATA / spec['file']} is absent")
    if case.kind == "real_tls_copy":
        pair = _real_copy_pair(case)
    elif "file" in spec:
        cloud = _real_cloud(spec["file"])
        a, b = (
            simulate_scan_from_cloud(cloud, p, angular_step_deg=spec["step_deg"], yaw_deg=y, name=n)
            for p, y, n in zip(spec["positions"], spec["yaw_deg"], ("a", "b"))
        )
        pair = CasePair(a.scan, b.scan, np.linalg.inv(a.pose) @ b.pose, np.zeros(3), 0.0)
    else:
        plot = simulate_plot(
            case.scene,
            spec["positions"],
            seed=case.seed,
            angular_step_deg=spec["step_deg"],
            size_m=spec["size_m"],
            yaw_deg=spec["yaw_deg"],
            scanner_options=scanner_options(spec["scanner"]),
        )
        pair = CasePair(
            plot.scans[0].scan,
            plot.scans[1].scan,
            plot.relative_pose(0, 1),
            np.zeros(3),
            0.0,
            info={"n_trees": len(plot.scene.trees), "n_posts": len(plot.scene.posts)},
        )
    pair.simulate_s = time.perf_counter() - t0
    pair.info["simulate_cpu_s"] = time.process_time() - c0
    pair.info["points"] = [len(pair.reference), len(pair.moving)]
    return pair


def _cropped(points: np.ndarray, crop: Mapping[str, Any]) -> np.ndarray:
    keep = np.ones(len(points), dtype=bool)
    if "max_range_m" in crop:
        keep &= np.hypot(points[:, 0], points[:, 1]) <= crop["max_range_m"]
    if "drop_sector_deg" in crop:
        centre, width = crop["drop_sector_deg"]
        az = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        keep &= np.abs((az - centre + 180.0) % 360.0 - 180.0) > width / 2.0
    keep &= np.random.default_rng(crop["seed"]).uniform(size=len(points)) < crop["keep_fraction"]
    return points[keep]


def _real_copy_pair(case: Case) -> CasePair:
    spec = case.spec
    scan = _real_cloud(spec["file"])
    pts = np.asarray(scan.points, dtype=np.float64)  # the scanner at the file origin
    ref = Scan.from_points(_cropped(pts, spec["crops"][0]), scanner_position=np.zeros(3), name="reference")
    a = math.radians(spec["yaw_deg"])
    move = np.eye(4)
    move[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    move[:3, 3] = spec["shift_m"]
    moved = _cropped(pts, spec["crops"][1]) @ move[:3, :3].T + move[:3, 3]
    position = move[:3, 3].copy() if spec["moving_position_given"] else None
    mov = Scan.from_points(moved, scanner_position=position, name="moved copy")
    return CasePair(
        ref,
        mov,
        np.linalg.inv(move),
        move[:3, 3].copy(),
        0.0,
        info={"moving_position": "given" if position is not None else "found from the data"},
    )


# ---------------------------------------------------------------------------------- evaluation


def true_errors(estimate: np.ndarray, truth: np.ndarray, moving_scanner: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg, the angle of ``R_est^T R_true``) and translation error (m) at the moving
    scanner (``|T_est p - T_true p|``, ``p`` in the moving file's coordinates)."""
    r = estimate[:3, :3].T @ truth[:3, :3]
    rot = math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))
    p = np.append(np.asarray(moving_scanner, dtype=np.float64), 1.0)
    return rot, float(np.linalg.norm((estimate @ p - truth @ p)[:3]))


def _as_params(params: Union[None, RegistrationParams, Mapping[str, Any]]) -> Optional[RegistrationParams]:
    if params is None or isinstance(params, RegistrationParams):
        return params
    return RegistrationParams().replace(**dict(params))


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if math.isfinite(v) else None
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if o is None or isinstance(o, (str, int, bool)):
        return o
    return str(o)


def evaluate_case(
    case: Case, params: Union[None, RegistrationParams, Mapping[str, Any]] = None, *, pair: Optional[CasePair] = None
) -> dict[str, Any]:
    """Register the pair of ``case`` (made by :func:`simulate_case` unless given as ``pair``, e.g.
    to try several ``params`` on the same scans) and compare the result with the truth.

    ``params``: :class:`RegistrationParams`, or a mapping of its fields, or None for the defaults.

    Returns a JSON-able row: the case (``id``, ``kind``, ``scene``, ``seed``, ``spec``),
    ``status`` ("ok", "failed", or "error" when the pair could not be made or registration raised;
    "skipped" when a real cloud is absent), ``reason``, the stated ``sigma_m`` / ``sigma_deg``, the
    true ``error_m`` / ``error_deg`` (at the moving scanner), ``ratio_m`` / ``ratio_deg`` (error
    over sigma, None without a matrix), ``wrong`` (an "ok" more than 0.5 m or 2 deg off), the
    matched VOPs, the whole ``uncertainty`` dict and the seconds spent (wall ``simulate_s`` and
    ``register_s``; CPU seconds of this process ``info["simulate_cpu_s"]`` and ``register_cpu_s``).
    """
    row: dict[str, Any] = {
        **case.to_dict(),
        "status": None,
        "reason": "",
        "sigma_m": None,
        "sigma_deg": None,
        "error_m": None,
        "error_deg": None,
        "ratio_m": None,
        "ratio_deg": None,
        "wrong": None,
    }
    try:
        if pair is None:
            pair = simulate_case(case)
    except FileNotFoundError as exc:
        row.update(status="skipped", reason=str(exc))
        return row
    except Exception as exc:  # a pair that cannot be made is reported, not fatal to the run
        row.update(status="error", reason=f"making the pair: {type(exc).__name__}: {exc}")
        return row
    row.update(simulate_s=pair.simulate_s, points=pair.info.get("points"), info=_jsonable(pair.info))
    t, c = time.perf_counter(), time.process_time()
    try:
        result = register(pair.reference, pair.moving, _as_params(params))
    except Exception as exc:
        row.update(
            status="error", reason=f"registration: {type(exc).__name__}: {exc}", register_s=time.perf_counter() - t
        )
        return row
    row["register_s"] = time.perf_counter() - t
    row["register_cpu_s"] = time.process_time() - c
    unc = result.uncertainty or {}
    row.update(
        status=result.status,
        reason=result.reason,
        matched=result.matched,
        second_matched=result.second_matched,
        icp_std_m=None if result.icp is None else float(result.icp.std_m),
        sigma_m=unc.get("translation_m"),
        sigma_deg=unc.get("rotation_deg"),
        uncertainty=_jsonable(unc),
        ambiguity_resolved=result.ambiguity_resolved,
    )
    if result.matrix is not None:
        rot, trans = true_errors(np.asarray(result.matrix), pair.truth, pair.moving_scanner)
        row.update(error_m=trans, error_deg=rot, wrong=bool(trans > WRONG_M or rot > WRONG_DEG))
        row["ratio_m"] = _ratio(trans, row["sigma_m"])
        row["ratio_deg"] = _ratio(rot, row["sigma_deg"])
    return _jsonable(row)


def _ratio(error: float, sigma: Optional[float]) -> float:
    if sigma is None or not math.isfinite(float(sigma)) or sigma <= 0:
        return math.inf
    return float(error / sigma)


# ------------------------------------------------------------------------------------- summary


def _r(row: Mapping[str, Any], key: str) -> float:
    v = row.get(key)
    return math.inf if v is None else float(v)


def worst_ratio(row: Mapping[str, Any]) -> float:
    """The larger of an "ok" row's translation and rotation error over sigma (inf: no sigma)."""
    return max(_r(row, "ratio_m"), _r(row, "ratio_deg"))


def summarise(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The figures of the report: ``overall`` and ``per_kind`` counts and shares, and
    ``beyond_promise``: every "ok" whose error exceeds 3 sigma (translation or rotation)."""

    def figures(sel: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
        ok = [r for r in sel if r["status"] == "ok"]
        failed = [r for r in sel if r["status"] == "failed"]
        right = [r for r in ok if not r["wrong"]]
        made = len(ok) + len(failed)
        out: dict[str, Any] = {
            "cases": len(sel),
            "ok": len(ok),
            "refused": len(failed),
            "errors": sum(r["status"] == "error" for r in sel),
            "skipped": sum(r["status"] == "skipped" for r in sel),
            "refusal_rate": len(failed) / made if made else None,
            "wrong": sum(bool(r["wrong"]) for r in ok),
            "beyond_3_sigma": sum(worst_ratio(r) > PROMISE for r in ok),
            "right": len(right),
        }
        for k in SIGMAS:
            for what, key in (("m", "ratio_m"), ("deg", "ratio_deg")):
                out[f"right_within_{k:g}_sigma_{what}"] = (
                    (sum(_r(r, key) <= k for r in right) / len(right)) if right else None
                )
            out[f"right_within_{k:g}_sigma"] = (sum(worst_ratio(r) <= k for r in right) / len(right)) if right else None
        for key in ("ratio_m", "ratio_deg", "error_m", "error_deg", "sigma_m", "sigma_deg"):
            vals = [_r(r, key) for r in ok]
            out[f"median_{key}"] = float(np.median(vals)) if vals else None
            out[f"max_{key}"] = float(np.max(vals)) if vals else None
        return out

    kinds = [k for k in KINDS if any(r["kind"] == k for r in rows)] + sorted({r["kind"] for r in rows} - set(KINDS))
    beyond = [
        {
            k: r.get(k)
            for k in (
                "id",
                "kind",
                "scene",
                "seed",
                "error_m",
                "sigma_m",
                "ratio_m",
                "error_deg",
                "sigma_deg",
                "ratio_deg",
                "wrong",
                "matched",
                "second_matched",
            )
        }
        for r in rows
        if r["status"] == "ok" and worst_ratio(r) > PROMISE
    ]
    return {
        "overall": figures(rows),
        "per_kind": {k: figures([r for r in rows if r["kind"] == k]) for k in kinds},
        "per_scene": {s: figures([r for r in rows if r["scene"] == s]) for s in sorted({r["scene"] for r in rows})},
        "beyond_promise": beyond,
    }


def _pct(v: Optional[float]) -> str:
    return "-" if v is None else f"{100.0 * v:.0f} %"


def _num(v: Optional[float], fmt: str = ".2f") -> str:
    if v is None:
        return "-"
    return "inf" if math.isinf(v) else format(v, fmt)


def format_report(rows: Sequence[Mapping[str, Any]], summary: Optional[Mapping[str, Any]] = None) -> str:
    """Plain-text tables of :func:`summarise`."""
    s = summary or summarise(rows)
    o = s["overall"]
    lines = [
        f"Calibration: {o['cases']} cases, {o['ok']} ok, {o['refused']} refused, {o['errors']} errors, {o['skipped']} skipped",
        f"  ok and wrong (> {WRONG_M} m or > {WRONG_DEG} deg): {o['wrong']}",
        f"  ok beyond {PROMISE:g} sigma (the promise broken): {o['beyond_3_sigma']}",
        f"  right answers ({o['right']}) within 0.5 / 1 / 2 sigma (translation and rotation both): "
        f"{_pct(o['right_within_0.5_sigma'])} / {_pct(o['right_within_1_sigma'])} / {_pct(o['right_within_2_sigma'])}",
        f"    translation only: {_pct(o['right_within_0.5_sigma_m'])} / {_pct(o['right_within_1_sigma_m'])} / "
        f"{_pct(o['right_within_2_sigma_m'])};  rotation only: {_pct(o['right_within_0.5_sigma_deg'])} / "
        f"{_pct(o['right_within_1_sigma_deg'])} / {_pct(o['right_within_2_sigma_deg'])}",
        "",
    ]
    head = (
        f"{'kind':<16}{'cases':>6}{'ok':>5}{'refused':>9}{'refusal':>9}{'wrong':>7}{'>3 sig':>8}"
        f"{'<=1 sig':>9}{'<=2 sig':>9}{'med err/sig m':>15}{'med err/sig deg':>17}{'max err/sig':>13}"
    )
    lines += [
        "Per kind (err/sig: true error over stated sigma of the ok; <=k sig: share of the right answers)",
        head,
        "-" * len(head),
    ]
    for kind, f in s["per_kind"].items():
        worst = None if f["max_ratio_m"] is None else max(f["max_ratio_m"], f["max_ratio_deg"])
        lines.append(
            f"{kind:<16}{f['cases']:>6}{f['ok']:>5}{f['refused']:>9}{_pct(f['refusal_rate']):>9}{f['wrong']:>7}"
            f"{f['beyond_3_sigma']:>8}{_pct(f['right_within_1_sigma']):>9}{_pct(f['right_within_2_sigma']):>9}"
            f"{_num(f['median_ratio_m']):>15}{_num(f['median_ratio_deg']):>17}{_num(worst, '.1f'):>13}"
        )
    lines.append("")
    if s["beyond_promise"]:
        head = (
            f"{'case':<24}{'scene':<18}{'error m':>10}{'sigma m':>10}{'x sig':>8}{'error deg':>11}{'sigma deg':>11}"
            f"{'x sig':>8}{'matched':>9}"
        )
        lines += [f"Every ok beyond {PROMISE:g} sigma", head, "-" * len(head)]
        for b in s["beyond_promise"]:
            lines.append(
                f"{b['id']:<24}{b['scene']:<18}{_num(b['error_m'], '.3f'):>10}{_num(b['sigma_m'], '.3f'):>10}"
                f"{_num(b['ratio_m'], '.1f'):>8}{_num(b['error_deg'], '.3f'):>11}{_num(b['sigma_deg'], '.3f'):>11}"
                f"{_num(b['ratio_deg'], '.1f'):>8}{str(b['matched']) + '/' + str(b['second_matched']):>9}"
            )
    else:
        lines.append(f"No ok beyond {PROMISE:g} sigma.")
    reasons: dict[str, int] = {}
    per_kind: dict[str, dict[str, int]] = {}
    for r in rows:
        if r["status"] in ("failed", "error"):
            key = reason_key(r["reason"])
            reasons[key] = reasons.get(key, 0) + 1
            kind = per_kind.setdefault(r["kind"], {})
            kind[key] = kind.get(key, 0) + 1
    if reasons:
        lines += ["", "Refusals and errors by reason (numbers as N)"]
        lines += [f"{n:>5}  {k}" for k, n in sorted(reasons.items(), key=lambda kv: -kv[1])]
        lines += ["", "Refusals per kind"]
        for kind in [k for k in s["per_kind"] if k in per_kind]:
            lines.append(
                f"  {kind:<16}"
                + "; ".join(f"{k} {n}" for k, n in sorted(per_kind[kind].items(), key=lambda kv: -kv[1]))
            )
    return "\n".join(lines)


def reason_key(reason: Optional[str]) -> str:
    """The kind of a refusal: its reason up to the first colon or parenthesis, numbers as N."""
    return re.sub(r"\d+(\.\d+)?", "N", (reason or "").split(":")[0].split(" (")[0])[:80]


def _case_line(i: int, n: int, row: Mapping[str, Any]) -> str:
    head = f"[{i:>3}/{n}] {row['id']:<22} {row['scene']:<30}"[:62]
    secs = (row.get("simulate_s") or 0.0) + (row.get("register_s") or 0.0)
    if row["status"] == "ok":
        flag = " WRONG" if row["wrong"] else (" BEYOND 3 SIGMA" if worst_ratio(row) > PROMISE else "")
        return (
            f"{head} ok     error {row['error_m']:.3f} m / {row['error_deg']:.3f} deg, sigma "
            f"{_num(row['sigma_m'], '.3f')} m / {_num(row['sigma_deg'], '.3f')} deg ({secs:.1f} s){flag}"
        )
    return f"{head} {row['status']:<6} {(row['reason'] or '')[:110]} ({secs:.1f} s)"


def run(
    seed: Optional[int] = None,
    n: Optional[int] = None,
    *,
    quick: bool = False,
    kinds: Optional[Sequence[str]] = None,
    params: Union[None, RegistrationParams, Mapping[str, Any]] = None,
    verbose: bool = True,
) -> dict[str, Any]:
    """Draw the cases (a fresh seed unless given), evaluate each, summarise: the JSON-able payload
    of ``--json`` (``seed``, ``cases``, ``rows``, ``summary``, ``wall_s``)."""
    seed = int(secrets.randbelow(2**31 - 1)) if seed is None else int(seed)
    kind_list = list(kinds) if kinds else list(KINDS)
    n = int(n if n is not None else (len(kind_list) if quick else 6 * len(kind_list)))
    if verbose:
        print(
            f"calibration: seed {seed}, {n} cases over {len(kind_list)} kinds (repeat with --seed {seed} --cases {n})",
            flush=True,
        )
    t0 = time.perf_counter()
    cases = make_cases(seed, n, kind_list)
    logger = logging.getLogger("forestreg")
    level = logger.level
    logger.setLevel(logging.ERROR)  # each refusal is a row here, not a warning
    rows = []
    try:
        for i, case in enumerate(cases, start=1):
            row = evaluate_case(case, params)
            rows.append(row)
            if verbose:
                print(_case_line(i, n, row), flush=True)
    finally:
        logger.setLevel(level)
    summary = summarise(rows)
    wall = time.perf_counter() - t0
    cpu = sum((r.get("info") or {}).get("simulate_cpu_s", 0.0) + (r.get("register_cpu_s") or 0.0) for r in rows)
    return {
        "seed": seed,
        "cpu_s": cpu,
        "n": n,
        "kinds": kind_list,
        "params": None if params is None else _jsonable(_as_params(params).to_dict()),
        "rows": rows,
        "summary": summary,
        "wall_s": wall,
    }


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, help="the seed of the cases (default: drawn afresh, printed)")
    ap.add_argument(
        "--cases", type=int, help=f"number of cases (default 6 per kind: {6 * len(KINDS)}; --quick: one per kind)"
    )
    ap.add_argument("--quick", action="store_true", help="one case per kind (a few minutes)")
    ap.add_argument(
        "--kinds", nargs="+", choices=list(KINDS), metavar="KIND", help=f"only these kinds: {', '.join(KINDS)}"
    )
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every case, row and the summary to this JSON file")
    args = ap.parse_args(argv)
    payload = run(args.seed, args.cases, quick=args.quick, kinds=args.kinds)
    print()
    print(format_report(payload["rows"], payload["summary"]))
    print(
        f"\nseed {payload['seed']}, {payload['n']} cases, wall time {payload['wall_s']:.0f} s "
        f"(CPU time of the cases {payload['cpu_s']:.0f} s)"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(_jsonable(payload), indent=1) + "\n")
        print(f"written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
