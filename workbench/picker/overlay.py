"""The picker's solution overlay: after a solve, each carriage's outline and every pick's residual, per photo.

``GET /api/overlay?view=NAME`` answers :func:`solution_overlay`. The cameras are those the solve used
(:func:`picker_cameras`): the incident's ``cameras.json`` (else georef's), each view's focal replaced by the one
``solution.json`` records (``focal_px``: the solved focal where the solve estimated it, the given one otherwise).
The poses are ``solution.json``'s ``world_from_carriage`` (a carried carriage's too: its status says so).

A pick's residual is where the solved pose puts its marked point minus the pick (``predicted - uv``, pixels, the
sign of the solve's ``residuals_px``); a pick is **flagged** when the residual is longer than
:data:`FLAG_SIGMAS` times its sigma: the solve's ``solver.pixel_sigma_px``, or the pick's own ``sigma_px`` when
larger (as the solve weighs it). The picks are those the next solve would read: the incident's manual picks and
the correspond stage's automatic points, less the rejected ones and those a manual pick replaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from ..files import correspondences as mf
from ..files.solution import Solution
from ..project import Project
from .geometry import model_edges, outline, project_points

FLAG_SIGMAS = 3.0


@dataclass(frozen=True)
class PickerCamera:
    """One photo's camera as the picker uses it; ``focal_from``: ``"solution"`` or ``"cameras"``;
    ``focal_known``: whether the focal may be taken as known (solved, or given as known)."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_world: np.ndarray
    focal_from: str
    focal_known: bool


def picker_cameras(project: Project, focal_px: dict[str, float] | None = None,
                   solution: Solution | None = None) -> dict[str, PickerCamera]:
    """The incident's cameras (``cameras.json``: the incident's own, else georef's), each view's focal replaced
    by ``focal_px[view]`` where given (a solve's), and in ``solution``'s frame when given (a relative scene's
    levelled frame); ``{}`` without a cameras file."""
    cams = project.cameras()
    if cams is None:
        return {}
    every = bool(project.settings.solver.estimate_focal)
    out = {}
    for v in cams.views:
        M = np.asarray(v.cam_from_world, float) if solution is None else solution.cam_from_world(v.cam_from_world)
        f = (focal_px or {}).get(v.name)
        if f is not None and math.isfinite(f) and f > 0:
            out[v.name] = PickerCamera(v.name, v.intrinsics.with_focal(float(f)), M, "solution", True)
        else:
            out[v.name] = PickerCamera(v.name, v.intrinsics, M, "cameras", bool(v.focal_known) and not every)
    return out


def current_picks(project: Project) -> list[mf.Observation]:
    """The points the next solve would read: manual picks, and automatic points not rejected nor replaced."""
    own = project.manual_picks_path
    manual, rejected = [], []
    if own.is_file():
        cf = mf.parse(project.read_json(own), own)
        manual, rejected = cf.observations, cf.rejected
    auto = []
    ap = project.stage_dir("correspond") / mf.FILE_NAME
    if ap.is_file():
        auto = [o for o in mf.parse(project.read_json(ap), ap).observations if o.source == "sift"]
    return mf.merge(auto, manual, rejected)


def residual_record(o: mf.Observation, predicted: list[float] | None, pixel_sigma_px: float) -> dict | None:
    """One pick's residual record (None when its point has no place in the photo)."""
    if predicted is None:
        return None
    du, dv = predicted[0] - float(o.uv[0]), predicted[1] - float(o.uv[1])
    dist = math.hypot(du, dv)
    limit = FLAG_SIGMAS * max(float(pixel_sigma_px), float(o.sigma_px or 0.0))
    rec = {"carriage": o.carriage, "point": o.point, "view": o.view, "uv": [float(o.uv[0]), float(o.uv[1])],
           "predicted": predicted, "residual_px": [round(du, 3), round(dv, 3)], "distance_px": round(dist, 3),
           "limit_px": round(limit, 3), "flagged": bool(dist > limit), "source": o.source}
    if o.method is not None:
        rec["method"] = o.method
    return rec


def strict(doc):
    """``doc`` with every float that is not finite replaced by None (the page parses strict JSON)."""
    if isinstance(doc, float):
        return doc if math.isfinite(doc) else None
    if isinstance(doc, dict):
        return {k: strict(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [strict(v) for v in doc]
    return doc


def _stale(project: Project, solution_path) -> str | None:
    cam = project.cameras_path()
    try:
        if cam is not None and cam.stat().st_mtime > solution_path.stat().st_mtime:
            return (f"{project.relative(cam)} changed after the solve: the outlines use the cameras as they are now; "
                    f"run the solve again")
    except OSError:
        return None
    return None


def solution_overlay(project: Project, view: str | None = None,
                     picks: list[mf.Observation] | None = None) -> dict:
    """The overlay document (module docstring): ``available`` false with a ``reason`` before a solve or without
    cameras; else the cameras' focal per view, every posed carriage's marked points in every photo
    (``predicted[view][car][point]``: ``[u, v]`` or None), the outlines in ``view`` (``outline[car]``: polylines),
    every pick's residual, and the flagged picks (longest residual first)."""
    if not project.solution_path.is_file():
        return {"available": False, "reason": "no solve yet: run `workbench run` (the outlines and residuals come "
                                              "from out/solve/solution.json)"}
    try:
        sol = project.solution("picker's overlay")
    except InputError as exc:
        return {"available": False, "reason": str(exc)}
    cams = picker_cameras(project, sol.focal_px, sol)  # the solution's poses are in its frame (relative: levelled)
    if not cams:
        return {"available": False, "reason": "no cameras.json (the solve's cameras are gone): run georef"}
    types = project.carriage_types()
    sigma = float(project.settings.solver.pixel_sigma_px)
    predicted: dict[str, dict[str, dict]] = {v: {} for v in cams}
    outlines: dict[str, list] = {}
    cars = []
    for c in sol.carriages:
        rec = {"number": c.number, "status": c.status, "posed": c.posed, "rms_px": c.record.get("rms_px")}
        if not c.posed:
            rec["reason"] = c.reason
        cars.append(rec)
        if not c.posed or c.number not in types:
            continue
        pts = types[c.number].marked_points
        for v, cam in cams.items():
            predicted[v][c.number] = project_points(pts, c.world_from_carriage, cam.intrinsics, cam.cam_from_world)
        if view in cams:
            outlines[c.number] = outline(model_edges(types[c.number]), c.world_from_carriage, cams[view].intrinsics,
                                         cams[view].cam_from_world)
    residuals = []
    for o in (current_picks(project) if picks is None else picks):
        p = predicted.get(o.view, {}).get(o.carriage, {}).get(o.point)
        r = residual_record(o, p, sigma)
        if r is not None:
            residuals.append(r)
    flagged = sorted((r for r in residuals if r["flagged"]), key=lambda r: -r["distance_px"])
    mtime = datetime.fromtimestamp(sol.path.stat().st_mtime, timezone.utc).isoformat(timespec="seconds")
    return {"available": True, "solution": project.relative(sol.path), "solved_utc": mtime,
            "stale": _stale(project, sol.path), "status": sol.doc.get("status"),
            "pixel_sigma_px": sigma, "flag_sigmas": FLAG_SIGMAS,
            "focal_px": {v: {"focal_px": round(cam.intrinsics.fx, 3), "from": cam.focal_from} for v, cam in cams.items()},
            "cars": cars, "view": view if view in cams else None, "predicted": predicted, "outline": outlines,
            "residuals": residuals, "flagged": flagged}
