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

Every command accepts such a file with ``--params``; ``forestreg params --toml`` prints the
defaults as a template. A file may set only the values it changes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path

from .core.params import Params, read_toml
from .change.params import ChangeParams
from .coreg.coregister import CoregistrationParams
from .coreg.fusion import FusionParams
from .tls.params import RegistrationParams, ScannerPositionParams, SurveyParams
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


def load_params(path: str | Path) -> ProductParams:
    """Read a nested parameter file. For files written before the sections existed, top-level
    registration keys (no section at all) are read as ``[registration]``."""
    data = read_toml(path)
    sections = {f.name for f in fields(ProductParams)}
    if data and not set(data) & sections and all(not isinstance(v, dict) for v in data.values()):
        data = {"registration": data}
    return ProductParams.from_mapping(data, where="")


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
