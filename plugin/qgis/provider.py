"""The forestreg Processing provider: "Register TLS pair (trunk shadows)" and "Register plot".

Each algorithm submits its command as a job to the forestreg job service through
:mod:`forestreg.plugin.adapter` (the service is started on first use when it is not running): the
job's progress events and output lines go to the Processing feedback, Cancel cancels the job, and
the scanner positions and the VOPs are loaded as delimited-text point layers when it completes.
"""

from __future__ import annotations

from pathlib import Path

from qgis.core import (
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterCrs,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
    QgsProcessingParameterNumber,
    QgsProcessingParameterString,
    QgsProcessingProvider,
    QgsSettings,
    QgsVectorLayer,
)

from .. import adapter

PROVIDER_ID = "forestreg"
PAIR_ALGORITHM = f"{PROVIDER_ID}:register_pair"
PLOT_ALGORITHM = f"{PROVIDER_ID}:register_plot"
SETTINGS_CLI = "forestreg/cli"  # QgsSettings key: the forestreg command (path or command line)
SCAN_FILTER = "Point clouds (*.las *.laz *.ply *.pcd *.e57 *.xyz *.txt *.csv);;All files (*.*)"


def _run_and_report(run, feedback):
    """Call ``run(progress, log, cancelled)`` with the Processing feedback wired in."""

    def progress(fraction: float, message: str) -> None:
        feedback.setProgress(100.0 * fraction)
        feedback.setProgressText(message)

    def log(line: str) -> None:
        feedback.pushConsoleInfo(line)

    try:
        outputs = run(progress, log, feedback.isCanceled)
        feedback.setProgress(100.0)  # the job ended: its last event may stop short of 1.0
        return outputs
    except adapter.CancelledError as exc:
        raise QgsProcessingException(str(exc)) from exc
    except adapter.AdapterError as exc:
        if exc.stderr:
            feedback.reportError(exc.stderr)
        raise QgsProcessingException(str(exc)) from exc


def _load_point_layer(path: Path, name: str, crs, context: QgsProcessingContext, output: str, feedback):
    authid = crs.authid() if crs is not None and crs.isValid() else None
    layer = QgsVectorLayer(adapter.delimited_text_uri(path, authid), name, "delimitedtext")
    if not layer.isValid():
        feedback.reportError(f"could not open {path} as a point layer")
        return None
    context.temporaryLayerStore().addMapLayer(layer)
    context.addLayerToLoadOnCompletion(layer.id(), QgsProcessingContext.LayerDetails(name, context.project(), output))
    return layer.id()


class _Base(QgsProcessingAlgorithm):
    OUTPUT = "OUTPUT"
    DR = "DR"
    CRS = "CRS"
    CLI = "CLI"
    SCANNERS = "SCANNERS"
    STATUS = "STATUS"
    REASON = "REASON"
    #: each algorithm's id, title and help text, which QGIS asks for by method
    NAME = DISPLAY_NAME = HELP = ""

    def name(self):
        return self.NAME

    def displayName(self):  # noqa: N802
        return self.DISPLAY_NAME

    def shortHelpString(self):  # noqa: N802
        return self.HELP

    def group(self):
        return "Registration"

    def groupId(self):  # noqa: N802
        return "registration"

    def createInstance(self):  # noqa: N802
        return type(self)()

    def _common_parameters(self) -> None:
        self.addParameter(QgsProcessingParameterNumber(
            self.DR, "VOP radius D_r in metres (empty: automatic)", type=QgsProcessingParameterNumber.Double,
            optional=True, minValue=1.0, maxValue=100.0,
        ))
        crs = QgsProcessingParameterCrs(self.CRS, "CRS of the scans' coordinates (for the layers)", optional=True)
        crs.setFlags(crs.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(crs)
        cli = QgsProcessingParameterString(
            self.CLI, "forestreg command that starts the service (path, or e.g. 'python3 -m forestreg.cli'; empty: forestreg on PATH)",
            defaultValue=QgsSettings().value(SETTINGS_CLI, "", type=str), optional=True,
        )
        cli.setFlags(cli.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(cli)
        self.addOutput(QgsProcessingOutputVectorLayer(self.SCANNERS, "Scanner positions", QgsProcessing.TypeVectorPoint))
        self.addOutput(QgsProcessingOutputString(self.STATUS, "Status (ok / failed)"))
        self.addOutput(QgsProcessingOutputString(self.REASON, "Reason of a failure"))

    def _dr(self, parameters, context):
        value = parameters.get(self.DR)
        return None if value in (None, "") else self.parameterAsDouble(parameters, self.DR, context)

    def _cli(self, parameters, context):
        return (self.parameterAsString(parameters, self.CLI, context) or "").strip() or None

    def _run_job(self, args, run, failure, layer_name, parameters, context, feedback):
        """Run the service job ``args`` through ``run(cli, progress, log, cancelled)``, report a
        failure as ``failure: reason``, write the layer CSVs and load the scanner positions as
        ``scanners (layer_name)``. Returns the outputs, the CRS, the layer files and the common
        result entries (output folder, scanners layer, status, reason)."""
        cli = self._cli(parameters, context)
        feedback.pushInfo("job: forestreg " + " ".join(args))
        outputs = _run_and_report(lambda p, l, c: run(cli, p, l, c), feedback)
        if outputs.status != "ok":
            feedback.reportError(f"{failure}: {outputs.reason}")
        crs = self.parameterAsCrs(parameters, self.CRS, context)
        files = adapter.write_layer_files(outputs)
        scanners = _load_point_layer(files.scanners, f"scanners ({layer_name})", crs, context, self.SCANNERS, feedback)
        return outputs, crs, files, {
            self.OUTPUT: self.parameterAsString(parameters, self.OUTPUT, context),
            self.SCANNERS: scanners,
            self.STATUS: outputs.status,
            self.REASON: outputs.reason,
        }


class RegisterPairAlgorithm(_Base):
    REFERENCE = "REFERENCE"
    MOVING = "MOVING"
    VOPS = "VOPS"
    MATCHED = "MATCHED"
    TRANSFORM = "TRANSFORM"
    NAME = "register_pair"
    DISPLAY_NAME = "Register TLS pair (trunk shadows)"
    HELP = (
        "Registers the moving scan onto the reference scan from the shadows the trunks cast "
        "(visual occlusion points), then ICP, as a 'forestreg register' job of the forestreg service. "
        "Writes result.json, transform.txt (p_reference = matrix @ p_moving), the VOP files and a figure "
        "into the output folder, and loads the scanner positions and the VOPs (in the reference scan's "
        "coordinates; 'matched' = 1 for matched VOPs) as point layers."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(self.REFERENCE, "Reference scan", fileFilter=SCAN_FILTER))
        self.addParameter(QgsProcessingParameterFile(self.MOVING, "Moving scan (mapped onto the reference)", fileFilter=SCAN_FILTER))
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self._common_parameters()
        self.addOutput(QgsProcessingOutputVectorLayer(self.VOPS, "Visual occlusion points", QgsProcessing.TypeVectorPoint))
        self.addOutput(QgsProcessingOutputNumber(self.MATCHED, "Matched VOPs"))
        self.addOutput(QgsProcessingOutputString(self.TRANSFORM, "transform.txt"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        out = self.parameterAsString(parameters, self.OUTPUT, context)
        job = adapter.PairJob(
            reference=self.parameterAsFile(parameters, self.REFERENCE, context),
            moving=self.parameterAsFile(parameters, self.MOVING, context),
            out_dir=out,
            vop_radius_m=self._dr(parameters, context),
        )
        stem = f"{Path(job.moving).stem} onto {Path(job.reference).stem}"
        outputs, crs, files, results = self._run_job(
            adapter.build_pair_args(job), lambda *a: adapter.register_pair(job, *a), "registration failed", stem,
            parameters, context, feedback,
        )
        return {
            **results,
            self.VOPS: _load_point_layer(files.vops, f"VOPs ({stem})", crs, context, self.VOPS, feedback),
            self.MATCHED: outputs.matched,
            self.TRANSFORM: str(Path(out) / "transform.txt") if outputs.status == "ok" else "",
        }


class RegisterPlotAlgorithm(_Base):
    SCANS = "SCANS"
    CENTRE = "CENTRE"
    NAME = "register_plot"
    DISPLAY_NAME = "Register plot"
    HELP = (
        "Registers all scans of a plot onto the centre scan (the first one unless given) as a "
        "'forestreg plot' job of the forestreg service. Writes project.json, poses.json (p_centre = matrix @ p_scan), "
        "one <scan>.transform.txt per registered scan and report.html into the output folder, and loads the "
        "scanner positions in the centre scan's coordinates as a point layer."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterMultipleLayers(self.SCANS, "Scan files", layerType=QgsProcessing.TypeFile))
        self.addParameter(QgsProcessingParameterString(self.CENTRE, "Centre scan (file name; empty: the first scan)", optional=True))
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self._common_parameters()

    def _scans(self, parameters, context):
        try:
            files = self.parameterAsFileList(parameters, self.SCANS, context)
        except AttributeError:  # pragma: no cover - QGIS < 3.10
            files = []
        if not files:
            value = parameters.get(self.SCANS) or []
            files = value.split(";") if isinstance(value, str) else [str(v) for v in value]
        return [f for f in files if f]

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        out = self.parameterAsString(parameters, self.OUTPUT, context)
        scans = self._scans(parameters, context)
        if len(scans) < 2:
            raise QgsProcessingException("a plot needs at least two scan files")
        job = adapter.PlotJob(
            scans=scans, out_dir=out,
            centre=(self.parameterAsString(parameters, self.CENTRE, context) or "").strip() or None,
            vop_radius_m=self._dr(parameters, context),
        )
        return self._run_job(
            adapter.build_plot_args(job), lambda *a: adapter.register_plot(job, *a), "not every scan was registered",
            Path(out).name, parameters, context, feedback,
        )[3]


class ForestregProvider(QgsProcessingProvider):
    def id(self):
        return PROVIDER_ID

    def name(self):
        return "forestreg"

    def longName(self):  # noqa: N802
        return "forestreg: marker-free registration of forest laser scans"

    def loadAlgorithms(self):  # noqa: N802
        self.addAlgorithm(RegisterPairAlgorithm())
        self.addAlgorithm(RegisterPlotAlgorithm())
