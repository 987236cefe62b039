"""A stand-in for ``qgis.core`` (and ``qgis.PyQt``) that holds just what the forestreg Processing
provider uses, so that its algorithms can be defined, given parameters and run headless where QGIS
is not installed. Parameters and outputs keep what they were built with; ``parameterAs*`` read
the value given, else the parameter's default, as QGIS does; layers are valid when their source
file exists. :func:`installed` puts the modules into ``sys.modules`` and imports the provider
afresh against them."""

from __future__ import annotations

import importlib
import sys
import types
from contextlib import contextmanager
from pathlib import Path


class Qgis:
    QGIS_VERSION_INT = 33400
    Warning = 1
    Info = 0


class QgsProcessingException(Exception):
    pass


class QgsProcessing:
    TypeVectorPoint = 0
    TypeFile = 4  # QgsProcessing.SourceType.TypeFile (TypeVector is 5)


class _Definition:
    """A parameter or an output: its class name (``kind``), name, description and keywords."""

    FlagAdvanced = 2
    FlagOptional = 8

    def __init__(self, name, description="", *args, **kw):
        self._name, self._description, self.args, self.kw = name, description, args, kw
        self._flags = self.FlagOptional if kw.get("optional") else 0

    kind = "definition"

    def name(self):
        return self._name

    def description(self):
        return self._description

    def flags(self):
        return self._flags

    def setFlags(self, flags):  # noqa: N802
        self._flags = flags

    def defaultValue(self):  # noqa: N802
        return self.kw.get("defaultValue")

    def optional(self):
        return bool(self._flags & self.FlagOptional)

    def advanced(self):
        return bool(self._flags & self.FlagAdvanced)

    def options(self):
        return self.kw.get("options")


def _kind(name):
    return type(name, (_Definition,), {"kind": name})


QgsProcessingParameterDefinition = _Definition
PARAMETERS = (
    "Boolean",
    "Crs",
    "Enum",
    "File",
    "FileDestination",
    "FolderDestination",
    "MultipleLayers",
    "Number",
    "String",
)
OUTPUTS = ("File", "Folder", "MultipleLayers", "Number", "PointCloudLayer", "String", "VectorLayer")
for _n in PARAMETERS:
    globals()[f"QgsProcessingParameter{_n}"] = _kind(f"QgsProcessingParameter{_n}")
for _n in OUTPUTS:
    globals()[f"QgsProcessingOutput{_n}"] = _kind(f"QgsProcessingOutput{_n}")
QgsProcessingParameterNumber.Integer, QgsProcessingParameterNumber.Double = 0, 1  # noqa: F821


class Crs:
    def __init__(self, text):
        self.text = text or ""

    def isValid(self):  # noqa: N802
        return bool(self.text)

    def authid(self):
        return self.text if self.text.upper().startswith("EPSG:") else ""

    def toWkt(self):  # noqa: N802
        return self.text


class QgsProcessingAlgorithm:
    def __init__(self):
        self._parameters, self._outputs = [], []

    def addParameter(self, p):  # noqa: N802
        self._parameters.append(p)

    def addOutput(self, o):  # noqa: N802
        self._outputs.append(o)

    def parameterDefinitions(self):  # noqa: N802
        return list(self._parameters)

    def outputDefinitions(self):  # noqa: N802
        return list(self._outputs)

    def parameterDefinition(self, name):  # noqa: N802
        return next((p for p in self._parameters if p.name() == name), None)

    def _value(self, parameters, name):
        value = parameters.get(name)
        if value is None:
            p = self.parameterDefinition(name)
            value = p.defaultValue() if p is not None else None
        return value

    def parameterAsString(self, parameters, name, context):  # noqa: N802
        value = self._value(parameters, name)
        return "" if value is None else str(value)

    parameterAsFile = parameterAsFileOutput = parameterAsString  # noqa: N815

    def parameterAsDouble(self, parameters, name, context):  # noqa: N802
        return float(self._value(parameters, name))

    def parameterAsInt(self, parameters, name, context):  # noqa: N802
        return int(self._value(parameters, name))

    def parameterAsEnum(self, parameters, name, context):  # noqa: N802
        return int(self._value(parameters, name) or 0)

    def parameterAsBool(self, parameters, name, context):  # noqa: N802
        return bool(self._value(parameters, name))

    def parameterAsCrs(self, parameters, name, context):  # noqa: N802
        return Crs(self._value(parameters, name))

    def parameterAsFileList(self, parameters, name, context):  # noqa: N802
        value = self._value(parameters, name) or []
        return [str(v) for v in value]

    def id(self):
        return f"forestreg:{self.name()}"


class QgsProcessingProvider:
    def __init__(self):
        self._algorithms = []

    def addAlgorithm(self, algorithm):  # noqa: N802
        algorithm.initAlgorithm()
        self._algorithms.append(algorithm)

    def algorithms(self):
        if not self._algorithms:
            self.loadAlgorithms()
        return list(self._algorithms)


class QgsCoordinateReferenceSystem(Crs):
    def __init__(self, text=""):
        super().__init__(text)

    def createFromUserInput(self, text):  # noqa: N802
        self.text = text or ""
        return self.isValid()


class QgsSettings:
    def value(self, key, default=None, type=None):  # noqa: A002
        return default


class _Layer:
    count = 0

    def __init__(self, source, name, provider):
        _Layer.count += 1
        self.source, self._name, self.provider, self._id = source, name, provider, f"layer{_Layer.count}"
        self.styles = []

    def id(self):
        return self._id

    def name(self):
        return self._name

    def isValid(self):  # noqa: N802
        return Path(self.source.split("|")[0].split("?")[0].removeprefix("file://")).exists()

    def setCrs(self, crs):  # noqa: N802
        self.crs = crs

    def importNamedStyle(self, doc):  # noqa: N802
        self.styles.append(doc.content)
        return True, ""


class QgsVectorLayer(_Layer):
    pass


class QgsPointCloudLayer(_Layer):
    pass


class _Store:
    def __init__(self):
        self.layers = {}

    def addMapLayer(self, layer):  # noqa: N802
        self.layers[layer.id()] = layer

    def mapLayer(self, layer_id):  # noqa: N802
        return self.layers.get(layer_id)


class QgsProcessingContext:
    class LayerDetails:
        def __init__(self, name, project, output):
            self.name, self.project, self.output = name, project, output

    def __init__(self):
        self.store, self.to_load = _Store(), {}

    def temporaryLayerStore(self):  # noqa: N802
        return self.store

    def project(self):
        return None

    def addLayerToLoadOnCompletion(self, layer_id, details):  # noqa: N802
        self.to_load[layer_id] = details


class Feedback:
    """What Processing's feedback records: progress (0-100), its texts, the log and errors;
    ``cancel_after`` progress events, it answers that the run was cancelled."""

    def __init__(self, cancel_after=None):
        self.progress, self.texts, self.info, self.console, self.errors = [], [], [], [], []
        self.cancel_after = cancel_after

    def setProgress(self, value):  # noqa: N802
        self.progress.append(value)

    def setProgressText(self, text):  # noqa: N802
        self.texts.append(text)

    def pushInfo(self, text):  # noqa: N802
        self.info.append(text)

    def pushConsoleInfo(self, text):  # noqa: N802
        self.console.append(text)

    def reportError(self, text, fatalError=False):  # noqa: N802, N803
        self.errors.append(text)

    def isCanceled(self):  # noqa: N802
        return self.cancel_after is not None and len(self.progress) >= self.cancel_after


class QDomDocument:
    def __init__(self):
        self.content = ""

    def setContent(self, text):  # noqa: N802
        self.content = text
        return True


class QgsApplication:
    @staticmethod
    def processingRegistry():  # noqa: N802
        return None


class QgsProviderRegistry:
    """The data providers QGIS was built with (``providers``: their keys)."""

    providers = ("ogr", "delimitedtext", "pdal")

    @classmethod
    def instance(cls):
        return cls()

    def providerList(self):  # noqa: N802
        return list(self.providers)


def _modules(version: int, point_clouds: bool, pdal: bool = True) -> dict:
    core = types.ModuleType("qgis.core")
    for key, value in globals().items():
        if key.startswith(("Qgs", "Qgis")):
            setattr(core, key, value)
    core.Qgis = type("Qgis", (Qgis,), {"QGIS_VERSION_INT": version})
    if not pdal:  # a QGIS built without its PDAL provider (Debian 12's 3.22): point cloud classes, no provider
        core.QgsProviderRegistry = type(
            "QgsProviderRegistry", (QgsProviderRegistry,), {"providers": ("ogr", "delimitedtext")}
        )
    if not point_clouds:
        del core.QgsPointCloudLayer
        del core.QgsProcessingOutputPointCloudLayer
    qgis = types.ModuleType("qgis")
    pyqt = types.ModuleType("qgis.PyQt")
    xml = types.ModuleType("qgis.PyQt.QtXml")
    xml.QDomDocument = QDomDocument
    qgis.core, qgis.PyQt, pyqt.QtXml = core, pyqt, xml
    return {"qgis": qgis, "qgis.core": core, "qgis.PyQt": pyqt, "qgis.PyQt.QtXml": xml}


@contextmanager
def installed(version: int = 33400, point_clouds: bool = True, pdal: bool = True):
    """The fake ``qgis`` modules in ``sys.modules`` (QGIS ``version``; without point cloud layers
    when ``point_clouds`` is false, without the PDAL provider when ``pdal`` is false), and
    :mod:`forestreg.plugin.qgis.provider` imported against them."""
    name = "forestreg.plugin.qgis.provider"
    saved = {k: sys.modules.get(k) for k in ("qgis", "qgis.core", "qgis.PyQt", "qgis.PyQt.QtXml", name)}
    sys.modules.update(_modules(version, point_clouds, pdal))
    sys.modules.pop(name, None)
    try:
        yield importlib.import_module(name)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
