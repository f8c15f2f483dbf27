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
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError, StageError
from ..project import Project
from ..runner import Progress, StageResult, StageSpec
from .control_points import CONTROL_POINTS_FILE, ControlPoint, load_control_points
from .gps import read_gps
from .solvers import GeorefOptions, GeorefResidualsLarge, RigView, SfmView, solve_central, solve_similarity

log = logging.getLogger(__name__)

__all__ = ["STAGE", "run_georef", "georef_route", "read_panorama_model", "read_reconstruction",
           "validate_cameras_doc", "UPSTREAM_STAGES"]

CAMERAS_FILE = "cameras.json"
UPSTREAM_STAGES = ("stitch", "sfm")  # the stages whose outputs georef reads
PANORAMA_MODEL = ("stitch", "panorama.json")
RECONSTRUCTION = ("sfm", "reconstruction.json")
PANORAMA_KEY = "panorama"  # pixel key of a pick made in the stitched panorama image


# ----------------------------------------------------------------------------------------------------------
# Which route, which files
# ----------------------------------------------------------------------------------------------------------
def georef_route(project: Project) -> str:
    """``known``, ``multiview``, ``single`` or ``panorama`` (see the module docstring)."""
    if (project.root / CAMERAS_FILE).is_file():
        return "known"
    cam = project.settings.camera
    if cam.source.value == "sfm":
        return "multiview"
    try:
        photos = project.photo_paths()
    except InputError:
        photos = []
    return "single" if len(photos) == 1 else "panorama"


def _control_points_path(project: Project) -> Path:
    return project.root / CONTROL_POINTS_FILE


def _inputs(project: Project) -> dict[str, Path]:
    files: dict[str, Path] = {}
    route = georef_route(project)
    if route == "known":
        files["cameras"] = project.root / CAMERAS_FILE
    cp = _control_points_path(project)
    if cp.is_file():
        files["control_points"] = cp
    if route == "panorama":
        p = project.stage_dir(PANORAMA_MODEL[0]) / PANORAMA_MODEL[1]
        if p.is_file():
            files["panorama_model"] = p
    elif route == "multiview":
        p = project.stage_dir(RECONSTRUCTION[0]) / RECONSTRUCTION[1]
        if p.is_file():
            files["reconstruction"] = p
    elif route == "single":
        files["photo"] = project.photo_paths()[0]
        if project.settings.camera.profile:
            prof = project.path(project.settings.camera.profile)
            if prof.is_file():
                files["camera_profile"] = prof
    return files


def _applies(project: Project) -> bool:
    """Known cameras, control points, or (multiview) an SfM model that the photos' GPS can place."""
    if (project.root / CAMERAS_FILE).is_file() or _control_points_path(project).is_file():
        return True
    return georef_route(project) == "multiview" and (project.stage_dir(RECONSTRUCTION[0]) / RECONSTRUCTION[1]).is_file()


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


def read_reconstruction(project: Project, path: Path) -> tuple[list[SfmView], dict]:
    """The images of an SfM reconstruction (``out/sfm/reconstruction.json``) and the document."""
    doc = project.read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("images"), list) or not doc["images"]:
        raise StageError(f"{path}: no 'images' list; run the sfm stage again")
    views = []
    for i, s in enumerate(doc["images"]):
        where = f"{path}: images[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{where}: needs 'name'")
        intr = _intrinsics(s.get("intrinsics"), f"{where}.intrinsics")
        M = _matrix(s.get("cam_from_model"), (4, 4), f"{where}.cam_from_model")
        _rotation(M[:3, :3], f"{where}.cam_from_model")
        views.append(SfmView(s["name"], intr, M))
    return views, doc


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
    if photos_root.is_dir():
        for p in sorted(photos_root.rglob("*")):
            if p.is_file():
                out.setdefault(p.name, p)
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
    path = _control_points_path(project)
    if not path.is_file():
        raise InputError(f"{path}: not found; georegistration needs control points (landmarks with known "
                         f"coordinates picked in the photos, docs/gis.md) or a hand-written {CAMERAS_FILE}")
    return load_control_points(path, project.frame)


# ----------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------
def run_georef(project: Project, progress: Progress, opts: GeorefOptions = GeorefOptions()) -> StageResult:
    route = georef_route(project)
    out_dir = project.stage_dir("georef")
    cp_path = _control_points_path(project)
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
    for k in ("sigma_centre_m", "sigma_rotation_deg", "prior", "centre_minus_prior_m", "scale", "n_triangulated",
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
    extra: dict[str, Any] = {"n_views": len(views), "source": project.relative(path)}
    cp_path = _control_points_path(project)
    if cp_path.is_file():  # check the known cameras against the control points
        cps = load_control_points(cp_path, project.frame)
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
    pano_path = project.stage_dir(PANORAMA_MODEL[0]) / PANORAMA_MODEL[1]
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


def _multiview(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    rec_path = project.stage_dir(RECONSTRUCTION[0]) / RECONSTRUCTION[1]
    if not rec_path.is_file():
        raise StageError(f"{rec_path}: not found; the multiview route needs the sfm stage's reconstruction: run "
                         f"`workbench run {project.root} --only sfm` first (or write a {CAMERAS_FILE} by hand)")
    views, rdoc = read_reconstruction(project, rec_path)
    cp_path = _control_points_path(project)
    cps = load_control_points(cp_path, project.frame) if cp_path.is_file() else []
    photos = _photo_by_name(project)
    gps = {v.name: g for v in views if (g := _gps_enu(project, photos.get(v.name))) is not None}
    res = solve_similarity(views, cps, gps_centres=gps, opts=opts, where=where)
    src = str(rdoc.get("intrinsics_source", "sfm"))
    images = {s["name"]: s.get("image", "") for s in rdoc["images"]}
    out_views = [_view_entry(v.name, images.get(v.name) or v.name, v.intrinsics, res.cam_from_world(v.cam_from_model),
                             src in ("calibrated", "sfm")) for v in views]
    doc = {"route": "multiview", "intrinsics_source": src,
           "georegistration": _georeg_block("control_points" if cps else "gps", res,
                                            {"world_from_model": res.matrix.tolist(),
                                             "reconstruction": project.relative(rec_path)}),
           "views": out_views, "panorama": None}
    return doc, {**_short_stats(res), "world_from_model": res.matrix.tolist()}


def _single(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    from ..render.exif import read_focal_px

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


STAGE = StageSpec(
    "georef", "place the cameras in the scene frame from control points (or known cameras)", run_georef,
    inputs=_inputs, settings_sections=("location", "camera"), depends_on=UPSTREAM_STAGES, applies=_applies)
