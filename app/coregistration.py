"""Co-registration: a ground-based cloud (merged TLS, backpack, handheld) onto a UAV cloud by
canopy keypoints (System B).

:func:`coregister_clouds` reads both clouds (or takes them as scans), co-registers
(:func:`forestreg.engine.coreg.coregister.coregister`), applies the last rigid check, converts the
matrix into the files' unit and writes the output folder (``result.json``, ``transform.txt``, the
keypoint tables, ``layers.gpkg``, the report) as one transaction. The outputs are in the UAV
cloud's frame and take its CRS (``result.json``'s ``crs`` says which frame each output is in when
the two files' CRSs differ, or one has none).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .common import (
    UNITS,
    RunOutcome,
    as_scan,
    check_units,
    given_crs,
    outcome_of,
    params_of,
    refuse_same_file,
    run_summary,
    scan_source,
    with_cancel,
)
from .saved import count_or_none, finite_or_none, mapping_or_empty

log = logging.getLogger("forestreg")


@dataclass(frozen=True, eq=False)
class CoregistrationOutcome(RunOutcome):
    """A co-registered (or failed) pair of clouds: ``result`` is the engine's
    :class:`~forestreg.engine.coreg.coregister.CoregistrationResult`; ``matrix`` maps the ground
    file coordinates onto the UAV file coordinates (files' unit); ``report`` the HTML report
    written (or None); ``ground`` / ``uav`` the clouds' frames (scans without points)."""

    method = "canopy keypoints + ICP"
    convention = "p_uav = matrix @ p_ground (files' coordinates)"
    report: Optional[Path] = None
    ground: Any = None
    uav: Any = None

    def line(self) -> str:
        """The one-line summary of the run."""
        return self.result.summary() if self.result is not None else f"{self.status}: {self.reason}"

    @property
    def figures(self) -> "CoregistrationSummary":
        """The ``result.json`` summary, typed."""
        return CoregistrationSummary.of(self.to_dict())


@dataclass(frozen=True)
class CoregistrationSummary:
    """A co-registration's ``result.json`` (the outcome's summary, or the file read back), typed:
    ``status``, ``reason``, ``matrix`` (p_uav = matrix @ p_ground, files' unit; None when failed or
    not a rigid 4x4), the clouds' names and files, keypoints found in each cloud, matched
    keypoints (and their share of the ground-based ones, %), the canopy surface correlation and
    that of the best distinct alternative, the heading (degrees), the keypoint residuals after
    the registration (mean, RMS; m), the fine fit (ICP overlap and std, m), the engine's standard
    errors by name and the engine time (s)."""

    status: str
    reason: str = ""
    matrix: Optional[np.ndarray] = None
    ground: str = ""
    uav: str = ""
    ground_file: str = ""
    uav_file: str = ""
    keypoints_ground: Optional[int] = None
    keypoints_uav: Optional[int] = None
    matched: Optional[int] = None
    matching_percentage: Optional[float] = None
    surface_correlation: Optional[float] = None
    alternative_correlation: Optional[float] = None
    heading_deg: Optional[float] = None
    residual_mean_m: Optional[float] = None
    residual_rms_m: Optional[float] = None
    icp_fitness: Optional[float] = None
    icp_std_m: Optional[float] = None
    standard_errors: dict = field(default_factory=dict)
    total_s: Optional[float] = None

    @classmethod
    def of(cls, d) -> "CoregistrationSummary":
        """The summary of a ``result.json`` dict (any version; the last rigid check applied)."""
        from ..engine.core.outcome import OutcomeRecord

        rec = OutcomeRecord.from_dict(d)
        data = rec.data
        kp = mapping_or_empty(data.get("keypoints"))
        res = mapping_or_empty(data.get("residuals_after_icp_m")) or mapping_or_empty(data.get("residuals_m"))
        icp = mapping_or_empty(data.get("icp"))
        errors = mapping_or_empty(data.get("standard_errors")) or mapping_or_empty(data.get("uncertainty"))
        return cls(
            rec.status,
            rec.reason,
            rec.matrix,
            str(data.get("ground") or ""),
            str(data.get("uav") or ""),
            str(data.get("ground_file") or ""),
            str(data.get("uav_file") or ""),
            count_or_none(kp.get("ground")),
            count_or_none(kp.get("uav")),
            count_or_none(data.get("matched")),
            matching_percentage=finite_or_none(data.get("matching_percentage")),
            surface_correlation=finite_or_none(data.get("surface_correlation")),
            alternative_correlation=finite_or_none(data.get("alternative_correlation")),
            heading_deg=finite_or_none(data.get("heading_deg")),
            residual_mean_m=finite_or_none(res.get("mean")),
            residual_rms_m=finite_or_none(res.get("rms")),
            icp_fitness=finite_or_none(icp.get("fitness")),
            icp_std_m=finite_or_none(icp.get("std_m")),
            standard_errors={str(k): float(v) for k, v in errors.items() if finite_or_none(v) is not None},
            total_s=finite_or_none(rec.timings.get("total_s")),
        )

    @property
    def ok(self) -> bool:
        return self.status == "ok" and self.matrix is not None

    @property
    def margin(self) -> Optional[float]:
        """The surface correlation's margin over the best alternative (None without both)."""
        if self.surface_correlation is None or self.alternative_correlation is None:
            return None
        return self.surface_correlation - self.alternative_correlation


def read_coregistration_folder(folder):
    """A ``forestreg coregister --out DIR`` folder
    (:class:`~forestreg.engine.io.results.CoregistrationOutput`) and its typed
    :class:`CoregistrationSummary`."""
    from ..engine.io.results import read_coregistration_dir

    out = read_coregistration_dir(folder)
    return out, CoregistrationSummary.of(out.result)


def default_params():
    """The co-registration parameters of the product (defaults)."""
    from ..engine.params import ProductParams

    return ProductParams().coregistration


def coregister_clouds(
    ground,
    uav,
    out: Optional[str | Path],
    params=None,
    *,
    units: str = "m",
    crs=None,
    progress=None,
    cancel=None,
) -> CoregistrationOutcome:
    """Co-register ``ground`` onto ``uav`` (each a file path or a
    :class:`~forestreg.engine.core.scan.Scan`); with ``out``, write that output folder as a
    transaction (``None``: nothing written). The outcome is checked the same way whichever door
    asked: a matrix that is not rigid is withheld. ``crs`` (e.g. "EPSG:32618"): the CRS of the UAV
    frame when its file declares none, or the one that wins over it."""
    from ..engine.core.atomic import check_output_folder
    from ..engine.coreg.coregister import coregister as coregister_scans
    from ..engine.io import read_scan
    from ..engine.report.samples import profile_sample

    given = given_crs(crs, units)
    if params is None:
        params = default_params()
    scale = UNITS[units]
    paths = [x for x in (ground, uav) if isinstance(x, (str, Path))]
    if len(paths) == 2:
        refuse_same_file(*paths, "GROUND and UAV are the same file: a cloud cannot be co-registered onto itself")
    if out is not None:
        out = check_output_folder(out, "coregister", inputs=paths)
    progress = with_cancel(progress, cancel)
    # the scans are read inside the co-registration, which lets each full cloud go once thinned;
    # kept here: each scan's frame and the points its figure draws
    kept: dict = {"read_s": 0.0}

    def reader(source, role: str):
        def load():
            t0 = time.perf_counter()
            if isinstance(source, (str, Path)):
                scan = read_scan(
                    source, unit_scale=scale, with_intensity=False
                )  # the co-registration uses x, y, z alone
                check_units(scan, units, str(source))
            else:
                scan = as_scan(source, role)
            kept["read_s"] += time.perf_counter() - t0
            kept[role] = scan.without_points()
            if out is not None:
                kept[role + "_profile"] = profile_sample(scan.points, role)
                if role == "ground":  # its outline from above, for layers.gpkg
                    from .layers import cloud_outline

                    kept["ground_outline"] = cloud_outline(scan.points[:, :2])
            return scan

        return load

    result = coregister_scans(reader(ground, "ground"), reader(uav, "uav"), params, progress=progress)
    inputs = {key: src for key, src in (("ground_file", ground), ("uav_file", uav)) if isinstance(src, (str, Path))}
    summary, ok = run_summary(
        result,
        {"read_s": kept["read_s"]},
        inputs,
        units,
        scale,
        facts={"distance_threshold_m": params.matching.distance_threshold_m},
    )
    frame = _frame_crs(kept, ground, uav, given)
    kept["crs"] = frame.crs
    summary["crs"] = frame.to_dict(
        frames={
            "transform.txt": f"maps {frame.label_of('ground')} onto {frame.label_of('uav')}",
            "keypoints_ground.csv": frame.label_of("ground"),
            "keypoints_uav.csv": frame.label_of("uav"),
            "layers.gpkg": f"the UAV frame ({frame.crs.label if frame.crs is not None else 'no CRS'})",
        }
    )
    report = None
    if out is not None:
        report = _write_coregistration_folder(out, result, summary, kept, scale)
    return outcome_of(
        summary,
        out=out,
        result=result,
        cls=CoregistrationOutcome,
        report=report,
        ground=kept["ground"],
        uav=kept["uav"],
    )


def _frame_crs(kept: dict, ground, uav, given):
    """The CRS of a co-registration's outputs: the UAV cloud's (or ``given``), and each cloud's."""
    from ..engine.io.crs import crs_of, frame_crs

    names = {
        role: (Path(src).name if isinstance(src, (str, Path)) else (getattr(kept.get(role), "name", "") or role))
        for role, src in (("ground", ground), ("uav", uav))
    }
    return frame_crs({"ground": crs_of(kept.get("ground")), "uav": crs_of(kept.get("uav"))}, "uav", given, names=names)


def coregister(ground, uav, params=None, progress=None, *, cancel=None):
    """Co-register ``ground`` (moving) onto ``uav`` (reference)
    (:func:`forestreg.engine.coreg.coregister.coregister`; returns its
    :class:`~forestreg.engine.coreg.coregister.CoregistrationResult`, ``p_uav = matrix @ p_ground``
    in file coordinates), each cloud checked as the ``coregister`` command checks it: a
    :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of finite x, y, z in metres, a point
    file's path (metres), or a function without arguments that reads one, its coordinates in
    metres (:func:`~forestreg.app.common.check_units`). ``params``: a
    :class:`~forestreg.engine.coreg.coregister.CoregistrationParams` (or a
    :class:`~forestreg.engine.params.ProductParams`). Bad input raises the product's errors."""
    from ..engine.coreg.coregister import CoregistrationParams
    from ..engine.coreg.coregister import coregister as coregister_scans

    params = params_of(params, CoregistrationParams, "coregistration")
    ground, uav = scan_source(ground, "ground"), scan_source(uav, "uav")
    from .common import rigid_or_withheld

    return rigid_or_withheld(coregister_scans(ground, uav, params, progress=with_cancel(progress, cancel)))


def _write_coregistration_folder(out: Path, result, summary: dict, kept: dict, scale: float) -> Optional[Path]:
    """The output folder of a co-registration, as one transaction
    (:func:`~forestreg.app.outputs.write_result_folder`): the keypoint tables, ``layers.gpkg`` and
    the report; returns the report's path (or None)."""
    from ..engine.io.tables import write_keypoints_csv
    from .layers import keypoint_layers, write_layers
    from .outputs import write_result_folder

    ok = summary["status"] == "ok"
    ground, uav = kept["ground"], kept["uav"]
    pairs = (
        result.matched_after_icp
        if result.matched_after_icp is not None
        else (result.match.pairs if result.match is not None else np.zeros((0, 2), dtype=int))
    )

    def write_files(tmp: Path) -> None:
        for scan, kp, column, other, name in (
            (ground, result.ground_keypoints, 0, 1, "keypoints_ground.csv"),
            (uav, result.uav_keypoints, 1, 0, "keypoints_uav.csv"),
        ):
            if kp is None:
                continue
            matched = np.full(len(kp), -1)
            if len(pairs):
                matched[pairs[:, column]] = pairs[:, other]
            write_keypoints_csv(tmp / name, kp, scan.local_to_file_matrix(), matched, unit_scale=scale)
        write_layers(
            tmp,
            keypoint_layers(result, ground, uav, ok=ok, unit_scale=scale, ground_outline=kept.get("ground_outline")),
            kept.get("crs"),
        )

    def draw(tmp: Path) -> None:
        from ..engine.report.coregistration_report import write_coregistration_report

        write_coregistration_report(result, tmp, kept["ground_profile"], kept["uav_profile"])

    return write_result_folder(
        out,
        "coregister",
        summary,
        write_files,
        draw=draw if result.ground_keypoints is not None else None,
        drawn_name="report.html",
    )
