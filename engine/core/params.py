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
import logging
import math
import numbers
import re
import sys
from dataclasses import field
from pathlib import Path
from typing import Any, Mapping, Optional, TypeVar

from .errors import ParameterError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Params", "param_field", "parameter_table", "read_toml", "validate_ranges", "validate_types"]

P = TypeVar("P", bound="Params")

log = logging.getLogger(__name__)


def param_field(
    default: Any,
    unit: str = "",
    lo: Optional[float] = None,
    hi: Optional[float] = None,
    help: str = "",
    paper: str = "",
) -> Any:
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


def _kind(f: dataclasses.Field) -> str:
    """A field's annotation as compact text: ``float``, ``Optional[float]``, ``tuple[int,...]``."""
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", None) or str(f.type)
    return t.replace("typing.", "").replace(" ", "")


def _is_bool(v: Any) -> bool:
    return isinstance(v, bool) or type(v).__name__ == "bool_"  # numpy's bool too


def _matches(kind: str, v: Any) -> Optional[str]:
    """None when ``v`` is of the annotated ``kind``, else what belongs there (for the message);
    kinds this checker does not know pass."""
    m = re.fullmatch(r"Optional\[(.+)\]|(.+)\|None|None\|(.+)", kind)
    if m:
        return None if v is None else _matches(next(g for g in m.groups() if g), v)
    if kind == "bool":
        return None if _is_bool(v) else "true or false"
    if kind == "int":
        return None if isinstance(v, numbers.Integral) and not _is_bool(v) else "a whole number"
    if kind == "float":
        return None if isinstance(v, numbers.Real) and not _is_bool(v) else "a number"
    if kind == "str":
        return None if isinstance(v, str) else "a text (in quotes)"
    m = re.fullmatch(r"tuple\[(.+)\]", kind)
    if m:
        parts = m.group(1).split(",")
        if len(parts) == 2 and parts[1] == "...":
            element, count = parts[0], None
        elif len(set(parts)) == 1:
            element, count = parts[0], len(parts)
        else:
            return None
        noun = {"float": "numbers", "int": "whole numbers", "str": "texts", "bool": "true/false values"}.get(
            element, element
        )
        what = f"a list of {f'{count} ' if count else ''}{noun}"
        if not isinstance(v, tuple) or (count is not None and len(v) != count):
            return what
        return what if any(_matches(element, x) for x in v) else None
    return None


def _shown(v: Any) -> str:
    """A value as the user wrote it in TOML (a string in quotes, a tuple as a list)."""
    if isinstance(v, str):
        return f'"{v}" (a text)'
    if isinstance(v, tuple):
        return str(list(v))
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, Mapping):
        return "a table"
    return repr(v)


def validate_types(params: Any) -> None:
    """Raise :class:`ParameterError` for a field whose value is not of its annotated type: a
    string, a boolean or a list where a number belongs, a number or a string where a boolean
    belongs, a fraction where a count belongs."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(f.default, Params):
            if not isinstance(value, type(f.default)):
                raise ParameterError(f"{f.name}: {_shown(value)} where a table of {type(f.default).__name__} belongs")
            continue
        wanted = _matches(_kind(f), value)
        if wanted is not None:
            unit = f.metadata.get("unit", "")
            raise ParameterError(
                f"{f.name} = {_shown(value)}: {wanted}{f' ({unit})' if unit and wanted != 'true or false' else ''} belongs here"
            )


def validate_ranges(params: Any) -> None:
    """Raise :class:`ParameterError` for a field of a parameter dataclass that is not of its
    annotated type (:func:`validate_types`), or a numeric one that is not a finite number inside
    its metadata ``range`` (nested parameter sets validate themselves)."""
    validate_types(params)
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
                raise ParameterError(
                    f"{f.name} = {v} {f.metadata.get('unit', '')} is outside [{lo}, {hi}]".replace("  ", " ")
                )
        # a pair of numbers whose default rises is a range (smallest, largest; inner, outer): its
        # ends stay in order (a pair such as a centre's x, y has no order)
        if _is_range(f) and isinstance(value, tuple) and len(value) == 2 and value[0] > value[1]:
            raise ParameterError(f"{f.name} = {list(value)}: a range, its first value must not exceed its second")


def _is_range(f: dataclasses.Field) -> bool:
    """Whether the field is a pair of numbers whose default rises (a range)."""
    d = f.default
    return _kind(f) == "tuple[float,float]" and isinstance(d, tuple) and len(d) == 2 and d[0] < d[1]


def _flat(value: Any) -> list[Any]:
    """The scalars of a (nested) tuple, or the value itself."""
    if isinstance(value, tuple):
        return [x for v in value for x in _flat(v)]
    return [value]


def _whole(kind: str, v: Any) -> Any:
    """A whole float where a count belongs (TOML ``40.0``) as the int it is; anything else as is."""
    if isinstance(v, float) and v.is_integer() and kind in ("int", "Optional[int]"):
        return int(v)
    if isinstance(v, tuple) and kind == "tuple[int,...]":
        return tuple(int(x) if isinstance(x, float) and x.is_integer() else x for x in v)
    return v


def _moved_names(cls: type, values: Mapping[str, Any], where: str) -> Mapping[str, Any]:
    """``values`` with the former names of fields that moved into a nested parameter set
    (``cls._moved``: ``{old name: "nested.name"}``, or a tuple of such places where one former
    setting now has several homes) put in their new place, each with a one-line deprecation
    warning; a value also given under its new name wins."""
    moved = getattr(cls, "_moved", {})
    old = [k for k in values if k in moved]
    if not old:
        return values
    out = {k: v for k, v in values.items() if k not in moved}
    section = where or cls.__name__
    for k in old:
        places = (moved[k],) if isinstance(moved[k], str) else tuple(moved[k])
        for place in places:
            nested, name = place.split(".", 1)
            table = out.get(nested, {})
            if isinstance(table, Mapping):
                out[nested] = {name: values[k], **table}
        log.warning(
            "parameter [%s] %s is now %s; the old name is read for now",
            section,
            k,
            " and ".join(f"[{section}.{p.split('.', 1)[0]}] {p.split('.', 1)[1]}" for p in places),
        )
    return out


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
    def from_mapping(cls: type[P], values: Mapping[str, Any], where: str = "", base: Optional[P] = None) -> P:
        """Build from a (nested) mapping, e.g. a TOML table: unknown keys are an error naming the
        known ones, lists become tuples, a number where a tuple is expected becomes a 1-tuple,
        missing keys keep their defaults (those of ``base`` when given: a nested set keeps the
        values its field holds, e.g. a product's own ICP settings)."""
        if not isinstance(values, Mapping):
            raise ParameterError(f"[{where or cls.__name__}] must be a table")
        values = _moved_names(cls, values, where)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ParameterError(
                f"unknown parameter(s) in [{where or cls.__name__}]: {', '.join(unknown)}; known: {', '.join(sorted(fields))}"
            )
        clean: dict[str, Any] = {}
        for k, v in values.items():
            default = fields[k].default if base is None else getattr(base, k)
            if isinstance(default, Params):
                v = type(default).from_mapping(v, f"{where}.{k}" if where else k, default)
            elif isinstance(v, list):
                v = tuple(v)
            elif isinstance(default, tuple) and isinstance(v, (int, float)) and not isinstance(v, bool):
                v = (v,)
            clean[k] = _whole(_kind(fields[k]), v)
        try:
            return cls(**clean) if base is None else dataclasses.replace(base, **clean)
        except TypeError as exc:
            raise ParameterError(f"[{where or cls.__name__}]: {exc}") from exc
        except ParameterError as exc:
            if str(exc).startswith("["):
                raise
            raise ParameterError(f"[{where or cls.__name__}] {exc}") from None

    @classmethod
    def table(cls, prefix: str = "", defaults: Optional["Params"] = None) -> list[dict[str, Any]]:
        """One row per parameter (nested ones with dotted names): name, default, unit, range,
        help, paper symbol; for docs, ``forestreg params`` and the GUI. A nested set's defaults
        are those of the instance its field holds (``defaults``), e.g. a product's own ICP."""
        rows: list[dict[str, Any]] = []
        for f in dataclasses.fields(cls):
            default = f.default if defaults is None else getattr(defaults, f.name)
            if isinstance(default, Params):
                rows += type(default).table(f"{prefix}{f.name}.", default)
                continue
            rows.append(
                {
                    "name": prefix + f.name,
                    "default": default,
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
    """A TOML file (UTF-8, a byte-order mark allowed) as a dict; a missing or unreadable file is a
    :class:`ParameterError`."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8-sig"))
    except FileNotFoundError as exc:
        raise ParameterError(f"parameter file {p} does not exist") from exc
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ParameterError(f"parameter file {p} cannot be read: {exc}") from exc
