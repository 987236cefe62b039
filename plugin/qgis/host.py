"""The QGIS plugin object: a menu action ("forestreg: register scans…") and the Processing provider."""

from __future__ import annotations

from qgis.core import QgsApplication
from qgis.PyQt.QtWidgets import QAction

from .provider import PAIR_ALGORITHM, ForestregProvider

MENU = "&forestreg"
ACTION_TEXT = "forestreg: register scans…"


class ForestregPlugin:
    """Loaded by QGIS through ``classFactory(iface)``."""

    def __init__(self, iface) -> None:
        self.iface = iface
        self.provider = None
        self.action = None

    def initProcessing(self) -> None:  # noqa: N802 - QGIS naming
        if self.provider is None:
            provider = ForestregProvider()
            # the registry owns the provider; a refused one (same id already there) is deleted
            self.provider = provider if QgsApplication.processingRegistry().addProvider(provider) else None

    def initGui(self) -> None:  # noqa: N802 - QGIS naming
        self.initProcessing()
        self.check_engine()
        parent = self.iface.mainWindow() if self.iface is not None else None
        self.action = QAction(ACTION_TEXT, parent)
        self.action.setObjectName("forestregRegisterScans")
        self.action.setToolTip("Register two TLS scans from trunk shadows (a job of the forestreg service)")
        self.action.triggered.connect(self.run)
        if self.iface is not None:
            self.iface.addPluginToMenu(MENU, self.action)

    def check_engine(self) -> None:
        """Say in QGIS's message bar (and the log) when the forestreg engine cannot run: which
        modules are missing and how to install them (:func:`~forestreg.plugin.adapter.engine_problem`)."""
        from qgis.core import Qgis, QgsMessageLog, QgsSettings

        from .. import adapter
        from .provider import SETTINGS_CLI

        problem = adapter.engine_problem(QgsSettings().value(SETTINGS_CLI, "", type=str) or None)
        if problem is None:
            return
        QgsMessageLog.logMessage(problem, "forestreg", Qgis.Warning)
        bar = getattr(self.iface, "messageBar", None)
        if bar is not None:
            bar().pushMessage("forestreg", problem, Qgis.Warning, 0)

    def unload(self) -> None:
        if self.action is not None:
            if self.iface is not None:
                self.iface.removePluginMenu(MENU, self.action)
            self.action.deleteLater()
            self.action = None
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None

    def run(self) -> None:
        """Open the pair algorithm's dialog (Processing runs it in the background with progress)."""
        import processing  # QGIS's Processing plugin, present whenever the provider is

        processing.execAlgorithmDialog(PAIR_ALGORITHM, {})
