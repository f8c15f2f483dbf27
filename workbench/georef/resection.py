"""The multi-view route's fallback: a photo of the SfM set in no placed model placed on its own from its
control points (resection: P3P RANSAC + refinement, as the single-photo route), when the fit passes the checks
of a separate model (docs/gis.md)."""

from __future__ import annotations

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
from .picks import pick_sigma

__all__ = ["IncidentPhotos", "resect_unplaced"]


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
    if rms is None or rms > opts.warn_rms_px:
        return f"control-point RMS residual {rms} px exceeds {opts.warn_rms_px:g} px"
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


def intrinsics_response(intr: CameraIntrinsics, cam_from_world: np.ndarray, cps: list[ControlPoint], name: str,
                        residuals: list[dict], params: tuple[str, ...], opts: GeorefOptions) -> np.ndarray | None:
    """(6, k) the first-order response of a photo's resected pose (the rotation vector of ``world_from_cam`` in
    the scene frame, the centre in m: ``pose_uncertainty``'s order) to an error of the intrinsics it was resected
    with (``params``, ``CameraIntrinsics.moved``'s names): ``-(J_p^T W J_p)^-1 J_p^T W J_k`` over its inlier picks
    (central differences); None with fewer than 4 of them."""
    inl = {(r["point"], r["view"]) for r in residuals if r.get("inlier")}
    obs = [(cp, np.asarray(cp.pixels[name], float)) for cp in cps if name in cp.pixels and (cp.name, name) in inl]
    if len(obs) < 4:
        return None
    X = np.array([cp.enu for cp, _ in obs])
    UV = np.array([uv for _, uv in obs])
    R0 = np.asarray(cam_from_world, float)[:3, :3]
    c0 = -R0.T @ np.asarray(cam_from_world, float)[:3, 3]
    depth = ((X - c0) @ R0.T)[:, 2]
    sig = np.array([pick_sigma(intr, opts.sigma_px, cp.sigma_m, abs(d)) for (cp, _), d in zip(obs, depth)])

    def r(p: np.ndarray, dk: np.ndarray) -> np.ndarray:
        q = (X - c0 - p[3:]) @ (exp_so3(p[:3]) @ R0).T  # cam_from_world' = Exp(p) R, centre c + dc
        return ((intr.moved(params, dk).project(q) - UV) / sig[:, None]).ravel()

    Jp, Jk = np.zeros((2 * len(X), 6)), np.zeros((2 * len(X), len(params)))
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1e-6 if j < 3 else 1e-4
        Jp[:, j] = (r(e, np.zeros(len(params))) - r(-e, np.zeros(len(params)))) / (2 * e[j])
    for j, k in enumerate(params):
        d = np.zeros(len(params))
        d[j] = 1e-6 * (abs(intr.fx) if k in ("f", "fx", "fy", "cx", "cy") else 1.0)
        Jk[:, j] = (r(np.zeros(6), d) - r(np.zeros(6), -d)) / (2 * d[j])
    D = -np.linalg.lstsq(Jp, Jk, rcond=None)[0]
    T = np.eye(6)
    T[:3, :3] = -R0.T  # cam_from_world' = Exp(q) R: world_from_cam' = Exp(-R^T q) R^T
    return T @ D


def _camera_groups(out: dict[str, dict], models, cps: list[ControlPoint], opts: GeorefOptions) -> None:
    """The photos resected with an SfM camera's intrinsics as SfM gave them (not refined), grouped by camera: each
    photo's pose error is its own fit's plus its response to that camera's stated error (:func:`intrinsics_response`),
    which the photos of one camera share with the intrinsics the solve projects them with; written as one factor
    per camera into each photo's ``joint`` (in place). Photos of a camera without a stated error keep their own."""
    cams = _sfm_camera_errors(models)
    groups: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for name, r in sorted(out.items()):
        intr = CameraIntrinsics.from_dict(r["entry"]["intrinsics"])
        key = intrinsics_key(intr)
        if r.get("joint") is not None or r.get("covariance") is None or key not in cams \
                or not r["report"]["intrinsics_from"].startswith(("sfm", "main model")):
            continue
        D = intrinsics_response(intr, np.asarray(r["entry"]["cam_from_world"], float), cps, name,
                                r["report"]["residuals"], cams[key][0], opts)
        if D is not None:
            groups.setdefault(key, []).append((name, covariance_factor(np.asarray(r["covariance"], float)), D))
    for key, members in sorted(groups.items()):
        params, Lk = cams[key]
        rank = sum(L.shape[1] for _, L, _ in members) + Lk.shape[1]
        K = np.zeros((len(params), rank))
        K[:, rank - Lk.shape[1]:] = Lk
        col = 0
        for name, L, D in members:
            F = np.zeros((6, rank))
            F[:, col:col + L.shape[1]] = L
            F[:, rank - Lk.shape[1]:] = D @ Lk
            col += L.shape[1]
            out[name]["joint"] = {"group": f"resection[camera of {members[0][0]}]", "pose_factor": F,
                                  "params": list(params), "intrinsics_factor": K}


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
    _camera_groups(out, models, cps, opts)
    return out, why
