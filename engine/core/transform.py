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
