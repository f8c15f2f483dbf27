"""The ``georef`` stage: every view in the scene frame, written to ``out/georef/cameras.json`` (docs/pipeline.md).

Routes (``route`` in cameras.json):

* **known**: the incident has a hand-written ``cameras.json``; it is validated and copied as it is (and, when
  ``control_points.json`` exists, the control points are checked against it).
* **panorama**: ``out/stitch/panorama.json`` (the stitch stage's panorama model: its sources' intrinsics and
  ``cam_from_pano``) is placed in the scene by ``world_from_pano`` from the control points
  (:func:`~workbench.georef.solvers.solve_central`), with ``camera.position_enu`` or EXIF GPS as a prior.
* **multiview** (``camera.source = "sfm"``): ``out/sfm/reconstruction.json`` (cameras in the SfM model frame)
  is mapped by a similarity ``world_from_model`` fitted to the control points and to the photos' GPS
  (:func:`~workbench.georef.solvers.solve_similarity`).
* **single** (one photo): PnP + refinement from the control points, intrinsics from the camera profile
  (``calibrated``) or the EXIF focal (``exif``).

Control-point residuals (pixels and metres, per point and per photo) go to ``out/georef/stats.json`` and into
``cameras.json``'s ``georegistration``; large ones are warned about (:class:`GeorefResidualsLarge`).
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import skew
from ..core.layout import CAMERAS_FILE
from ..errors import InputError, StageError
from ..project import Project
from ..core.stage_api import Progress, StageResult
from .control_points import CONTROL_POINTS_FILE, ControlPoint, load_control_points
from .gps import read_gps
from .solvers import (GeorefOptions, GeorefResidualsLarge, RigView, SfmView, refine_resection_focal, solve_central,
                      solve_similarity)

log = logging.getLogger(__name__)

__all__ = ["run_georef", "read_panorama_model", "read_reconstruction", "validate_cameras_doc"]

PANORAMA_KEY = "panorama"  # pixel key of a pick made in the stitched panorama image


# ----------------------------------------------------------------------------------------------------------
# Reading the upstream files
# ----------------------------------------------------------------------------------------------------------
def _matrix(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    from ..core.io import matrix_from_json

    return matrix_from_json(value, shape, where)


def _rotation(R: np.ndarray, where: str) -> np.ndarray:
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise InputError(f"{where}: not a rotation (orthonormal with determinant +1)")
    return R


def _intrinsics(d: Any, where: str) -> CameraIntrinsics:
    if not isinstance(d, dict):
        raise InputError(f"{where}: needs an 'intrinsics' object (camera_profile.json model)")
    try:
        return CameraIntrinsics.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def read_panorama_model(project: Project, path: Path) -> tuple[list[RigView], dict]:
    """The sources of a panorama model (``out/stitch/panorama.json``) as rig views, and the document."""
    doc = project.read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("sources"), list) or not doc["sources"]:
        raise StageError(f"{path}: no 'sources' list; run the stitch stage again")
    views = []
    for i, s in enumerate(doc["sources"]):
        where = f"{path}: sources[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{where}: needs 'name'")
        intr = _intrinsics(s.get("intrinsics"), f"{where}.intrinsics")
        R = _rotation(_matrix(s.get("cam_from_pano"), (3, 3), f"{where}.cam_from_pano"), f"{where}.cam_from_pano")
        views.append(RigView(s["name"], intr, R))
    return views, doc


def _sfm_views(images: Any, where: str) -> list[SfmView]:
    if not isinstance(images, list) or not images:
        raise StageError(f"{where}: no 'images' list; run the sfm stage again")
    views = []
    for i, s in enumerate(images):
        w = f"{where}[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{w}: needs 'name'")
        intr = _intrinsics(s.get("intrinsics"), f"{w}.intrinsics")
        M = _matrix(s.get("cam_from_model"), (4, 4), f"{w}.cam_from_model")
        _rotation(M[:3, :3], f"{w}.cam_from_model")
        views.append(SfmView(s["name"], intr, M))
    return views


def read_reconstruction(project: Project, path: Path) -> tuple[list[SfmView], dict]:
    """The images of an SfM reconstruction's main model (``out/sfm/reconstruction.json``) and the document."""
    doc = project.read_json(path)
    if not isinstance(doc, dict):
        raise StageError(f"{path}: not a reconstruction; run the sfm stage again")
    return _sfm_views(doc.get("images"), f"{path}: images"), doc


def read_reconstruction_models(project: Project, path: Path) -> tuple[list[tuple[str, list[SfmView]]], dict]:
    """Every model of an SfM reconstruction, each in its own frame: ``[("main", views), ("models[0]", views),
    ...]`` (the separate models in the file's order, largest first), and the document. A file written before
    separate models were kept has the main model only."""
    views, doc = read_reconstruction(project, path)
    models = doc.get("models", [])
    if not isinstance(models, list):
        raise StageError(f"{path}: 'models' must be a list; run the sfm stage again")
    out = [("main", views)]
    for k, m in enumerate(models):
        if not isinstance(m, dict):
            raise StageError(f"{path}: models[{k}] must be an object; run the sfm stage again")
        out.append((f"models[{k}]", _sfm_views(m.get("images"), f"{path}: models[{k}].images")))
    return out, doc


def validate_cameras_doc(doc: Any, where: str) -> list[dict]:
    """Check a ``cameras.json`` document (docs/pipeline.md); returns its views. Errors name the entry."""
    if not isinstance(doc, dict) or not isinstance(doc.get("views"), list) or not doc["views"]:
        raise InputError(f"{where}: needs a non-empty 'views' list; see docs/pipeline.md (cameras.json)")
    if doc.get("route") not in ("panorama", "multiview", "single"):
        raise InputError(f"{where}: route = {doc.get('route')!r}; give 'panorama', 'multiview' or 'single'")
    names = set()
    for i, v in enumerate(doc["views"]):
        w = f"{where}: views[{i}]"
        if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not v["name"]:
            raise InputError(f"{w}: needs a 'name' (the photo's file name)")
        w = f"{where}: views[{i}] ({v['name']!r})"
        if v["name"] in names:
            raise InputError(f"{w}: the name is used twice")
        names.add(v["name"])
        _intrinsics(v.get("intrinsics"), f"{w}.intrinsics")
        M = _matrix(v.get("cam_from_world"), (4, 4), f"{w}.cam_from_world")
        _rotation(M[:3, :3], f"{w}.cam_from_world")
        if not np.allclose(M[3], [0, 0, 0, 1]):
            raise InputError(f"{w}.cam_from_world: last row must be 0 0 0 1")
        if "center_enu" in v:
            c = _matrix(v["center_enu"], (3,), f"{w}.center_enu") if np.ndim(v["center_enu"]) == 1 else None
            if c is None or np.linalg.norm(c + M[:3, :3].T @ M[:3, 3]) > 1e-3:
                raise InputError(f"{w}.center_enu = {v['center_enu']} disagrees with cam_from_world (its centre is "
                                 f"{(-M[:3, :3].T @ M[:3, 3]).round(4).tolist()}); fix one of them")
    pano = doc.get("panorama")
    if pano is not None:
        if not isinstance(pano, dict):
            raise InputError(f"{where}: 'panorama' must be an object or null")
        if "world_from_pano" in pano:
            _rotation(_matrix(pano["world_from_pano"], (4, 4), f"{where}: panorama.world_from_pano")[:3, :3],
                      f"{where}: panorama.world_from_pano")
    return doc["views"]


def _view_entry(name: str, image: str, intr: CameraIntrinsics, cam_from_world: np.ndarray, focal_known: bool) -> dict:
    M = np.asarray(cam_from_world, float)
    return {"name": name, "image": image, "intrinsics": intr.to_dict(), "focal_known": bool(focal_known),
            "cam_from_world": M.tolist(), "center_enu": (-M[:3, :3].T @ M[:3, 3]).tolist()}


def _photo_by_name(project: Project) -> dict[str, Path]:
    out = {}
    photos_root = project.root / "photos"
    if photos_root.is_dir():  # every photo set, following linked folders (Path.rglob does not)
        for folder, _dirs, files in sorted(os.walk(photos_root, followlinks=True)):
            for f in sorted(files):
                out.setdefault(f, Path(folder) / f)
    try:
        for p in project.photo_paths():
            out[p.name] = p
    except InputError:
        pass
    return out


def _gps_enu(project: Project, path: Path | None) -> np.ndarray | None:
    if path is None or not path.is_file():
        return None
    g = read_gps(path)
    if g is None:
        return None
    lon, lat, alt = g
    enu = project.frame.enu_from_wgs84(np.array([lon, lat, alt if alt is not None else project.frame.height_m]))
    return enu


def _load_cps(project: Project) -> list[ControlPoint]:
    path = project.control_points_path
    if not path.is_file():
        raise InputError(f"{path}: not found; georegistration needs control points (landmarks with known "
                         f"coordinates picked in the photos, docs/gis.md) or a hand-written {CAMERAS_FILE}")
    return _control_points_of_photos(project, path)


def _unknown_photo(project: Project, name: str, where: str, what: str) -> InputError:
    known = sorted(_photo_by_name(project))
    listed = ", ".join(known[:8]) + (f" and {len(known) - 8} more" if len(known) > 8 else "")
    return InputError(f"{where}: {what} {name!r} is not a photo of this incident (under {project.root / 'photos'}: "
                      f"{listed}); give the photo's file name, or put the photo there")


def _control_points_of_photos(project: Project, path: Path) -> list[ControlPoint]:
    """The control points of ``path``; a pixel keyed by a photo the incident does not have is an error naming the
    point (a renamed or missing photo would otherwise just leave the point out)."""
    cps = load_control_points(path, project.frame)
    photos = _photo_by_name(project)
    if photos:
        for cp in cps:
            for name in cp.pixels:
                if name != PANORAMA_KEY and name not in photos:
                    raise _unknown_photo(project, name, f"{path}: point {cp.name!r}", "pixels of photo")
    return cps


# ----------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------
def run_georef(project: Project, progress: Progress, opts: GeorefOptions = GeorefOptions()) -> StageResult:
    route = project.georef_route()
    out_dir = project.stage_dir("georef")
    cp_path = project.control_points_path
    where = str(cp_path)
    stats: dict[str, Any] = {"route": route}
    progress(0.05, route)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GeorefResidualsLarge)
        if route == "known":
            doc, extra = _known(project, opts)
        elif route == "panorama":
            doc, extra = _panorama(project, opts, where)
        elif route == "multiview":
            doc, extra = _multiview(project, opts, where)
        else:
            doc, extra = _single(project, opts, where)
    stats.update(extra)
    stats["warnings"] = [str(w.message) for w in caught if issubclass(w.category, GeorefResidualsLarge)]
    progress(0.9, "writing cameras.json")
    path = project.write_json(out_dir / CAMERAS_FILE, doc)
    return StageResult(outputs={"cameras": path}, stats=stats)


def _georeg_block(method: str, res, extra: dict | None = None) -> dict:
    s = res.stats
    block = {"method": method, "rms_m": s.get("rms_m"), "rms_px": s.get("rms_px"), "max_m": s.get("max_m"),
             "max_px": s.get("max_px"), "n_points": s.get("n_points"), "n_observations": s.get("n_observations"),
             "n_outliers": s.get("n_outliers"), "control_points": CONTROL_POINTS_FILE,
             "residuals": res.residuals, "warnings": res.warnings}
    for k in ("sigma_centre_m", "sigma_rotation_deg", "covariance_world_rotation_centre", "prior",
              "centre_minus_prior_m", "scale", "n_triangulated",
              "n_gps_centres", "gps_residuals_m", "gps_rms_m"):
        if k in s:
            block[k] = s[k]
    block.update(extra or {})
    return block


def _short_stats(res) -> dict:
    return {k: v for k, v in res.stats.items()}


def _known(project: Project, opts: GeorefOptions) -> tuple[dict, dict]:
    path = project.root / CAMERAS_FILE
    doc = project.read_json(path)
    views = validate_cameras_doc(doc, str(path))
    photos = _photo_by_name(project)
    for i, v in enumerate(views):  # an incident without photo files (hand-written, solved from picks) is allowed
        if photos and v["name"] not in photos:
            raise _unknown_photo(project, v["name"], f"{path}: views[{i}].name", "view")
    extra: dict[str, Any] = {"n_views": len(views), "source": project.relative(path)}
    cp_path = project.control_points_path
    if cp_path.is_file():  # check the known cameras against the control points
        cps = _control_points_of_photos(project, cp_path)
        resid = []
        for v in views:
            intr = CameraIntrinsics.from_dict(v["intrinsics"])
            M = np.asarray(v["cam_from_world"], float)
            for cp in cps:
                uv = cp.pixels.get(v["name"])
                if uv is None:
                    continue
                q = M[:3, :3] @ cp.enu + M[:3, 3]
                e = float(np.hypot(*(intr.project(q[None])[0] - uv))) if q[2] > 0 else None
                resid.append({"point": cp.name, "view": v["name"], "error_px": e})
        px = np.array([r["error_px"] for r in resid if r["error_px"] is not None])
        extra["control_point_check"] = {"n_observations": len(resid),
                                        "rms_px": float(np.sqrt(np.mean(px ** 2))) if px.size else None,
                                        "max_px": float(px.max()) if px.size else None, "residuals": resid}
        if px.size and float(np.sqrt(np.mean(px ** 2))) > opts.warn_rms_px:
            msg = (f"{path}: the known cameras disagree with {cp_path.name} by {np.sqrt(np.mean(px ** 2)):.1f} px "
                   f"RMS; check the cameras or the control points")
            log.warning(msg)
            warnings.warn(msg, GeorefResidualsLarge, stacklevel=2)
    return doc, extra


def _prior(project: Project, photo_paths: list[Path | None], opts: GeorefOptions) -> tuple[np.ndarray | None, Any, str]:
    pos = project.settings.camera.position_enu
    if pos is not None:
        return np.asarray(pos, float), opts.prior_sigma_m, "camera.position_enu"
    gps = [g for g in (_gps_enu(project, p) for p in photo_paths) if g is not None]
    if gps:
        return np.mean(gps, axis=0), np.asarray(opts.gps_sigma_m, float), "exif_gps"
    return None, None, "none"


def _panorama(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    pano_path = project.panorama_model_path
    if not pano_path.is_file():
        raise StageError(f"{pano_path}: not found; the panorama route needs the stitch stage's panorama model: run "
                         f"`workbench run {project.root} --only stitch` first (or write a {CAMERAS_FILE} by hand)")
    views, pdoc = read_panorama_model(project, pano_path)
    cps = _panorama_pixels_to_sources(_load_cps(project), pdoc, pano_path, where)
    photos = _photo_by_name(project)
    prior, prior_sigma, prior_src = _prior(project, [photos.get(v.name) for v in views], opts)
    res = solve_central(views, cps, prior_centre=prior, prior_sigma_m=prior_sigma, opts=opts, where=where)
    src = str(pdoc.get("intrinsics_source", project.settings.camera.source.value))
    focal_known = src in ("calibrated", "sfm")
    images = {s["name"]: s.get("image", "") for s in pdoc["sources"]}
    out_views = [_view_entry(v.name, images.get(v.name) or (project.relative(photos[v.name]) if v.name in photos
                                                            else v.name),
                             v.intrinsics, res.cam_from_world(v.cam_from_rig), focal_known) for v in views]
    pano_image = project.stage_dir("stitch") / "panorama.jpg"
    doc = {"route": "panorama", "intrinsics_source": src,
           "georegistration": _georeg_block("control_points", res, {"prior_source": prior_src}),
           "views": out_views,
           "panorama": {"model": project.relative(pano_path), "image": project.relative(pano_image),
                        "world_from_pano": res.world_from_rig.tolist()}}
    return doc, {**_short_stats(res), "prior_source": prior_src, "centre_enu": res.centre_enu.tolist()}


def _panorama_pixels_to_sources(cps: list[ControlPoint], pdoc: dict, pano_path: Path,
                                where: str) -> list[ControlPoint]:
    """Picks made in the stitched panorama (pixel key ``"panorama"``) mapped exactly into the source photo."""
    from dataclasses import replace

    if not any(PANORAMA_KEY in cp.pixels for cp in cps):
        return cps
    try:
        from ..core.panorama import PanoramaModel

        model = PanoramaModel.from_dict(pdoc)
    except (ImportError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{where}: has picks in the panorama image, but {pano_path} cannot be read as a panorama "
                         f"model ({exc}); pick the points in the source photos instead") from None
    out = []
    for cp in cps:
        if PANORAMA_KEY not in cp.pixels:
            out.append(cp)
            continue
        pix = dict(cp.pixels)
        uv = pix.pop(PANORAMA_KEY)
        idx, uv_src = model.to_source(np.asarray(uv, float)[None])
        if idx[0] < 0:
            raise InputError(f"{where}: control point {cp.name!r}: panorama pixel {list(map(float, uv))} is outside "
                             f"every source photo (the panorama is {model.width}x{model.height}); fix the pick")
        pix.setdefault(model.sources[int(idx[0])].name, uv_src[0])
        out.append(replace(cp, pixels=pix))
    return out


def _rot_deg(A: np.ndarray, B: np.ndarray) -> float:
    c = (np.trace(np.asarray(A)[:3, :3] @ np.asarray(B)[:3, :3].T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _separate_model_verdict(res, views: list[SfmView], opts: GeorefOptions) -> tuple[str | None, dict]:
    """Why a separate SfM model's similarity cannot be trusted (None: it can), and the figures checked.

    A surveyor's test: enough of the model's own control points triangulated in it and fitting, spread out (not
    on a line), small residuals, and the fit fixing every camera centre to ``model_max_sigma_centre_m``."""
    by_point: dict[str, list[dict]] = {}
    for r in res.residuals:
        by_point.setdefault(r["point"], []).append(r)
    good = [name for name, X in res.triangulated.items()
            if by_point.get(name) and all(r["inlier"] for r in by_point[name])]
    X = np.array([res.apply(res.triangulated[n]) for n in good]).reshape(-1, 3)
    spread = float(np.linalg.svd(X - X.mean(axis=0), compute_uv=False)[1] / np.sqrt(len(X))) if len(X) >= 3 else 0.0
    n_obs = len(res.residuals)
    n_out = sum(1 for r in res.residuals if not r["inlier"])
    sig = [res.centre_sigma_m(v.cam_from_model) for v in views]
    sig_max = None if any(x is None for x in sig) else float(max(sig))
    finite = [r["error_px"] for r in res.residuals if r["error_px"] is not None]
    rms_all = float(np.sqrt(np.mean(np.square(finite)))) if finite else None
    figures = {"n_fitting_triangulated": len(good), "spread_m": spread, "n_observations": n_obs,
               "n_outliers": n_out, "rms_px": res.stats.get("rms_px"), "rms_all_px": rms_all,
               "sigma_centre_max_m": sig_max}
    if len(good) < opts.model_min_points and len(res.triangulated) >= opts.model_min_points:
        # the points are there (picked in two or more photos, their rays meet): the model disagrees with them
        behind = n_obs - len(finite)
        return (f"control-point RMS residual {'-' if rms_all is None else f'{rms_all:.1f}'} px over its {n_obs} "
                f"picks ({n_out} beyond {opts.ransac_threshold_px:g} px"
                + (f", {behind} behind the camera" if behind else "")
                + f"): of the {len(res.triangulated)} control points triangulated in it, {len(good)} fit it "
                f"({opts.model_min_points} are needed): the model or its camera (focal) disagrees with the control "
                f"points"), figures
    if len(good) < opts.model_min_points:
        return (f"{len(good)} control point(s) triangulated in this model fit it (all picks within "
                f"{opts.ransac_threshold_px:g} px); {opts.model_min_points} are needed: pick more control points in "
                f"two or more of its photos ({', '.join(v.name for v in views)})"), figures
    if spread < opts.model_min_spread_m:
        return (f"its {len(good)} fitting control points lie {spread:.2f} m (RMS) from one line; "
                f"{opts.model_min_spread_m:g} m is needed to fix the rotation: add a point off that line"), figures
    if res.stats.get("rms_px") is None or res.stats["rms_px"] > opts.warn_rms_px:
        return (f"control-point RMS residual {res.stats.get('rms_px')} px exceeds {opts.warn_rms_px:g} px: the "
                f"model or a point is wrong"), figures
    if n_out > opts.model_max_outlier_fraction * n_obs:
        return (f"{n_out} of {n_obs} control-point picks are outliers (more than "
                f"{100 * opts.model_max_outlier_fraction:.0f} %): the model or the points disagree"), figures
    if sig_max is None or sig_max > opts.model_max_sigma_centre_m:
        return (f"the control points fix its cameras only to {sig_max if sig_max is None else round(sig_max, 2)} m "
                f"(1-sigma; {opts.model_max_sigma_centre_m:g} m allowed): add control points spread over its "
                f"photos"), figures
    return None, figures


def _cov_report(C: np.ndarray) -> dict:
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    return {"sigma_centre_m": float(np.sqrt(max(np.linalg.eigvalsh(C).max(), 0.0))),
            "sigma_centre_enu_m": np.sqrt(np.clip(np.diag(C), 0.0, None)).tolist(), "cov_centre_enu_m2": C.tolist()}


def _camera_adjustment(models, placed: dict, resected: dict, out_views: list[dict], cps: list[ControlPoint],
                       opts: GeorefOptions) -> tuple[dict, list, dict]:
    """Every placed photo's stated uncertainty, and the shared camera's intrinsics refined from the picks.

    Photos that share one SfM camera (identical SfM intrinsics) and have ``resect_min_points`` fitting picks are
    adjusted together (:func:`~workbench.georef.solvers.adjust_shared_camera`): focal, principal point and k1
    free (loose prior at SfM's values), every photo's pose free. Its covariance (times the variance factor: the
    reduced chi-square when above 1, or with ``variance_factor_min_dof`` degrees of freedom) is each such photo's
    stated uncertainty: it counts the picks' noise, the residual
    scatter and the intrinsics' uncertainty. The refined intrinsics (the parameter set with the lowest
    two-fold cross-validated residual of held-out picks) replace SfM's, and the photos take their adjusted
    poses, only when that residual is lower than with SfM's intrinsics kept, which is scored on the poses it
    keeps: the photos' poses as placed (by their model's similarity, or their resection refitted on held-out
    halves; ``held_out_rms_px``: ``sfm``, beside ``sfm_poses_refit``, every pose refitted). A photo placed by its model with
    too few picks to be adjusted states the similarity's covariance plus the scatter of its model's
    adjusted photos about their model poses (the SfM model's own error). ``out_views`` is updated in place."""
    from .solvers import INTRINSIC_SETS, adjust_shared_camera, held_out_errors, held_out_picks, robust_rms

    by_name = {v["name"]: v for v in out_views}
    sfm_intr: dict[str, CameraIntrinsics] = {}
    for _, vs in models:
        for v in vs:
            sfm_intr.setdefault(v.name, v.intrinsics)
    main_cam = models[0][1][0].intrinsics if models and models[0][1] else None
    groups: dict[str, list[str]] = {}
    base_of: dict[str, CameraIntrinsics] = {}
    for name in by_name:
        it = sfm_intr.get(name) or main_cam
        if it is None:
            continue
        key = _intr_key(it)
        groups.setdefault(key, []).append(name)
        base_of[key] = it
    uncertainty: dict[str, dict] = {}
    adjustments: list[dict] = []
    adjusted_centres: dict[str, np.ndarray] = {}  # photo -> centre from the intrinsics-free adjustment
    refined: dict[str, CameraIntrinsics] = {}  # SfM camera (key) -> its refined intrinsics
    for key, names in (groups.items() if opts.adjust_camera else ()):
        base = base_of[key]
        poses, fit = {}, []
        for n in sorted(names):
            v = by_name[n]
            M = np.asarray(v["cam_from_world"], float)
            it = CameraIntrinsics.from_dict(v["intrinsics"])
            ok = []
            for cp in cps:
                uv = cp.pixels.get(n)
                if uv is None:
                    continue
                q = M[:3, :3] @ cp.enu + M[:3, 3]
                if q[2] > 0 and np.hypot(*(it.project(q[None])[0] - uv)) < opts.ransac_threshold_px:
                    ok.append(cp.name)
            if len(ok) >= opts.resect_min_points:
                poses[n] = M
                fit.extend((p, n) for p in ok)
        n_par = 4 + 6 * len(poses)
        if not poses or 2 * len(fit) < n_par + 4:
            continue
        use = set(fit)
        cps_use = [cp for cp in cps]
        report: dict[str, Any] = {"photos": sorted(poses), "n_observations": len(fit),
                                  "sfm_intrinsics": {"f": base.fx, "cx": base.cx, "cy": base.cy, "k1": base.k1}}
        try:
            free_adj = adjust_shared_camera(base, poses, cps_use, opts, free=INTRINSIC_SETS["f_pp_k1"], use=use)
            picks_use = _only(cps_use, use)
            cv = {"sfm_poses_refit": held_out_errors(base, poses, picks_use, opts, ())}
            for lbl, fr in INTRINSIC_SETS.items():
                cv[lbl] = held_out_errors(base, poses, picks_use, opts, fr)
        except (ValueError, np.linalg.LinAlgError) as exc:
            report["error"] = str(exc)
            adjustments.append(report)
            continue
        # "sfm" (SfM's camera kept) keeps the photos' poses as placed, so it is scored on those poses: a photo
        # placed by its SfM model by its picks' errors under the model pose (the similarity's 7 parameters are
        # fitted to all the model's picks, so these are nearly held out: inflated by sqrt(m / (m - 7)), m the
        # fit's residuals); a resected photo (its pose fitted to these very picks) by its pose refitted on
        # held-out halves. Scoring "sfm" by poses refitted to each photo's own picks would compare the
        # alternatives with poses "sfm" does not deliver: an exact SfM model lost to a refined focal on noise,
        # and its photos took poses from their few own picks (a 5-pick photo 0.14 m and 0.25 deg off where
        # its model pose was within 0.01 m).
        hp = held_out_picks(poses, picks_use)
        cps_by = {cp.name: cp for cp in cps_use}
        as_placed = {}
        for n, names_ in hp.items():
            if n in placed and n not in resected:
                label, res_m, _ = placed[n]
                M = poses[n]
                X = np.array([cps_by[p].enu for p in names_])
                q = X @ M[:3, :3].T + M[:3, 3]
                uv = np.array([cps_by[p].pixels[n] for p in names_], float)
                e = np.full(len(names_), np.inf)
                front = q[:, 2] > 1e-6
                e[front] = np.hypot(*(base.project(q[front]) - uv[front]).T)
                m = 2 * int(res_m.stats.get("n_observations") or 0)
                as_placed[n] = e * (math.sqrt(m / (m - 7)) if m > 14 else 1.0)
            else:
                as_placed[n] = cv["sfm_poses_refit"][n]
        cv = {"sfm": as_placed, **cv}
        ho = {k: (robust_rms(np.concatenate(list(v.values())), opts) if v else None) for k, v in cv.items()}
        report.update({"free_intrinsics": {k: free_adj["values"][k] for k in ("f", "cx", "cy", "k1")},
                       "sigma_intrinsics": free_adj["sigma_intrinsics"], "condition": free_adj["condition"],
                       "chi2_red": free_adj["chi2_red"], "dof": free_adj["dof"],
                       "variance_factor": free_adj["variance_factor"], "rms_px": free_adj["rms_px"],
                       "held_out_rms_px": ho, "n_held_out": int(sum(len(v) for v in as_placed.values()))})
        scored = {k: v for k, v in ho.items() if v is not None and k != "sfm_poses_refit"}
        best = min(scored, key=scored.get) if "sfm" in scored else "sfm"
        report["chosen"] = best
        chosen = free_adj
        if best != "sfm":
            chosen = (free_adj if best == "f_pp_k1"
                      else adjust_shared_camera(base, poses, cps_use, opts, free=INTRINSIC_SETS[best], use=use))
            report["refined_intrinsics"] = chosen["intrinsics"].to_dict()
            refined[key] = chosen["intrinsics"]
            report["sigma_refined"] = chosen["sigma_intrinsics"]
            for n, M in chosen["poses"].items():
                by_name[n]["intrinsics"] = chosen["intrinsics"].to_dict()
                by_name[n]["cam_from_world"] = M.tolist()
                by_name[n]["center_enu"] = (-M[:3, :3].T @ M[:3, 3]).tolist()
        for n in poses:
            # the stated uncertainty: the intrinsics-free adjustment's (or the chosen one's, if larger)
            C = free_adj["cov_centre"][n]
            if np.linalg.eigvalsh(chosen["cov_centre"][n]).max() > np.linalg.eigvalsh(C).max():
                C = chosen["cov_centre"][n]
            uncertainty[n] = {**_cov_report(C), "sigma_rotation_deg": max(free_adj["sigma_rot_deg"][n],
                                                                          chosen["sigma_rot_deg"][n]),
                              "from": "joint adjustment of the shared camera (intrinsics free)",
                              "intrinsics": "refined (" + best + ")" if best != "sfm" else "sfm"}
            M = free_adj["poses"][n]
            adjusted_centres[n] = -M[:3, :3].T @ M[:3, 3]
        adjustments.append(report)
    # photos placed by a model but not adjusted: the similarity's covariance plus the model's own scatter
    for n, v in by_name.items():
        if n in uncertainty:
            continue
        if n in placed:
            label, res, sv = placed[n]
            C = np.zeros((3, 3))
            if res.covariance is not None:
                q = res.scale * res.rotation @ (-sv.cam_from_model[:3, :3].T @ sv.cam_from_model[:3, 3])

                Jc = np.hstack([q[:, None], -skew(q), np.eye(3)])
                C = Jc @ res.covariance @ Jc.T
            d2 = []
            for m, c_adj in adjusted_centres.items():
                if m in placed and placed[m][0] == label:
                    A = res.cam_from_world(placed[m][2].cam_from_model)
                    d2.append(float(np.sum((-A[:3, :3].T @ A[:3, 3] - c_adj) ** 2)))
            shape = float(np.mean(d2) / 3.0) if d2 else None
            uncertainty[n] = {**_cov_report(C + (shape or 0.0) * np.eye(3)),
                              "from": "similarity of SfM " + label + (
                                  f" plus its photos' scatter about their adjusted poses ({len(d2)} photos)" if d2 else
                                  " (the SfM model's own error not included: no photo of it could be adjusted)")}
        elif n in resected:
            r = resected[n]["report"]
            uncertainty[n] = {"sigma_centre_m": r.get("sigma_centre_max_m"),
                              "from": "resection (the intrinsics' error not included: too few picks to adjust)"}
    return uncertainty, adjustments, refined


def _intr_key(it: CameraIntrinsics) -> str:
    return repr(sorted(it.to_dict().items()))


def _only(cps: list[ControlPoint], use: set) -> list[ControlPoint]:
    """The control points with only the picks in ``use`` ((point, photo) pairs)."""
    from dataclasses import replace

    out = []
    for cp in cps:
        pix = {ph: uv for ph, uv in cp.pixels.items() if (cp.name, ph) in use}
        if pix:
            out.append(replace(cp, pixels=pix))
    return out


def _resect_unplaced(project: Project, rdoc: dict, models, placed: dict, cps: list[ControlPoint], gps: dict,
                     opts: GeorefOptions, where: str,
                     refined: dict[str, CameraIntrinsics] | None = None) -> tuple[dict[str, dict], dict[str, str]]:
    """Photos of the SfM set in no placed model, each placed on its own from its control points (resection:
    P3P RANSAC + refinement, as the single-photo route), when the fit passes the checks of a separate model.

    Returns (photo -> {"entry": cameras.json view, "report": figures}, photo -> why it was not placed)."""
    from PIL import Image

    try:
        photo_paths = {p.name: p for p in project.photo_paths()}
    except InputError:
        photo_paths = {}
    sfm_intr: dict[str, CameraIntrinsics] = {}
    for _, vs in models:
        for v in vs:
            sfm_intr.setdefault(v.name, v.intrinsics)
    shared = bool(rdoc.get("stats", {}).get("single_camera", True))
    main_cam = models[0][1][0].intrinsics if models and models[0][1] else None
    picks: dict[str, int] = {}
    for cp in cps:
        for k in cp.pixels:
            picks[k] = picks.get(k, 0) + 1
    # the cameras a placed SfM model checked against its control points (its photos' intrinsics)
    checked_cameras = {_intr_key(x[2].intrinsics) for x in placed.values() if isinstance(x, tuple)}
    out, why = {}, {}
    for name in sorted(set(photo_paths) | set(sfm_intr)):
        if name in placed:
            continue
        n = picks.get(name, 0)
        if n < opts.resect_min_points:
            why[name] = (f"{n} control point(s) picked in it; {opts.resect_min_points} are needed to place a photo "
                         f"on its own")
            continue
        intr = sfm_intr.get(name)
        if intr is None:
            size = None
            if name in photo_paths:
                with Image.open(photo_paths[name]) as im:
                    size = im.size
            if not (shared and main_cam is not None and size == (main_cam.width, main_cam.height)):
                why[name] = "no SfM intrinsics for it (not in any model, and the photos do not share one camera)"
                continue
            intr = main_cam
        from_refined = False
        camera_checked = _intr_key(intr) in checked_cameras
        if refined and _intr_key(intr) in refined:  # the shared camera as the joint adjustment refined it
            intr, from_refined = refined[_intr_key(intr)], True
        import warnings as _w

        try:
            with _w.catch_warnings(record=True) as caught:
                _w.simplefilter("always", GeorefResidualsLarge)
                g = gps.get(name)
                res = solve_central([RigView(name, intr, np.eye(3))], cps, prior_centre=g,
                                    prior_sigma_m=None if g is None else np.asarray(opts.gps_sigma_m, float),
                                    opts=opts, where=f"{where} (photo {name} on its own)")
        except InputError as exc:
            why[name] = str(exc)
            continue
        s = res.stats
        n_out = int(s.get("n_outliers") or 0)
        sig = s.get("sigma_centre_m")
        sig_max = float(max(sig)) if sig else None
        rms = s.get("rms_px")
        report = {"name": name, "placed_by": "resection", "n_points": s.get("n_points"),
                  "n_observations": s.get("n_observations"), "n_outliers": n_out, "rms_px": rms,
                  "max_px": s.get("max_px"), "rms_m": s.get("rms_m"), "sigma_centre_max_m": sig_max,
                  "intrinsics_from": ("the shared camera refined from the control points (joint adjustment)"
                                      if from_refined else "sfm" if name in sfm_intr else
                                      "main model's camera (shared)"),
                  "residuals": res.residuals}
        cam_from_world = res.cam_from_world(np.eye(3))
        ff = refine_resection_focal(intr, res, cps, name, opts)
        if ff is not None:
            report["focal_check"] = {"sfm_focal_px": intr.fx, "refined_focal_px": ff["focal_px"],
                                     "sigma_focal_px": ff["sigma_focal_px"], "rms_px": ff["rms_px"]}
            if abs(ff["focal_px"] - intr.fx) > opts.resect_focal_disagree_sigma * ff["sigma_focal_px"]:
                intr, cam_from_world = ff["intrinsics"], ff["cam_from_world"]
                rms, sig_max = ff["rms_px"], ff["sigma_centre_max_m"]
                report.update({"intrinsics_from": report["intrinsics_from"] + ", focal refined in the resection "
                               "(SfM's disagrees with this photo's control points)", "rms_px": rms,
                               "sigma_centre_max_m": sig_max})
        reason = None
        if ff is None and not (from_refined or camera_checked):
            # SfM's camera, checked by no placed model (its model failed its checks, or none was placed), and
            # too few picks to check its focal here: a focal 8 % off moved such a photo (5 picks) 2.5 m along
            # its line of sight with small residuals and a 0.41 m 1-sigma that does not count the focal
            n_fit = sum(1 for r in res.residuals if r.get("inlier"))
            reason = (f"its camera (SfM's) is checked by no placed SfM model, and {n_fit} of its "
                      f"{len(res.residuals)} picks fit with it: too few to check the focal (6 are needed)")
        elif rms is None or rms > opts.warn_rms_px:
            reason = f"control-point RMS residual {rms} px exceeds {opts.warn_rms_px:g} px"
        elif int(s.get("n_points") or 0) - n_out < opts.resect_min_points:
            reason = f"only {int(s.get('n_points') or 0) - n_out} of its control points fit"
        elif n_out > opts.model_max_outlier_fraction * max(int(s.get("n_observations") or 0), 1):
            reason = f"{n_out} of its {s.get('n_observations')} picks are outliers"
        elif sig_max is None or sig_max > opts.model_max_sigma_centre_m:
            reason = (f"its control points fix it only to {sig_max if sig_max is None else round(sig_max, 2)} m "
                      f"(1-sigma; {opts.model_max_sigma_centre_m:g} m allowed)")
        if reason is not None:
            why[name] = f"placing it on its own failed the checks: {reason}"
            continue
        for wmsg in caught:
            _w.warn(wmsg.message, wmsg.category, stacklevel=2)
        image = rdoc_image(rdoc, name) or (project.relative(photo_paths[name]) if name in photo_paths else name)
        out[name] = {"entry": _view_entry(name, image, intr, cam_from_world, True), "report": report}
    return out, why


def rdoc_image(rdoc: dict, name: str) -> str | None:
    for images in [rdoc.get("images", [])] + [m.get("images", []) for m in rdoc.get("models", [])]:
        for s_ in images:
            if s_.get("name") == name:
                return s_.get("image")
    return None


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


def _multiview(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    """Every SfM model placed by its own similarity (docs/gis.md): the main model as before, each separate model
    from the control points triangulated in it, when they fix it (:func:`_separate_model_verdict`)."""
    import warnings as _w

    rec_path = project.reconstruction_path
    if not rec_path.is_file():
        raise StageError(f"{rec_path}: not found; the multiview route needs the sfm stage's reconstruction: run "
                         f"`workbench run {project.root} --only sfm` first (or write a {CAMERAS_FILE} by hand)")
    models, rdoc = read_reconstruction_models(project, rec_path)
    cp_path = project.control_points_path
    cps = _control_points_of_photos(project, cp_path) if cp_path.is_file() else []
    photos = _photo_by_name(project)
    all_views = {v.name: v for _, vs in models for v in vs}
    gps = {n: g for n, v in all_views.items() if (g := _gps_enu(project, photos.get(n))) is not None}
    if cps:  # a pick outside its photo is bad input, whichever model the photo is in
        from .solvers import _observations

        _observations(cps, list(all_views.values()), where)
    src = str(rdoc.get("intrinsics_source", "sfm"))
    images = {s["name"]: s.get("image", "") for s in rdoc["images"]}
    for m in rdoc.get("models", []):
        for s_ in m.get("images", []):
            images.setdefault(s_["name"], s_.get("image", ""))

    placed: dict[str, tuple[str, Any, SfmView]] = {}  # photo -> (model label, similarity, view)
    reports, main_res, main_error, first_res = [], None, None, None
    for label, views in models:
        report: dict[str, Any] = {"model": label, "views": [v.name for v in views]}
        try:
            with _w.catch_warnings(record=True) as caught:
                _w.simplefilter("always", GeorefResidualsLarge)
                res = solve_similarity(views, cps, gps_centres={v.name: gps[v.name] for v in views if v.name in gps},
                                       opts=opts,
                                       where=where if label == "main" else f"{where} ({label} of the SfM models)")
        except InputError as exc:
            report.update({"status": "unregistered", "reason": str(exc)})
            if label == "main":
                main_error = exc
            reports.append(report)
            continue
        where_m = where if label == "main" else f"{where} ({label} of the SfM models)"
        # a photo whose own picks mostly disagree with the fitted model was placed wrongly by SfM (look-alike
        # matches): it is left out of this model (and may be placed on its own below), and the model fitted again
        # without it (its rays also went into the triangulated points)
        rejected = {}
        for v in views:
            mine = [r for r in res.residuals if r["view"] == v.name]
            bad = [r for r in mine if not r["inlier"]]
            if opts.reject_disagreeing_views and len(bad) >= 2 and 2 * len(bad) > len(mine):
                med = np.median([r["error_px"] if r["error_px"] is not None else np.inf for r in mine])
                rejected[v.name] = (f"{len(bad)} of its {len(mine)} control-point picks are more than "
                                    f"{opts.ransac_threshold_px:g} px from where SfM's pose puts them (median "
                                    f"{med:.0f} px): its SfM pose disagrees with the control points")
        fitted_views = views
        if rejected and len(rejected) < len(views):
            keep = [v for v in views if v.name not in rejected]
            try:
                with _w.catch_warnings(record=True) as caught2:
                    _w.simplefilter("always", GeorefResidualsLarge)
                    res2 = solve_similarity(keep, cps, gps_centres={v.name: gps[v.name] for v in keep if v.name in gps},
                                            opts=opts, where=where_m)
                res, caught, fitted_views = res2, caught2, keep
            except InputError as exc:
                report["refit_failed"] = str(exc)
        if rejected:
            report["rejected_views"] = rejected
        # every model, the main one too, must pass the checks when control points exist (a main model placed by
        # GPS alone is not checked: it has no control points to check against)
        reason, figures = ((None, {}) if (label == "main" and not cps)
                           else _separate_model_verdict(res, fitted_views, opts))
        if label == "main" and reason is not None:
            main_error = InputError(f"{where}: the main SfM model could not be placed: {reason}")
        report.update(figures)
        report.update({"world_from_model": res.matrix.tolist(), "scale": res.scale,
                       "n_triangulated": res.stats.get("n_triangulated"), "rms_px": res.stats.get("rms_px"),
                       "max_px": res.stats.get("max_px"), "rms_m": res.stats.get("rms_m"),
                       "n_gps_centres": res.stats.get("n_gps_centres")})
        if reason is None and len(rejected) == len(views):
            reason = "every photo of it disagrees with the control points"
        if reason is not None:
            report.update({"status": "unregistered", "reason": reason, "residuals": res.residuals})
            report.pop("rejected_views", None)
            reports.append(report)
            continue
        for wmsg in caught:  # the residual warnings of a model that is used
            _w.warn(wmsg.message, wmsg.category, stacklevel=2)
        report["status"] = "georegistered"
        if label != "main":
            report["residuals"] = res.residuals
            report["warnings"] = res.warnings
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
                                   "rotation_difference_deg": _rot_deg(A, B)}
            else:
                placed[v.name] = (label, res, v)
        if overlap:
            report["overlap"] = overlap
        report["placed"] = sorted(n for n in report["views"] if n in placed and placed[n][0] == label)
        if label == "main":
            main_res = res
        first_res = first_res or res
        reports.append(report)

    resected: dict[str, dict] = {}  # photo -> {"entry": view entry, "report": ...}
    resect_reasons: dict[str, str] = {}
    if opts.resect_unplaced and cps:
        resected, resect_reasons = _resect_unplaced(project, rdoc, models, placed, cps, gps, opts, where)
    if not placed and not resected:
        if len(models) == 1 and main_error is not None and not resect_reasons:
            raise main_error
        raise InputError(f"{where}: no SfM model could be placed in the scene: "
                         + "; ".join(f"{r['model']} ({len(r['views'])} photos): {r['reason']}" for r in reports)
                         + ("; and no photo could be placed on its own: "
                            + "; ".join(f"{n}: {why}" for n, why in sorted(resect_reasons.items()))
                            if resect_reasons else ""))
    def views_out():
        out = []
        for name in sorted(set(placed) | set(resected)):
            if name in resected:
                out.append(dict(resected[name]["entry"]))
                continue
            label, res, v = placed[name]
            out.append(_view_entry(name, images.get(name) or name, v.intrinsics,
                                   res.cam_from_world(v.cam_from_model), src in ("calibrated", "sfm")))
        return out

    out_views = views_out()
    uncertainty, adjustments, refined = _camera_adjustment(models, placed, resected, out_views, cps, opts)
    if refined and opts.resect_unplaced and cps:  # photos still unplaced, tried again with the refined camera
        more, more_why = _resect_unplaced(project, rdoc, models, {**placed, **resected}, cps, gps, opts, where,
                                          refined=refined)
        if more:
            resected.update(more)
            for n in more:
                resect_reasons.pop(n, None)
            for n, why in more_why.items():
                if n in resect_reasons:
                    resect_reasons[n] = f"{resect_reasons[n]}; with the refined camera: {why}"
            out_views = views_out()
            uncertainty, adjustments, refined = _camera_adjustment(models, placed, resected, out_views, cps, opts)
            for a in adjustments:
                a["second_pass"] = True
    for n, r in resected.items():  # the stated uncertainty beside the resection's own check
        if n in uncertainty:
            r["report"]["sigma_centre_stated_m"] = uncertainty[n].get("sigma_centre_m")

    done = set(placed) | set(resected)
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
    res0 = main_res or first_res
    if res0 is None:  # only resected photos
        doc, stats = _resected_only_doc(project, rec_path, src, resected, reports, unreg)
        doc["views"] = out_views
        doc["georegistration"].update({"view_uncertainty": uncertainty, "camera_adjustment": adjustments})
        if main_error is not None:
            doc["georegistration"]["main_model_error"] = str(main_error)
        stats.update({"view_uncertainty": uncertainty, "camera_adjustment": adjustments})
        return doc, stats
    block_label = ("main" if main_res is not None
                   else next(r["model"] for r in reports if r["status"] == "georegistered"))
    block = _georeg_block("control_points" if cps else "gps", res0,
                          {"world_from_model": res0.matrix.tolist(), "model": block_label,
                           "reconstruction": project.relative(rec_path),
                           "models": [{k: v for k, v in r.items() if k != "residuals"} | (
                               {"residuals": r["residuals"]} if r["model"] != block_label and "residuals" in r else {})
                               for r in reports],
                           "n_views_placed": len(done), "unregistered": unreg,
                           "resected": [r["report"] for _, r in sorted(resected.items())],
                           "view_uncertainty": uncertainty, "camera_adjustment": adjustments})
    if main_res is None:
        block["main_model_error"] = str(main_error)
    doc = {"route": "multiview", "intrinsics_source": src, "georegistration": block, "views": out_views,
           "panorama": None}
    n_sfm = len(rdoc["images"]) + len(rdoc.get("unregistered", []))
    stats = {**_short_stats(res0), "world_from_model": res0.matrix.tolist(), "model": block_label,
             "n_views_placed": len(done), "n_photos": n_sfm,
             "resected": [{k: v for k, v in r["report"].items() if k != "residuals"}
                          for _, r in sorted(resected.items())],
             "models": [{k: v for k, v in r.items() if k not in ("residuals", "world_from_model")} for r in reports],
             "unregistered": unreg, "view_uncertainty": uncertainty, "camera_adjustment": adjustments}
    return doc, stats


def _single(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    from ..files.exif import read_focal_px

    photo = project.photo_paths()[0]
    cam = project.settings.camera
    from PIL import Image

    with Image.open(photo) as im:
        w, h = im.size
    if cam.profile:
        prof_path = project.require_file(cam.profile, "camera.profile")
        prof = project.read_json(prof_path)
        intr = _intrinsics(prof.get("intrinsics") if isinstance(prof, dict) else None, f"{prof_path}: intrinsics")
        if (intr.width, intr.height) != (w, h):
            if abs(intr.width / w - intr.height / h) > 1e-3:
                raise InputError(f"{prof_path}: intrinsics are for {intr.width}x{intr.height} but {photo} is {w}x{h} "
                                 f"(another aspect ratio); use the profile of this camera")
            intr = intr.scaled(w / intr.width)
        src = "calibrated"
    else:
        f = read_focal_px(photo)
        if f is None:
            raise InputError(f"{photo}: no EXIF focal length and no camera.profile; single-photo georegistration "
                             f"needs the focal: calibrate the camera (camera.profile) or use a photo with EXIF")
        intr = CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0)
        src = "exif"
    cps = _load_cps(project)
    prior, prior_sigma, prior_src = _prior(project, [photo], opts)
    view = RigView(photo.name, intr, np.eye(3))
    res = solve_central([view], cps, prior_centre=prior, prior_sigma_m=prior_sigma, opts=opts, where=where)
    doc = {"route": "single", "intrinsics_source": src,
           "georegistration": _georeg_block("control_points", res, {"solver": "p3p_ransac_refined",
                                                                    "prior_source": prior_src}),
           "views": [_view_entry(photo.name, project.relative(photo), intr, res.cam_from_world(np.eye(3)),
                                 src == "calibrated")],
           "panorama": None}
    return doc, {**_short_stats(res), "prior_source": prior_src, "centre_enu": res.centre_enu.tolist()}
