"""Small rotation geometry used by every solver: cross-product matrices, rotations about the axes, SO(3) exp/log
and its left Jacobian, quaternions.

Rotation vectors are axis * angle in radians; ``Exp(w)`` is the rotation matrix (Rodrigues). Quaternions are
``xyzw`` (scalar last, as SciPy and glTF). Conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import math

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1] = -v[..., 2]
    S[..., 0, 2] = v[..., 1]
    S[..., 1, 0] = v[..., 2]
    S[..., 1, 2] = -v[..., 0]
    S[..., 2, 0] = -v[..., 1]
    S[..., 2, 1] = v[..., 0]
    return S


def rot_x(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about x (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about y (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about z (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) -> rotation matrices (..., 3, 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    if w.shape == (3,):  # one vector (the solvers' inner loops): the same arithmetic without the array machinery
        x, y, z = w
        th2 = x * x + y * y + z * z
        small = th2 < 1e-16
        th = np.sqrt(th2)
        a = 1.0 - th2 / 6.0 if small else np.sin(th) / th
        b = 0.5 - th2 / 24.0 if small else (1.0 - np.cos(th)) / th2
        K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
        return np.eye(3) + a * K + b * (K @ K)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-16
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / np.where(small, 1.0, th))
        b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    K = skew(w)
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) (..., 3, 3): ``Exp(w + dw) = Exp(J_l(w) dw) Exp(w)`` to first order."""
    w = np.asarray(w, dtype=float)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-10
    safe = np.where(small, 1.0, th)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / safe**2)
        b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th - np.sin(th)) / safe**3)
    K = skew(w)
    return np.eye(3) + a * K + b * (K @ K)


def exp_and_left_jacobian_so3(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) rotation vectors -> their rotation matrices exp([phi]x) (Rodrigues) and left Jacobians J_l(phi):
    exp(phi + d) = exp(J_l(phi) d) exp(phi) to first order; (n, 3, 3) each, from one set of trigonometric terms
    (the adjustment unpacks its parameters at every evaluation)."""
    th = np.sqrt(np.einsum("ij,ij->i", phi, phi))
    K = skew(phi)
    KK = K @ K
    small = th < 1e-6
    t = np.where(small, 1.0, th)
    s, c = np.sin(t), np.cos(t)
    a = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - c) / t ** 2)
    b = np.where(small, 1.0 / 6.0 - th ** 2 / 120.0, (t - s) / t ** 3)
    sinc = np.where(small, 1.0 - th ** 2 / 6.0, s / t)
    eye = np.eye(3)[None]
    return eye + sinc[:, None, None] * K + a[:, None, None] * KK, eye + a[:, None, None] * K + b[:, None, None] * KK


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> its rotation vector (3,), angle in [0, pi] (the inverse of :func:`exp_so3`);
    accurate near 0 (the skew part) and near pi (the axis from the symmetric part)."""
    R = np.asarray(R, dtype=float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    th = float(np.arctan2(0.5 * np.linalg.norm(w), c))  # sin and cos: accurate at every angle (arccos is not near pi)
    if th < 1e-6:
        return 0.5 * w * (1.0 + th * th / 6.0)
    if np.pi - th < 1e-3:  # the axis from the symmetric part, (1 - cos) a a^T (the skew part vanishes at pi)
        B = 0.5 * (R + R.T) - c * np.eye(3)
        k = int(np.argmax(np.diag(B)))
        v = B[:, k] / np.linalg.norm(B[:, k])
        return th * v * (1.0 if float(v @ w) >= 0.0 else -1.0)
    return th / (2.0 * np.sin(th)) * w


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (deg) of the rotation ``R = Ra Rb^T`` between ``Ra`` and ``Rb`` (3, 3), from its cosine
    ``(tr R - 1) / 2`` and its sine ``|vee(R - R^T)| / 2`` by ``atan2``: exact to rounding at every angle (the
    ``arccos`` of the cosine alone resolves nothing under about 1e-6 deg, as ``arccos(1 - eps)``)."""
    R = np.asarray(Ra)[:3, :3] @ np.asarray(Rb)[:3, :3].T
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.rad2deg(np.arctan2(s, 0.5 * (np.trace(R) - 1.0))))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking the direction ``a`` (3,) to the direction ``b`` (3,) (any lengths)."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis normal to a
        n = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        n /= np.linalg.norm(n)
        return 2.0 * np.outer(n, n) - np.eye(3)
    K = skew(v)
    return np.eye(3) + K + K @ K / (1.0 + c)


def orthonormal(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``R`` (3, 3) (SVD, determinant +1): removes the drift of composed small rotations
    and the rounding of an estimate stored in single precision, and gives the rotation a noisy matrix known up to
    scale stands for (``K_j^-1 H K_i`` of a homography between two photos of a rotating camera)."""
    U, _, Vt = np.linalg.svd(R)
    if np.linalg.det(U @ Vt) < 0.0:  # a reflection: the nearest rotation turns the least singular direction
        U[:, 2] = -U[:, 2]
    return U @ Vt


def quaternion_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,), ``xyzw`` (scalar last), with SciPy's choice of sign.

    From the largest of the trace and the diagonal (Markley 2008, as ``scipy.spatial.transform.Rotation``), so
    no division by a small number at any angle."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"{R.shape=} but expected (3, 3)")
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], tr]))
    q = np.empty(4)
    if i == 3:
        q[:] = (R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1.0 + tr)
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    return q / np.linalg.norm(q)


def boxes_overlap(c1: np.ndarray, R1: np.ndarray, h1: np.ndarray, c2: np.ndarray, R2: np.ndarray, h2: np.ndarray,
                  margin: float = 0.0) -> bool:
    """Whether two oriented boxes overlap (the separating-axis test): centres ``c`` (3,), rotations ``R`` (3, 3)
    box -> world, half extents ``h`` (3,), same units. ``margin`` > 0 counts boxes closer than it as overlapping;
    ``margin`` < 0 only boxes that interpenetrate by more than ``-margin`` along every axis."""
    return boxes_depth(c1, R1, h1, c2, R2, h2) >= -margin


def boxes_depth(c1: np.ndarray, R1: np.ndarray, h1: np.ndarray, c2: np.ndarray, R2: np.ndarray,
                h2: np.ndarray) -> float:
    """How deep two oriented boxes (as :func:`boxes_overlap`) interpenetrate, in their units: the least overlap of
    their projections over the separating-axis test's 15 axes (> 0: they share space, at least this deep along every
    axis; < 0: they are apart, by minus it along the axis that separates them most)."""
    axes = [R1[:, i] for i in range(3)] + [R2[:, i] for i in range(3)]
    axes += [np.cross(R1[:, i], R2[:, j]) for i in range(3) for j in range(3)]
    d = c2 - c1
    depth = math.inf
    for a in axes:
        n = np.linalg.norm(a)
        if n < 1e-9:
            continue
        a = a / n
        r1 = np.sum(np.abs(R1.T @ a) * h1)
        r2 = np.sum(np.abs(R2.T @ a) * h2)
        depth = min(depth, float(r1 + r2 - abs(d @ a)))
    return depth
