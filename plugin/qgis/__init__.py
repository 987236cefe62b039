"""forestreg in QGIS: a menu action and a Processing provider (seven algorithms: register pair,
register plot, coregister, fuse, trees, evaluate, change) that submit jobs to the forestreg job
service (started when it is not running), show their progress, and load what the jobs wrote: the
styled layers of ``layers.gpkg``, point cloud layers, the scanner positions and VOPs.
``metadata.txt`` declares ``hasProcessingProvider=yes``, so ``qgis_process`` runs them too.

QGIS has its own Qt binding: nothing here imports PySide6, and ``qgis`` is imported only by the
modules QGIS loads through :func:`classFactory` (``host``, ``provider``), never by this package.
"""

from __future__ import annotations


def classFactory(iface):  # noqa: N802 - the name QGIS looks for
    """QGIS plugin entry point: the plugin object for ``iface`` (a ``QgisInterface``)."""
    from .host import ForestregPlugin

    return ForestregPlugin(iface)
