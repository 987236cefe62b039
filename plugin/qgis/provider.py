"""The forestreg Processing provider: seven algorithms, one per command of the CLI.

"Register TLS pair (trunk shadows)" (``register``), "Register plot" (``plot``), "Co-register
ground onto UAV" (``coregister``), "Fuse ground and UAV clouds" (``fuse``), "Measure trees"
(``trees``), "Evaluate trees against field records" (``evaluate``) and "Re-survey change"
(``change``). Each algorithm submits its command as a job to the forestreg job service through
:mod:`forestreg.plugin.adapter` (the service is started on first use when it is not running): the
job's progress events and output lines go to the Processing feedback, Cancel cancels the job.
When the job completes, the layers of the output folder's ``layers.gpkg`` (each with its QML
style from the GeoPackage's ``layer_styles``) load into the project, and a registered or fused
LAS/LAZ/COPC cloud loads as a point cloud layer (QGIS 3.18 or newer, "pdal" provider). The
pair's scanner positions and VOPs load as delimited-text point layers.

Each algorithm's parameters mirror its command's options with the same defaults; its output
folder (or file) is declared as an output, so the algorithms chain in the Graphical Modeler
(``register_plot``'s merged cloud -> ``trees``'s cloud, ``trees``'s ``trees.csv`` -> ``change``).
"""

from __future__ import annotations

from pathlib import Path

from qgis.core import (
    Qgis,
    QgsCoordinateReferenceSystem,
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingOutputFile,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
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
COREGISTER_ALGORITHM = f"{PROVIDER_ID}:coregister"
FUSE_ALGORITHM = f"{PROVIDER_ID}:fuse"
TREES_ALGORITHM = f"{PROVIDER_ID}:trees"
EVALUATE_ALGORITHM = f"{PROVIDER_ID}:evaluate"
CHANGE_ALGORITHM = f"{PROVIDER_ID}:change"
SETTINGS_CLI = "forestreg/cli"  # QgsSettings key: the forestreg command (path or command line)
SCAN_FILTER = "Point clouds (*.las *.laz *.ply *.pcd *.e57 *.xyz *.txt *.csv);;All files (*.*)"
LAS_FILTER = "LAZ (*.laz);;LAS (*.las);;COPC (*.copc.laz)"
CSV_FILTER = "CSV (*.csv);;All files (*.*)"
TOML_FILTER = "TOML (*.toml);;All files (*.*)"
TRANSFORM_FILTER = "Transform (*.txt *.json);;All files (*.*)"
SURVEY_FILTER = "Survey (*.csv *.json *.las *.laz *.ply *.pcd *.e57 *.xyz *.txt);;All files (*.*)"
#: the ``--units`` choices of the CLI (``forestreg.app.units.UNITS``, sorted), its default "m"
UNITS = ("cm", "ft", "m", "mm", "usft")
DEFAULT_UNITS = "m"
#: QGIS version from which point cloud layers (``QgsPointCloudLayer``, "pdal") exist
POINT_CLOUD_MIN_VERSION = 31800


def _qgis_version() -> int:
    return int(getattr(Qgis, "QGIS_VERSION_INT", 0) or 0)


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


def _layer_crs(crs, summary):
    """The CRS of a run's point layers: ``crs`` (the CRS parameter) when valid, else the CRS the
    run's ``result.json``/``poses.json`` names (the scans' own); None for local coordinates."""
    if crs is not None and crs.isValid():
        return crs
    text = adapter.output_crs(summary)
    if not text:
        return None
    found = QgsCoordinateReferenceSystem()
    found.createFromUserInput(text)
    return found if found.isValid() else None


def _load_point_layer(path: Path, name: str, crs, context: QgsProcessingContext, output: str, feedback):
    """A layer CSV (``x``, ``y``, ``z`` columns) as a point layer in ``crs`` (None: none), loaded
    when the algorithm completes; its id, or None."""
    authid = crs.authid() if crs is not None else None
    layer = QgsVectorLayer(adapter.delimited_text_uri(path, authid or None), name, "delimitedtext")
    if not layer.isValid():
        feedback.reportError(f"could not open {path} as a point layer")
        return None
    if crs is not None and not authid:  # a CRS without an EPSG id (from its WKT)
        layer.setCrs(crs)
    context.temporaryLayerStore().addMapLayer(layer)
    context.addLayerToLoadOnCompletion(layer.id(), QgsProcessingContext.LayerDetails(name, context.project(), output))
    return layer.id()


def _apply_style(layer, qml: str, feedback) -> None:
    """The QML of the GeoPackage's ``layer_styles`` on ``layer`` (QGIS also reads it as the
    layer's default style; applied here as well so that it holds however the layer was opened)."""
    if not qml:
        return
    try:
        from qgis.PyQt.QtXml import QDomDocument

        doc = QDomDocument()
        doc.setContent(qml)
        layer.importNamedStyle(doc)
    except Exception as exc:  # noqa: BLE001 - a style that does not apply leaves QGIS's default
        feedback.pushInfo(f"style of {layer.name()} not applied: {exc}")


def _load_gpkg_layers(folder, label: str, context: QgsProcessingContext, output: str, feedback) -> dict:
    """Each feature layer of ``folder/layers.gpkg`` (trees, crowns, scanners, links, tree_changes,
    keypoints, plot_outline), styled, loaded into the project when the algorithm completes: its
    name -> layer id, in the GeoPackage's order ({} when the run wrote no ``layers.gpkg``)."""
    path = Path(folder) / adapter.LAYERS_FILE
    try:
        layers = adapter.gpkg_layers(path)
    except adapter.AdapterError as exc:
        feedback.reportError(str(exc))
        return {}
    ids = {}
    for item in layers:
        name = f"{item.name} ({label})"
        layer = QgsVectorLayer(item.uri, name, "ogr")
        if not layer.isValid():
            feedback.reportError(f"could not open layer {item.name} of {path}")
            continue
        _apply_style(layer, item.style, feedback)
        context.temporaryLayerStore().addMapLayer(layer)
        context.addLayerToLoadOnCompletion(
            layer.id(), QgsProcessingContext.LayerDetails(name, context.project(), output)
        )
        ids[item.name] = layer.id()
    return ids


def _load_point_cloud(path, name: str, context: QgsProcessingContext, output: str, feedback):
    """A LAS/LAZ/COPC cloud as a point cloud layer ("pdal" provider) loaded on completion, where
    the QGIS version has them (3.18 or newer) and was built with its PDAL provider; its id, or
    None (older QGIS, a QGIS without PDAL, no such file, or a cloud the provider cannot open: the
    file stays in the output folder)."""
    if not adapter.is_point_cloud_file(path):
        return None
    if _qgis_version() < POINT_CLOUD_MIN_VERSION:
        feedback.pushInfo(f"{path}: point cloud layers need QGIS 3.18 or newer; add the file by hand")
        return None
    try:
        from qgis.core import QgsPointCloudLayer, QgsProviderRegistry
    except ImportError:
        feedback.pushInfo(f"{path}: this QGIS has no point cloud layers")
        return None
    if "pdal" not in QgsProviderRegistry.instance().providerList():
        feedback.pushInfo(
            f"{path}: this QGIS was built without its PDAL provider, so it opens no LAS/LAZ file; "
            "the cloud stays in the output folder (a QGIS with PDAL, or CloudCompare, opens it)"
        )
        return None
    layer = QgsPointCloudLayer(str(path), name, "pdal")
    if not layer.isValid():
        feedback.reportError(f"could not open {path} as a point cloud layer (is QGIS's PDAL provider installed?)")
        return None
    context.temporaryLayerStore().addMapLayer(layer)
    context.addLayerToLoadOnCompletion(layer.id(), QgsProcessingContext.LayerDetails(name, context.project(), output))
    return layer.id()


def _point_cloud_output(name: str, description: str):
    """A point cloud layer output where QGIS declares them (3.24+), else the layer id as a string."""
    try:
        from qgis.core import QgsProcessingOutputPointCloudLayer

        return QgsProcessingOutputPointCloudLayer(name, description)
    except ImportError:
        return QgsProcessingOutputString(name, description)


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
        self.addParameter(
            QgsProcessingParameterNumber(
                self.DR,
                "VOP radius D_r in metres (empty: automatic)",
                type=QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=1.0,
                maxValue=100.0,
            )
        )
        crs = QgsProcessingParameterCrs(
            self.CRS, "CRS of the scans' coordinates where they declare none (--crs)", optional=True
        )
        crs.setFlags(crs.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(crs)
        cli = QgsProcessingParameterString(
            self.CLI,
            "forestreg command that starts the service (path, or e.g. 'python3 -m forestreg.cli'; empty: forestreg on PATH)",
            defaultValue=QgsSettings().value(SETTINGS_CLI, "", type=str),
            optional=True,
        )
        cli.setFlags(cli.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(cli)
        self.addOutput(
            QgsProcessingOutputVectorLayer(self.SCANNERS, "Scanner positions", QgsProcessing.TypeVectorPoint)
        )
        self.addOutput(QgsProcessingOutputString(self.STATUS, "Status (ok / failed)"))
        self.addOutput(QgsProcessingOutputString(self.REASON, "Reason of a failure"))

    def _dr(self, parameters, context):
        value = parameters.get(self.DR)
        return None if value in (None, "") else self.parameterAsDouble(parameters, self.DR, context)

    def _cli(self, parameters, context):
        return (self.parameterAsString(parameters, self.CLI, context) or "").strip() or None

    def _crs_text(self, parameters, context):
        """The ``--crs`` value: the CRS's authority id (EPSG:...), else its WKT; None when not given."""
        if parameters.get(self.CRS) in (None, ""):
            return None
        crs = self.parameterAsCrs(parameters, self.CRS, context)
        if crs is None or not crs.isValid():
            return None
        return crs.authid() or crs.toWkt() or None

    def _run_job(self, args, run, failure, layer_name, parameters, context, feedback, layers_output=None):
        """Run the service job ``args`` through ``run(cli, progress, log, cancelled)``, report a
        failure as ``failure: reason``, write the layer CSVs and load the scanner positions as
        ``scanners (layer_name)``. With ``layers_output`` the styled layers of the output folder's
        ``layers.gpkg`` load too (that output: their ids), and its own ``scanners`` layer is the
        scanner positions (one scanners layer, not two). Returns the outputs, the CRS, the layer
        files and the common result entries (output folder, scanners layer, status, reason)."""
        cli = self._cli(parameters, context)
        feedback.pushInfo("job: forestreg " + " ".join(args))
        outputs = _run_and_report(lambda p, l, c: run(cli, p, l, c), feedback)
        if outputs.status != "ok":
            feedback.reportError(f"{failure}: {outputs.reason}")
        crs = _layer_crs(self.parameterAsCrs(parameters, self.CRS, context), outputs.summary)
        files = adapter.write_layer_files(outputs)
        gpkg = _load_gpkg_layers(outputs.out_dir, layer_name, context, layers_output, feedback) if layers_output else {}
        scanners = gpkg.get("scanners") or _load_point_layer(
            files.scanners, f"scanners ({layer_name})", crs, context, self.SCANNERS, feedback
        )
        results = {
            self.OUTPUT: self.parameterAsString(parameters, self.OUTPUT, context),
            self.SCANNERS: scanners,
            self.STATUS: outputs.status,
            self.REASON: outputs.reason,
        }
        if layers_output:
            results[layers_output] = list(gpkg.values())
        return outputs, crs, files, results


class RegisterPairAlgorithm(_Base):
    REFERENCE = "REFERENCE"
    MOVING = "MOVING"
    VOPS = "VOPS"
    MATCHED = "MATCHED"
    TRANSFORM = "TRANSFORM"
    WRITE_REGISTERED = "WRITE_REGISTERED"
    POINT_CLOUD = "POINT_CLOUD"
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
        self.addParameter(
            QgsProcessingParameterFile(self.MOVING, "Moving scan (mapped onto the reference)", fileFilter=SCAN_FILTER)
        )
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterBoolean(
                self.WRITE_REGISTERED,
                "Also write the moving scan in the reference frame (--write-registered; LAZ, loaded as a point cloud)",
                defaultValue=False,
            )
        )
        self._common_parameters()
        self.addOutput(
            QgsProcessingOutputVectorLayer(self.VOPS, "Visual occlusion points", QgsProcessing.TypeVectorPoint)
        )
        self.addOutput(QgsProcessingOutputNumber(self.MATCHED, "Matched VOPs"))
        self.addOutput(QgsProcessingOutputString(self.TRANSFORM, "transform.txt"))
        self.addOutput(_point_cloud_output(self.POINT_CLOUD, "Registered moving scan (point cloud layer)"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        out = self.parameterAsString(parameters, self.OUTPUT, context)
        job = adapter.PairJob(
            reference=self.parameterAsFile(parameters, self.REFERENCE, context),
            moving=self.parameterAsFile(parameters, self.MOVING, context),
            out_dir=out,
            vop_radius_m=self._dr(parameters, context),
            write_registered=bool(parameters.get(self.WRITE_REGISTERED))
            and self.parameterAsBool(parameters, self.WRITE_REGISTERED, context),
            crs=self._crs_text(parameters, context),
        )
        stem = f"{Path(job.moving).stem} onto {Path(job.reference).stem}"
        outputs, crs, files, results = self._run_job(
            adapter.build_pair_args(job),
            lambda *a: adapter.register_pair(job, *a),
            "registration failed",
            stem,
            parameters,
            context,
            feedback,
        )
        return {
            **results,
            self.VOPS: _load_point_layer(files.vops, f"VOPs ({stem})", crs, context, self.VOPS, feedback),
            self.MATCHED: outputs.matched,
            self.TRANSFORM: str(Path(out) / "transform.txt") if outputs.status == "ok" else "",
            self.POINT_CLOUD: _load_point_cloud(
                next(iter(sorted(Path(out).glob("*_registered.laz"))), None),
                f"registered ({stem})",
                context,
                self.POINT_CLOUD,
                feedback,
            )
            if job.write_registered
            else None,
        }


class RegisterPlotAlgorithm(_Base):
    SCANS = "SCANS"
    CENTRE = "CENTRE"
    MERGED = "MERGED"
    LAYERS = "LAYERS"
    POINT_CLOUD = "POINT_CLOUD"
    NAME = "register_plot"
    DISPLAY_NAME = "Register plot"
    HELP = (
        "Registers all scans of a plot onto the centre scan (the first one unless given) as a "
        "'forestreg plot' job of the forestreg service. Writes project.json, poses.json (p_centre = matrix @ p_scan), "
        "one <scan>.transform.txt per registered scan, layers.gpkg and report.html into the output folder, and loads the "
        "scanner positions in the centre scan's coordinates as a point layer, the layers of layers.gpkg (scanners, links, "
        "plot outline; styled) and, when asked for, the merged cloud of all registered scans as a point cloud layer "
        "(its file is the cloud of 'Measure trees' in a model)."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(
            QgsProcessingParameterMultipleLayers(self.SCANS, "Scan files", layerType=QgsProcessing.TypeFile)
        )
        self.addParameter(
            QgsProcessingParameterString(self.CENTRE, "Centre scan (file name; empty: the first scan)", optional=True)
        )
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterFileDestination(
                self.MERGED,
                "Merged cloud of all registered scans (--merged; .laz/.las, .copc.laz for COPC)",
                fileFilter=LAS_FILTER,
                optional=True,
                createByDefault=False,
            )
        )
        self._common_parameters()
        self.addOutput(QgsProcessingOutputMultipleLayers(self.LAYERS, "Layers of layers.gpkg"))
        self.addOutput(_point_cloud_output(self.POINT_CLOUD, "Merged cloud (point cloud layer)"))

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
        merged = (
            (self.parameterAsFileOutput(parameters, self.MERGED, context) or "").strip()
            if parameters.get(self.MERGED)
            else ""
        )
        job = adapter.PlotJob(
            scans=scans,
            out_dir=out,
            centre=(self.parameterAsString(parameters, self.CENTRE, context) or "").strip() or None,
            vop_radius_m=self._dr(parameters, context),
            merged=merged or None,
            crs=self._crs_text(parameters, context),
        )
        label = Path(out).name
        results = self._run_job(
            adapter.build_plot_args(job),
            lambda *a: adapter.register_plot(job, *a),
            "not every scan was registered",
            label,
            parameters,
            context,
            feedback,
            layers_output=self.LAYERS,
        )[3]
        return {
            **results,
            self.MERGED: merged,
            self.POINT_CLOUD: _load_point_cloud(merged, f"merged ({label})", context, self.POINT_CLOUD, feedback),
        }


# ----------------------------------------------------------------------------- the other commands


class _JobAlgorithm(_Base):
    """An algorithm that runs one command (not a registration) as a job of the service: its
    arguments come from :meth:`job` (an adapter job), the job's exit status gives STATUS ("ok" for
    0, "failed" for 1, with the command's last line as REASON)."""

    PARAMS = "PARAMS"
    UNITS = "UNITS"
    LAYERS = "LAYERS"
    GROUP, GROUP_ID = "Registration", "registration"

    def group(self):
        return self.GROUP

    def groupId(self):  # noqa: N802
        return self.GROUP_ID

    # ---- parameters shared by the commands (each mirrors a CLI option, with its default)

    def _crs_parameter(self, what: str) -> None:
        """``--crs``: the CRS of the input coordinates where a file declares none (or that wins)."""
        crs = QgsProcessingParameterCrs(self.CRS, f"CRS of the input coordinates (--crs; {what})", optional=True)
        crs.setFlags(crs.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(crs)

    def _units_parameters(self, what: str) -> None:
        """``--units`` (default m) and ``--params``."""
        self.addParameter(
            QgsProcessingParameterEnum(
                self.UNITS, f"Units ({what}; --units)", options=list(UNITS), defaultValue=UNITS.index(DEFAULT_UNITS)
            )
        )
        params = QgsProcessingParameterFile(
            self.PARAMS, "Parameter file (--params; TOML)", optional=True, fileFilter=TOML_FILTER
        )
        params.setFlags(params.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(params)

    def _cli_parameter(self) -> None:
        cli = QgsProcessingParameterString(
            self.CLI,
            "forestreg command that starts the service (path, or e.g. 'python3 -m forestreg.cli'; empty: forestreg on PATH)",
            defaultValue=QgsSettings().value(SETTINGS_CLI, "", type=str),
            optional=True,
        )
        cli.setFlags(cli.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        self.addParameter(cli)

    def _status_outputs(self) -> None:
        self.addOutput(QgsProcessingOutputString(self.STATUS, "Status (ok / failed)"))
        self.addOutput(QgsProcessingOutputString(self.REASON, "Reason of a failure"))

    # ---- reading parameters

    def _file(self, parameters, name, context):
        return (self.parameterAsFile(parameters, name, context) or "").strip() or None

    def _string(self, parameters, name, context):
        return (self.parameterAsString(parameters, name, context) or "").strip() or None

    def _optional_number(self, parameters, name, context, integer=False):
        if parameters.get(name) in (None, ""):
            return None
        return (
            self.parameterAsInt(parameters, name, context)
            if integer
            else self.parameterAsDouble(parameters, name, context)
        )

    def _units(self, parameters, context, name=None, first=()):
        """The unit chosen in the enum ``name`` (``UNITS``); None for the CLI's default, "m"."""
        name = name or self.UNITS
        if parameters.get(name) in (None, ""):
            return None
        choices = list(first) + list(UNITS)
        value = choices[self.parameterAsEnum(parameters, name, context)]
        return None if value in first or (name == self.UNITS and value == DEFAULT_UNITS) else value

    # ---- running

    def job(self, parameters, context):  # pragma: no cover - each algorithm defines it
        raise NotImplementedError

    def run_service_job(self, job, parameters, context, feedback) -> "adapter.JobRun":
        """Run ``job`` as a job of the service with the feedback wired in (progress, log, cancel)."""
        args = adapter.build_args(job)
        cli = self._cli(parameters, context)
        feedback.pushInfo("job: forestreg " + " ".join(args))
        run = _run_and_report(lambda p, l, c: adapter.run_job(args, progress=p, log=l, cancelled=c, cli=cli), feedback)
        if run.returncode != adapter.EXIT_OK:
            feedback.reportError(f"{self.displayName()} failed: {run.message}")
        return run

    def status(self, run) -> dict:
        ok = run.returncode == adapter.EXIT_OK
        message = run.message or ""
        return {self.STATUS: "ok" if ok else "failed", self.REASON: "" if ok else message.removeprefix("failed: ")}


class CoregisterAlgorithm(_JobAlgorithm):
    GROUND = "GROUND"
    UAV = "UAV"
    MIN_CLUSTER_SIZE = "MIN_CLUSTER_SIZE"
    VOXEL = "VOXEL"
    DISTANCE_THRESHOLD = "DISTANCE_THRESHOLD"
    TRANSFORM = "TRANSFORM"
    RESULT = "RESULT"
    NAME = "coregister"
    DISPLAY_NAME = "Co-register ground onto UAV (canopy keypoints)"
    HELP = (
        "Co-registers a ground-based cloud (merged TLS, backpack or handheld) onto a UAV LiDAR cloud of the same plot "
        "from canopy keypoints, as a 'forestreg coregister' job of the forestreg service. Writes result.json, "
        "transform.txt (p_uav = matrix @ p_ground), the keypoint tables, layers.gpkg and a report into the output "
        "folder, and loads the layers of layers.gpkg (keypoints, outlines; styled). Its transform.txt is the "
        "transform of 'Fuse ground and UAV clouds' and of 'Measure trees'."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(self.GROUND, "Ground-based cloud", fileFilter=SCAN_FILTER))
        self.addParameter(
            QgsProcessingParameterFile(self.UAV, "UAV cloud (the reference frame)", fileFilter=SCAN_FILTER)
        )
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterNumber(
                self.MIN_CLUSTER_SIZE,
                "HDBSCAN MinClusterSize (--min-cluster-size; empty: from the point density)",
                type=QgsProcessingParameterNumber.Integer,
                optional=True,
                minValue=2,
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                self.VOXEL,
                "Thinning voxel before clustering, m (--voxel; empty: 0.3)",
                type=QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=0.0,
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                self.DISTANCE_THRESHOLD,
                "D_thr for matched keypoints, m (--distance-threshold; empty: 1)",
                type=QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=0.0,
            )
        )
        self._crs_parameter("result.json and layers.gpkg are in the UAV cloud's frame and take its CRS")
        self._units_parameters("of the input coordinates; results are written in the same unit")
        self._cli_parameter()
        self.addOutput(QgsProcessingOutputFile(self.TRANSFORM, "transform.txt (p_uav = matrix @ p_ground)"))
        self.addOutput(QgsProcessingOutputFile(self.RESULT, "result.json"))
        self.addOutput(QgsProcessingOutputMultipleLayers(self.LAYERS, "Layers of layers.gpkg"))
        self._status_outputs()

    def job(self, parameters, context):
        return adapter.CoregisterJob(
            ground=self._file(parameters, self.GROUND, context),
            uav=self._file(parameters, self.UAV, context),
            out_dir=self.parameterAsString(parameters, self.OUTPUT, context),
            min_cluster_size=self._optional_number(parameters, self.MIN_CLUSTER_SIZE, context, integer=True),
            voxel_m=self._optional_number(parameters, self.VOXEL, context),
            distance_threshold_m=self._optional_number(parameters, self.DISTANCE_THRESHOLD, context),
            crs=self._crs_text(parameters, context),
            units=self._units(parameters, context),
            params_file=self._file(parameters, self.PARAMS, context),
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        job = self.job(parameters, context)
        run = self.run_service_job(job, parameters, context, feedback)
        out = Path(job.out_dir)
        transform = out / "transform.txt"
        return {
            self.OUTPUT: str(out),
            **self.status(run),
            self.TRANSFORM: str(transform) if run.returncode == adapter.EXIT_OK and transform.is_file() else "",
            self.RESULT: str(out / "result.json"),
            self.LAYERS: list(
                _load_gpkg_layers(
                    out, f"{Path(job.ground).stem} onto {Path(job.uav).stem}", context, self.LAYERS, feedback
                ).values()
            ),
        }


class FuseAlgorithm(_JobAlgorithm):
    GROUND = "GROUND"
    UAV = "UAV"
    TRANSFORM = "TRANSFORM"
    EPSILON = "EPSILON"
    CUBE = "CUBE"
    POINT_CLOUD = "POINT_CLOUD"
    NAME = "fuse"
    DISPLAY_NAME = "Fuse ground and UAV clouds"
    HELP = (
        "Fuses a ground-based and a UAV cloud into one LAS/LAZ cloud in the UAV cloud's frame (redundant points and "
        "noise removed, a per-point source label), as a 'forestreg fuse' job of the forestreg service, and loads it as "
        "a point cloud layer (QGIS 3.18 or newer). The transform is the transform.txt or result.json of "
        "'Co-register ground onto UAV' (identity when empty). The fused cloud is the cloud of 'Measure trees'."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(self.GROUND, "Ground-based cloud", fileFilter=SCAN_FILTER))
        self.addParameter(QgsProcessingParameterFile(self.UAV, "UAV cloud (the output frame)", fileFilter=SCAN_FILTER))
        self.addParameter(
            QgsProcessingParameterFile(
                self.TRANSFORM,
                "Transform (--transform: transform.txt or result.json of coregister; empty: identity)",
                optional=True,
                fileFilter=TRANSFORM_FILTER,
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(self.OUTPUT, "Fused cloud (.laz/.las)", fileFilter=LAS_FILTER)
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                self.EPSILON,
                "Redundancy distance, m (--epsilon; empty: 0.01)",
                type=QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=0.0,
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                self.CUBE,
                "Cube side of the redundancy search, m (--cube; empty: the default)",
                type=QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=0.0,
            )
        )
        self._crs_parameter("the fused cloud takes it; needed when the two files declare different CRSs")
        self._units_parameters("of the input coordinates and of the fused cloud")
        self._cli_parameter()
        self.addOutput(_point_cloud_output(self.POINT_CLOUD, "Fused cloud (point cloud layer)"))
        self._status_outputs()

    def job(self, parameters, context):
        return adapter.FuseJob(
            ground=self._file(parameters, self.GROUND, context),
            uav=self._file(parameters, self.UAV, context),
            out=self.parameterAsFileOutput(parameters, self.OUTPUT, context),
            transform=self._file(parameters, self.TRANSFORM, context),
            epsilon_m=self._optional_number(parameters, self.EPSILON, context),
            cube_m=self._optional_number(parameters, self.CUBE, context),
            crs=self._crs_text(parameters, context),
            units=self._units(parameters, context),
            params_file=self._file(parameters, self.PARAMS, context),
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        job = self.job(parameters, context)
        run = self.run_service_job(job, parameters, context, feedback)
        return {
            self.OUTPUT: str(job.out),
            **self.status(run),
            self.POINT_CLOUD: _load_point_cloud(job.out, Path(str(job.out)).name, context, self.POINT_CLOUD, feedback),
        }


SINGLE_TREE_OPTIONS = ("decided from the cloud", *adapter.SINGLE_TREE_CHOICES)


class TreesAlgorithm(_JobAlgorithm):
    CLOUD = "CLOUD"
    TRANSFORM = "TRANSFORM"
    FIELD = "FIELD"
    CYLINDERS = "CYLINDERS"
    SINGLE_TREE = "SINGLE_TREE"
    REPORT = "REPORT"
    TREES = "TREES"
    NAME = "trees"
    DISPLAY_NAME = "Measure trees"
    GROUP, GROUP_ID = "Trees", "trees"
    HELP = (
        "Detects and measures the trees (DBH, height, crown, stem curves, cylinder models) of a ground-based or fused "
        "cloud, ground included, as a 'forestreg trees' job of the forestreg service. Writes trees.csv, stem_curves.csv, "
        "cylinders/, layers.gpkg and report.html into the output folder and loads the layers of layers.gpkg (trees at "
        "breast height graduated by DBH, crowns, plot outline; styled). Its trees.csv is a survey of 'Re-survey change' "
        "and the trees of 'Evaluate trees against field records'."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(self.CLOUD, "Cloud (ground included)", fileFilter=SCAN_FILTER))
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterFile(
                self.TRANSFORM,
                "Move the cloud first (--transform: transform.txt of coregister)",
                optional=True,
                fileFilter=TRANSFORM_FILTER,
            )
        )
        self.addParameter(
            QgsProcessingParameterFile(
                self.FIELD,
                "Field records CSV: also evaluate the trees against them (--field)",
                optional=True,
                fileFilter=CSV_FILTER,
            )
        )
        self.addParameter(
            QgsProcessingParameterBoolean(
                self.CYLINDERS,
                "Cylinder models and leaf-wood separation (off: --no-cylinders; faster, no volume)",
                defaultValue=True,
            )
        )
        self.addParameter(
            QgsProcessingParameterEnum(
                self.SINGLE_TREE,
                "The cloud is one tree (--single-tree)",
                options=list(SINGLE_TREE_OPTIONS),
                defaultValue=0,
            )
        )
        self.addParameter(
            QgsProcessingParameterBoolean(self.REPORT, "HTML report (off: --no-report)", defaultValue=True)
        )
        self._crs_parameter("layers.gpkg is in it")
        self._units_parameters("of the input coordinates")
        self._cli_parameter()
        self.addOutput(QgsProcessingOutputFile(self.TREES, "trees.csv"))
        self.addOutput(QgsProcessingOutputMultipleLayers(self.LAYERS, "Layers of layers.gpkg"))
        self._status_outputs()

    def job(self, parameters, context):
        single = (
            SINGLE_TREE_OPTIONS[self.parameterAsEnum(parameters, self.SINGLE_TREE, context)]
            if parameters.get(self.SINGLE_TREE) not in (None, "")
            else None
        )
        return adapter.TreesJob(
            cloud=self._file(parameters, self.CLOUD, context),
            out_dir=self.parameterAsString(parameters, self.OUTPUT, context),
            transform=self._file(parameters, self.TRANSFORM, context),
            field=self._file(parameters, self.FIELD, context),
            cylinders=self.parameterAsBool(parameters, self.CYLINDERS, context)
            if parameters.get(self.CYLINDERS) is not None
            else True,
            single_tree=None if single in (None, SINGLE_TREE_OPTIONS[0]) else single,
            report=self.parameterAsBool(parameters, self.REPORT, context)
            if parameters.get(self.REPORT) is not None
            else True,
            crs=self._crs_text(parameters, context),
            units=self._units(parameters, context),
            params_file=self._file(parameters, self.PARAMS, context),
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        job = self.job(parameters, context)
        run = self.run_service_job(job, parameters, context, feedback)
        out = Path(job.out_dir)
        trees = out / "trees.csv"
        return {
            self.OUTPUT: str(out),
            **self.status(run),
            self.TREES: str(trees) if trees.is_file() else "",
            self.LAYERS: list(
                _load_gpkg_layers(out, Path(str(job.cloud)).stem, context, self.LAYERS, feedback).values()
            ),
        }


class EvaluateAlgorithm(_JobAlgorithm):
    TREES = "TREES"
    FIELD = "FIELD"
    RUN_NAME = "RUN_NAME"
    ALSO = "ALSO"
    BY = "BY"
    MAX_DISTANCE = "MAX_DISTANCE"
    EVALUATION = "EVALUATION"
    NAME = "evaluate"
    DISPLAY_NAME = "Evaluate trees against field records"
    GROUP, GROUP_ID = "Trees", "trees"
    HELP = (
        "Compares the trees.csv of 'Measure trees' with field records (tree_id, x, y and any of dbh_m/dbh_cm, height_m, ...): "
        "R2, RMSE and rRMSE per parameter, as a 'forestreg evaluate' job of the forestreg service. Writes evaluation.csv, "
        "evaluation.json, figures and report.html into the output folder. Other runs to show side by side: "
        "[NAME=]TREES entries separated by ';'."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(self.TREES, "trees.csv of Measure trees", fileFilter=CSV_FILTER))
        self.addParameter(QgsProcessingParameterFile(self.FIELD, "Field records CSV", fileFilter=CSV_FILTER))
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterString(
                self.RUN_NAME, "Name of the first run (--name; empty: its folder name)", optional=True
            )
        )
        self.addParameter(
            QgsProcessingParameterString(
                self.ALSO, "Other runs side by side (--also; [NAME=]TREES entries separated by ';')", optional=True
            )
        )
        self.addParameter(
            QgsProcessingParameterEnum(
                self.BY, "Match trees by (--by)", options=list(adapter.EVALUATE_BY), defaultValue=0
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                self.MAX_DISTANCE,
                "Largest distance of a position match, m (--max-distance)",
                type=QgsProcessingParameterNumber.Double,
                defaultValue=1.0,
                minValue=0.0,
            )
        )
        self._cli_parameter()
        self.addOutput(QgsProcessingOutputFile(self.EVALUATION, "evaluation.json"))
        self._status_outputs()

    def job(self, parameters, context):
        also = [a.strip() for a in (self._string(parameters, self.ALSO, context) or "").split(";") if a.strip()]
        by = (
            adapter.EVALUATE_BY[self.parameterAsEnum(parameters, self.BY, context)]
            if parameters.get(self.BY) not in (None, "")
            else "position"
        )
        distance = self._optional_number(parameters, self.MAX_DISTANCE, context)
        return adapter.EvaluateJob(
            trees=self._file(parameters, self.TREES, context),
            field=self._file(parameters, self.FIELD, context),
            out_dir=self.parameterAsString(parameters, self.OUTPUT, context),
            name=self._string(parameters, self.RUN_NAME, context),
            also=also,
            by=by,
            max_distance_m=1.0 if distance is None else distance,
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        job = self.job(parameters, context)
        run = self.run_service_job(job, parameters, context, feedback)
        evaluation = Path(job.out_dir) / "evaluation.json"
        return {
            self.OUTPUT: str(job.out_dir),
            **self.status(run),
            self.EVALUATION: str(evaluation) if evaluation.is_file() else "",
        }


class ChangeAlgorithm(_JobAlgorithm):
    BEFORE = "BEFORE"
    AFTER = "AFTER"
    REPORT = "REPORT"
    UNITS_BEFORE = "UNITS_BEFORE"
    UNITS_AFTER = "UNITS_AFTER"
    CHANGES = "CHANGES"
    RESULT = "RESULT"
    NAME = "change"
    DISPLAY_NAME = "Re-survey change (persisting, removed, new trees)"
    GROUP, GROUP_ID = "Trees", "trees"
    HELP = (
        "Compares two surveys of one plot years apart: registers AFTER onto BEFORE from the persisting stems, then "
        "persisting / removed / new trees with DBH and height growth, as a 'forestreg change' job of the forestreg "
        "service. Each survey is a merged ground-based cloud, a saved plot project (.json) or the trees.csv of "
        "'Measure trees'. Writes result.json, tree_changes.csv, layers.gpkg and report.html into the output folder "
        "and loads the layers of layers.gpkg (tree changes coloured by status, outline; styled)."
    )

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(
            QgsProcessingParameterFile(
                self.BEFORE, "Earlier survey (cloud, project .json or trees.csv)", fileFilter=SURVEY_FILTER
            )
        )
        self.addParameter(
            QgsProcessingParameterFile(
                self.AFTER, "Later survey (cloud, project .json or trees.csv)", fileFilter=SURVEY_FILTER
            )
        )
        self.addParameter(QgsProcessingParameterFolderDestination(self.OUTPUT, "Output folder"))
        self.addParameter(
            QgsProcessingParameterBoolean(self.REPORT, "HTML report (off: --no-report)", defaultValue=True)
        )
        self._crs_parameter("result.json and layers.gpkg are in BEFORE's frame and take its CRS")
        self._units_parameters("of both surveys' coordinates")
        for name, role in ((self.UNITS_BEFORE, "earlier"), (self.UNITS_AFTER, "later")):
            units = QgsProcessingParameterEnum(
                name,
                f"Units of the {role} survey when the two differ (--units-{'before' if role == 'earlier' else 'after'})",
                options=["as Units", *UNITS],
                defaultValue=0,
            )
            units.setFlags(units.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
            self.addParameter(units)
        self._cli_parameter()
        self.addOutput(QgsProcessingOutputFile(self.CHANGES, "tree_changes.csv"))
        self.addOutput(QgsProcessingOutputFile(self.RESULT, "result.json"))
        self.addOutput(QgsProcessingOutputMultipleLayers(self.LAYERS, "Layers of layers.gpkg"))
        self._status_outputs()

    def job(self, parameters, context):
        return adapter.ChangeJob(
            before=self._file(parameters, self.BEFORE, context),
            after=self._file(parameters, self.AFTER, context),
            out_dir=self.parameterAsString(parameters, self.OUTPUT, context),
            report=self.parameterAsBool(parameters, self.REPORT, context)
            if parameters.get(self.REPORT) is not None
            else True,
            crs=self._crs_text(parameters, context),
            units=self._units(parameters, context),
            units_before=self._units(parameters, context, self.UNITS_BEFORE, first=("as Units",)),
            units_after=self._units(parameters, context, self.UNITS_AFTER, first=("as Units",)),
            params_file=self._file(parameters, self.PARAMS, context),
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        job = self.job(parameters, context)
        run = self.run_service_job(job, parameters, context, feedback)
        out = Path(job.out_dir)
        changes = out / "tree_changes.csv"
        return {
            self.OUTPUT: str(out),
            **self.status(run),
            self.CHANGES: str(changes) if changes.is_file() else "",
            self.RESULT: str(out / "result.json"),
            self.LAYERS: list(
                _load_gpkg_layers(
                    out,
                    f"{Path(str(job.after)).stem} since {Path(str(job.before)).stem}",
                    context,
                    self.LAYERS,
                    feedback,
                ).values()
            ),
        }


#: the provider's algorithms, in the order of the toolbox
ALGORITHMS = (
    RegisterPairAlgorithm,
    RegisterPlotAlgorithm,
    CoregisterAlgorithm,
    FuseAlgorithm,
    TreesAlgorithm,
    EvaluateAlgorithm,
    ChangeAlgorithm,
)


class ForestregProvider(QgsProcessingProvider):
    def id(self):
        return PROVIDER_ID

    def name(self):
        return "forestreg"

    def longName(self):  # noqa: N802
        return "forestreg: marker-free registration of forest laser scans"

    def loadAlgorithms(self):  # noqa: N802
        for algorithm in ALGORITHMS:
            self.addAlgorithm(algorithm())
