"""Small helpers for 4x4 rigid transforms (homogeneous column vectors, metres, degrees out)."""

from __future__ import annotations

import numpy as np


def apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 matrix to (N, 3) points: ``matrix @ [p, 1]``."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle of a 3x3 rotation matrix, degrees in [0, 180]."""
    c = (np.trace(rotation[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """3x3 rotation of the rotation vector ``omega`` (axis times angle, radians), Rodrigues."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = np.asarray(omega, dtype=float) / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def rigid_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and translation error (m) of a 4x4 estimate against the truth:
    the angle of ``R_est^T R_true`` and ``|t_est - t_true|``."""
    rot = rotation_angle_deg(estimate[:3, :3].T @ truth[:3, :3])
    return rot, float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


def matrix_from_yaw(yaw_deg: float, translation: np.ndarray | None = None) -> np.ndarray:
    """4x4 rotation about +z by ``yaw_deg`` (counter-clockwise), then a translation."""
    a = np.radians(yaw_deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    if translation is not None:
        m[:3, 3] = translation
    return m


def fit_rigid(moving: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (Kabsch/Umeyama, no scale) with ``reference ~ T @ moving``
    from (N, 3) corresponding points, N >= 3 and not collinear."""
    mc, rc = moving.mean(axis=0), reference.mean(axis=0)
    h = (moving - mc).T @ (reference - rc)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = rc - r @ mc
    return m


def format_matrix(matrix: np.ndarray) -> str:
    """The 4x4 as four lines of numbers (CloudCompare / RiSCAN ``.txt`` layout)."""
    return "\n".join(" ".join(f"{v:.10f}" for v in row) for row in np.asarray(matrix)) + "\n"


def check_rigid(matrix, what: str = "matrix", *, atol: float = 1e-5) -> np.ndarray:
    """Return ``matrix`` as a float 4x4 if it is a finite proper rigid transform (orthonormal
    rotation with determinant +1, no scale, no shear, last row 0 0 0 1); otherwise raise
    :class:`~forestreg.engine.core.errors.TransformError` saying what is wrong with it.

    The one checker of every 4x4 the product reads or returns (files, project links, results).
    """
    from .errors import TransformError

    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TransformError(f"{what}: not a 4x4 matrix of numbers") from exc
    if m.shape != (4, 4):
        raise TransformError(f"{what}: not a 4x4 matrix (shape {'x'.join(map(str, m.shape)) or 'scalar'})")
    if not np.isfinite(m).all():
        raise TransformError(f"{what}: the matrix holds NaN or infinite values")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise TransformError(f"{what}: last row is not 0 0 0 1 (not a rigid transform)")
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=atol):
        scale = np.linalg.norm(r, axis=0)
        raise TransformError(
            f"{what}: not a rigid transform (rotation not orthonormal: column lengths "
            f"{', '.join(f'{s:.4g}' for s in scale)}; scaled or sheared)"
        )
    if np.linalg.det(r) < 0:
        raise TransformError(f"{what}: a reflection (determinant -1), not a rotation")
    return m


def read_matrix(path, what: str = "transform") -> np.ndarray:
    """A rigid 4x4 from a text file (16 numbers, row by row: ``transform.txt``) or from a
    ``result.json`` (its ``matrix``), as written (in the files' units), checked by
    :func:`check_rigid`. Raises
    :class:`~forestreg.engine.core.errors.TransformError` with one line."""
    import json
    from pathlib import Path

    from .errors import TransformError

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise TransformError(f"the {what} {p} does not exist") from exc
    except IsADirectoryError as exc:
        raise TransformError(f"the {what} {p} is a folder; give its transform.txt") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise TransformError(f"cannot read the {what} {p}: {getattr(exc, 'strerror', None) or exc}") from exc
    if text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise TransformError(f"{p}: damaged JSON ({exc.msg}, line {exc.lineno})") from exc
        m = data.get("matrix") if isinstance(data, dict) else None
        if m is None:
            raise TransformError(f"{p}: the result holds no matrix (the registration failed)")
        return check_rigid(m, str(p))
    try:
        values = np.asarray(text.replace(",", " ").split(), dtype=np.float64)
    except ValueError as exc:
        raise TransformError(f"{p}: not a 4x4 matrix (non-numeric values)") from exc
    if values.size != 16:
        raise TransformError(f"{p}: not a 4x4 matrix ({values.size} numbers, expected 16)")
    return check_rigid(values.reshape(4, 4), str(p))


def to_file_units(matrix: np.ndarray, unit_scale: float) -> np.ndarray:
    """A rigid 4x4 in metres re-expressed for coordinates in file units (``unit_scale`` metres
    per unit): the rotation is unchanged, the translation divided by ``unit_scale``."""
    m = np.array(matrix, dtype=np.float64)
    m[:3, 3] /= unit_scale
    return m


def to_metres(matrix: np.ndarray, unit_scale: float) -> np.ndarray:
    """Inverse of :func:`to_file_units`: a rigid 4x4 for file-unit coordinates in metres."""
    m = np.array(matrix, dtype=np.float64)
    m[:3, 3] *= unit_scale
    return m


def withhold_unless_rigid(summary: dict) -> dict:
    """The last check before a result dict (``status``, ``reason``, ``matrix``) is called "ok": its
    matrix must pass :func:`check_rigid`. Otherwise a copy with ``status`` "failed", the reason and
    ``matrix`` None: never a NaN or scaled "ok"."""
    from .errors import TransformError

    if summary.get("status") != "ok":
        return summary
    try:
        check_rigid(summary.get("matrix"), "the result")
    except TransformError as exc:
        summary = dict(summary)
        summary["status"] = "failed"
        summary["reason"] = f"{exc}; withheld"
        summary["matrix"] = None
    return summary
