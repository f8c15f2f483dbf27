"""The multi-view route's fallback: a photo of the SfM set in no placed model placed on its own from its
control points (resection: P3P RANSAC + refinement, as the single-photo route), when the fit passes the checks
of a separate model (docs/gis.md)."""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_so3
from ..errors import InputError
from .camera_adjustment import intrinsics_key
from .central import CentralResult, refine_resection_focal, solve_central
from .shared_camera import covariance_factor, joint_factor
from ..files.control_points import ControlPoint
from .documents import view_entry
from ..files.panorama import RigView
from .options import GeorefOptions, GeorefResidualsLarge
from .picks import influence_weights, misfit_doubt, pick_sigma

log = logging.getLogger(__name__)

__all__ = ["IncidentPhotos", "resect_unplaced", "intrinsics_response", "survey_response"]


@dataclass(frozen=True)
class IncidentPhotos:
    """The incident's photos as the resection needs them (the stage reads them): their names, whether SfM found
    one camera for all (``single_camera``), a photo's size (w, h) px (None: no such file), and its ``image``
    path for cameras.json."""

    names: frozenset[str]
    single_camera: bool
    size_of: Callable[[str], tuple[int, int] | None]
    image_of: Callable[[str], str]


def _photo_intrinsics(name: str, sfm_intr: dict[str, CameraIntrinsics], photos: IncidentPhotos,
                      main_cam: CameraIntrinsics | None) -> CameraIntrinsics | None:
    """SfM's intrinsics of the photo, else the main model's camera when all photos share one and the photo has
    its size, else None."""
    intr = sfm_intr.get(name)
    if intr is not None:
        return intr
    size = photos.size_of(name)
    if not (photos.single_camera and main_cam is not None and size == (main_cam.width, main_cam.height)):
        return None
    return main_cam


def _report(name: str, res: CentralResult, from_refined: bool, has_sfm: bool) -> dict:
    s = res.stats
    sig = s.get("sigma_centre_m")
    return {"name": name, "placed_by": "resection", "n_points": s.get("n_points"),
            "n_observations": s.get("n_observations"), "n_outliers": int(s.get("n_outliers") or 0),
            "rms_px": s.get("rms_px"), "max_px": s.get("max_px"), "rms_m": s.get("rms_m"),
            "sigma_centre_max_m": float(max(sig)) if sig else None,
            "intrinsics_from": ("the shared camera refined from the control points (joint adjustment)"
                                if from_refined else "sfm" if has_sfm else "main model's camera (shared)"),
            "residuals": res.residuals}


def _failed_check(res: CentralResult, report: dict, focal_checked: bool, camera_checked: bool,
                  opts: GeorefOptions) -> str | None:
    """Why a photo placed on its own is not trusted (None: it is)."""
    s = res.stats
    n_out, rms, sig_max = report["n_outliers"], report["rms_px"], report["sigma_centre_max_m"]
    if not (focal_checked or camera_checked):
        # SfM's camera, checked by no placed model (its model failed its checks, or none was placed), and
        # too few picks to check its focal here: a focal 8 % off moved such a photo (5 picks) 2.5 m along
        # its line of sight with small residuals and a 0.41 m 1-sigma that does not count the focal
        n_fit = sum(1 for r in res.residuals if r.get("inlier"))
        return (f"its camera (SfM's) is checked by no placed SfM model, and {n_fit} of its "
                f"{len(res.residuals)} picks fit with it: too few to check the focal (6 are needed)")
    if rms is None:
        return "no control-point pick fits it"
    doubt = misfit_doubt(res.residuals, rms, opts, 6)
    if doubt is not None:
        return doubt
    if int(s.get("n_points") or 0) - n_out < opts.resect_min_points:
        return f"only {int(s.get('n_points') or 0) - n_out} of its control points fit"
    if n_out > opts.model_max_outlier_fraction * max(int(s.get("n_observations") or 0), 1):
        return f"{n_out} of its {s.get('n_observations')} picks are outliers"
    if sig_max is None or sig_max > opts.model_max_sigma_centre_m:
        return (f"its control points fix it only to {sig_max if sig_max is None else round(sig_max, 2)} m "
                f"(1-sigma; {opts.model_max_sigma_centre_m:g} m allowed)")
    return None


def _resect_photo(name: str, intr: CameraIntrinsics, from_refined: bool, camera_checked: bool, has_sfm: bool,
                  cps: list[ControlPoint], g: np.ndarray | None, opts: GeorefOptions, where: str):
    """One photo placed on its own: ((intrinsics, cam_from_world, report, its residual warnings, its pose's
    covariance (6, 6; scene rotation vector, centre: ``covariance_world_rotation_centre``) or None), None), or
    (None, why it was not placed)."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", GeorefResidualsLarge)
            res = solve_central([RigView(name, intr, np.eye(3))], cps, prior_centre=g,
                                prior_sigma_m=None if g is None else np.asarray(opts.gps_sigma_m, float),
                                opts=opts, where=f"{where} (photo {name} on its own)")
    except InputError as exc:
        return None, str(exc)
    report = _report(name, res, from_refined, has_sfm)
    cam_from_world = res.cam_from_world(np.eye(3))
    cov = res.stats.get("covariance_world_rotation_centre")
    ff = refine_resection_focal(intr, res, cps, name, opts)
    if ff is not None:
        report["focal_check"] = {"sfm_focal_px": intr.fx, "refined_focal_px": ff["focal_px"],
                                 "sigma_focal_px": ff["sigma_focal_px"], "rms_px": ff["rms_px"]}
        if abs(ff["focal_px"] - intr.fx) > opts.resect_focal_disagree_sigma * ff["sigma_focal_px"]:
            intr, cam_from_world, cov = ff["intrinsics"], ff["cam_from_world"], ff["covariance_world_rotation_centre"]
            order = [6, 0, 1, 2, 3, 4, 5]  # the focal first, as joint_factor reads it
            C7 = np.asarray(ff["covariance_pose_focal"], float)[np.ix_(order, order)]
            j = joint_factor(C7, intr, ("f",), [name], [cam_from_world[:3, :3]])
            report["joint"] = {"group": f"resection[{name}]", "pose_factor": j["poses"][name],
                               "params": j["params"], "intrinsics_factor": j["intrinsics"]}
            report.update({"intrinsics_from": report["intrinsics_from"] + ", focal refined in the resection "
                           "(SfM's disagrees with this photo's control points)", "rms_px": ff["rms_px"],
                           "sigma_centre_max_m": ff["sigma_centre_max_m"]})
    reason = _failed_check(res, report, ff is not None or from_refined, camera_checked, opts)
    if reason is not None:
        return None, f"placing it on its own failed the checks: {reason}"
    return (intr, cam_from_world, report, caught, cov), None


def _sfm_camera_errors(models) -> dict[str, tuple[tuple[str, ...], np.ndarray]]:
    """SfM camera (:func:`intrinsics_key`) -> (its refined intrinsics' names, a factor (k, q) of their stated
    marginal covariance), for the cameras the sfm stage stated it for (``intrinsics_factor``)."""
    out: dict[str, tuple[tuple[str, ...], np.ndarray]] = {}
    for _, vs in models:
        for v in vs:
            key = intrinsics_key(v.intrinsics)
            if v.intrinsics_factor is not None and v.intrinsics_params and key not in out:
                K = np.asarray(v.intrinsics_factor, float)
                out[key] = (tuple(v.intrinsics_params), covariance_factor(K @ K.T))
    return out


def _pose_rows(intr: CameraIntrinsics, cam_from_world: np.ndarray, cps: list[ControlPoint], name: str,
               residuals: list[dict], opts: GeorefOptions):
    """A resected photo's inlier picks as its refinement weighs them: (their control points' indices (n,), the
    whitened residuals' function ``r(p, dk, params)`` of a pose step ``p`` (rotation vector on the left of
    ``cam_from_world``, centre shift m) and an intrinsics step ``dk``, its Jacobian in the pose (2 n, 6: central
    differences), and ``T`` (6, 6): that pose step in ``pose_uncertainty``'s order); None with fewer than 4 picks.
    Rows and Jacobian are scaled by the square root of the robust loss's influence weights at the solution
    (:func:`influence_weights`), so that least squares on them gives the robust fit's first-order response."""
    inl = {(r["point"], r["view"]) for r in residuals if r.get("inlier")}
    idx = [k for k, cp in enumerate(cps) if name in cp.pixels and (cp.name, name) in inl]
    if len(idx) < 4:
        return None
    X = np.array([cps[k].enu for k in idx], float)
    UV = np.array([np.asarray(cps[k].pixels[name], float) for k in idx])
    R0 = np.asarray(cam_from_world, float)[:3, :3]
    c0 = -R0.T @ np.asarray(cam_from_world, float)[:3, 3]
    depth = ((X - c0) @ R0.T)[:, 2]
    sig = np.array([pick_sigma(intr, opts.sigma_px, cps[k].sigma_m, abs(d)) for k, d in zip(idx, depth)])

    def r(p: np.ndarray, dk: np.ndarray | None = None, params: tuple[str, ...] = ()) -> np.ndarray:
        q = (X - c0 - p[3:]) @ (exp_so3(p[:3]) @ R0).T  # cam_from_world' = Exp(p) R, centre c + dc
        it = intr if dk is None else intr.moved(params, dk)
        return ((it.project(q) - UV) / sig[:, None]).ravel()

    sw = np.sqrt(influence_weights(r(np.zeros(6)), opts))  # the robust loss's weights at the solution

    def rw(p: np.ndarray, dk: np.ndarray | None = None, params: tuple[str, ...] = ()) -> np.ndarray:
        return sw * r(p, dk, params)

    Jp = np.zeros((2 * len(X), 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1e-6 if j < 3 else 1e-4
        Jp[:, j] = (rw(e) - rw(-e)) / (2 * e[j])
    T = np.eye(6)
    T[:3, :3] = -R0.T  # cam_from_world' = Exp(q) R: world_from_cam' = Exp(-R^T q) R^T
    return np.asarray(idx, int), rw, Jp, T


def intrinsics_response(intr: CameraIntrinsics, cam_from_world: np.ndarray, cps: list[ControlPoint], name: str,
                        residuals: list[dict], params: tuple[str, ...], opts: GeorefOptions) -> np.ndarray | None:
    """(6, k) the first-order response of a photo's resected pose (the rotation vector of ``world_from_cam`` in
    the scene frame, the centre in m: ``pose_uncertainty``'s order) to an error of the intrinsics it was resected
    with (``params``, ``CameraIntrinsics.moved``'s names): ``-(J_p^T W J_p)^-1 J_p^T W J_k`` over its inlier picks
    (central differences; ``W`` the robust loss's influence weights); None with fewer than 4 of them."""
    rows = _pose_rows(intr, cam_from_world, cps, name, residuals, opts)
    if rows is None:
        return None
    _, r, Jp, T = rows
    Jk = np.zeros((len(Jp), len(params)))
    for j, k in enumerate(params):
        d = np.zeros(len(params))
        d[j] = 1e-6 * (abs(intr.fx) if k in ("f", "fx", "fy", "cx", "cy") else 1.0)
        Jk[:, j] = (r(np.zeros(6), d, params) - r(np.zeros(6), -d, params)) / (2 * d[j])
    return T @ -np.linalg.lstsq(Jp, Jk, rcond=None)[0]


def survey_response(intr: CameraIntrinsics, cam_from_world: np.ndarray, cps: list[ControlPoint], name: str,
                    residuals: list[dict], opts: GeorefOptions) -> np.ndarray | None:
    """(6, 3 K) the first-order response of a photo's resected pose (``pose_uncertainty``'s order) to the survey
    errors of the K control points, each column per unit of one point's error along east, north or up in its
    1-sigma (``sigma_m``): ``(J^T J)^-1 J_n^T J_n,c sigma_n`` for point n picked in the photo (``J_n`` its whitened
    rows weighted as :func:`_pose_rows` weighs them, ``J_n,c`` their centre columns: a pick depends on the point
    less the centre), zero for points it does not use. Photos resected from the same points move together by as
    much (the same survey error in each); the sandwich covariance of the fit (``central``) is ``U U^T`` plus the
    picks' own noise. None with fewer than 4 inlier picks."""
    rows = _pose_rows(intr, cam_from_world, cps, name, residuals, opts)
    if rows is None:
        return None
    idx, _, Jp, T = rows
    Hi = np.linalg.pinv(Jp.T @ Jp)
    U = np.zeros((6, 3 * len(cps)))
    for i, k in enumerate(idx):
        Jn = Jp[2 * i:2 * i + 2]
        U[:, 3 * k:3 * k + 3] = T @ Hi @ Jn.T @ Jn[:, 3:6] * float(cps[k].sigma_m)
    return U


def _resection_groups(out: dict[str, dict], models, cps: list[ControlPoint], opts: GeorefOptions) -> None:
    """The photos placed on their own, as one group whose errors are shared where their causes are (in place: each
    photo's ``joint``): every resected photo's pose error is its picks' own noise (independent), plus its response
    to the control points' survey errors (:func:`survey_response`; the same points' errors move every photo
    resected from them), plus, for a photo resected with an SfM camera's intrinsics as SfM gave them, its response
    to that camera's stated error (:func:`intrinsics_response`; shared with the intrinsics the solve projects the
    camera's photos with). The shares are the stated errors' (the survey's ``sigma_m``, the camera's factor); the
    photo's own noise is what its stated covariance leaves, its variance factor's widening included (so each
    photo's marginal stays its fit's, and a widening no residual attributes to a shared cause stays its own). A
    photo whose focal its resection refined (a group of its own) stays out; so does the lone photo with nothing to
    share."""
    cams = _sfm_camera_errors(models)
    members = []
    for name, r in sorted(out.items()):
        if r.get("joint") is not None or r.get("covariance") is None:
            continue
        intr = CameraIntrinsics.from_dict(r["entry"]["intrinsics"])
        M = np.asarray(r["entry"]["cam_from_world"], float)
        C = np.asarray(r["covariance"], float)
        U = survey_response(intr, M, cps, name, r["report"]["residuals"], opts)
        key = intrinsics_key(intr)
        D = None
        if key in cams and r["report"]["intrinsics_from"].startswith(("sfm", "main model")):
            D = intrinsics_response(intr, M, cps, name, r["report"]["residuals"], cams[key][0], opts)
        members.append((name, C, U, key if D is not None else None, D))
    shared = [m for m in members if m[2] is not None]
    if not any(m[3] is not None for m in members) and len(shared) < 2:
        return
    used = np.zeros(3 * len(cps), bool)
    for m in shared:
        used |= np.any(m[2] != 0.0, axis=0)
    keys = sorted({m[3] for m in members if m[3] is not None})
    owns = []
    for name, C, U, key, D in members:  # the photo's own noise: what its stated covariance leaves
        rest = C if U is None else C - U @ U.T
        ev, V = np.linalg.eigh(0.5 * (rest + rest.T))
        if ev[0] < -1e-6 * max(ev[-1], 1e-300):
            log.info("resection of %s: its stated covariance is smaller than its survey share along %d direction(s) "
                     "(least eigenvalue %.3g); that part of its own noise is taken as zero", name,
                     int(np.sum(ev < 0)), ev[0])
        owns.append(covariance_factor(V @ np.diag(np.maximum(ev, 0.0)) @ V.T))
    n_own = sum(L.shape[1] for L in owns)
    n_srv = int(used.sum())
    cam_cols = {}
    col = n_own + n_srv
    for key in keys:
        cam_cols[key] = col
        col += cams[key][1].shape[1]
    rank = col
    col = 0
    # named by its photos: a second pass (with the refined camera) makes a group of its own
    group = f"resection[shared errors of {', '.join(m[0] for m in members)}]"
    for (name, C, U, key, D), L in zip(members, owns):
        F = np.zeros((6, rank))
        F[:, col:col + L.shape[1]] = L
        col += L.shape[1]
        if U is not None:
            F[:, n_own:n_own + n_srv] = U[:, used]
        K = None
        if key is not None:
            params, Lk = cams[key]
            c0 = cam_cols[key]
            F[:, c0:c0 + Lk.shape[1]] = D @ Lk
            K = np.zeros((len(params), rank))
            K[:, c0:c0 + Lk.shape[1]] = Lk
        out[name]["joint"] = {"group": group, "pose_factor": F,
                              "params": list(cams[key][0]) if key is not None else [], "intrinsics_factor": K}


def resect_unplaced(photos: IncidentPhotos, models, placed: dict, cps: list[ControlPoint], gps: dict,
                    opts: GeorefOptions, where: str,
                    refined: dict[str, CameraIntrinsics] | None = None) -> tuple[dict[str, dict], dict[str, str]]:
    """Photos of the SfM set in no placed model, each placed on its own (module docstring); ``refined``: the
    shared cameras as the joint adjustment refined them (SfM camera key -> intrinsics).

    Returns (photo -> {"entry": cameras.json view, "report": figures, "covariance": its pose's (6, 6) or None},
    photo -> why it was not placed)."""
    sfm_intr: dict[str, CameraIntrinsics] = {}
    for _, vs in models:
        for v in vs:
            sfm_intr.setdefault(v.name, v.intrinsics)
    main_cam = models[0][1][0].intrinsics if models and models[0][1] else None
    picks: dict[str, int] = {}
    for cp in cps:
        for k in cp.pixels:
            picks[k] = picks.get(k, 0) + 1
    # the cameras a placed SfM model checked against its control points (its photos' intrinsics)
    checked_cameras = {intrinsics_key(x[2].intrinsics) for x in placed.values() if isinstance(x, tuple)}
    out, why = {}, {}
    for name in sorted(set(photos.names) | set(sfm_intr)):
        if name in placed:
            continue
        n = picks.get(name, 0)
        if n < opts.resect_min_points:
            why[name] = (f"{n} control point(s) picked in it; {opts.resect_min_points} are needed to place a photo "
                         f"on its own")
            continue
        intr = _photo_intrinsics(name, sfm_intr, photos, main_cam)
        if intr is None:
            why[name] = "no SfM intrinsics for it (not in any model, and the photos do not share one camera)"
            continue
        from_refined = False
        camera_checked = intrinsics_key(intr) in checked_cameras
        if refined and intrinsics_key(intr) in refined:  # the shared camera as the joint adjustment refined it
            intr, from_refined = refined[intrinsics_key(intr)], True
        done, failed = _resect_photo(name, intr, from_refined, camera_checked, name in sfm_intr, cps, gps.get(name),
                                     opts, where)
        if done is None:
            why[name] = failed
            continue
        intr, cam_from_world, report, caught, cov = done
        for wmsg in caught:
            warnings.warn(wmsg.message, wmsg.category, stacklevel=2)
        joint = report.pop("joint", None)  # the pose and the refined focal together, where it was refined
        out[name] = {"entry": view_entry(name, photos.image_of(name), intr, cam_from_world, True), "report": report,
                     "covariance": cov, "joint": joint}
    _resection_groups(out, models, cps, opts)
    return out, why
