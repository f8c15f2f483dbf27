"""What the multi-view cameras' stated errors leave in the fit's residuals, so the pixel sigma is not inflated by them.

On the multi-view route each photo's pose (and, for some, its intrinsics) is off by an error the georegistration
states (``georegistration.pose_uncertainty``); the carriages cannot follow several photos' errors at once, so the
photos disagree and the residuals grow. The fit estimates its pixel sigma from those residuals
(:func:`.uncertainty.covariance_model`, pooled with the configured sigma): without this module it counts the
cameras' disagreement as pixel noise, widening the fit's covariance, while the camera term
(:func:`.camera_term.add_view_camera_uncertainty`) adds the same cameras' error again. Counted twice: the
real-SfM calibration sample's carriages came out wide (RMS of error / sigma 0.78-0.82 east and north), the fit's
sigma 1.1-1.9 times the one the same picks give with the true cameras (docs/calibration.md, "Session 20").

What the camera errors ``e ~ N(0, C)`` (the photos' stated errors stacked, :class:`ViewCameraErrors`) leave in
the residuals is, to first order, ``r = (I - J H^-1 J^T / s^2) D e`` (``D`` the whitened pixel shift per unit of
``e`` that a carriage would have to follow, ``J`` the whitened pixel rows, ``H = J^T J / s^2 + H_prior`` the fit's
information at pixel sigma ``s``): a few directions of the residual space (at most one per camera-error parameter).
The fit estimates its pixel sigma from the residuals with those directions set aside where the cameras' stated
error fills them more than the pixel noise (:func:`camera_directions`; one degree of freedom fewer each), a
variance-component split that does not rest on the size of the cameras' stated error, only on where it acts. (The
method of moments, subtracting the cameras' expected share, was tried first: on that sample their stated error
predicts 2.2 times the residuals they leave, and the pixel sigma fell to nothing.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .camera_term import camera_pose_jacobian, intrinsics_pixel_jacobian


@dataclass(frozen=True, eq=False)
class ViewCameraErrors:
    """The multi-view photos' stated errors as one parameter vector ``e ~ N(0, covariance)`` (n,): each SfM
    model's (or shared-camera adjustment's) parameters once, shared by its photos, then each photo placed on its own.
    ``pose``: photo name -> (6, n), its pose error (scene rotation vector of ``world_from_cam``, rad; centre, m)
    as ``pose @ e``; ``intrinsics``: photo name -> (the intrinsics' names, (k, n)): the error of the intrinsics it is
    projected with."""

    covariance: np.ndarray
    pose: dict[str, np.ndarray]
    intrinsics: dict[str, tuple[tuple[str, ...], np.ndarray]] = field(default_factory=dict)


def view_camera_errors(pu: Any) -> ViewCameraErrors | None:
    """The :class:`ViewCameraErrors` of a parsed ``pose_uncertainty``
    (:class:`~workbench.files.cameras.PoseUncertainty`), or None when it states no photo's error."""
    blocks: list[np.ndarray] = []
    start: dict[str, int] = {}
    n = 0
    for label, C in pu.model_covariance.items():
        start[label] = n
        blocks.append(np.asarray(C, float))
        n += len(C)
    own_start: dict[str, int] = {}
    for name, C in pu.own_covariance.items():
        own_start[name] = n
        blocks.append(np.asarray(C, float))
        n += 6
    if n == 0:
        return None
    cov = np.zeros((n, n))
    i = 0
    for B in blocks:
        cov[i:i + len(B), i:i + len(B)] = B
        i += len(B)
    pose: dict[str, np.ndarray] = {}
    for name, (label, J) in pu.jacobian.items():
        if label in start:
            T = np.zeros((6, n))
            T[:, start[label]:start[label] + np.shape(J)[1]] = J
            pose[name] = T
    for name, s in own_start.items():
        if name not in pose:
            T = np.zeros((6, n))
            T[:, s:s + 6] = np.eye(6)
            pose[name] = T
    intr: dict[str, tuple[tuple[str, ...], np.ndarray]] = {}
    for name, (label, params, Jk) in (pu.intrinsics_jacobian or {}).items():
        if label in start and name in pu.jacobian and pu.jacobian[name][0] == label:
            K = np.zeros((len(params), n))
            K[:, start[label]:start[label] + np.shape(Jk)[1]] = Jk
            intr[name] = (tuple(params), K)
    return ViewCameraErrors(0.5 * (cov + cov.T), pose, intr)


def camera_shift_rows(prob: Any, R: np.ndarray, t: np.ndarray, J: np.ndarray, col: dict[int, int],
                      errors: ViewCameraErrors, rel_step: float = 1e-6) -> np.ndarray:
    """(2M, n) whitened pixel shift of every row of ``prob`` per unit of the camera errors ``e``, in the sense the
    carriage would have to follow (the camera term's: a pose error moves a carriage seen only in that photo with
    it, ``J A e``; an intrinsics error ``dk`` of the photo, ``-K dk``). ``J`` (2M, P): the whitened pixel rows of
    :func:`.uncertainty.pixel_rows` at poses ``R`` (N, 3, 3), ``t`` (N, 3); ``col``: carriage -> first column."""
    n = len(errors.covariance)
    D = np.zeros((J.shape[0], n))
    names = [v.name for v in prob.views]
    centres = [v.camera_centre for v in prob.views]
    for k in prob.active:
        idx = prob.by_car[k]
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R[k], t[k]
        c = col[k]
        for v in np.unique(prob.view[idx]):
            rows = idx[prob.view[idx] == v]
            T = errors.pose.get(names[v])
            if T is not None:
                AT = camera_pose_jacobian(M, centres[v]) @ T
                D[2 * rows] += J[2 * rows, c:c + 6] @ AT
                D[2 * rows + 1] += J[2 * rows + 1, c:c + 6] @ AT
            ki = errors.intrinsics.get(names[v])
            if ki is None:
                continue
            params, Kt = ki
            wK = intrinsics_pixel_jacobian(prob.P[rows], R[k], t[k], prob.views[v].cam_from_world,
                                           prob.views[v].intrinsics, params, rel_step) * prob.w[rows, None, None]
            D[2 * rows] -= wK[:, 0, :] @ Kt
            D[2 * rows + 1] -= wK[:, 1, :] @ Kt
    return D


def camera_directions(D: np.ndarray, J: np.ndarray, covariance: np.ndarray, noise_var: np.ndarray,
                      assemble: Callable[[float], tuple[np.ndarray, np.ndarray]], sigma: float) -> np.ndarray:
    """(2M, m) orthonormal directions of the whitened residual space along which the camera errors
    ``e ~ N(0, covariance)`` leave more residual variance than the rows' pixel noise (``noise_var`` (2M,), each
    row's at the pixel sigma ``sigma``). ``D`` (2M, n) from :func:`camera_shift_rows`, ``J`` (2M, P) the rows the
    covariance uses (robust weights applied as there), ``assemble(s) -> (H, H^-1)`` the fit's information at ``s``.
    What the camera errors leave is ``r = (I - J H^-1 J^T / s^2) D e`` (the fit follows what it can); its
    covariance ``S`` has at most n non-zero eigenvalues, and the directions kept are those whose eigenvalue, in
    units of the rows' noise (whitened by it), exceeds 1."""
    if D.shape[1] == 0 or not np.any(D):
        return np.zeros((D.shape[0], 0))
    _, Hi = assemble(sigma)
    Dr = D - J @ (Hi @ (J.T @ D)) / sigma**2
    ev, V = np.linalg.eigh(0.5 * (covariance + covariance.T))
    half = V * np.sqrt(np.clip(ev, 0.0, None))  # covariance = half half^T
    Z = (Dr @ half) / np.sqrt(np.maximum(noise_var, 1e-300))[:, None]  # whitened by the rows' noise
    U, sv, _ = np.linalg.svd(Z, full_matrices=False)
    keep = sv**2 > 1.0
    if not keep.any():
        return np.zeros((D.shape[0], 0))
    # back in the rows' units: orthonormal there (the residuals r are compared in those units)
    Q, _ = np.linalg.qr(U[:, keep] * np.sqrt(np.maximum(noise_var, 1e-300))[:, None])
    return Q
