"""JSON-ready copies of results: numpy arrays and scalars become lists and Python numbers."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["to_jsonable"]


def to_jsonable(value: Any, *, nan_as_null: bool = False) -> Any:
    """``value`` with dicts, lists and tuples copied, numpy arrays as (nested) lists and numpy
    scalars as Python numbers; with ``nan_as_null`` non-finite floats become None (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v, nan_as_null=nan_as_null) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v, nan_as_null=nan_as_null) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist(), nan_as_null=nan_as_null) if nan_as_null else value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        value = value.item()
    if nan_as_null and isinstance(value, float) and not math.isfinite(value):
        return None
    return value
