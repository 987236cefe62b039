"""forestreg: marker-free registration of forest laser scans and tree measurements.

The repository root is both a QGIS plugin folder and the import package ``forestreg``. Importing
it stays cheap and Qt-free: the engine is imported on first use of a public name (``__all__``).

Python API (headless; metres, degrees; a matrix maps the moving/ground cloud's file coordinates
onto the reference/UAV cloud's: ``p_reference = matrix @ p_moving``). The functions go through the
use cases' checks (:mod:`forestreg.app`), as the command line does, before any work: a cloud may be
a ``Scan``, an (N, 3) array of finite x, y, z in metres or a point file's path, and one in another
unit (cm, mm, feet) is refused at once with the likely unit; anything else raises a
:class:`ForestregError` saying what was expected::

    import forestreg

    # System A: a pair of TLS scans, and a whole plot project
    reference = forestreg.read_scan("scan1.laz")
    moving = forestreg.read_scan("scan2.laz")
    result = forestreg.register(reference, moving)          # PairResult
    if result.ok:
        print(result.matrix)
    else:
        print(result.reason)
    project = forestreg.Project.load("plot.json")
    forestreg.register_project(project)

    # System B: ground-based onto UAV, fusion, trees, evaluation against field records
    ground, uav = forestreg.read_scan("backpack.laz"), forestreg.read_scan("uav.laz")
    co = forestreg.coregister(ground, uav)                   # CoregistrationResult
    fused = forestreg.fuse_scans(ground, uav, co.matrix)     # FusionResult
    trees = forestreg.measure_trees(fused.points)            # TreeInventory (a Scan, an array or a file)
    report = forestreg.evaluate(trees.rows(), "field.csv")   # Evaluation (R2, RMSE, rRMSE)

    # every parameter: one dataclass per step, one nested TOML file for all of them
    params = forestreg.load_params("params.toml")            # ProductParams
    result = forestreg.register(reference, moving, params.registration)
"""

from __future__ import annotations

import importlib
from typing import Any

from ._version import __version__  # noqa: F401 - forestreg.__version__

# public name -> module (relative to this package) that defines it: the functions that take clouds,
# projects or tables are the use cases' checked entries (app), the types and parameters the engine's
_LAZY = {
    # foundations
    "Scan": ".engine.core.scan",
    "ForestregError": ".engine.core.errors",
    "ParameterError": ".engine.core.errors",
    "ScanDataError": ".engine.core.errors",
    "ScanReadError": ".engine.core.errors",
    "Cancelled": ".engine.core.errors",
    "CancelToken": ".engine.core.progress",
    "Outcome": ".engine.core.outcome",
    "OutcomeRecord": ".engine.core.outcome",
    "read_scan": ".app.common",
    "read_scans": ".app.common",
    "write_scan": ".app.common",
    "terrain_model": ".app.trees",
    "TerrainParams": ".engine.terrain",
    # parameters
    "ProductParams": ".engine.params",
    "load_params": ".engine.params",
    # System A: pairs, plots, targets
    "register": ".app.pair",
    "PairResult": ".engine.tls.pair",
    "ManualResult": ".engine.tls.manual",
    "LinkResult": ".engine.tls.project",
    "RegistrationParams": ".engine.tls.params",
    "Project": ".engine.tls.project",
    "register_project": ".app.common",
    "plot_scans": ".app.plot",
    "register_manual": ".app.pair",
    "compare_auto_manual": ".app.common",
    "register_survey": ".app.common",
    "SurveyParams": ".engine.tls.survey",
    "locate_scanner": ".app.pair",
    # System B: co-registration, fusion, trees, evaluation
    "coregister": ".app.coregistration",
    "CoregistrationParams": ".engine.coreg.coregister",
    "CoregistrationResult": ".engine.coreg.coregister",
    "fuse": ".app.fusion",
    "fuse_scans": ".app.fusion",
    "fuse_files": ".app.fusion",
    "FusionParams": ".engine.coreg.fusion",
    "FusionResult": ".engine.coreg.fusion",
    "measure_trees": ".app.trees",
    "TreeParams": ".engine.trees.inventory",
    "TreeInventory": ".engine.trees.inventory",
    "evaluate": ".app.evaluation",
    "Evaluation": ".engine.trees.evaluate",
}

__all__ = sorted(_LAZY)


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
