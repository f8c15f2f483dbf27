"""Pinhole camera with Brown-Conrady distortion (k1, k2, k3, p1, p2) and skew.

Conventions (``docs/conventions.md``): camera axes x right, y down, z forward; pixel (0, 0) is the
**centre** of the top-left pixel (OpenCV's convention; COLMAP's differs by half a pixel); the intrinsic
matrix is ``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``. Distortion acts on normalised coordinates
exactly as OpenCV's ``projectPoints`` (coefficient order k1, k2, p1, p2, k3).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated, Sequence

import numpy as np

from .options import Range, check_options


@dataclass(frozen=True, kw_only=True)
class CameraIntrinsics:
    """Intrinsics of one photo: image size (px), focal (px), principal point (px), skew, distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size {self.width}x{self.height} must be positive")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths fx={self.fx}, fy={self.fy} must be positive")
        for name in ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "k3", "p1", "p2"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name}={getattr(self, name)} is not finite")

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int, dist: np.ndarray | None = None) -> "CameraIntrinsics":
        """From a (3, 3) K and OpenCV-ordered distortion (k1, k2, p1, p2[, k3])."""
        K = np.asarray(K, dtype=float)
        d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).reshape(-1)
        d = np.concatenate([d, np.zeros(max(0, 5 - d.size))])
        return cls(width=int(width), height=int(height), fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2],
                   skew=K[0, 1], k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV order: (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist_coeffs != 0.0))

    def without_distortion(self) -> "CameraIntrinsics":
        return replace(self, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0)

    def with_focal(self, fx: float) -> "CameraIntrinsics":
        """The same camera with focal ``fx`` (px) and ``fy`` in the same ratio (the focal the solver estimates)."""
        return replace(self, fx=float(fx), fy=float(fx) * self.fy / self.fx)

    def scaled(self, factor: float) -> "CameraIntrinsics":
        """The same camera for an image resized by ``factor`` (pixel centres kept consistent)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        return replace(self, width=w, height=h, fx=self.fx * factor, fy=self.fy * factor, skew=self.skew * factor,
                       cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5)

    # -- normalised coordinates ------------------------------------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised (n, 2) -> distorted normalised (n, 2)."""
        _, _, xd, yd = brown_distortion(xy[:, 0], xy[:, 1], self)
        return np.column_stack([xd, yd])

    def undistort(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted normalised (n, 2) -> undistorted normalised (n, 2), by Newton iterations."""
        xy = np.array(xy_d, dtype=float, copy=True)
        if not self.has_distortion:
            return xy
        # x and y held apart, each contiguous (a column of the (n, 2) array is strided: every operation on it
        # about twice as slow), with the same arithmetic as on the columns, so the same numbers to the bit
        xd0, yd0 = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
        x, y = xd0.copy(), yd0.copy()
        eps = 1e-7
        for _ in range(iterations):
            _, _, xd, yd = brown_distortion(x, y, self)
            fx, fy = xd - xd0, yd - yd0
            # numeric 2x2 Jacobian per point: central differences in x, then in y
            _, _, xp, yp = brown_distortion(x + eps, y, self)
            _, _, xm, ym = brown_distortion(x - eps, y, self)
            jxx, jxy = (xp - xm) / (2 * eps), (yp - ym) / (2 * eps)
            _, _, xp, yp = brown_distortion(x, y + eps, self)
            _, _, xm, ym = brown_distortion(x, y - eps, self)
            jyx, jyy = (xp - xm) / (2 * eps), (yp - ym) / (2 * eps)
            det = jxx * jyy - jyx * jxy
            x -= (jyy * fx - jyx * fy) / det
            y -= (-jxy * fx + jxx * fy) / det
            if np.maximum(np.max(np.abs(fx)), np.max(np.abs(fy))) < 1e-13:  # (a NaN anywhere: not converged)
                break
        xy[:, 0], xy[:, 1] = x, y
        return xy

    def pixels_from_normalized(self, xy_d: np.ndarray) -> np.ndarray:
        u, v = self.pixel_coords(xy_d[:, 0], xy_d[:, 1])
        return np.column_stack([u, v])

    def pixel_coords(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates x (n,), y (n,) -> pixel coordinates u (n,), v (n,) (for inner loops
        that keep the two apart)."""
        return self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy

    def normalized_from_pixels(self, uv: np.ndarray) -> np.ndarray:
        y = (uv[:, 1] - self.cy) / self.fy
        x = (uv[:, 0] - self.cx - self.skew * y) / self.fx
        return np.column_stack([x, y])

    # -- projection ------------------------------------------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Points in the camera frame (n, 3) metres -> pixels (n, 2). Points behind the camera give NaN."""
        P = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        return self.pixels_from_normalized(self.distort(xy))

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) -> unit ray directions in the camera frame (n, 3)."""
        xy = self.undistort(self.normalized_from_pixels(np.asarray(uv, dtype=float).reshape(-1, 2)))
        d = np.column_stack([xy, np.ones(len(xy))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask (n,) of pixels inside the image (pixel centres span [-0.5, w - 0.5])."""
        u, v = uv[:, 0], uv[:, 1]
        return ((u >= -0.5 + margin) & (u <= self.width - 0.5 - margin)
                & (v >= -0.5 + margin) & (v <= self.height - 0.5 - margin))

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("width", "height", "fx", "fy", "cx", "cy", "skew",
                                              "k1", "k2", "k3", "p1", "p2")}

    @classmethod
    def from_dict(cls, d: dict) -> "CameraIntrinsics":
        return cls(**d)

    def moved(self, params: Sequence[str], delta: np.ndarray) -> "CameraIntrinsics":
        """These intrinsics with the fields ``params`` moved by ``delta`` (len(params),): ``f`` moves ``fx`` and
        ``fy`` together (a single-focal model's), the others are fields (pixels for fx, fy, cx, cy)."""
        d = self.to_dict()
        for name, x in zip(params, np.asarray(delta, dtype=float).reshape(-1)):
            for k in (("fx", "fy") if name == "f" else (name,)):
                d[k] += float(x)
        return CameraIntrinsics.from_dict(d)


@dataclass(frozen=True, kw_only=True)
class LensPrior:
    """Weak priors on a lens an adjustment estimates, 1-sigma each: the focal relative to its prior value, the
    principal point's offset from its prior as a fraction of the focal, radial ``k1`` and ``k2`` (about 0). They
    keep the parameters the data say little about where they were; where the data decide, they do."""

    focal_rel: Annotated[float, Range(gt=0.0)]
    principal_point_rel: Annotated[float, Range(gt=0.0)]
    k1: Annotated[float, Range(gt=0.0)]
    k2: Annotated[float, Range(gt=0.0)]

    def __post_init__(self) -> None:
        check_options(self, "lens prior")


def project_world(intrinsics: CameraIntrinsics, cam_from_world: np.ndarray,
                  points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (n, 3) -> (pixels (n, 2), depth along the optical axis (n,) metres).

    ``cam_from_world``: (4, 4) matrix, ``p_cam = R @ p_world + t``.
    """
    M = np.asarray(cam_from_world, dtype=float)
    P = np.asarray(points_world, dtype=float).reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
    return intrinsics.project(P), P[:, 2]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """``cam_from_world`` (4, 4) for a camera at ``eye`` looking at ``target`` with world ``up`` above.

    Camera axes: x right, y down, z forward (towards ``target``).
    """
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])  # rows: camera axes in world
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M


def brown_distortion(x: np.ndarray, y: np.ndarray, intr: CameraIntrinsics):
    """Brown-Conrady distortion of normalised (x, y) (OpenCV's model): ``(r^2, radial factor, xd, yd)``."""
    k1, k2, k3, p1, p2 = intr.k1, intr.k2, intr.k3, intr.p1, intr.p2
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return r2, radial, xd, yd


def distort_with_derivs(x: np.ndarray, y: np.ndarray, intr: CameraIntrinsics):
    """Brown-Conrady distortion of normalised (x, y): r^2, the distorted (xd, yd) and d(xd, yd) / d(x, y)."""
    k1, k2, k3, p1, p2 = intr.k1, intr.k2, intr.k3, intr.p1, intr.p2
    r2, radial, xd, yd = brown_distortion(x, y, intr)
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    dxd_dx = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    return r2, xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy
