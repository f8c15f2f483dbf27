"""The camera term: the georegistration's camera-pose error carried into the carriages' pose covariances.

A carriage's scene pose is solved from pixels, so an error of the camera's pose moves it; how far depends on what
else holds it. Pixels move with the camera, terms fixed in the world (the terrain contact, the track prior) do
not: the fit's response to a camera motion ``e`` is ``B e = H^-1 H_moving A e = (A - H^-1 H_world A) e``
(``H`` the estimator's information, ``A`` the rigid motion of every carriage with the camera), computed by the
solve (:func:`workbench.solve.uncertainty.camera_responses`) and kept on each carriage result
(:func:`set_camera_response`); without world-fixed terms ``B = A``. Also the arithmetic the other camera terms
share (levelling, principal point, multi-view cameras): a carriage's covariance set or widened and its sigmas
recomputed. ``docs/solver.md``, "The camera's uncertainty"; ``docs/calibration.md``.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from ..core.frames import hpr_from_rotation
from ..core.geometry import exp_so3, skew
from .projection import project_with_jacobians


def inverse_psd(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi-)definite matrix: by Cholesky, else the pseudo-inverse."""
    try:
        L = np.linalg.cholesky(H)
        Li = np.linalg.solve(L, np.eye(len(H)))
        return Li.T @ Li
    except np.linalg.LinAlgError:
        return np.linalg.pinv(H)


def hpr_jacobian(Rk: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d (heading, pitch, roll) / d scene rotation vector (degrees per radian), central differences."""
    J = np.zeros((3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        hp = np.array(hpr_from_rotation(exp_so3(d) @ Rk))
        hm = np.array(hpr_from_rotation(exp_so3(-d) @ Rk))
        diff = hp - hm
        diff[0] = (diff[0] + 180.0) % 360.0 - 180.0
        diff[2] = (diff[2] + 180.0) % 360.0 - 180.0
        J[:, i] = diff / (2 * eps)
    return J  # degrees per radian


def pose_determined(C: np.ndarray, rtol: float = 1e-9) -> bool:
    """Whether a carriage's (6, 6) pose covariance is a covariance: finite and positive semi-definite to within
    rounding (its least eigenvalue no lower than ``-rtol`` times its largest). Not so when the information it
    inverts is numerically singular (a carriage whose measured points do not fix its pose: its predictions
    placed it), where the computed variances are rounding noise, some of them negative."""
    C = np.asarray(C, dtype=float)
    if not np.all(np.isfinite(C)):
        return False
    ev = np.linalg.eigvalsh(0.5 * (C + C.T))
    return bool(ev[0] >= -rtol * max(ev[-1], 0.0))


def swing_second_moment(S_rot: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """(3, 3) second moment (m^2) of the second-order term of a point ``lever`` (3,) (m, scene frame) from a pivot
    the data hold, turned about that pivot by a rotation error ``d ~ N(0, S_rot)`` (rad^2, scene rotation vector):
    ``Exp(d) l = l + d x l + s``, ``s = (d x (d x l)) / 2`` (the arc's sagitta, towards the pivot), which the
    first-order covariance leaves out (it draws the arc straight). ``E[s s^T]`` by Isserlis' theorem, with
    ``m = S l`` and ``t = tr S``: ``(S (l.m) + 2 m m^T - (t m + 2 S m) l^T - l (t m + 2 S m)^T
    + (t^2 + 2 tr(S^2)) l l^T) / 4``; for a turn about one axis normal to ``l`` (sigma rad), ``3 sigma^4 l l^T / 4``.
    The second moment, not the covariance: the interval stays centred on the estimate, which the sagitta's mean
    lies off."""
    S = 0.5 * (np.asarray(S_rot, dtype=float) + np.asarray(S_rot, dtype=float).T)
    ln = np.asarray(lever, dtype=float).reshape(3)
    m = S @ ln
    t = float(np.trace(S))
    a = t * m + 2.0 * S @ m
    M = (S * float(ln @ m) + 2.0 * np.outer(m, m) - np.outer(a, ln) - np.outer(ln, a)
         + (t * t + 2.0 * float(np.sum(S * S))) * np.outer(ln, ln)) / 4.0
    return 0.5 * (M + M.T)


def set_pose_covariance(cr: Any, C: np.ndarray, R: np.ndarray, lever: np.ndarray, q: float,
                        determined: bool = True) -> np.ndarray:
    """Set a carriage result's ``covariance_pose`` (6, 6: scene rotation vector, origin) and the sigmas and 95 %
    half widths (``q`` sigmas) of its origin, body centre and heading / pitch / roll that follow from it (all None,
    no interval, when the data leave the pose ``determined`` False or the covariance is not one:
    :func:`pose_determined`).
    ``R`` (3, 3) its rotation, ``lever`` (3,) the body centre minus the origin in the scene frame (m). The body
    centre's covariance also takes, for a carriage with a ``swing_lever_m`` (a carried one: its body centre less
    the point its held couplings hold it at, scene frame), that swing's second-order term under this rotation
    covariance (:func:`swing_second_moment`, kept as ``centre_curvature_m2``). Returns the body centre's
    Jacobian (3, 6)."""
    if not (determined and pose_determined(C)):
        # the measured points leave a direction of the pose undetermined (the inverse of a numerically singular
        # information): its variances are rounding noise, and negative ones clipped to 0 would read "exact"
        cr.covariance_pose = None
        cr.sigma_position_m = cr.ci95_position_m = cr.sigma_body_centre_m = cr.ci95_body_centre_m = None
        cr.sigma_hpr_deg = cr.ci95_hpr_deg = None
        return np.hstack([-skew(lever), np.eye(3)])
    cr.covariance_pose = C
    sp = np.sqrt(np.maximum(np.diag(C[3:, 3:]), 0))
    cr.sigma_position_m, cr.ci95_position_m = sp, q * sp
    Jb = np.hstack([-skew(lever), np.eye(3)])
    Cb = Jb @ C @ Jb.T
    if getattr(cr, "swing_lever_m", None) is not None:  # a carried carriage's swing, to second order
        cr.centre_curvature_m2 = swing_second_moment(C[:3, :3], cr.swing_lever_m)
        Cb = Cb + cr.centre_curvature_m2
    sb = np.sqrt(np.maximum(np.diag(Cb), 0))
    cr.sigma_body_centre_m, cr.ci95_body_centre_m = sb, q * sb
    Jh = hpr_jacobian(R)
    sh = np.sqrt(np.maximum(np.diag(Jh @ C[:3, :3] @ Jh.T), 0))
    cr.sigma_hpr_deg, cr.ci95_hpr_deg = sh, q * sh
    return Jb


def camera_pose_jacobian(world_from_carriage: np.ndarray, centre_enu: np.ndarray) -> np.ndarray:
    """(6, 6) derivative of a carriage's pose parameters (scene rotation vector ``w``, origin ``t``: the order of
    ``covariance_pose``) with respect to a rigid error of the camera (rig) pose: a rotation ``d_theta`` (rad,
    scene frame) about the camera centre ``centre_enu`` (3,) and a shift ``d_c`` (m) of that centre.

    Poses solved from pixels move with the camera: ``R' = Exp(d_theta) R``, ``t' = c + d_c + Exp(d_theta) (t - c)``,
    so ``d_w = d_theta`` and ``d_t = d_c - [t - c]x d_theta``."""
    M = np.asarray(world_from_carriage, dtype=float)
    A = np.eye(6)
    A[3:, :3] = -skew(M[:3, 3] - np.asarray(centre_enu, dtype=float))
    return A


def motion_about(centre_enu: np.ndarray) -> np.ndarray:
    """(6, 6) ``G``: a camera motion given about its centre ``centre_enu`` (3,) (rotation ``d_theta`` about it, shift
    ``d_c`` of it) as the same rigid motion of the scene about the ENU origin (rotation ``d_theta``, translation
    ``d_c + [c]x d_theta``): ``x' = c + d_c + Exp(d_theta) (x - c) = Exp(d_theta) x + d_c + (I - Exp(d_theta)) c``.
    ``camera_pose_jacobian(M, c) = camera_pose_jacobian(M, 0) @ motion_about(c)``."""
    G = np.eye(6)
    G[3:, :3] = skew(np.asarray(centre_enu, dtype=float))
    return G


CAMERA_RESPONSE_ATTR = "camera_response_pose"  # where the solve keeps a carriage result's (6, 6) response


WORLD_INFORMATION_ATTR = "world_information_pose"  # (its (6, 6) world-fixed information, the cost's pixel sigma)


def set_camera_response(cr: Any, response: np.ndarray | None, world_information: np.ndarray | None = None,
                        pixel_sigma_px: float | None = None) -> None:
    """Keep on a carriage result its pose's first-order response (6, 6: scene rotation vector, origin) to a rigid
    motion of the camera about the ENU origin (rotation vector, translation: :func:`motion_about`), as the solve
    computed it with the terms fixed in the world holding the carriage (None: it moves rigidly with the camera),
    and the information of those terms on its pose (6, 6; in the cost's units, pixels at ``pixel_sigma_px``: the
    multi-view term, :func:`add_view_camera_uncertainty`, adds it). Not fields of the result: they are not written
    to ``solution.json``, and a result rebuilt from its fields (``dataclasses.replace``) does not keep them (the
    camera term then moves the carriage rigidly)."""
    setattr(cr, CAMERA_RESPONSE_ATTR, None if response is None else np.asarray(response, dtype=float))
    setattr(cr, WORLD_INFORMATION_ATTR, None if world_information is None or not pixel_sigma_px else
            (np.asarray(world_information, dtype=float), float(pixel_sigma_px)))


def camera_response(cr: Any, centre_enu: np.ndarray) -> np.ndarray:
    """(6, 6) derivative of a carriage's pose (scene rotation vector, origin) with respect to the camera's pose error
    about its centre ``centre_enu`` (rotation vector, rad; centre shift, m; the order of the georegistration's
    covariance): the solve's response kept by :func:`set_camera_response` where there is one, else the rigid
    motion :func:`camera_pose_jacobian`."""
    B0 = getattr(cr, CAMERA_RESPONSE_ATTR, None)
    if B0 is None:
        return camera_pose_jacobian(np.asarray(cr.world_from_carriage, dtype=float), centre_enu)
    return B0 @ motion_about(centre_enu)


def add_camera_uncertainty(res: Any, centre_enu: np.ndarray, cov_camera: np.ndarray) -> list[str]:
    """Add the georegistration's uncertainty of the camera pose to every carriage's covariance, in place.

    ``cov_camera`` (6, 6): covariance of the camera's scene rotation vector (rad) and centre (m, ENU), as the
    georef stage writes it (``georegistration.covariance_world_rotation_centre``). The fit's covariance
    (``covariance_pose``) is that of the poses *relative to the camera*; a camera error ``e`` moves a carriage by
    ``B e`` (:func:`camera_response`: rigidly with the camera, ``B = A`` (:func:`camera_pose_jacobian`), unless the
    terrain contact or the track prior holds it in the world), so to first order its covariance is
    ``C_fit + B C_cam B^T`` (the two errors are independent: the control points are not the marked points). The
    sigmas and 95 % intervals (position, body centre, heading / pitch / roll) are recomputed from the sum with the
    fit's ``ci95_factor``; ``res.covariance`` (the fit's joint covariance, of which the neighbour correlations are
    computed) stays the fit's. Returns the numbers of the carriages changed."""
    C_cam = np.asarray(cov_camera, dtype=float)
    if C_cam.shape != (6, 6) or not np.all(np.isfinite(C_cam)):
        raise ValueError(f"camera covariance must be a finite (6, 6) matrix, got shape {C_cam.shape}")
    c = np.asarray(centre_enu, dtype=float)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"camera centre must be a finite (3,) ENU point, got {c!r}")
    extra = {}
    for cr in res.carriages:
        if cr.world_from_carriage is not None:
            B = camera_response(cr, c)
            extra[cr.number] = B @ C_cam @ B.T
    return list(add_pose_covariance(res, extra))


def add_pose_covariance(res: Any, extra: dict[str, np.ndarray]) -> dict[str, dict]:
    """Add ``extra[number]`` (6, 6: scene rotation vector, origin) to that carriage's ``covariance_pose``, in place,
    and recompute its sigmas and 95 % intervals with the fit's ``ci95_factor`` (carriages without an interval
    are left as they are). Returns, per carriage changed, the sigmas of the term alone: ``sigma_hpr_deg`` (3,),
    ``sigma_body_centre_m`` (3,)."""
    q = float(res.ci95_factor) if getattr(res, "ci95_factor", None) else 1.959963984540054
    out = {}
    for cr in res.carriages:
        if cr.number not in extra or cr.covariance_pose is None or cr.world_from_carriage is None \
                or cr.body_centre_m is None:
            continue
        M = np.asarray(cr.world_from_carriage, dtype=float)
        X = np.asarray(extra[cr.number], dtype=float)
        C = np.asarray(cr.covariance_pose, dtype=float) + X
        Jb = set_pose_covariance(cr, 0.5 * (C + C.T), M[:3, :3],
                                  np.asarray(cr.body_centre_m, dtype=float) - M[:3, 3], q)
        Jh = hpr_jacobian(M[:3, :3])
        out[cr.number] = {"sigma_hpr_deg": np.sqrt(np.maximum(np.diag(Jh @ X[:3, :3] @ Jh.T), 0.0)).tolist(),
                          "sigma_body_centre_m": np.sqrt(np.maximum(np.diag(Jb @ X @ Jb.T), 0.0)).tolist()}
    return out


def view_information(world_from_carriage: np.ndarray, rows: dict[int, tuple[np.ndarray, np.ndarray]],
                     views: Sequence[Any]) -> dict[int, np.ndarray]:
    """Each view's pixel information (6, 6) on one carriage's pose parameters (scene rotation vector, origin: the
    order of ``covariance_pose``) at ``world_from_carriage`` (4, 4). ``rows``: view index -> (the measured
    points (n, 3) in the carriage frame, their weights (n,): 1 / sigma^2 in px^-2)."""
    M = np.asarray(world_from_carriage, dtype=float)
    out = {}
    for v, (P, w) in rows.items():
        _, J, _ = project_with_jacobians(P, M[:3, :3], M[:3, 3], views[v].cam_from_world, views[v].intrinsics, ())
        out[v] = np.einsum("nai,n,naj->ij", J, np.asarray(w, float), J)
    return out


def intrinsics_pixel_jacobian(P: np.ndarray, R: np.ndarray, t: np.ndarray, cam_from_world: np.ndarray, intr: Any,
                              names: Sequence[str], rel_step: float = 1e-6) -> np.ndarray:
    """(n, 2, k) derivative of the pixels of carriage-frame points ``P`` (n, 3), the carriage at ``(R, t)``, in the
    view's intrinsics ``names`` (``CameraIntrinsics.moved``'s): central differences, steps of ``rel_step`` times
    the focal for pixel quantities, ``rel_step`` for the others."""
    K = np.zeros((len(P), 2, len(names)))
    for j, name in enumerate(names):
        h = rel_step * (abs(intr.fx) if name in ("f", "fx", "fy", "cx", "cy") else 1.0)
        d = np.zeros(len(names))
        d[j] = h
        up, _, _ = project_with_jacobians(P, R, t, cam_from_world, intr.moved(names, d), ())
        dn, _, _ = project_with_jacobians(P, R, t, cam_from_world, intr.moved(names, -d), ())
        K[:, :, j] = (up - dn) / (2 * h)
    return K


def view_intrinsics_cross(world_from_carriage: np.ndarray, rows: dict[int, tuple[np.ndarray, np.ndarray]],
                          views: Sequence[Any], params: dict[int, tuple[str, ...]], rel_step: float = 1e-6
                          ) -> dict[int, np.ndarray]:
    """Per view ``v`` in ``params`` (view index -> the names of its intrinsics, fields of ``CameraIntrinsics``):
    ``sum_n w_n J_n^T K_n`` (6, k) over one carriage's measured points in that view, ``J_n`` (2, 6) the pixel's
    derivative in the carriage's pose (the order of ``covariance_pose``), ``K_n`` (2, k) in the view's intrinsics
    (central differences, steps of ``rel_step`` times the focal for pixel quantities, ``rel_step`` for the
    others). ``rows`` as :func:`view_information`'s."""
    M = np.asarray(world_from_carriage, dtype=float)
    out = {}
    for v, (P, w) in rows.items():
        names = params.get(v)
        if not names:
            continue
        intr, cam = views[v].intrinsics, views[v].cam_from_world
        _, J, _ = project_with_jacobians(P, M[:3, :3], M[:3, 3], cam, intr, ())
        K = intrinsics_pixel_jacobian(P, M[:3, :3], M[:3, 3], cam, intr, names, rel_step)
        out[v] = np.einsum("nai,n,naj->ij", J, np.asarray(w, float), K)
    return out


def view_shares(info: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``W_v = H^-1 H_v`` (6, 6) per view, ``H = sum_v H_v``: how a carriage's pose follows each view's camera
    when the cameras move apart (the first-order response of its least-squares pose to a shift of view ``v``'s
    pixels, each view's shift being the one that camera's own error would cause); the ``W_v`` sum to I, so a
    motion common to every camera moves the carriage with it exactly. Where ``H`` is singular (the pose rests on
    the chain as well), scalar shares ``trace H_v / trace H`` times I."""
    H = sum(info.values())
    ev = np.linalg.eigvalsh(0.5 * (H + H.T))
    if ev[0] > 1e-10 * max(ev[-1], 1e-300):
        return {v: np.linalg.solve(H, Hv) for v, Hv in info.items()}
    tr = float(np.trace(H))
    return {v: (float(np.trace(Hv)) / tr if tr > 0 else 1.0 / len(info)) * np.eye(6) for v, Hv in info.items()}


def _measured_rows(cin: Any, cr: Any, vindex: dict[str, int], pixel_sigma_px: float
                   ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A solved carriage's measured points in its final fit (its residuals' rows, predictions left out), per view
    index: (points (n, 3) in the carriage frame, weights (n,): (pixel sigma / the point's sigma)^2)."""
    rows: dict[int, tuple[list, list]] = {}
    for vname, pts in (cr.residuals_px or {}).items():
        for p in pts:
            o = (cin.observations.get(vname) or {}).get(p)
            if o is None or getattr(o, "derived", False) or vname not in vindex:
                continue
            sig = getattr(o, "sigma_px", None) or pixel_sigma_px
            P, w = rows.setdefault(vindex[vname], ([], []))
            P.append(cin.carriage_type.marked_points[p])
            w.append((pixel_sigma_px / float(sig)) ** 2)
    return {v: (np.asarray(P, float), np.asarray(w, float)) for v, (P, w) in rows.items()}


def _coupler_information(links: Sequence[Any], carriages: Sequence[Any], res: Any, pos: dict[int, int],
                         P: int) -> np.ndarray:
    """(P, P) information of the held couplings' offset prior (``T ~ N(0, (slack / sqrt 5)^2 I)``, as the
    covariance) between carriages both in ``pos`` (consist index -> block)."""
    H = np.zeros((P, P))
    for L in links:
        a, b = int(L.front), int(L.rear)
        if L.slack_m is None or a not in pos or b not in pos:
            continue
        Ra = np.asarray(res.carriages[a].world_from_carriage, float)[:3, :3]
        Rb = np.asarray(res.carriages[b].world_from_carriage, float)[:3, :3]
        JT = np.zeros((3, P))
        ca, cb = 6 * pos[a], 6 * pos[b]
        JT[:, ca:ca + 3] = skew(Ra @ np.asarray(carriages[a].carriage_type.coupler_rear, float))
        JT[:, ca + 3:ca + 6] = -np.eye(3)
        JT[:, cb:cb + 3] = -skew(Rb @ np.asarray(carriages[b].carriage_type.coupler_front, float))
        JT[:, cb + 3:cb + 6] = np.eye(3)
        H += JT.T @ JT / (float(L.slack_m) / math.sqrt(5.0)) ** 2
    return H


def add_view_camera_uncertainty(res: Any, carriages: Sequence[Any], links: Sequence[Any], views: Sequence[Any],
                                pixel_sigma_px: float, model_covariance: dict[str, np.ndarray],
                                jacobian: dict[str, tuple[str, np.ndarray]], own_covariance: dict[str, np.ndarray],
                                weighting: str = "per_carriage",
                                intrinsics_jacobian: dict[str, tuple[str, tuple[str, ...], np.ndarray]] | None = None
                                ) -> dict[str, dict]:
    """Add the multi-view cameras' pose uncertainty to every carriage's covariance, in place (first order).

    A view's pose error ``e_v`` (6: scene rotation vector of ``world_from_cam``, centre) is ``J_v e_m`` for a view
    placed by SfM model ``m``'s similarity (``jacobian[view] = (m, J_v)``; ``e_m`` of covariance
    ``model_covariance[m]`` (7, 7), shared by all of ``m``'s views, so their errors are correlated) or its own
    (``own_covariance[view]`` (6, 6), independent). A view projected with SfM intrinsics that err with the model
    (``intrinsics_jacobian[view] = (m, params, J_k)``: ``dk = J_k e_m``) moves the carriages by
    ``-H^-1 sum_k J^T W K dk`` as well (``K`` the pixels' derivative in those intrinsics): a pose error that the
    intrinsics' error compensates in the image moves the photo but hardly the carriages. The carriages' poses respond as the least squares does:
    ``dx = H^-1 sum_v H_v A_v e_v``, with ``H_v`` view ``v``'s pixel information on every carriage's pose
    (their measured points, the carriage weighting, the pixel sigma ``res.sigma_px``), ``H`` all of it plus the
    held couplings' prior, and ``A_v`` (:func:`camera_pose_jacobian` about view ``v``'s centre) the poses that keep
    view ``v``'s pixels: a carriage seen in one view moves with that camera (as the central route's
    :func:`add_camera_uncertainty`), a motion common to all cameras moves every carriage rigidly with it, and the
    scale moves each by its cameras' information-weighted shifts. The terrain contact and the track prior,
    fixed in the world, hold a carriage (their information, kept by the solve with :func:`set_camera_response`,
    is in ``H`` but moves with no camera). Predictions
    (``Observation.derived``) carry no information and take no share. The fit's joint covariance
    ``res.covariance`` stays the fit's. Returns carriage number -> {"views": view -> its share of the carriage's
    own information (trace of ``H_k^-1 H_kv`` / 6), "not_modelled": the views it is measured in whose error is
    not modelled}."""
    q = float(res.ci95_factor) if getattr(res, "ci95_factor", None) else 1.959963984540054
    vindex = {v.name: i for i, v in enumerate(views)}
    centres = [-np.asarray(v.cam_from_world, float)[:3, :3].T @ np.asarray(v.cam_from_world, float)[:3, 3]
               for v in views]
    jac_k = {vindex[n]: t for n, t in (intrinsics_jacobian or {}).items() if n in vindex and n in jacobian}
    k_params = {v: t[1] for v, t in jac_k.items()}
    info: dict[int, dict[int, np.ndarray]] = {}
    cross: dict[int, dict[int, np.ndarray]] = {}
    counts: dict[int, int] = {}
    for k, (cin, cr) in enumerate(zip(carriages, res.carriages)):
        if cr.covariance_pose is None or cr.world_from_carriage is None or cr.body_centre_m is None:
            continue
        rows = _measured_rows(cin, cr, vindex, pixel_sigma_px)
        if rows:
            info[k] = view_information(cr.world_from_carriage, rows, views)
            cross[k] = view_intrinsics_cross(cr.world_from_carriage, rows, views, k_params) if k_params else {}
            counts[k] = sum(len(w) for _, w in rows.values())
    if not info:
        return {}
    pos = {k: i for i, k in enumerate(info)}
    P = 6 * len(pos)
    n_mean = float(np.mean(list(counts.values())))
    sig = float(res.sigma_px) if math.isfinite(float(getattr(res, "sigma_px", math.nan))) else pixel_sigma_px
    H = _coupler_information(links, carriages, res, pos, P)
    G = {v: np.zeros((P, 6)) for v in range(len(views))}  # H_v A_v
    G_k = {v: np.zeros((P, len(t[1]))) for v, t in jac_k.items()}  # J^T W K, per view's intrinsics
    for k, per_view in info.items():
        c = 6 * pos[k]
        w2 = (n_mean / counts[k] if weighting == "per_carriage" else 1.0) / sig**2
        M = np.asarray(res.carriages[k].world_from_carriage, float)
        for v, Hkv in per_view.items():
            H[c:c + 6, c:c + 6] += w2 * Hkv
            G[v][c:c + 6] += w2 * Hkv @ camera_pose_jacobian(M, centres[v])
        for v, Xkv in cross[k].items():
            G_k[v][c:c + 6] += w2 * Xkv
        held = getattr(res.carriages[k], WORLD_INFORMATION_ATTR, None)
        if held is not None:  # the terrain contact, the track prior: fixed in the world, they hold the carriage
            Hw, ps = held  # in the cost's units (pixels at ps); the pixel rows here are at sig
            H[c:c + 6, c:c + 6] += Hw * (ps / sig) ** 2
    Hi = inverse_psd(0.5 * (H + H.T))
    C_cam = np.zeros((P, P))
    B: dict[str, np.ndarray] = {}
    missing: set[str] = set()
    for v, Gv in G.items():
        if not Gv.any():
            continue
        Rv = Hi @ Gv  # (P, 6): every carriage's response to view v's pose error
        name = views[v].name
        if name in jacobian:
            label, J = jacobian[name]
            B[label] = B.get(label, np.zeros((P, np.shape(J)[1]))) + Rv @ np.asarray(J, float)
            if v in jac_k and jac_k[v][0] == label and G_k[v].any():
                B[label] -= Hi @ G_k[v] @ np.asarray(jac_k[v][2], float)
        elif name in own_covariance:
            C_cam += Rv @ np.asarray(own_covariance[name], float) @ Rv.T
        else:
            missing.add(name)
    for label, Bm in B.items():
        C_cam += Bm @ np.asarray(model_covariance[label], float) @ Bm.T
    out = {}
    for k, i in pos.items():
        cr = res.carriages[k]
        M = np.asarray(cr.world_from_carriage, dtype=float)
        C = np.asarray(cr.covariance_pose, dtype=float) + C_cam[6 * i:6 * i + 6, 6 * i:6 * i + 6]
        set_pose_covariance(cr, 0.5 * (C + C.T), M[:3, :3], np.asarray(cr.body_centre_m, dtype=float) - M[:3, 3], q)
        shares = view_shares(info[k])
        out[cr.number] = {"views": {views[v].name: float(np.trace(W)) / 6.0 for v, W in shares.items()},
                          "not_modelled": sorted(views[v].name for v in info[k] if views[v].name in missing)}
    return out
