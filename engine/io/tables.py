"""Tables the product writes beside its results: VOPs of a pair registration and canopy keypoints
of a co-registration, always in the input file's own coordinates and units."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.atomic import write_text_atomic
from ..core.transform import apply

VOP_COLUMNS = ("id", "x", "y", "z", "radius_m", "support_points", "matched_with")
KEYPOINT_COLUMNS = ("id", "x", "y", "z", "peak_z", "cluster_size", "matched_with")


def write_vops_csv(
    path: str | Path,
    xy: np.ndarray,
    z: np.ndarray,
    to_file: np.ndarray,
    radius: np.ndarray,
    support: np.ndarray,
    matched_with: Sequence[int],
    *,
    unit_scale: float = 1.0,
) -> Path:
    """VOPs (levelled-frame ``xy``, ``z``, metres) as a CSV in file coordinates.

    ``to_file`` maps the levelled frame to the file frame in metres; ``unit_scale`` (metres per
    file unit) turns the coordinates back into the file's own unit. ``radius_m`` stays in metres.
    """
    pts = apply(to_file, np.column_stack([xy, z])) / unit_scale if len(xy) else np.zeros((0, 3))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(VOP_COLUMNS)
    for k in range(len(xy)):
        w.writerow([k, f"{pts[k, 0]:.4f}", f"{pts[k, 1]:.4f}", f"{pts[k, 2]:.4f}", f"{radius[k]:.3f}",
                    int(support[k]), "" if matched_with[k] < 0 else int(matched_with[k])])
    write_text_atomic(path, buf.getvalue())
    return Path(path)


def write_keypoints_csv(path: str | Path, keypoints, local_to_file: np.ndarray, matched_with: np.ndarray, *, unit_scale: float = 1.0) -> Path:
    """Canopy keypoints in file coordinates (file units): id, x, y, z (on the DEM), peak_z,
    cluster_size, matched_with (-1: unmatched)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(KEYPOINT_COLUMNS)
    xyz = apply(local_to_file, keypoints.xyz) / unit_scale
    peak = (keypoints.peak_z + local_to_file[2, 3]) / unit_scale
    for i, (p, z, n, m) in enumerate(zip(xyz, peak, keypoints.cluster_sizes, matched_with)):
        w.writerow([i, f"{p[0]:.3f}", f"{p[1]:.3f}", f"{p[2]:.3f}", f"{z:.3f}", int(n), int(m)])
    write_text_atomic(path, buf.getvalue())
    return Path(path)


def pair_vop_tables(result, reference, moving):
    """The VOP tables of a pair result: ``[(scan, to_file, vops, matched_with, file name), ...]``
    (empty when no attempt was chosen). ``to_file`` maps each scan's levelled frame (metres) into
    its file coordinates (metres)."""
    det = result.details
    if det is None or det.chosen is None:
        return []
    att = det.chosen
    ref_match = np.full(len(att.reference_vops), -1)
    mov_match = np.full(len(att.moving_vops), -1)
    if att.match is not None and len(att.match.matched_pairs):
        ref_match[att.match.matched_pairs[:, 0]] = att.match.matched_pairs[:, 1]
        mov_match[att.match.matched_pairs[:, 1]] = att.match.matched_pairs[:, 0]
    tables = []
    for scan, prep, vops, matched, name in (
        (reference, det.reference, att.reference_vops, ref_match, "reference_vops.csv"),
        (moving, det.moving, att.moving_vops, mov_match, "moving_vops.csv"),
    ):
        to_file = scan.local_to_file_matrix() @ np.linalg.inv(prep.local_to_lsf)
        tables.append((scan, to_file, vops, matched, name))
    return tables
