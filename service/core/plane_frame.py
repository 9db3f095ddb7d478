"""Frames of reference tied to the net plane: the rotation that faces it, and its axes.

The estimator, the damage detector and the damage renderer all need the same two: a virtual
camera looking straight at the net (to rectify the lattice), and the plane's horizontal and
vertical (along which hole sizes are measured). One definition keeps what is rendered and what
is measured in the same axes.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


def rotation_to_z(direction: npt.ArrayLike) -> F64:
    """The smallest rotation taking the unit vector `direction` onto +z."""
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    # v x z, written out: np.cross costs more than the rest of this function (it runs on
    # every rectified pass).
    axis = np.array([v[1], -v[0], 0.0])
    sin = float(np.linalg.norm(axis))
    cos = float(v[2])
    if sin < 1e-12:
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / sin
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.asarray(np.eye(3) + sin * kx + (1 - cos) * (kx @ kx), dtype=np.float64)


def plane_axes(normal: npt.ArrayLike) -> tuple[F64, F64]:
    """The net plane's horizontal and vertical: the camera's x (right) and y (down) laid onto
    the plane, y made perpendicular to x within it. Either sign of the normal gives the same
    axes."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    h = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(h) < 1e-6:  # looking along the plane's horizontal: cannot happen in view
        h = np.array([0.0, 0.0, 1.0]) - n[2] * n
    h = h / np.linalg.norm(h)
    v = np.cross(n, h)
    if v[1] < 0:
        v = -v
    return h, v
