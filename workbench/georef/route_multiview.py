"""The ``multiview`` route: every SfM model placed by its own similarity (docs/gis.md): the main model, and each
separate model from the control points triangulated in it when they fix it (:func:`model_verdict`); photos in
no placed model placed on their own (:mod:`.resection`); the shared cameras adjusted and every photo's
uncertainty stated (:mod:`.camera_adjustment`)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from PIL import Image

from ..core.geometry import rotation_angle_deg
from ..core.layout import CAMERAS_FILE, CONTROL_POINTS_FILE
from ..errors import InputError
from ..project import Project
from .camera_adjustment import adjust_cameras
from ..files.control_points import ControlPoint
from .documents import georeg_block, view_entry
from ..files.reconstruction import Reconstruction, read_reconstruction
from .inputs import control_points_of_photos, gps_enu, photos_by_name
from .model_checks import model_verdict
from ..files.reconstruction import SfmView
from .options import GeorefOptions, GeorefResidualsLarge
from .picks import picks_in_views
from .resection import IncidentPhotos, resect_unplaced
from .similarity import SimilarityResult, solve_similarity

__all__ = ["multiview_route"]


@dataclass
class _Placement:
    """The SfM models placed: photo -> (model label, similarity, view), and one report per model."""

    placed: dict[str, tuple[str, SimilarityResult, SfmView]] = field(default_factory=dict)
    reports: list[dict] = field(default_factory=list)
    main_res: SimilarityResult | None = None
    main_error: InputError | None = None
    first_res: SimilarityResult | None = None


def _similarity(views: list[SfmView], cps: list[ControlPoint], gps: dict, opts: GeorefOptions, where: str):
    """The model's similarity and the residual warnings it raised (held back until the model is used)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GeorefResidualsLarge)
        res = solve_similarity(views, cps, gps_centres={v.name: gps[v.name] for v in views if v.name in gps},
                               opts=opts, where=where)
    return res, caught


def _disagreeing_views(res: SimilarityResult, views: list[SfmView], opts: GeorefOptions) -> dict[str, str]:
    """Photos whose own picks mostly disagree with the fitted model: SfM placed them wrongly (look-alike matches);
    photo -> why."""
    rejected = {}
    for v in views:
        mine = [r for r in res.residuals if r["view"] == v.name]
        bad = [r for r in mine if not r["inlier"]]
        if opts.reject_disagreeing_views and len(bad) >= 2 and 2 * len(bad) > len(mine):
            med = np.median([r["error_px"] if r["error_px"] is not None else np.inf for r in mine])
            rejected[v.name] = (f"{len(bad)} of its {len(mine)} control-point picks are more than "
                                f"{opts.ransac_threshold_px:g} px (or 4 times their stated sigma) from where SfM's "
                                f"pose puts them (median {med:.0f} px): its SfM pose disagrees with the control "
                                f"points")
    return rejected


def _fit_model(label: str, views: list[SfmView], cps: list[ControlPoint], gps: dict, opts: GeorefOptions, where: str,
               report: dict) -> tuple[SimilarityResult, list, dict[str, str], str | None, InputError | None]:
    """One model's similarity: (result, its warnings, rejected photos, why it is not placed (None: placed), the
    error that stops the route if it is the main model). Raises InputError when no similarity can be fitted.

    A photo whose picks mostly disagree is left out of the model (it may be placed on its own later) and the
    model fitted again without it (its rays also went into the triangulated points)."""
    where_m = where if label == "main" else f"{where} ({label} of the SfM models)"
    res, caught = _similarity(views, cps, gps, opts, where_m)
    rejected = _disagreeing_views(res, views, opts)
    fitted_views = views
    if rejected and len(rejected) < len(views):
        keep = [v for v in views if v.name not in rejected]
        try:
            res, caught = _similarity(keep, cps, gps, opts, where_m)
            fitted_views = keep
        except InputError as exc:
            report["refit_failed"] = str(exc)
    if rejected:
        report["rejected_views"] = rejected
    # every model, the main one too, must pass the checks when control points exist (a main model placed by
    # GPS alone is not checked: it has no control points to check against)
    reason, figures = (None, {}) if (label == "main" and not cps) else model_verdict(res, fitted_views, opts)
    main_error = None
    if label == "main" and reason is not None:
        main_error = InputError(f"{where}: the main SfM model could not be placed: {reason}")
    report.update(figures)
    report.update({"world_from_model": res.matrix.tolist(), "scale": res.scale,
                   "n_triangulated": res.stats.get("n_triangulated"), "rms_px": res.stats.get("rms_px"),
                   "max_px": res.stats.get("max_px"), "rms_m": res.stats.get("rms_m"),
                   "n_gps_centres": res.stats.get("n_gps_centres")})
    if reason is None and len(rejected) == len(views):
        reason = "every photo of it disagrees with the control points"
    return res, caught, rejected, reason, main_error


def _record_placed(label: str, views: list[SfmView], res: SimilarityResult, rejected: dict, report: dict,
                   placed: dict) -> None:
    """The model's photos into ``placed``; a photo already placed by a larger model keeps that pose, and the
    difference goes into the report's ``overlap``."""
    overlap = {}
    for v in views:
        if v.name in rejected:
            continue
        if v.name in placed:  # already placed by a larger model: compare, keep that one
            _, other, ov = placed[v.name]
            A, B = other.cam_from_world(ov.cam_from_model), res.cam_from_world(v.cam_from_model)
            overlap[v.name] = {"placed_by": placed[v.name][0],
                               "centre_difference_m": float(np.linalg.norm(
                                   (-A[:3, :3].T @ A[:3, 3]) - (-B[:3, :3].T @ B[:3, 3]))),
                               "rotation_difference_deg": rotation_angle_deg(A, B)}
        else:
            placed[v.name] = (label, res, v)
    if overlap:
        report["overlap"] = overlap
    report["placed"] = sorted(n for n in report["views"] if n in placed and placed[n][0] == label)


def _place_models(models, cps: list[ControlPoint], gps: dict, opts: GeorefOptions, where: str) -> _Placement:
    """Every SfM model placed by its similarity, largest first, when it passes the checks."""
    out = _Placement()
    for label, views in models:
        report: dict[str, Any] = {"model": label, "views": [v.name for v in views]}
        try:
            res, caught, rejected, reason, error = _fit_model(label, views, cps, gps, opts, where, report)
        except InputError as exc:
            report.update({"status": "unregistered", "reason": str(exc)})
            if label == "main":
                out.main_error = exc
            out.reports.append(report)
            continue
        if error is not None:
            out.main_error = error
        if reason is not None:
            report.update({"status": "unregistered", "reason": reason, "residuals": res.residuals})
            report.pop("rejected_views", None)
            out.reports.append(report)
            continue
        for wmsg in caught:  # the residual warnings of a model that is used
            warnings.warn(wmsg.message, wmsg.category, stacklevel=2)
        report["status"] = "georegistered"
        if label != "main":
            report["residuals"] = res.residuals
            report["warnings"] = res.warnings
        _record_placed(label, views, res, rejected, report, out.placed)
        if label == "main":
            out.main_res = res
        out.first_res = out.first_res or res
        out.reports.append(report)
    return out


def _views_out(placed: dict, resected: dict, images: dict[str, str], src: str) -> list[dict]:
    """The cameras.json views of every placed photo, by name."""
    out = []
    for name in sorted(set(placed) | set(resected)):
        if name in resected:
            out.append(dict(resected[name]["entry"]))
            continue
        label, res, v = placed[name]
        out.append(view_entry(name, images.get(name) or name, v.intrinsics,
                              res.cam_from_world(v.cam_from_model), src in ("calibrated", "sfm")))
    return out


POSE_PARAMETRISATION = ("a model's similarity error: [log scale, rotation vector (rad, scene frame, applied on the "
                        "left), translation (m, ENU)]; a view's pose error: [rotation vector of world_from_cam (rad, "
                        "scene frame), centre (m, ENU)] = jacobian @ its model's similarity error + sfm_factor @ z "
                        "(its SfM model's own error, z ~ N(0, I_sfm_rank) shared by the model's views, the "
                        "similarity's response to it included); its SfM intrinsics' error: "
                        "sfm_intrinsics_factor @ z")


def _sfm_factor(res: SimilarityResult, sv: SfmView) -> np.ndarray | None:
    """(6, r) the view's scene pose error per unit of its model's SfM pose error ``z``: its SfM pose factor (model
    frame, :mod:`workbench.intrinsics.sfm_covariance`) carried into the scene by the similarity (a rotation turns
    by ``R``, a centre moves by ``s R``), plus the similarity's own response to ``z`` (it was fitted to the
    control points seen through those erring poses: ``res.sfm_sensitivity``, through the view's Jacobian); None
    when SfM stated none."""
    if sv.pose_factor is None:
        return None
    T = np.zeros((6, 6))
    T[:3, :3] = res.rotation
    T[3:, 3:] = res.scale * res.rotation
    F = T @ np.asarray(sv.pose_factor, float)
    if res.sfm_sensitivity is not None and res.sfm_sensitivity.shape == (7, F.shape[1]):
        F = F + res.view_jacobian(sv.cam_from_model) @ res.sfm_sensitivity
    return F


def _for_reading(uncertainty: dict) -> dict:
    """``view_uncertainty`` as written: each photo's figures, without the joint factor ``pose_uncertainty`` carries."""
    return {n: {k: v for k, v in u.items() if k != "joint"} for n, u in uncertainty.items()}


def _group_view(models: dict, views: dict, name: str, joint: dict, source: str) -> None:
    """A photo whose error is shared by a group of photos placed without a similarity (one shared camera's
    adjustment, the photos resected on their own from shared control points and SfM cameras, a resection with its
    focal refined): the group written as a model with no similarity error (its ``covariance`` zero) whose ``z``
    moves the photos' poses (``sfm_factor``) and the intrinsics they are projected with (``sfm_intrinsics_factor``).
    ``joint``: {"group", "pose_factor" (6, r), "params", "intrinsics_factor" (k, r) or None (the photo's
    intrinsics taken as exact)} (camera_adjustment.py, resection.py)."""
    F = np.asarray(joint["pose_factor"], float)
    K = None if joint.get("intrinsics_factor") is None else np.asarray(joint["intrinsics_factor"], float)
    m = models.setdefault(joint["group"], {"covariance": np.zeros((7, 7)).tolist(), "translation_enu": [0.0] * 3,
                                           "scale": 1.0, "sfm_rank": int(F.shape[1]), "sfm_response": None,
                                           "kind": source})
    if m["sfm_rank"] != F.shape[1]:  # two groups under one name would share a z they do not share
        raise RuntimeError(f"pose_uncertainty: group {joint['group']!r} has factors of rank {m['sfm_rank']} and "
                           f"{F.shape[1]} (photo {name})")
    views[name] = {"source": source, "model": joint["group"], "jacobian": np.zeros((6, 7)).tolist(),
                   "sfm_factor": F.tolist(),
                   "sfm_intrinsics_factor": None if K is None else {"params": list(joint["params"]),
                                                                    "factor": K.tolist()},
                   "covariance_rotation_centre": (F @ F.T).tolist()}


def _pose_uncertainty(placed: dict, resected: dict, out_views: list[dict], uncertainty: dict) -> dict:
    """``georegistration.pose_uncertainty`` (docs/formats.md): each placed model's similarity covariance (7, 7)
    and each view's Jacobian (6, 7) from it, so that views of one model keep their shared (correlated) error; a
    view whose pose the shared-camera adjustment replaced carries that adjustment's covariance on its own, and so
    does a view placed on its own (resection: its control points' fit, the refined focal's doubt included when
    the focal was refined). The SfM poses' own error, where the sfm stage stated it (each view's
    ``pose_factor``), is each view's ``sfm_factor`` beside its Jacobian: its model's views share it."""
    models: dict[str, dict] = {}
    views: dict[str, dict] = {}
    for ve in out_views:
        name = ve["name"]
        if name in placed and name not in resected:
            label, res, sv = placed[name]
            M = np.asarray(ve["cam_from_world"], float)
            if np.allclose(M, res.cam_from_world(sv.cam_from_model), rtol=0.0, atol=1e-9):
                F = _sfm_factor(res, sv)
                if label not in models:
                    models[label] = {"covariance": None if res.covariance is None else res.covariance.tolist(),
                                     "translation_enu": np.asarray(res.translation, float).tolist(),
                                     "scale": float(res.scale), "sfm_rank": None if F is None else int(F.shape[1]),
                                     # (7, r): the similarity's response to the SfM error z, in each sfm_factor
                                     "sfm_response": None if F is None or res.sfm_sensitivity is None else
                                     np.asarray(res.sfm_sensitivity, float).tolist()}
                C = res.view_covariance(sv.cam_from_model)
                if C is not None and F is not None:  # the similarity's share and the SfM pose's own
                    C = C + F @ F.T
                views[name] = {"source": "similarity", "model": label,
                               "jacobian": res.view_jacobian(sv.cam_from_model).tolist(),
                               "sfm_factor": None if F is None else F.tolist(),
                               "sfm_intrinsics_factor": None if F is None or sv.intrinsics_factor is None else
                               {"params": list(sv.intrinsics_params),
                                "factor": np.asarray(sv.intrinsics_factor, float).tolist()},
                               "covariance_rotation_centre": None if C is None else C.tolist()}
                continue
        u = uncertainty.get(name) or {}
        if u.get("joint") is not None:  # the shared camera's adjustment replaced its pose and intrinsics (a photo
            # placed by its model or on its own): their joint error, not the pose's it replaced
            _group_view(models, views, name, u["joint"], "camera_adjustment")
            continue
        if name in placed and name not in resected:
            if u.get("cov_centre_enu_m2") is not None and u.get("sigma_rotation_deg") is not None:
                C = np.zeros((6, 6))
                C[:3, :3] = np.radians(float(u["sigma_rotation_deg"])) ** 2 * np.eye(3)
                C[3:, 3:] = np.asarray(u["cov_centre_enu_m2"], float)
                views[name] = {"source": "camera_adjustment", "model": None, "jacobian": None,
                               "covariance_rotation_centre": C.tolist()}
                continue
        C = resected[name].get("covariance") if name in resected else None
        j = resected[name].get("joint") if name in resected else None
        if j is not None:  # its focal refined, or its SfM camera's error carried: a group (resection.py)
            _group_view(models, views, name, j, "resection")
            continue
        views[name] = {"source": "resection" if name in resected else "other", "model": None, "jacobian": None,
                       "covariance_rotation_centre": None if C is None else np.asarray(C, float).tolist()}
    return {"parametrisation": POSE_PARAMETRISATION,
            "not_included": ("the SfM poses' own error relative to one another (the reconstruction states none)"
                             if any(m.get("sfm_rank") is None for m in models.values()) else
                             "the SfM intrinsics' error beyond its first-order effect on the poses"
                             if any(v.get("model") and v.get("sfm_intrinsics_factor") is None for v in views.values())
                             else "the SfM error beyond first order")
            + "; a photo placed on its own (resection): the correlation of its error with the placed models' and "
              "the camera adjustment's through the control points and the SfM camera they share (with the other "
              "photos placed on their own it is carried: the same points' survey errors, the same camera's error)",
            "models": models, "views": views}


def _no_placement_error(p: _Placement, models, resect_reasons: dict[str, str], where: str) -> InputError:
    if len(models) == 1 and p.main_error is not None and not resect_reasons:
        return p.main_error
    return InputError(f"{where}: no SfM model could be placed in the scene: "
                      + "; ".join(f"{r['model']} ({len(r['views'])} photos): {r['reason']}" for r in p.reports)
                      + ("; and no photo could be placed on its own: "
                         + "; ".join(f"{n}: {why}" for n, why in sorted(resect_reasons.items()))
                         if resect_reasons else ""))


def _incident_photos(project: Project, rec: Reconstruction) -> IncidentPhotos:
    """The run's photos (none when the incident has no photo files) as :func:`resect_unplaced` needs them."""
    try:
        photo_paths = {p.name: p for p in project.photo_paths()}
    except InputError:
        photo_paths = {}

    def size_of(name: str) -> tuple[int, int] | None:
        if name not in photo_paths:
            return None
        with Image.open(photo_paths[name]) as im:
            return im.size

    def image_of(name: str) -> str:
        return (rec.image_of(name)
                or (project.relative(photo_paths[name]) if name in photo_paths else name))

    return IncidentPhotos(frozenset(photo_paths), bool(rec.doc.get("stats", {}).get("single_camera", True)), size_of,
                          image_of)


def _resect_and_adjust(photos: IncidentPhotos | None, models, p: _Placement, cps: list[ControlPoint], gps: dict,
                       images: dict[str, str], src: str, opts: GeorefOptions, where: str):
    """Photos in no placed model resected (``photos``: None when there is no resection), the shared cameras
    adjusted, and the photos still unplaced tried again with the refined camera: (resected, why not resected,
    views, uncertainty, adjustments)."""
    resected: dict[str, dict] = {}  # photo -> {"entry": view entry, "report": ...}
    resect_reasons: dict[str, str] = {}
    if photos is not None:
        resected, resect_reasons = resect_unplaced(photos, models, p.placed, cps, gps, opts, where)
    if not p.placed and not resected:
        raise _no_placement_error(p, models, resect_reasons, where)
    out_views = _views_out(p.placed, resected, images, src)
    uncertainty, adjustments, refined = adjust_cameras(models, p.placed, resected, out_views, cps, opts)
    if refined and photos is not None:  # photos still unplaced, tried again with the refined camera
        more, more_why = resect_unplaced(photos, models, {**p.placed, **resected}, cps, gps, opts, where,
                                         refined=refined)
        if more:
            resected.update(more)
            for n in more:
                resect_reasons.pop(n, None)
            for n, why in more_why.items():
                if n in resect_reasons:
                    resect_reasons[n] = f"{resect_reasons[n]}; with the refined camera: {why}"
            out_views = _views_out(p.placed, resected, images, src)
            uncertainty, adjustments, refined = adjust_cameras(models, p.placed, resected, out_views, cps, opts)
            for a in adjustments:
                a["second_pass"] = True
    for n, r in resected.items():  # the stated uncertainty beside the resection's own check
        if n in uncertainty:
            r["report"]["sigma_centre_stated_m"] = uncertainty[n].get("sigma_centre_m")
    return resected, resect_reasons, out_views, uncertainty, adjustments


def _unregistered(rdoc: dict, reports: list[dict], done: set[str], resect_reasons: dict[str, str]) -> list[dict]:
    """Every photo of the set not placed, with every reason: SfM's, its model's, its rejection, its resection."""
    unreg = [{"name": u["name"], "reason": u.get("reason", "")} for u in rdoc.get("unregistered", [])
             if u.get("name") not in done]
    for r in reports:
        if r["status"] == "unregistered":
            for n in r["views"]:
                if n not in done and not any(u["name"] == n for u in unreg):
                    unreg.append({"name": n,
                                  "reason": f"in SfM {r['model']}, which could not be placed: {r['reason']}"})
    for r in reports:
        for n, why in r.get("rejected_views", {}).items():
            if n not in done and not any(u["name"] == n for u in unreg):
                unreg.append({"name": n, "reason": f"left out of SfM {r['model']}: {why}"})
    for u in unreg:
        for r in reports:
            why = r.get("rejected_views", {}).get(u["name"])
            if why is not None and not u["reason"].startswith("left out of"):
                u["reason"] = f"{u['reason']}; left out of SfM {r['model']}: {why}"
        m = next((r for r in reports if u["name"] in r["views"] and r["status"] == "unregistered"), None)
        if m is not None and not u["reason"].startswith("in SfM"):
            u["reason"] = f"{u['reason']}; that model could not be placed: {m['reason']}"
        if u["name"] in resect_reasons:
            u["reason"] = f"{u['reason']}; not placed on its own either: {resect_reasons[u['name']]}"
    return unreg


def _resected_only_doc(project: Project, rec_path: Path, src: str, resected: dict, reports: list,
                       unreg: list) -> tuple[dict, dict]:
    """cameras.json when no SfM model could be placed but some photos were, each on its own."""
    views = [r["entry"] for _, r in sorted(resected.items())]
    reps = [r["report"] for _, r in sorted(resected.items())]
    px = [r["rms_px"] for r in reps if r.get("rms_px") is not None]
    block = {"method": "control_points", "model": None, "world_from_model": None,
             "rms_px": float(np.sqrt(np.mean(np.square(px)))) if px else None,
             "reconstruction": project.relative(rec_path), "control_points": CONTROL_POINTS_FILE,
             "models": [{k: v for k, v in r.items()} for r in reports], "n_views_placed": len(views),
             "unregistered": unreg, "resected": reps, "residuals": [], "warnings": []}
    doc = {"route": "multiview", "intrinsics_source": src, "georegistration": block, "views": views, "panorama": None}
    stats = {"model": None, "n_views_placed": len(views), "rms_px": block["rms_px"],
             "models": [{k: v for k, v in r.items() if k not in ("residuals", "world_from_model")} for r in reports],
             "resected": [{k: v for k, v in r.items() if k != "residuals"} for r in reps], "unregistered": unreg}
    return doc, stats


def _placed_doc(project: Project, rec_path: Path, rdoc: dict, src: str, p: _Placement, cps: list[ControlPoint],
                resected: dict, out_views: list[dict], unreg: list[dict], uncertainty: dict, adjustments: list,
                n_done: int) -> tuple[dict, dict]:
    """cameras.json and the stage statistics when an SfM model was placed (the main one, else the largest)."""
    res0 = p.main_res or p.first_res
    block_label = ("main" if p.main_res is not None
                   else next(r["model"] for r in p.reports if r["status"] == "georegistered"))
    block = georeg_block("control_points" if cps else "gps", res0,
                         {"world_from_model": res0.matrix.tolist(), "model": block_label,
                          "reconstruction": project.relative(rec_path),
                          "models": [{k: v for k, v in r.items() if k != "residuals"} | (
                              {"residuals": r["residuals"]} if r["model"] != block_label and "residuals" in r else {})
                              for r in p.reports],
                          "n_views_placed": n_done, "unregistered": unreg,
                          "resected": [r["report"] for _, r in sorted(resected.items())],
                          "view_uncertainty": _for_reading(uncertainty), "camera_adjustment": adjustments,
                          "pose_uncertainty": _pose_uncertainty(p.placed, resected, out_views, uncertainty)})
    if p.main_res is None:
        block["main_model_error"] = str(p.main_error)
    doc = {"route": "multiview", "intrinsics_source": src, "georegistration": block, "views": out_views,
           "panorama": None}
    n_sfm = len(rdoc["images"]) + len(rdoc.get("unregistered", []))
    stats = {**dict(res0.stats), "world_from_model": res0.matrix.tolist(), "model": block_label,
             "n_views_placed": n_done, "n_photos": n_sfm,
             "resected": [{k: v for k, v in r["report"].items() if k != "residuals"}
                          for _, r in sorted(resected.items())],
             "models": [{k: v for k, v in r.items() if k not in ("residuals", "world_from_model")}
                        for r in p.reports],
             "unregistered": unreg, "view_uncertainty": _for_reading(uncertainty), "camera_adjustment": adjustments}
    return doc, stats


def multiview_route(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    """(cameras.json document, stage statistics) of the multi-view route (module docstring)."""
    rec_path = project.require_output(project.reconstruction_path, "sfm", "multiview route",
                                      f" (or write a {CAMERAS_FILE} by hand)")
    rec = read_reconstruction(rec_path)
    models, rdoc = [(label, list(vs)) for label, vs in rec.models], rec.doc
    cp_path = project.control_points_path
    cps = control_points_of_photos(project, cp_path) if cp_path.is_file() else []
    photos = photos_by_name(project)
    all_views = {v.name: v for _, vs in models for v in vs}
    gps = {n: g for n, v in all_views.items() if (g := gps_enu(project, photos.get(n))) is not None}
    if cps:  # a pick outside its photo is bad input, whichever model the photo is in
        picks_in_views(cps, list(all_views.values()), where)
    src = str(rdoc.get("intrinsics_source", "sfm"))
    images = {s["name"]: s.get("image", "") for s in rdoc["images"]}
    for m in rdoc.get("models", []):
        for s_ in m.get("images", []):
            images.setdefault(s_["name"], s_.get("image", ""))
    p = _place_models(models, cps, gps, opts, where)
    photos_to_resect = _incident_photos(project, rec) if opts.resect_unplaced and cps else None
    resected, resect_reasons, out_views, uncertainty, adjustments = _resect_and_adjust(
        photos_to_resect, models, p, cps, gps, images, src, opts, where)
    done = set(p.placed) | set(resected)
    unreg = _unregistered(rdoc, p.reports, done, resect_reasons)
    if p.main_res is None and p.first_res is None:  # only resected photos
        doc, stats = _resected_only_doc(project, rec_path, src, resected, p.reports, unreg)
        doc["views"] = out_views
        doc["georegistration"].update({"view_uncertainty": _for_reading(uncertainty), "camera_adjustment": adjustments,
                                       "pose_uncertainty": _pose_uncertainty(p.placed, resected, out_views,
                                                                             uncertainty)})
        if p.main_error is not None:
            doc["georegistration"]["main_model_error"] = str(p.main_error)
        stats.update({"view_uncertainty": _for_reading(uncertainty), "camera_adjustment": adjustments})
        return doc, stats
    return _placed_doc(project, rec_path, rdoc, src, p, cps, resected, out_views, unreg, uncertainty, adjustments,
                       len(done))
