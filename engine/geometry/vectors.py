"""Small 3-vector helpers shared by the simulator's meshes and the cylinder models (pure numpy,
no frame of their own: results are in the frame of the inputs)."""

from __future__ import annotations

import math

import numpy as np


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product ``a x b`` of two 3-vectors (faster than ``np.cross`` for single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def perpendicular_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``u, v`` completing the unit vector ``axis`` to a right-handed
    orthonormal frame (``u`` perpendicular to ``axis`` and to x, or to y when ``axis`` is near x;
    ``v = axis x u``)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = cross3(axis, helper)
    u /= math.sqrt(float(u @ u))
    return u, cross3(axis, u)
