"""One outcome shape for every registration the product makes.

A pair registration (trunk shadows), a manual registration (targets) and a co-registration
(canopy keypoints) all end the same way: a ``status`` ("ok" or "failed"), a ``reason`` when it
failed, a 4x4 ``matrix`` (None when failed) with the ``convention`` saying which frame it maps to
which, the ``evidence`` a user checks before trusting it, and ``timings`` in seconds whose keys end
in ``_s``. :class:`Outcome` gives the result classes that shared part; :class:`OutcomeRecord` is the
typed, read-only form of a saved outcome (``result.json``, a project's link) read back from its
dict, whatever produced it.

Example
-------
>>> rec = OutcomeRecord.from_dict({"status": "ok", "matrix": np.eye(4).tolist(), "timings": {"icp": 1.5}})
>>> rec.ok, rec.timings
(True, {'icp_s': 1.5})
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Iterator, Optional

import numpy as np

from .jsonable import to_jsonable

__all__ = ["Outcome", "OutcomeRecord", "StepTimer", "seconds_keys"]

STATUSES = ("ok", "failed")


def seconds_keys(timings: Optional[Mapping[str, Any]]) -> dict[str, float]:
    """``timings`` with every key ending in ``_s`` (files written before the rename used bare step
    names: ``{"icp": 2.0}`` becomes ``{"icp_s": 2.0}``); values as floats, non-numbers dropped."""
    out: dict[str, float] = {}
    for key, value in (timings or {}).items():
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            continue
        name = str(key)
        out[name if name.endswith("_s") else f"{name}_s"] = seconds
    return out


class StepTimer(dict):
    """Seconds per named step of a run, summed over repeats; keys end in ``_s``.

    >>> timer = StepTimer()
    >>> vops = timer.run("vops", sorted, [3, 1, 2])
    >>> list(timer)
    ['vops_s']
    """

    def run(self, name: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, its wall time added to ``name + "_s"``."""
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.add(name, time.perf_counter() - t0)

    def add(self, name: str, seconds: float) -> None:
        """Add ``seconds`` to step ``name`` (the ``_s`` is appended when missing)."""
        key = name if name.endswith("_s") else f"{name}_s"
        self[key] = self.get(key, 0.0) + float(seconds)


class Outcome:
    """The part every registration result shares (a mixin for frozen result dataclasses).

    Subclasses have the fields ``status``, ``reason``, ``matrix`` (4x4 or None) and ``timings``
    (seconds per step, keys ending in ``_s``), set the class attributes ``method`` and
    ``convention``, and implement :meth:`evidence`. Their ``to_dict`` starts from
    :meth:`outcome_dict`, so every ``result.json`` has the same first keys.
    """

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    timings: dict[str, float]

    #: how the result was found, e.g. "auto (trunk shadows + ICP)"
    method: ClassVar[str] = ""
    #: what ``matrix`` maps, e.g. "p_reference = matrix @ p_moving (...)"
    convention: ClassVar[str] = ""

    @property
    def ok(self) -> bool:
        """True when ``status`` is "ok" (then ``matrix`` is a rigid 4x4)."""
        return self.status == "ok"

    def __bool__(self) -> bool:
        return self.ok

    @property
    def total_s(self) -> float:
        """Wall time of the run, seconds (``timings["total_s"]`` when recorded, else the sum)."""
        t = self.timings or {}
        return float(t["total_s"]) if "total_s" in t else float(sum(t.values()))

    def evidence(self) -> dict[str, Any]:
        """The figures a user checks before trusting ``matrix`` (JSON-able, method-specific)."""
        raise NotImplementedError

    def outcome_dict(self) -> dict[str, Any]:
        """The shared keys of ``to_dict``: method, status, reason, matrix, convention, evidence,
        timings (seconds, ``*_s`` keys)."""
        return {
            "method": self.method,
            "status": self.status,
            "reason": self.reason,
            "matrix": None if self.matrix is None else np.asarray(self.matrix, dtype=float).tolist(),
            "convention": self.convention,
            "evidence": to_jsonable(self.evidence()),
            "timings": seconds_keys(self.timings),
        }

    def record(self) -> "OutcomeRecord":
        """This result as a typed record of its JSON form (what a project keeps per link)."""
        return OutcomeRecord.from_dict(to_jsonable(self.to_dict()))  # type: ignore[attr-defined]


@dataclass(frozen=True, eq=False)
class OutcomeRecord(Mapping):
    """A saved registration outcome, typed: ``status``, ``reason``, ``matrix`` (4x4 array or
    None), ``method``, ``evidence``, ``timings`` (seconds, ``*_s`` keys) and the whole JSON
    ``data`` it was read from.

    It is also a read-only mapping over ``data`` (``rec["matched"]``, ``rec.get("icp")``), so
    tables and reports read any method-specific figure the same way; two records are equal when
    their data are. Build one with :meth:`from_dict`; change one with :meth:`replace`.
    """

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    method: str = ""
    evidence: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "OutcomeRecord":
        """A record from a result dict (any producer, any version). A status other than "ok" or
        "failed", or an "ok" whose matrix is missing or not a finite proper rigid 4x4, is read as
        "failed" with the reason and no matrix (never a NaN or scaled "ok")."""
        if isinstance(d, OutcomeRecord):
            return cls(
                **{k: getattr(d, k) for k in ("status", "reason", "matrix", "method", "evidence", "timings", "data")}
            )
        if not isinstance(d, Mapping):
            raise TypeError(f"an outcome is a mapping, got {type(d).__name__}")
        from .transform import withhold_unless_rigid

        data = to_jsonable(dict(d))
        status = str(data.get("status") or "failed")
        if status not in STATUSES:
            data.update(status="failed", reason=str(data.get("reason") or f"unknown status {status!r}"))
        if data["status"] == "ok" and data.get("matrix") is None:
            data.update(status="failed", reason="no matrix; withheld")
        data = withhold_unless_rigid(data)  # an "ok" is never NaN, scaled or mirrored
        matrix = _matrix_or_none(data.get("matrix"))
        if matrix is None:
            data["matrix"] = None
        status, reason = str(data["status"]), str(data.get("reason") or "")
        timings = seconds_keys(data.get("timings") if isinstance(data.get("timings"), Mapping) else None)
        data.update(reason=reason, timings=timings)
        evidence = data.get("evidence") if isinstance(data.get("evidence"), Mapping) else {}
        return cls(status, reason, matrix, str(data.get("method") or ""), dict(evidence), timings, data)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (a copy of ``data``)."""
        return to_jsonable(self.data)

    def replace(self, **changes: Any) -> "OutcomeRecord":
        """A new record with ``changes`` merged into the data (e.g. ``retried=[...]``)."""
        return type(self).from_dict({**self.data, **changes})

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def __bool__(self) -> bool:  # falsy when not ok, as every outcome; test ``is None`` for "not run"
        return self.ok

    # read-only mapping over the JSON data
    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.data)

    def __len__(self) -> int:
        return len(self.data)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Mapping):
            return self.to_dict() == to_jsonable(dict(other))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]


def _matrix_or_none(value: Any) -> Optional[np.ndarray]:
    """A finite 4x4 float array from ``value``, or None."""
    if value is None:
        return None
    try:
        m = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None
    if m.shape != (4, 4) or not all(math.isfinite(v) for v in m.ravel()):
        return None
    return m
