"""The multi-view route's fallback: a photo of the SfM set in no placed model placed on its own from its
control points (resection: P3P RANSAC + refinement, as the single-photo route), when the fit passes the checks
of a separate model (docs/gis.md)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from .camera_adjustment import intrinsics_key
from .central import CentralResult, refine_resection_focal, solve_central
from .shared_camera import joint_factor
from ..files.control_points import ControlPoint
from .documents import view_entry
from ..files.panorama import RigView
from .options import GeorefOptions, GeorefResidualsLarge

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
            report["joint"] = joint_factor(C7, intr, ("f",), [name], [cam_from_world[:3, :3]])
            report.update({"intrinsics_from": report["intrinsics_from"] + ", focal refined in the resection "
                           "(SfM's disagrees with this photo's control points)", "rms_px": ff["rms_px"],
                           "sigma_centre_max_m": ff["sigma_centre_max_m"]})
    reason = _failed_check(res, report, ff is not None or from_refined, camera_checked, opts)
    if reason is not None:
        return None, f"placing it on its own failed the checks: {reason}"
    return (intr, cam_from_world, report, caught, cov), None


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
    return out, why
