"""Closed-form fits the georegistration solvers start from: rotations, similarities, ray intersections."""

from __future__ import annotations

import numpy as np

from ..core.geometry import orthonormal  # re-exported: the georef solvers take it from here with the fits

__all__ = ["rotation_kabsch", "umeyama", "triangulate_rays", "orthonormal", "point_line_distance"]


def rotation_kabsch(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotation R (3, 3) minimising sum w |R a_k - b_k|^2 for (n, 3) vectors a, b."""
    w = np.ones(len(a)) if w is None else w
    H = (a * w[:, None]).T @ b
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


def umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) with ``dst ~ s R src + t`` for (n, 3) points (weighted Umeyama 1991)."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    w = np.ones(len(src)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    xs, xd = src - ms, dst - md
    cov = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    var = float(w @ np.sum(xs * xs, axis=1))
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    t = md - s * R @ ms
    return s, R, t


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares intersection of rays (n, 3) centres, (n, 3) unit directions -> (point (3,), max angle deg)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, dirs):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    X = np.linalg.lstsq(A, b, rcond=None)[0]
    cosines = np.clip(dirs @ dirs.T, -1.0, 1.0)
    return X, float(np.degrees(np.arccos(cosines.min())))


def point_line_distance(X: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """Distance of point ``X`` (3,) from the line through ``c`` (3,) along the unit vector ``d`` (3,)."""
    v = X - c
    return float(np.linalg.norm(v - (v @ d) * d))
