"""forestreg: marker-free registration of forest laser scans and tree measurements.

The repository root is both a QGIS plugin folder and the import package ``forestreg``. Importing
it stays cheap and Qt-free: the engine is imported on first use of a public name.

Python API (headless)::

    import forestreg
    reference = forestreg.read_scan("scan1.laz")
    moving = forestreg.read_scan("scan2.laz")
    result = forestreg.register(reference, moving)
    if result.ok:
        print(result.matrix)      # p_reference = matrix @ p_moving, file coordinates
    else:
        print(result.reason)

    # System B: a ground-based cloud onto a UAV cloud of the same plot
    ground = forestreg.read_scan("backpack.laz")
    uav = forestreg.read_scan("uav.laz")
    result = forestreg.coregister(ground, uav)   # p_uav = result.matrix @ p_ground
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> module (relative to this package) that defines it
_LAZY = {
    "Scan": ".engine.core.scan",
    "ForestregError": ".engine.core.errors",
    "CancelToken": ".engine.core.progress",
    "read_scan": ".engine.io",
    "read_scans": ".engine.io",
    "write_scan": ".engine.io",
    "register": ".engine.tls.pair",
    "coregister": ".engine.coreg.coregister",
    "CoregistrationParams": ".engine.coreg.coregister",
    "terrain_model": ".engine.terrain",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'forestreg' has no attribute {name!r}")
    return getattr(importlib.import_module(module, __name__), name)


def classFactory(iface):  # noqa: N802 - the name QGIS looks for in a plugin folder
    """QGIS plugin entry point (the repository root is the plugin folder). Imports the QGIS side
    only when QGIS calls it, so ``import forestreg`` stays Qt-free."""
    from .plugin.qgis import classFactory as factory

    return factory(iface)


def __dir__() -> list[str]:
    return sorted(list(globals()) + list(_LAZY))
