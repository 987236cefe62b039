"""The documented Python API: every public name resolves, importing stays light."""

from __future__ import annotations

import subprocess
import sys

import forestreg


def test_every_public_name_resolves_and_is_documented():
    assert forestreg.__all__ == sorted(forestreg.__all__)
    for name in forestreg.__all__:
        obj = getattr(forestreg, name)
        assert obj.__doc__, f"forestreg.{name} has no docstring"
    for name in (
        "register",
        "register_project",
        "coregister",
        "fuse_scans",
        "measure_trees",
        "evaluate",
        "load_params",
    ):
        assert callable(getattr(forestreg, name))
    assert forestreg.load_params.__module__ == "forestreg.engine.params"


def test_import_forestreg_stays_cheap_and_qt_free():
    code = "import sys, forestreg; bad = [m for m in ('numpy', 'open3d', 'PySide6', 'pyvista', 'matplotlib') if m in sys.modules]; print(bad)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
