"""The parameter base of every step of the product.

Each step's settings are one frozen dataclass deriving from :class:`Params`; every field is made
by :func:`param_field` and carries ``unit``, ``range`` (lo, hi), ``help`` and ``paper`` (the
paper's symbol and value) metadata, which validates it, documents it (``forestreg params``, the
README) and builds the GUI's parameter panel. Defaults are the papers' tables where they give a
value. Cross-field rules go in ``_check``. Nested step parameters (e.g. the terrain inside the
tree parameters) are fields whose default is another :class:`Params`.

Example::

    from forestreg.engine.tls.params import RegistrationParams
    p = RegistrationParams().replace(vop_radius_m=15.0)
    RegistrationParams.from_mapping(p.to_dict()) == p     # True
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import field
from pathlib import Path
from typing import Any, Mapping, Optional, TypeVar

from .errors import ParameterError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Params", "param_field", "parameter_table", "read_toml", "validate_ranges"]

P = TypeVar("P", bound="Params")


def param_field(default: Any, unit: str = "", lo: Optional[float] = None, hi: Optional[float] = None, help: str = "", paper: str = "") -> Any:
    """A dataclass field carrying ``unit``, ``range`` (lo, hi), ``help`` and ``paper`` metadata;
    lists become tuples (parameters are immutable).

    Every number has a unit: ``"m"``, ``"deg"``, a count's noun (``"points"``, ``"iterations"``)
    or ``"1"`` for a dimensionless ratio, fraction, factor or seed; switches and names have none.
    The documentation's parameter reference is generated from these, and its test fails for a
    parameter without help or a number without a unit."""
    meta = {"unit": unit, "range": (lo, hi), "help": help, "paper": paper}
    if isinstance(default, (list, tuple)):
        return field(default=tuple(default), metadata=meta)
    return field(default=default, metadata=meta)


def validate_ranges(params: Any) -> None:
    """Raise :class:`ParameterError` for a numeric field of a parameter dataclass that is not a
    finite number inside its metadata ``range`` (booleans, strings, ``None`` and nested
    parameter sets are skipped; nested sets validate themselves)."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if value is None or isinstance(value, (bool, str, Params)):
            continue
        lo, hi = f.metadata.get("range", (None, None))
        for v in _flat(value):
            if isinstance(v, (bool, str)):
                continue
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ParameterError(f"{f.name}: {v!r} is not a finite number")
            if (lo is not None and v < lo) or (hi is not None and v > hi):
                raise ParameterError(f"{f.name} = {v} {f.metadata.get('unit', '')} is outside [{lo}, {hi}]".replace("  ", " "))


def _flat(value: Any) -> list[Any]:
    """The scalars of a (nested) tuple, or the value itself."""
    if isinstance(value, tuple):
        return [x for v in value for x in _flat(v)]
    return [value]


class Params:
    """Base of every parameter dataclass: validation on construction, :meth:`replace`,
    :meth:`to_dict` / :meth:`from_mapping` (nested, for TOML and JSON) and :meth:`table`.

    Subclasses are ``@dataclass(frozen=True)`` and put cross-field rules in ``_check``.
    """

    def __post_init__(self) -> None:
        validate_ranges(self)
        self._check()

    def _check(self) -> None:
        """Cross-field rules of a subclass (raise :class:`ParameterError`)."""

    def replace(self: P, **changes: Any) -> P:
        """A copy with some fields changed (validated); unknown names are a ParameterError."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise ParameterError(f"unknown {type(self).__name__} parameter(s): {', '.join(unknown)}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-able nested dict of every field (tuples as lists)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to_dict() if isinstance(v, Params) else list(v) if isinstance(v, tuple) else v
        return out

    @classmethod
    def from_mapping(cls: type[P], values: Mapping[str, Any], where: str = "") -> P:
        """Build from a (nested) mapping, e.g. a TOML table: unknown keys are an error naming the
        known ones, lists become tuples, a number where a tuple is expected becomes a 1-tuple,
        missing keys keep their defaults."""
        if not isinstance(values, Mapping):
            raise ParameterError(f"[{where or cls.__name__}] must be a table")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ParameterError(
                f"unknown parameter(s) in [{where or cls.__name__}]: {', '.join(unknown)}; known: {', '.join(sorted(fields))}"
            )
        clean: dict[str, Any] = {}
        for k, v in values.items():
            default = fields[k].default
            if isinstance(default, Params):
                v = type(default).from_mapping(v, f"{where}.{k}" if where else k)
            elif isinstance(v, list):
                v = tuple(v)
            elif isinstance(default, tuple) and isinstance(v, (int, float)):
                v = (v,)
            clean[k] = v
        try:
            return cls(**clean)
        except TypeError as exc:
            raise ParameterError(f"[{where or cls.__name__}]: {exc}") from exc

    @classmethod
    def table(cls, prefix: str = "") -> list[dict[str, Any]]:
        """One row per parameter (nested ones with dotted names): name, default, unit, range,
        help, paper symbol; for docs, ``forestreg params`` and the GUI."""
        rows: list[dict[str, Any]] = []
        for f in dataclasses.fields(cls):
            if isinstance(f.default, Params):
                rows += type(f.default).table(f"{prefix}{f.name}.")
                continue
            rows.append(
                {
                    "name": prefix + f.name,
                    "default": f.default,
                    "unit": f.metadata.get("unit", ""),
                    "range": f.metadata.get("range", (None, None)),
                    "help": f.metadata.get("help", ""),
                    "paper": f.metadata.get("paper", ""),
                }
            )
        return rows


def parameter_table(cls: type) -> list[dict[str, Any]]:
    """The rows of :meth:`Params.table` for a parameter class."""
    return cls.table()


def read_toml(path: str | Path) -> dict[str, Any]:
    """A TOML file as a dict; a missing or unreadable file is a :class:`ParameterError`."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ParameterError(f"parameter file {p} does not exist") from exc
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ParameterError(f"parameter file {p} cannot be read: {exc}") from exc
