"""forestreg in QGIS: a menu action and a Processing provider that submit jobs to the forestreg
job service (started when it is not running), show their progress, and load the scanner positions
and VOPs as point layers.

QGIS has its own Qt binding: nothing here imports PySide6, and ``qgis`` is imported only by the
modules QGIS loads through :func:`classFactory` (``host``, ``provider``), never by this package.
"""

from __future__ import annotations


def classFactory(iface):  # noqa: N802 - the name QGIS looks for
    """QGIS plugin entry point: the plugin object for ``iface`` (a ``QgisInterface``)."""
    from .host import ForestregPlugin

    return ForestregPlugin(iface)
