"""The product's parameters in one place: every step's parameter set under one nested TOML file.

Sections (each a :class:`~forestreg.engine.core.params.Params` subclass, defaults = the papers'
tables)::

    [registration]            System A pair/plot registration (Guan et al. 2020, table 2)
    [scanner_position]        where the scanner stood, when a file does not say
    [survey]                  every pair of a plot, pose graph, loop closure
    [coregistration]          System B ground/UAV co-registration (Fekry et al. 2022, sec. 4.1)
    [coregistration.terrain]  ... with its nested steps ([coregistration.keypoints], ...)
    [fusion]                  redundancy and noise removal (sec. 4.2)
    [trees]                   tree measurement ([trees.stems], [trees.qsm], ...)
    [change]                  re-surveys: persisting stems, registration, tree matching
    [plan]                    where to scan next: the next-scan planner

Every command accepts such a file with ``--params``; ``forestreg params --toml`` prints the
defaults as a template. A file may set only the values it changes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path

from .change.params import ChangeParams
from .core.errors import ParameterError
from .core.params import Params, read_toml
from .coreg.coregister import CoregistrationParams
from .coreg.fusion import FusionParams
from .tls.params import PlanParams, RegistrationParams, ScannerPositionParams, SurveyParams
from .trees.inventory import TreeParams

__all__ = ["ProductParams", "load_params", "params_toml"]


@dataclass(frozen=True)
class ProductParams(Params):
    """Every parameter of the product, one section per product step."""

    registration: RegistrationParams = RegistrationParams()
    scanner_position: ScannerPositionParams = ScannerPositionParams()
    survey: SurveyParams = SurveyParams()
    coregistration: CoregistrationParams = CoregistrationParams()
    fusion: FusionParams = FusionParams()
    trees: TreeParams = TreeParams()
    change: ChangeParams = ChangeParams()
    plan: PlanParams = PlanParams()


def load_params(path: str | Path) -> ProductParams:
    """Read a nested parameter file. A key outside every section is refused, naming the sections
    whose parameter sets have a field of that name (a key is never guessed into a section)."""
    data = read_toml(path)
    sections = {f.name for f in fields(ProductParams)}
    loose = [k for k, v in data.items() if k not in sections and not isinstance(v, dict)]
    if loose:
        raise ParameterError(f"parameter file {path}: " + "; ".join(_homes_of(k) for k in loose))
    return ProductParams.from_mapping(data, where="")


def _sections_with(name: str, params: Params, prefix: str = "") -> list[str]:
    """The sections (dotted) of ``params`` whose parameter set has a field ``name``."""
    out = []
    for f in fields(params):
        value = getattr(params, f.name)
        if isinstance(value, Params):
            here = f"{prefix}{f.name}"
            if any(g.name == name and not isinstance(getattr(value, g.name), Params) for g in fields(value)):
                out.append(here)
            out += _sections_with(name, value, here + ".")
    return out


def _homes_of(key: str) -> str:
    """Where a key found outside every section belongs, as one clause of the refusal."""
    homes = _sections_with(key, ProductParams())
    if homes:
        return f"{key} is outside every section: put it under {' or '.join(f'[{h}]' for h in homes)}"
    return (
        f"{key} is outside every section, and no section has a parameter of that name "
        f"(sections: {', '.join(f'[{f.name}]' for f in fields(ProductParams))}; 'forestreg params' lists them all)"
    )


def _toml_value(v: object) -> str:
    if isinstance(v, tuple):
        return json.dumps(list(v))
    return json.dumps(v)


def params_toml(params: Params = ProductParams()) -> str:
    """A TOML file of ``params`` (all sections, with unit and help as comments); a field whose
    value is None ("automatic") is written as a comment."""
    lines: list[str] = []

    def section(name: str, p: Params) -> None:
        lines.append(f"[{name}]")
        nested = []
        for f in fields(p):
            v = getattr(p, f.name)
            if isinstance(v, Params):
                nested.append((f"{name}.{f.name}", v))
                continue
            unit = f.metadata.get("unit", "")
            note = " ".join(x for x in (unit if unit != "1" else "", f.metadata.get("help", "")) if x)
            paper = f.metadata.get("paper", "")
            if paper:
                note += f" (paper: {paper})"
            if v is None:
                lines.append(f"# {f.name} = ...  # automatic when absent. {note}".rstrip())
            else:
                lines.append(f"{f.name} = {_toml_value(v)}  # {note}".rstrip(" #"))
        lines.append("")
        for n, sub in nested:
            section(n, sub)

    for f in fields(params):
        section(f.name, getattr(params, f.name))
    return "\n".join(lines)
