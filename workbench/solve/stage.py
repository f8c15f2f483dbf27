"""The ``solve`` stage: every carriage's pose from the marked points seen in the photos (docs/pipeline.md).

Reads the views (``cameras.json`` written by hand in the incident folder, else ``out/georef/cameras.json``),
the correspondences (``out/correspond/correspondences.json`` when the ``correspond`` stage wrote it, else the
incident's hand-written ``correspondences.json``), the consist and its couplings, and the terrain; runs
:func:`workbench.solve.solve_consist`; writes ``out/solve/solution.json``. A solve that does not converge
raises (the runner keeps the previous solution) after writing the attempt to ``out/solve/attempt.json``.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.frames import hpr_from_rotation
from ..core.layout import CAMERAS_FILE, CORRESPONDENCES_FILE
from ..errors import InputError, StageError
from ..project import Project
from ..core.stage_api import Progress, StageResult
from ..files import correspondences
from ..files.cameras import parse_pose_uncertainty, read_cameras
from ..files.panorama import read_panorama
from .level import Levelling, UprightCar, add_levelling_uncertainty, level_from_carriages
from .principal_point import guessed_principal_point_errors, guessed_principal_point_term
from .model import CarriageInput, ChainLink, Observation, SolveOptions, SolveWarning, View
from .problem import AlignedObservation
from .solver import solve_consist
from .camera_residual import view_camera_errors
from .camera_term import add_camera_uncertainty, add_view_camera_uncertainty

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------------
# Reading and checking
# ---------------------------------------------------------------------------------------------------------
def read_views(project: Project, path: Path) -> tuple[list[View], dict]:
    """``(views, document)`` of a ``cameras.json`` (read by :mod:`workbench.files.cameras`); a view's focal is
    unknown when the file says so or when ``solver.estimate_focal`` asks for every focal to be estimated."""
    cameras = read_cameras(path)
    every = bool(project.settings.solver.estimate_focal)
    views = [View(name=v.name, intrinsics=v.intrinsics, cam_from_world=v.cam_from_world,
                  focal_known=v.focal_known and not every) for v in cameras.views]
    return views, cameras.doc


def _group(o: dict, method: str | None, where: str) -> str | None:
    """The shared-misfit group of a measured automatic point: the face its homography placed it on."""
    face = o.get("face")
    if method != "homography" or face is None:
        return None
    if not isinstance(face, str):
        raise InputError(f"{where}: face = {face!r} must be a face name (left, right, front, rear, roof)")
    return face


def _ecc(o: dict, where: str) -> float | None:
    """A measured automatic point's face alignment's ECC correlation, or None."""
    ecc = o.get("ecc")
    if ecc is None:
        return None
    if isinstance(ecc, bool) or not isinstance(ecc, (int, float)) or not -1.0 <= float(ecc) <= 1.0:
        raise InputError(f"{where}: ecc = {ecc!r} must be a correlation coefficient in [-1, 1] (or left out)")
    return float(ecc)


def read_correspondences(project: Project, path: Path, views: list, panorama: Any = None) -> tuple[dict, dict]:
    """``({car number: {view name: {point: Observation}}}, stats)``; every bad item is an :class:`InputError`
    naming it. ``view == "panorama"`` pixels are mapped into their source photo with the panorama model."""
    doc = project.read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("observations"), list):
        raise InputError(f"{path}: needs an 'observations' list; see docs/pipeline.md (correspondences.json)")
    correspondences.parse(doc, path)  # the format (keys, types, finite numbers); its meaning is checked below
    types = project.carriage_types()
    vby = {v.name: v for v in views}
    out: dict[str, dict[str, dict[str, tuple[float, float]]]] = {}
    src: dict[tuple, str] = {}
    n_pano = 0
    sources: dict[str, int] = {}
    n_derived = n_aligned = 0
    for i, o in enumerate(doc["observations"]):
        where = f"{path}: observations[{i}]"
        if not isinstance(o, dict):
            raise InputError(f"{where}: must be an object with carriage, point, view, uv")
        car, point, view = o.get("carriage"), o.get("point"), o.get("view")
        if car not in types:
            raise InputError(f"{where}: carriage {car!r} is not in the consist ({', '.join(types)}); fix the car "
                             f"number or the consist in project.toml")
        if point not in types[car].marked_points:
            raise InputError(f"{where}: point {point!r} is not a marked point of car {car} (type "
                             f"{types[car].id}: {', '.join(types[car].marked_points)})")
        uv = o.get("uv")
        try:
            a = np.asarray(uv, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            a = np.full(1, np.nan)
        if a.size != 2 or not np.all(np.isfinite(a)):
            raise InputError(f"{where} (car {car}, point {point}): uv = {uv!r} is not a finite [u, v] pair")
        if view == "panorama":
            if panorama is None:
                raise InputError(f"{where}: view 'panorama' but no stitched panorama model is known (run the "
                                 f"stitch and georef stages, or give source-photo pixels)")
            if not (-0.5 <= a[0] <= panorama.width - 0.5 and -0.5 <= a[1] <= panorama.height - 0.5):
                raise InputError(f"{where} (car {car}, point {point}): ({a[0]:.1f}, {a[1]:.1f}) is outside the "
                                 f"{panorama.width}x{panorama.height} panorama")
            idx, uv_src = panorama.to_source(a[None])
            view = panorama.sources[int(idx[0])].name
            a = np.asarray(uv_src[0], dtype=float)
            n_pano += 1
        if view not in vby:
            raise InputError(f"{where}: view {view!r} is not a photo of the cameras file ({', '.join(vby)})")
        intr = vby[view].intrinsics
        if not intr.in_image(a[None])[0]:
            raise InputError(f"{where} (car {car}, point {point}, view {view}): ({a[0]:.1f}, {a[1]:.1f}) is outside "
                             f"the {intr.width}x{intr.height} image")
        sig = o.get("sigma_px")
        if sig is not None:
            try:
                sig = float(sig)
            except (TypeError, ValueError):
                sig = float("nan")
            if not (math.isfinite(sig) and sig > 0):
                raise InputError(f"{where} (car {car}, point {point}): sigma_px = {o.get('sigma_px')!r} must be a "
                                 f"positive number of pixels (or left out)")
        method = o.get("method")
        if method not in (None, "homography", "pose", "carried"):
            raise InputError(f"{where} (car {car}, point {point}): method = {method!r} must be 'homography', "
                             f"'pose' or 'carried' (or left out)")
        key = (car, view, point)
        if key in src:
            raise InputError(f"{where}: car {car}, point {point} in view {view} is given twice (also "
                             f"{src[key]}); keep one")
        src[key] = f"observations[{i}]"
        # a point's own sigma can only down-weight it: the solve's pixel sigma is the floor (a finder's sub-pixel
        # claims on one face are correlated through its homography, not independent evidence)
        sig_used = None if sig is None else max(sig, float(project.settings.solver.pixel_sigma_px))
        group = _group(o, method, where)
        ecc = _ecc(o, where) if group is not None else None
        al = o.get("alignment")  # the face alignment's share of the point's error (checked by the format)
        if isinstance(al, dict) and group is not None:
            ob = AlignedObservation(point, float(a[0]), float(a[1]), True, sig_used, False, group, ecc,
                                    loading=tuple(tuple(float(x) for x in row) for row in al["loading_px"]))
            n_aligned += 1
        else:
            ob = Observation(point, float(a[0]), float(a[1]), True, sig_used, method in ("pose", "carried"), group,
                             ecc, carried=method == "carried")
        out.setdefault(car, {}).setdefault(view, {})[point] = ob
        s = str(o.get("source", "manual"))
        sources[s] = sources.get(s, 0) + 1
        n_derived += method in ("pose", "carried")
    stats = {"file": project.relative(path), "n_observations": len(src), "by_source": sources,
             "n_predicted": n_derived, "n_with_alignment": n_aligned,
             "from_panorama_pixels": n_pano, "needs_manual": doc.get("needs_manual", [])}
    return out, stats


def _load_panorama(project: Project, doc: dict) -> Any:
    pano = doc.get("panorama")
    if not isinstance(pano, dict) or not pano.get("model"):
        return None
    return read_panorama(project.require_file(pano["model"], "panorama.model")).model()


# ---------------------------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------------------------
def run_solve(project: Project, progress: Progress) -> StageResult:
    s = project.settings
    cam_path = project.cameras_path()
    if cam_path is None:
        raise InputError(f"{project.root}: no cameras: run the georef stage (it needs control_points.json), or "
                         f"write {project.root / CAMERAS_FILE} by hand (docs/pipeline.md)")
    corr_path = project.correspondences_path()
    if corr_path is None:
        raise InputError(f"{project.root}: no marked points: run the correspond stage, or write "
                         f"{project.root / CORRESPONDENCES_FILE} by hand (docs/pipeline.md)")
    progress(0.05, "cameras and marked points")
    views, cam_doc = read_views(project, cam_path)
    panorama = _load_panorama(project, cam_doc)
    obs, corr_stats = read_correspondences(project, corr_path, views, panorama)
    types = project.carriage_types()
    carriages = [CarriageInput(number=c.number, carriage_type=types[c.number], observations=obs.get(c.number, {}),
                               on_track=bool(c.on_track)) for c in s.consist]
    links = []
    for i, c in enumerate(s.consist[:-1]):
        held = c.coupling_to_next is not None and c.coupling_to_next.value == "held"
        links.append(ChainLink(i, i + 1, s.solver.slack_held_m if held else s.solver.slack_broken_m))
    focal_unknown = [v.name for v in views if not v.focal_known]
    opts = SolveOptions(pixel_sigma_px=s.solver.pixel_sigma_px, robust_loss=s.solver.robust_loss.value
                        if hasattr(s.solver.robust_loss, "value") else str(s.solver.robust_loss),
                        loss_scale_px=s.solver.loss_scale_px, max_iterations=s.solver.max_iterations,
                        estimate_focal=bool(focal_unknown),
                        terrain_sigma_m=s.terrain.dem_vertical_accuracy_m,
                        face_sigma_px=None if s.solver.face_sigma_px == "estimate" else s.solver.face_sigma_px,
                        bias_correction=bool(s.solver.bias_correction),
                        prediction_release=float(s.solver.prediction_release),
                        hfov_range_deg=tuple(float(x) for x in s.solver.hfov_range_deg),
                        track_sigma_m=float(s.solver.track_sigma_m),
                        camera_errors=_camera_errors(cam_doc, cam_path, views))
    relative = cam_doc.get("frame") == "relative"
    terrain = None
    if s.terrain.dem and not relative:
        progress(0.15, "terrain")
        terrain = project.terrain_model()
    elif s.terrain.dem:
        log.warning("solve: the scene is relative (no control points): the DEM (terrain.dem) is not in its frame "
                    "and is not used to settle the carriages; add control_points.json to georeference it")
    railways = _railways_for_prior(project, carriages, relative, progress)
    progress(0.3, f"solving {len(carriages)} carriages")
    res, rejected = _solve_rejecting(carriages, links, views, opts, terrain, s.solver, progress, railways)
    exif_check = _exif_focal_check(carriages, links, views, opts, terrain, cam_doc)
    levelling = None
    if relative and any(c.status != "left_out" for c in res.carriages):
        progress(0.8, "levelling the relative scene")
        res, views, levelling = _level(res, carriages, links, views, opts, s.solver)
        placed = _gps_placement(project, cam_doc, levelling)
        if placed is not None:  # the photo's GPS and compass put the levelled scene on the Earth
            progress(0.85, "placing the scene by the photo's GPS and compass")
            inv = np.linalg.inv(placed["world_from_levelled"])
            views = [replace(v, cam_from_world=np.asarray(v.cam_from_world, float) @ inv) for v in views]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SolveWarning)
                res = solve_consist(carriages, links, views, opts, None)
            levelling.placement = placed
            log.info("solve: placed by %s: centre sigma %s m, azimuth sigma %.1f deg", placed["record"]["source"],
                     placed["record"]["sigma_enu_m"], placed["record"]["sigma_azimuth_deg"])
    progress(0.9, "writing the solution")
    fit_sigmas = {c.number: (c.sigma_body_centre_m, c.sigma_hpr_deg) for c in res.carriages}
    camera_unc = camera_uncertainty(cam_doc) if levelling is None else _levelling_uncertainty(levelling)
    if camera_unc is not None and levelling is not None and levelling.placement is None:
        camera_unc["carriages"] = add_levelling_uncertainty(res, levelling)  # the fit's share of it kept
    elif camera_unc is not None:
        camera_unc["carriages"] = add_camera_uncertainty(res, camera_unc["centre_enu"], camera_unc["cov"])
    elif levelling is None:
        camera_unc = multiview_camera_uncertainty(res, carriages, links, views, cam_doc, cam_path, opts)
    # a relative scene with a guessed camera: the principal point's error (docs/solver.md, "Relative scenes")
    pp_term = guessed_principal_point_term(res, carriages, links, views, opts, levelling,
                                           cam_doc.get("intrinsics_source"))
    used = {c.number: c.observations for c in carriages}
    doc = solution_document(project, res, views, cam_doc, used, levelling)
    doc["camera_uncertainty"] = _camera_uncertainty_record(camera_unc, cam_doc)
    if pp_term is not None:
        doc["camera_uncertainty"]["principal_point"] = pp_term
    for rec in doc["carriages"]:
        sb, sh = fit_sigmas.get(rec["number"], (None, None))
        rec["sigma_body_centre_fit_m"] = None if sb is None else np.asarray(sb, dtype=float).tolist()
        rec["sigma_hpr_fit_deg"] = None if sh is None else np.asarray(sh, dtype=float).tolist()
    doc["correspondences"] = corr_stats
    doc["rejected_points"] = rejected
    doc["exif_focal_check"] = exif_check
    doc["track_prior"] = res.track_prior
    for c in exif_check:
        if c.get("warning"):
            doc["warnings"].append({"car": None, "index": None, "kind": "exif_focal", "message": c["warning"]})
            log.warning("solve: %s", c["warning"])
    out_dir = project.stage_dir("solve")
    if all(c.status == "left_out" for c in res.carriages):
        attempt = project.write_json(out_dir / "attempt.json", doc)
        needs = ", ".join(str(n.get("carriage")) for n in corr_stats.get("needs_manual") or []
                          if isinstance(n, dict)) or "see the warnings"
        raise InputError(f"no carriage could be solved: too few marked points were found ({corr_stats['n_observations']} "
                         f"in all; carriages needing manual points: {needs}); pick them with `workbench pick "
                         f"{project.root}` (or write {project.root / CORRESPONDENCES_FILE}); details in {attempt}")
    if not res.converged:
        attempt = project.write_json(out_dir / "attempt.json", doc)
        raise StageError(f"solve did not converge ({res.message}); the previous solution is kept; this attempt is in "
                         f"{attempt}")
    path = project.write_json(out_dir / "solution.json", doc)
    n_status = {k: sum(1 for c in res.carriages if c.status == k) for k in ("solved", "carried", "left_out")}
    stats = {"status": res.status, "time_s": res.time_s, "iterations": res.iterations, "final_cost": res.final_cost,
             "carriages": n_status, "n_views": len(views), "n_observations": corr_stats["n_observations"],
             "observations_by_source": corr_stats["by_source"], "sigma_px": _num(res.sigma_px),
             "sigma_px_estimated": _num(res.sigma_px_estimated), "focal_px": res.focal_px,
             "route": cam_doc.get("route"), "intrinsics_source": cam_doc.get("intrinsics_source"),
             "cameras": project.relative(cam_path), "correspondences_file": project.relative(corr_path),
             "steps": [{"name": st.name, "ran": st.ran, "note": st.note, "cost_before": _num(st.cost_before),
                        "cost_after": _num(st.cost_after), "iterations": st.iterations, "time_s": st.time_s,
                        "facts": st.facts}
                       for st in res.steps],
             "rejected_points": len(rejected), "warnings": [w.get("message") for w in res.warnings]}
    return StageResult(outputs={"solution": path}, stats=stats)


def _railways_for_prior(project: Project, carriages: list, relative: bool, progress: Progress) -> tuple:
    """The railway lines (scene frame) for the carriages marked on the rails; none without such a carriage, and
    none in a relative scene (the map is not in its frame: warned)."""
    marked = [c.number for c in carriages if c.on_track]
    if not marked:
        return ()
    if relative:
        log.warning("solve: car(s) %s are marked on_track, but the scene is relative (no control points): the "
                    "railway line is not in its frame and is not used; add control_points.json", ", ".join(marked))
        return ()
    progress(0.2, "railway lines")
    layer = project.railways(heights=False)  # the prior is horizontal: no draping on the DEM
    return tuple(layer.lines) if layer is not None else ()


def _solve_rejecting(carriages: list, links: list, views: list, opts: Any, terrain: Any, solver: Any,
                     progress: Progress, railways: tuple = ()) -> tuple[Any, list[dict]]:
    """Solve; while a marked point lies farther than ``reject_outliers_sigma`` pixel sigmas from the fit, drop the
    worst point of each such carriage and solve again (a wrong automatic match must not bend the consist)."""
    rejected: list[dict] = []
    thr = float(solver.reject_outliers_sigma) * float(solver.pixel_sigma_px)
    for rnd in range(int(solver.max_rejection_rounds) + 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)  # recorded in the result's warnings
            res = solve_consist(carriages, links, views, opts, terrain, railways)
        if thr <= 0 or rnd == int(solver.max_rejection_rounds):
            break
        dropped = False
        for cin, cr in zip(carriages, res.carriages):
            if cr.status == "left_out" or not cr.residuals_px:
                continue
            def scale(v: str, p: str) -> float:  # the point's own sigma relative to the solve's
                o = cin.observations.get(v, {}).get(p)
                sig = getattr(o, "sigma_px", None)
                return 1.0 if sig is None else float(sig) / float(solver.pixel_sigma_px)

            # predictions (points projected from a face's pose or carried from another photo) are released in the
            # last fit (SolveOptions.prediction_release): their residuals say how far the prediction was off, not
            # that a measurement is wrong
            worst = max(((math.hypot(*e) / scale(v, p), v, p, math.hypot(*e))
                         for v, pts in cr.residuals_px.items() for p, e in pts.items()
                         if not getattr(cin.observations.get(v, {}).get(p), "derived", False)), default=None)
            if worst is None or worst[0] <= thr:
                continue
            _, v, p, r_px = worst
            obs = {vn: dict(pts) for vn, pts in cin.observations.items()}
            o = obs[v].pop(p)
            cin.observations = obs
            rejected.append({"carriage": cin.number, "view": v, "point": p, "uv": [o.u, o.v],
                             "residual_px": round(r_px, 2), "round": rnd + 1})
            dropped = True
        if not dropped:
            break
        log.info("solve: round %d dropped %d outlying point(s)", rnd + 1, sum(r["round"] == rnd + 1 for r in rejected))
        progress(0.3 + 0.1 * (rnd + 1), f"{len(rejected)} outlying point(s) dropped")
    return res, rejected


def _level(res: Any, carriages: list, links: list, views: list, opts: Any, solver: Any
           ) -> tuple[Any, list, Levelling]:
    """A relative scene levelled from its upright carriages (:mod:`workbench.solve.level`): the views turned
    about the camera into the levelled frame and the consist solved again there (the same points: the
    rejections of the first solve stand), so every figure of the solution is in the levelled frame."""
    cars = [UprightCar(c.number, np.asarray(c.world_from_carriage, float)[:3, :3],
                       None if c.covariance_pose is None else np.asarray(c.covariance_pose, float)[:3, :3])
            for c in res.carriages if c.status == "solved" and c.world_from_carriage is not None]
    R_ref = np.asarray(views[0].cam_from_world, float)[:3, :3]
    intr = views[0].intrinsics  # the frame's y: the ray through the reference photo's centre pixel
    ray = intr.rays(np.array([[(intr.width - 1) / 2.0, (intr.height - 1) / 2.0]]))[0]
    lev = level_from_carriages(cars, -R_ref[1], R_ref.T @ ray, sigma_car_deg=float(solver.level_sigma_car_deg),
                               sigma_common_deg=float(solver.level_sigma_common_deg))
    provisional_from_world = np.linalg.inv(lev.world_from_provisional)
    views = [replace(v, cam_from_world=np.asarray(v.cam_from_world, float) @ provisional_from_world) for v in views]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(carriages, links, views, opts, None)
    if lev.method == "camera":
        res.warnings.append({"car": None, "index": None, "kind": "not_levelled", "message": lev.note})
        log.warning("solve: %s", lev.note)
    log.info("solve: %s; tilt sigma %.2f, %.2f deg", lev.note, *lev.sigma_tilt_deg)
    return res, views, lev


EXIF_FOCAL_TOLERANCE = 0.05  # a focal from EXIF is trusted to 5 % (rounded 35 mm-equivalent focal lengths)


def _exif_focal_check(carriages: list, links: list, views: list, opts: Any, terrain: Any,
                      cam_doc: dict) -> list[dict]:
    """The EXIF focal of each photo checked against the picks: the consist solved again with those focals free;
    where the picks put a focal more than 3 sigma and 5 % from the EXIF one (a cropped or resized photo whose
    EXIF still describes the original frame), a warning names the photo and both focals. Nothing is checked
    where the picks cannot tell the focal (no car pins it: the free solve fails or gives no sigma)."""
    if cam_doc.get("intrinsics_source") != "exif":
        return []
    exif = {v.name: float(v.intrinsics.fx) for v in views if v.focal_known}
    if not exif:
        return []
    free = [replace(v, focal_known=False) if v.name in exif else v for v in views]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(carriages, links, free, replace(opts, estimate_focal=True, bias_correction=False),
                                terrain)
    except Exception as exc:  # noqa: BLE001 - a check, never the reason a solve fails
        log.info("solve: the EXIF focal could not be checked (%s)", exc)
        return []
    out = []
    for name, f_exif in exif.items():
        f, s = res.focal_px.get(name), res.sigma_focal_px.get(name)
        rec: dict[str, Any] = {"view": name, "focal_exif_px": f_exif, "focal_picks_px": _num(f),
                               "sigma_focal_picks_px": _num(s)}
        if not res.converged or _num(f) is None or _num(s) is None:
            rec["note"] = "the picks do not determine the focal: not checked"
        elif abs(f - f_exif) > max(3.0 * s, EXIF_FOCAL_TOLERANCE * f_exif):
            rec["warning"] = (f"{name}: the EXIF focal ({f_exif:.0f} px) disagrees with the marked points, which "
                              f"give {f:.0f} ± {s:.0f} px (1 sigma): a cropped or resized photo whose EXIF "
                              f"describes the original? Set camera.source = \"unknown\" to estimate the focal, or "
                              f"give a camera profile")
        out.append(rec)
    return out


def _levelling_uncertainty(lev: Levelling) -> dict:
    """The levelling's tilt error as a camera-pose covariance about the origin (the camera), for
    :func:`add_camera_uncertainty`; with a GPS placement, its heading and centre errors too, about the camera."""
    placed = getattr(lev, "placement", None)
    if placed is not None:
        return {"cov": placed["cov"], "centre_enu": placed["centre_enu"], "levelling": True, "gps": True}
    C = np.zeros((6, 6))
    C[:3, :3] = lev.cov_rotation
    return {"cov": C, "centre_enu": np.zeros(3), "levelling": True}


EYE_HEIGHT_M = 1.6  # a photo without GPS altitude: taken at eye height above the DEM, +-1 m (1 sigma)


def _gps_placement(project: Project, cam_doc: dict, lev: Levelling) -> dict | None:
    """``world_from_levelled`` (4, 4), its covariance as a camera pose (6, 6: rotation vector, centre; about the
    camera) and a record, where the reference photo's EXIF gives a position and a true-north compass azimuth
    (``cameras.json`` ``relative.anchor``): y (the photo's centre ray) turned to that azimuth, the camera to that
    position; the height from GPS altitude, else the DEM plus eye height. None (the scene stays relative) without
    them; the reason is logged."""
    a = (cam_doc.get("relative") or {}).get("anchor")
    if not a:
        return None
    sig = a.get("sigma_enu_m") or [None] * 3
    if a.get("azimuth_deg") is None or sig[0] is None or sig[1] is None:
        log.info("solve: the photo's EXIF gives a position but no true-north compass direction: the scene stays "
                 "relative")
        return None
    C = np.asarray(a["centre_enu"], float).copy()
    s_up, height_from = sig[2], "GPS altitude"
    if s_up is None:
        if not project.settings.terrain.dem:
            log.info("solve: the photo's EXIF has no GPS altitude and the incident no DEM: the scene stays relative")
            return None
        tm = project.terrain_model()
        C[2] = float(tm.height_at(C[None, :2])[0]) + EYE_HEIGHT_M
        s_up = math.hypot(float(project.settings.terrain.dem_vertical_accuracy_m), 1.0)
        height_from = f"the DEM + {EYE_HEIGHT_M} m (eye height)"
    al = math.radians(float(a["azimuth_deg"]))
    Rz = np.array([[math.cos(al), math.sin(al), 0.0], [-math.sin(al), math.cos(al), 0.0], [0.0, 0.0, 1.0]])
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = Rz, C
    cov = np.zeros((6, 6))
    cov[:3, :3] = Rz @ lev.cov_rotation @ Rz.T
    cov[2, 2] += math.radians(float(a["sigma_azimuth_deg"])) ** 2
    cov[3:, 3:] = np.diag([float(sig[0]) ** 2, float(sig[1]) ** 2, float(s_up) ** 2])
    rec = {"source": a.get("source"), "centre_enu": C.tolist(), "sigma_enu_m": [sig[0], sig[1], s_up],
           "height_from": height_from, "azimuth_deg": float(a["azimuth_deg"]),
           "sigma_azimuth_deg": float(a["sigma_azimuth_deg"]), "priors": a.get("priors")}
    return {"world_from_levelled": W, "cov": cov, "centre_enu": C, "record": rec}


def camera_uncertainty(cam_doc: dict) -> dict | None:
    """The georegistration's camera-pose covariance to carry into the carriages' poses, or None.

    Present when the georef stage registered one central camera (a panorama's photos, or a single photo) from
    control points: ``georegistration.covariance_world_rotation_centre`` (6, 6; scene rotation vector in rad,
    centre in m, ENU) and every view's centre at the same place. Cameras written by hand carry no such
    covariance (they are taken as exact); the multi-view route's (a camera each) are
    :func:`multiview_camera_uncertainty`'s."""
    g = cam_doc.get("georegistration") or {}
    cov = g.get("covariance_world_rotation_centre")
    if cov is None:
        return None
    C = np.asarray(cov, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        log.warning("georegistration.covariance_world_rotation_centre is not a finite 6 x 6 matrix: the camera's "
                    "uncertainty is not carried into the carriages' intervals")
        return None
    centres = []
    for v in cam_doc.get("views", []):
        M = np.asarray(v.get("cam_from_world"), dtype=float)
        if M.shape != (4, 4):
            return None
        centres.append(-M[:3, :3].T @ M[:3, 3])
    if not centres or np.max(np.linalg.norm(np.asarray(centres) - centres[0], axis=1)) > 1e-3:
        return None
    return {"cov": C, "centre_enu": centres[0]}


def _camera_errors(cam_doc: dict, cam_path: Path, views: list) -> Any:
    """The camera errors the fit's pixel sigma sets aside (:mod:`.camera_residual`): the multi-view photos' stated
    errors, or a relative scene's guessed principal point (the one :func:`guessed_principal_point_term` adds), or
    None."""
    if cam_doc.get("frame") == "relative":
        return guessed_principal_point_errors(views, cam_doc.get("intrinsics_source"))
    pu = parse_pose_uncertainty(cam_doc, cam_path)
    return view_camera_errors(pu) if pu is not None else None


def multiview_camera_uncertainty(res: Any, carriages: list, links: list, views: list, cam_doc: dict, cam_path: Path,
                                 opts: SolveOptions) -> dict | None:
    """The multi-view route's camera uncertainty (``georegistration.pose_uncertainty``, docs/formats.md) added
    to every carriage's covariance (:func:`add_view_camera_uncertainty`), and the figures of its record; None
    when the cameras file states none (cameras written by hand, an older cameras.json) or none of it is modelled."""
    pu = parse_pose_uncertainty(cam_doc, cam_path)
    if pu is None or not (pu.jacobian or pu.own_covariance):
        return None
    per_car = add_view_camera_uncertainty(res, carriages, links, views, opts.pixel_sigma_px, pu.model_covariance,
                                          pu.jacobian, pu.own_covariance, opts.weighting, pu.intrinsics_jacobian)
    names = {v.name for v in views}
    sd = np.array([np.sqrt(np.clip(np.diag(C), 0.0, None)) for n in sorted(names)
                   if (C := pu.view_covariance(n)) is not None]).reshape(-1, 6)
    models = {}
    for label, C7 in pu.model_covariance.items():
        d = np.sqrt(np.clip(np.diag(C7), 0.0, None))
        models[label] = {"sigma_log_scale": float(d[0]), "sigma_rotation_deg": np.degrees(d[1:4]).tolist(),
                         "sigma_translation_m": d[4:7].tolist(),
                         "sfm_rank": int(len(d) - 7),  # the SfM poses' own error carried beside the similarity
                         "views": sorted(n for n, (m, _) in pu.jacobian.items() if m == label and n in names)}
    return {"multiview": True, "models": models, "per_carriage": per_car,
            "own": sorted(n for n in pu.own_covariance if n in names),
            "not_modelled": sorted(n for n in names if pu.view_covariance(n) is None),
            "sigma_rotation_deg": np.degrees(sd[:, :3].max(axis=0)).tolist() if len(sd) else [0.0] * 3,
            "sigma_centre_m": sd[:, 3:].max(axis=0).tolist() if len(sd) else [0.0] * 3}


def _multiview_record(camera_unc: dict) -> dict:
    per_car = camera_unc["per_carriage"]
    partly = sorted(n for n, r in per_car.items() if r["not_modelled"])
    note = ("multi-view cameras: each SfM model's similarity covariance (7 x 7: log scale, rotation, translation, "
            "from the control points) carried to its photos' poses, the photos of one model sharing that error; "
            "a photo placed on its own (resection) carries that fit's covariance on its own; the photos whose poses "
            "the shared-camera adjustment replaced share that adjustment's error with the camera's refined "
            "intrinsics. Each carriage follows the photos it is measured in, weighted by their information on its pose "
            "and the couplings (first order: a common motion of the cameras moves it rigidly, the scale by its "
            "cameras' weighted shifts; the terrain contact and the track prior hold it in the world); "
            "sigma_*_fit_* give the fit's alone (its pixel sigma estimated with the residual directions these "
            "errors fill set aside: sigma_px_camera). The SfM model's own error (its poses "
            "relative to one another, its refined intrinsics where stated (and a focal held at the EXIF's with that "
            "prior's error), and the similarity's response to "
            "both through the control points) is carried for a model whose reconstruction states it "
            "(sfm_rank > 0). Not included: the SfM error where the reconstruction states none")
    if camera_unc["not_modelled"]:
        note += "; the pose error of " + ", ".join(camera_unc["not_modelled"]) + " (no pose covariance stated)"
    if partly:
        note += "; so the camera term of " + ", ".join(partly) + " is partial"
    return {"included": True, "note": note, "route": "multiview",
            "sigma_rotation_deg": camera_unc["sigma_rotation_deg"], "sigma_centre_m": camera_unc["sigma_centre_m"],
            "centre_enu": None, "models": camera_unc["models"], "views_own_covariance": camera_unc["own"],
            "views_not_modelled": camera_unc["not_modelled"], "carriages": sorted(per_car),
            "view_shares": {n: r["views"] for n, r in per_car.items()}}


def _camera_uncertainty_record(camera_unc: dict | None, cam_doc: dict) -> dict:
    if camera_unc is not None and camera_unc.get("multiview"):
        return _multiview_record(camera_unc)
    if camera_unc is None:
        g = cam_doc.get("georegistration") or {}
        why = ("cameras given as exact (no georegistration covariance in the cameras file)" if not g else
               "georegistration.pose_uncertainty states no pose covariance for any photo (every model's "
               "similarity undetermined, or only photos placed on their own): the intervals are the fit's alone"
               if g.get("pose_uncertainty") else
               "the georegistration states no camera-pose covariance (an older cameras.json, or a multi-view "
               "one without georegistration.pose_uncertainty): the intervals are the fit's alone")
        return {"included": False, "note": why}
    C = camera_unc["cov"]
    sd = np.sqrt(np.clip(np.diag(C), 0.0, None))
    if camera_unc.get("gps"):
        return {"included": True,
                "note": "placed by the photo's GPS and compass: the levelling's tilt, the compass's heading and the "
                        "GPS centre's uncertainty are added to every carriage's (first order: the scene turns and "
                        "moves with the camera); sigma_*_fit_* give the fit's alone",
                "sigma_rotation_deg": np.degrees(sd[:3]).tolist(), "sigma_centre_m": sd[3:].tolist(),
                "centre_enu": np.asarray(camera_unc["centre_enu"], dtype=float).tolist(),
                "carriages": camera_unc.get("carriages", [])}
    if camera_unc.get("levelling"):
        return {"included": True,
                "note": "relative scene: the levelling's tilt uncertainty (from the upright carriages) is added to "
                        "every carriage's (first order: the scene turns about the camera); sigma_*_fit_* give "
                        "the fit's alone",
                "sigma_rotation_deg": np.degrees(sd[:3]).tolist(), "sigma_centre_m": [0.0, 0.0, 0.0],
                "centre_enu": [0.0, 0.0, 0.0], "carriages": camera_unc.get("carriages", [])}
    return {"included": True,
            "note": "the georegistration's camera-pose covariance is added to every carriage's (first order: the "
                    "poses move with the camera, held where the terrain contact or the track prior holds them); "
                    "sigma_*_fit_* give the fit's alone",
            "sigma_rotation_deg": np.degrees(sd[:3]).tolist(), "sigma_centre_m": sd[3:].tolist(),
            "centre_enu": np.asarray(camera_unc["centre_enu"], dtype=float).tolist(),
            "carriages": camera_unc.get("carriages", [])}


def _num(x: Any) -> float | None:
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _frame_record(project: Project, levelling: Levelling | None) -> dict:
    """``solution.json``'s ``frame``: the project's georeference, or (a relative scene) the levelled local frame
    and how it was made, with no latitude, longitude or CRS (docs/pipeline.md)."""
    loc = project.settings.location
    if levelling is None:
        return {"kind": "georeferenced", "crs": loc.crs, "lat": loc.lat, "lon": loc.lon, "height_m": loc.height_m}
    placed = levelling.placement
    if placed is not None:  # levelled from the carriages, placed by the photo's GPS and compass
        W = placed["world_from_levelled"] @ levelling.world_from_provisional
        return {"kind": "gps", "crs": loc.crs, "lat": loc.lat, "lon": loc.lon, "height_m": loc.height_m,
                "world_from_cameras": W.tolist(), "levelling": levelling.to_dict(), "placement": placed["record"]}
    return {"kind": "relative", "crs": None,
            "axes": "origin at the camera centre; z up (levelled from the carriages standing on their wheels); y "
                    "along the ray through the reference photo's centre pixel, x to its right; metres (the cars' "
                    "dimensions)",
            "world_from_cameras": levelling.world_from_provisional.tolist(), "levelling": levelling.to_dict()}


def solution_document(project: Project, res: Any, views: list, cam_doc: dict, obs: dict,
                      levelling: Levelling | None = None) -> dict:
    """The ``solution.json`` document (docs/pipeline.md) of a :class:`SolveResult`; ``levelling`` for a relative
    scene (no CRS or WGS84 figures then)."""
    frame = project.frame
    georeferenced = levelling is None or levelling.placement is not None
    d = res.to_dict()
    s = project.settings
    cars_out = []
    by_number = {c.number: c for c in res.carriages}
    for i, car in enumerate(s.consist):
        cr = by_number[car.number]
        e = d["carriages"][i]
        rec: dict[str, Any] = {"index": i, "number": car.number, "type": cr.type_id, "status": cr.status,
                               "n_points": cr.n_points, "coupling_to_next": car.coupling_to_next.value
                               if car.coupling_to_next else None}
        if cr.world_from_carriage is not None:
            M = np.asarray(cr.world_from_carriage)
            c_enu = np.asarray(cr.body_centre_m, dtype=float)
            h, p, r = hpr_from_rotation(M[:3, :3])
            rec.update({
                "world_from_carriage": M.tolist(), "origin_enu": M[:3, 3].tolist(),
                "body_centre_enu": c_enu.tolist(),
                "body_centre_crs": frame.crs_from_enu(c_enu[None])[0].tolist() if georeferenced else None,
                "body_centre_wgs84": frame.wgs84_from_enu(c_enu[None])[0].tolist() if georeferenced else None,
                "heading_deg": float(h), "pitch_deg": float(p), "roll_deg": float(r),
            })
        for k in ("sigma_body_centre_m", "ci95_body_centre_m", "sigma_position_m", "ci95_position_m",
                  "sigma_hpr_deg", "ci95_hpr_deg", "covariance_pose", "centre_curvature_m2", "residuals_px", "rms_px",
                  "clearance_m"):
            rec[k] = e.get(k)
        rec["observations"] = {v: {p: [o.u, o.v] for p, o in pts.items()} for v, pts in obs.get(car.number, {}).items()}
        sig = {v: {p: o.sigma_px for p, o in pts.items() if o.sigma_px is not None}
               for v, pts in obs.get(car.number, {}).items()}
        rec["sigma_px"] = {v: d for v, d in sig.items() if d}
        pred = {v: sorted(p for p, o in pts.items() if o.derived) for v, pts in obs.get(car.number, {}).items()}
        rec["predicted"] = {v: ps for v, ps in pred.items() if ps}  # points that guide but add no information
        cars_out.append(rec)
    # reprojection residuals of the measured points and of the predictions, apart (predictions are not fitted
    # as measurements: their residuals say how far the one-face poses they came from were off)
    sq = {True: [], False: []}
    for rec in cars_out:
        for v, pts in (rec.get("residuals_px") or {}).items():
            for p, e in pts.items():
                if e is not None and np.all(np.isfinite(e)):
                    sq[p in rec["predicted"].get(v, [])].append(float(np.sum(np.square(e))))
    rms = {k: (float(np.sqrt(np.mean(x))) if x else None) for k, x in sq.items()}
    # coupler gaps along the consist
    types = project.carriage_types()
    for i in range(len(cars_out) - 1):
        a, b = cars_out[i], cars_out[i + 1]
        gap = None
        if "world_from_carriage" in a and "world_from_carriage" in b:
            Ma, Mb = np.asarray(a["world_from_carriage"]), np.asarray(b["world_from_carriage"])
            ra = Ma[:3, :3] @ np.asarray(types[a["number"]].coupler_rear) + Ma[:3, 3]
            fb = Mb[:3, :3] @ np.asarray(types[b["number"]].coupler_front) + Mb[:3, 3]
            gap = float(np.linalg.norm(ra - fb))
        a["coupler_gap_to_next_m"] = gap
    if cars_out:
        cars_out[-1]["coupler_gap_to_next_m"] = None
    return {
        "status": res.status, "message": res.message,
        "frame": _frame_record(project, levelling),
        "route": cam_doc.get("route"), "intrinsics_source": cam_doc.get("intrinsics_source"),
        "georegistration": cam_doc.get("georegistration"),
        "views": [v.name for v in views], "focal_px": d.get("focal_px"), "sigma_focal_px": d.get("sigma_focal_px"),
        "sigma_px": d.get("sigma_px"), "sigma_px_estimated": d.get("sigma_px_estimated"),
        "sigma_px_camera": d.get("sigma_px_camera"), "dof": d.get("dof"),
        "face_sigma_px": d.get("face_sigma_px"), "face_misfit_max_px": d.get("face_misfit_max_px"),
        "aligned_misfit_max_px": d.get("aligned_misfit_max_px"), "noise_estimated": d.get("noise_estimated"),
        "ci95_factor": d.get("ci95_factor"), "iterations": d.get("iterations"), "time_s": d.get("time_s"),
        "final_cost": d.get("final_cost"), "cost_at_minimum": d.get("cost_at_minimum"),
        "bias_correction": d.get("bias_correction") or {}, "carriages": cars_out, "links": d.get("links", []),
        "neighbour_correlation": d.get("neighbour_correlation", []), "steps": d.get("steps", []),
        "warnings": d.get("warnings", []),
        "residual_rms_px": {"measured": rms[False], "predicted": rms[True], "n_measured": len(sq[False]),
                            "n_predicted": len(sq[True])},
    }
