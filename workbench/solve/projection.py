"""Camera projection of carriage points with exact (analytic) Jacobians.

Conventions: ``docs/conventions.md``. A point ``p`` in the carriage frame goes to the scene by
``X = R_wc p + t_wc`` (``world_from_carriage``), to the camera by ``cam_from_world``, and to pixels by
:class:`workbench.core.camera.CameraIntrinsics` (Brown-Conrady distortion exactly as OpenCV's
``projectPoints``, skew, pixel (0, 0) at the centre of the top-left pixel).

Pose parametrisation of the Jacobian: ``(omega, tau)`` with
``R_wc <- Exp(omega) R_wc`` (a rotation-vector increment in the **scene** frame, left-multiplied) and
``t_wc <- t_wc + tau``; the Jacobian is taken at ``omega = 0, tau = 0``. For a finite rotation-vector
offset ``Exp(delta) R0`` chain with :func:`workbench.core.geometry.left_jacobian_so3` (``d/d delta = J_pose_rot @ J_l(delta)``).

Intrinsic parameters (columns of ``J_intr``, in the order asked): ``"f"`` (fx = fy = f, moved together),
``"cx"``, ``"cy"``, ``"k1"``, ``"k2"``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..core.camera import CameraIntrinsics, distort_with_derivs
from ..core.geometry import skew

INTRINSIC_NAMES = ("f", "cx", "cy", "k1", "k2")


def project_world_points_with_jacobians(
    points_world: np.ndarray, cam_from_world: np.ndarray, intrinsics: CameraIntrinsics,
    intrinsic_params: Sequence[str] = ("f",),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scene points (n, 3) -> pixels (n, 2), d uv / d X_world (n, 2, 3), d uv / d intrinsics (n, 2, k)."""
    X = np.asarray(points_world, dtype=float).reshape(-1, 3)
    M = np.asarray(cam_from_world, dtype=float)
    Rc = M[:3, :3]
    P = X @ Rc.T + M[:3, 3]
    Z = P[:, 2]
    iz = 1.0 / Z
    x = P[:, 0] * iz
    y = P[:, 1] * iz
    r2, xd, yd, a, b, c, d = distort_with_derivs(x, y, intrinsics)
    fx, fy, s = intrinsics.fx, intrinsics.fy, intrinsics.skew
    uv = np.column_stack([fx * xd + s * yd + intrinsics.cx, fy * yd + intrinsics.cy])
    # d uv / d (xd, yd)
    # u = fx xd + s yd ; v = fy yd
    # d (xd, yd) / d (x, y) = [[a, b], [c, d]]
    du_dx = fx * a + s * c
    du_dy = fx * b + s * d
    dv_dx = fy * c
    dv_dy = fy * d
    # d (x, y) / d P = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    J_P = np.empty((len(X), 2, 3))
    J_P[:, 0, 0] = du_dx * iz
    J_P[:, 0, 1] = du_dy * iz
    J_P[:, 0, 2] = -(du_dx * x + du_dy * y) * iz
    J_P[:, 1, 0] = dv_dx * iz
    J_P[:, 1, 1] = dv_dy * iz
    J_P[:, 1, 2] = -(dv_dx * x + dv_dy * y) * iz
    J_X = J_P @ Rc  # (n, 2, 3)
    cols = []
    for name in intrinsic_params:
        if name == "f":
            # fx = fy = f moved together; skew fixed in pixels
            cols.append(np.column_stack([xd, yd]))
        elif name == "cx":
            cols.append(np.column_stack([np.ones_like(x), np.zeros_like(x)]))
        elif name == "cy":
            cols.append(np.column_stack([np.zeros_like(x), np.ones_like(x)]))
        elif name in ("k1", "k2"):
            rp = r2 if name == "k1" else r2 * r2
            cols.append(np.column_stack([(fx * x + s * y) * rp, fy * y * rp]))
        else:
            raise ValueError(f"unknown intrinsic parameter {name!r}; expected one of {INTRINSIC_NAMES}")
    J_intr = np.stack(cols, axis=2) if cols else np.zeros((len(X), 2, 0))
    return uv, J_X, J_intr


def project_with_jacobians(
    points_carriage: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, cam_from_world: np.ndarray,
    intrinsics: CameraIntrinsics, intrinsic_params: Sequence[str] = ("f",),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project carriage-frame points (n, 3) of a carriage at ``world_from_carriage = (R_wc, t_wc)``.

    Returns ``uv`` (n, 2) pixels, ``J_pose`` (n, 2, 6) with columns (omega_x, omega_y, omega_z, tau_x,
    tau_y, tau_z) — the scene-frame rotation increment ``R_wc <- Exp(omega) R_wc`` and the translation
    increment — and ``J_intr`` (n, 2, k) for ``intrinsic_params`` (subset of ``("f", "cx", "cy", "k1", "k2")``).
    Points behind the camera are not masked (the caller keeps them in front).
    """
    p = np.asarray(points_carriage, dtype=float).reshape(-1, 3)
    R = np.asarray(R_wc, dtype=float)
    q = p @ R.T  # R p
    X = q + np.asarray(t_wc, dtype=float).reshape(3)
    uv, J_X, J_intr = project_world_points_with_jacobians(X, cam_from_world, intrinsics, intrinsic_params)
    # d X / d omega = -[R p]x ; d X / d tau = I
    J_pose = np.empty((len(p), 2, 6))
    J_pose[:, :, :3] = -J_X @ skew(q)
    J_pose[:, :, 3:] = J_X
    return uv, J_pose, J_intr
