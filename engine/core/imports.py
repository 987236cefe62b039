"""Imports of heavy optional libraries that must not break when another thread imports at the
same time.

``import open3d`` walks ``sys.modules`` at the end of its ``__init__``: when another thread of the
process imports a module at that moment (a scan reader, the report's matplotlib loaded in the
background), the walk fails with "dictionary changed size during iteration". The import is then
tried again (the compiled part is loaded already, only the walk runs again).
"""

from __future__ import annotations

import time
from types import ModuleType

__all__ = ["import_open3d"]


def import_open3d(attempts: int = 5) -> ModuleType:
    """``open3d``, imported (again, if a concurrent import broke its first walk of sys.modules)."""
    for attempt in range(attempts):
        try:
            import open3d

            return open3d
        except RuntimeError as exc:
            if "changed size during iteration" not in str(exc) or attempt == attempts - 1:
                raise
            time.sleep(0.05 * (attempt + 1))
    raise AssertionError("unreachable")  # pragma: no cover
