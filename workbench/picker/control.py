"""Control points in the picker (docs/picker.md, "Control points"): the incident's ``control_points.json`` as the
page shows it, a coordinate or a map click resolved to project-CRS easting/northing, WGS84 and the DEM's height,
a save (checked completely, then written atomically by :func:`workbench.files.control_points.save_control_points`)
and the georef stage run in-process with its residuals, camera placements and uncertainties.

The page sends points in the project CRS ``[E, N, h]``; the file is written in the project CRS (a file the user
wrote in another CRS is read, shown in the project CRS, and written back in it; the previous file is kept as
``control_points.json.bak``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..core.io import read_json
from ..errors import InputError, WorkbenchError
from ..files.control_points import load_control_points, parse_track_picks, save_control_points
from ..project import Project
from .map import MapService

log = logging.getLogger(__name__)

__all__ = ["ControlPointsApi", "CHI2_3_95", "LOCATE_KEYS"]

FLAG_SIGMAS = 3.0  # a pick is flagged beyond this many of its point's 1-sigma
MIN_POINTS_ALONE = 4  # control points a photo needs to be placed on its own and checked (georef's single route)
COLLINEAR_RATIO = 0.02  # second over first singular value of the centred points: below it, "on one line"
MIN_PHOTO_SPAN = 0.05  # the picks' bounding box as a fraction of the photo's area: below it, "crowded"
CHI2_3_95 = 7.815  # 95 % quantile of chi-squared with 3 degrees of freedom (a 3-D ellipsoid)
LOCATE_KEYS = {"e", "n", "lat", "lon", "from"}
SAVE_KEYS = {"crs", "description", "points", "track_picks"}


def _number(payload: dict, key: str, where: str) -> float:
    v = payload.get(key)
    try:
        x = float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan
    except OverflowError:  # an integer of hundreds of digits
        x = math.nan
    if not math.isfinite(x):
        raise InputError(f"{where}: {key} = {str(v)[:40]!r} must be a finite number")
    return x


def _azimuth_tilt(cam_from_world: np.ndarray) -> tuple[float, float]:
    """The optical axis' azimuth (degrees clockwise from true north: the scene's +y) and tilt (degrees below the
    horizon) of a camera ``cam_from_world`` (4, 4)."""
    z = np.asarray(cam_from_world, float)[2, :3]  # the camera's +z in the scene frame (the rotation's third row)
    return float(math.degrees(math.atan2(z[0], z[1])) % 360.0), float(math.degrees(math.asin(-np.clip(z[2], -1, 1))))


class ControlPointsApi:
    """The control-point endpoints of one picker; ``image_sizes`` gives the incident's photos and their sizes."""

    def __init__(self, project: Project, image_sizes: Callable[[], dict[str, tuple[int, int]]]) -> None:
        self.project = project
        self.map = MapService(project)
        self.image_sizes = image_sizes
        self._lock = threading.Lock()

    @property
    def path(self) -> Path:
        return self.project.control_points_path

    # -- reading -------------------------------------------------------------------------------------------
    def document(self) -> dict:
        """The control points as the page shows them: each in the project CRS and WGS84, its pixels."""
        frame = self.project.frame
        out: dict[str, Any] = {"file": str(self.path), "crs": self.project.settings.location.crs, "points": [],
                               "description": ""}
        if not self.path.is_file():
            return out
        cps = load_control_points(self.path, frame)
        raw = self.project.read_json(self.path)
        out["description"] = raw.get("description", "") if isinstance(raw, dict) else ""
        out["file_crs"] = raw.get("crs") if isinstance(raw, dict) else None
        out["track_picks"] = [{"photo": t.photo, "line": t.line, "rail": t.rail, "gauge_m": t.gauge_m,
                               "pixels": [[float(u), float(v)] for u, v in t.pixels]}
                              for t in parse_track_picks(raw, str(self.path))]
        for cp in cps:
            en = frame.crs_from_enu(cp.enu)
            geo = frame.wgs84_from_enu(cp.enu)
            out["points"].append({"name": cp.name, "coords": [round(float(en[0]), 3), round(float(en[1]), 3),
                                                              round(float(cp.coords[2]), 3)],
                                  "lon": float(geo[0]), "lat": float(geo[1]), "sigma_m": cp.sigma_m, "kind": cp.kind,
                                  "pixels": {k: [float(v[0]), float(v[1])] for k, v in cp.pixels.items()}})
        return out

    def locate(self, payload: Any) -> dict:
        """``{"e", "n"}`` (project CRS) or ``{"lat", "lon"}`` (WGS84, degrees), ``"from": "map" | "typed"`` ->
        both, the map pixel and the DEM's height (bilinear). A map click outside the DEM is refused with its
        extent; a typed point outside it, or any point of an incident without a DEM, gets no DEM height (type
        one)."""
        where = "locate"
        if not isinstance(payload, dict):
            raise InputError(f"{where}: send an object {{\"e\", \"n\"}} or {{\"lat\", \"lon\"}}")
        unknown = sorted(set(payload) - LOCATE_KEYS)
        if unknown:
            raise InputError(f"{where}: unknown key {unknown[0]!r} (keys: e, n or lat, lon; from)")
        source = payload.get("from", "typed")
        if source not in ("map", "typed"):
            raise InputError(f"{where}: from = {str(source)[:20]!r} must be 'map' or 'typed'")
        frame = self.project.frame
        if "lat" in payload or "lon" in payload:
            lat, lon = _number(payload, "lat", where), _number(payload, "lon", where)
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise InputError(f"{where}: lat {lat}, lon {lon} is not a WGS84 position (lat -90..90, lon -180..180)")
            e, n = (float(x) for x in frame.crs_from_wgs84(np.array([lon, lat, 0.0]))[:2])
        else:
            e, n = _number(payload, "e", where), _number(payload, "n", where)
        geo = frame.wgs84_from_crs(np.array([e, n, 0.0]))
        enu = frame.enu_from_crs(np.array([e, n, frame.height_m]))
        if float(np.hypot(enu[0], enu[1])) > 20_000.0:
            raise InputError(f"{where}: ({e:.1f}, {n:.1f}) lies {np.hypot(enu[0], enu[1]) / 1000:.1f} km from the "
                             f"incident; check the coordinates ({self.project.settings.location.crs}: easting, "
                             f"northing; WGS84: latitude, longitude)")
        out = {"e": e, "n": n, "lon": float(geo[0]), "lat": float(geo[1]), "map_uv": self._map_uv(e, n)}
        try:
            out["dem_height_m"] = self.map.height_at(e, n)
        except InputError as exc:
            if source == "map" and self.map.terrain() is not None:  # outside the DEM: refused with its extent
                raise InputError(f"map click refused: {exc}") from None
            out["dem_height_m"], out["dem_note"] = None, str(exc)  # typed, or no DEM at all: type the height
        return out

    def _map_uv(self, e: float, n: float) -> list[float] | None:
        """The map pixel of (e, n), or None when the incident has no map (no orthophoto and no DEM)."""
        try:
            return self.map.image().pixel_from_crs(np.array([[e, n]]))[0].tolist()
        except InputError:
            return None

    # -- saving --------------------------------------------------------------------------------------------
    def check(self, payload: Any) -> dict:
        """The document a save of ``payload`` writes, checked beyond the file's own rules: only the keys of
        control_points.json, pixels only in the incident's photos and inside them. Writes nothing."""
        if not isinstance(payload, dict):
            raise InputError('the save must be a JSON object {"crs": ..., "points": [...]}')
        unknown = sorted(set(payload) - SAVE_KEYS)
        if unknown:
            raise InputError(f"unknown key {unknown[0]!r} in the save (its keys: crs, description, points, "
                             f"track_picks)")
        points = payload.get("points")
        track = payload.get("track_picks", [])
        if not isinstance(points, list) or not isinstance(track, list) or not (points or track):
            raise InputError("points: a save needs a list of at least one point, or track_picks a list of at least "
                             "one pick on the track (nothing is written for none)")
        sizes = dict(self.image_sizes())
        others: list = []  # the incident's other photos, read once when a pick names one

        def check_pixel(where: str, photo: Any, uv: Any) -> None:
            """``photo`` is a photo of the incident (of any photo set: the file may name several; docs/gis.md)
            and ``uv`` (a pair of numbers: the file's reader checks the rest) lies inside it."""
            if not isinstance(photo, str) or photo not in sizes:
                if not others:
                    others.append(self._other_photos())
                if photo not in others[0]:
                    raise InputError(f"{where}: photo {str(photo)[:60]!r} is not a photo of this incident (under "
                                     f"{self.project.root / 'photos'})")
                sizes[photo] = others[0][photo]
            w, h = sizes[photo]
            if (isinstance(uv, list) and len(uv) == 2 and all(isinstance(x, (int, float)) for x in uv)
                    and not (-0.5 <= uv[0] <= w - 0.5 and -0.5 <= uv[1] <= h - 0.5)):
                raise InputError(f"{where}: pixel {uv} lies outside {photo} ({w}x{h})")

        for i, p in enumerate(points):
            pix = p.get("pixels", {}) if isinstance(p, dict) else {}
            if not isinstance(pix, dict):
                raise InputError(f"points[{i}].pixels must be an object photo -> [u, v]")
            for photo, uv in pix.items():
                check_pixel(f"points[{i}] ({str(p.get('name'))[:40]!r})", photo, uv)
        for i, t in enumerate(track):  # picks on the track: in a photo of the incident, every pixel inside it
            if not isinstance(t, dict) or not isinstance(t.get("pixels"), list):
                raise InputError(f"track_picks[{i}] must be an object with a list of pixels "
                                 f'{{"photo", "line", "rail", "pixels": [[u, v], ...]}}')
            if not t["pixels"]:
                check_pixel(f"track_picks[{i}]", t.get("photo"), None)
            for uv in t["pixels"]:
                check_pixel(f"track_picks[{i}]", t.get("photo"), uv)
        return {k: payload[k] for k in ("crs", "description", "points", "track_picks") if k in payload}

    def _other_photos(self) -> dict[str, tuple[int, int]]:
        """Every photo of the incident under ``photos/`` (all photo sets, inside the folder) by name, with its
        size."""
        from PIL import Image

        from ..georef.inputs import photos_by_name

        out = {}
        root = self.project.root.resolve()
        for name, path in photos_by_name(self.project).items():
            try:
                if not path.resolve().is_relative_to(root):
                    continue
                with Image.open(path) as im:
                    out[name] = im.size
            except (OSError, ValueError):
                continue
        return out

    def _kept_track_picks(self) -> list:
        """The ``track_picks`` of the file as it is (docs/gis.md), which a save from the page keeps; none when the
        file is missing or unreadable (the save then checks and writes the points alone)."""
        try:
            old = read_json(self.path) if self.path.is_file() else {}
        except (InputError, OSError):
            return []
        tp = old.get("track_picks") if isinstance(old, dict) else None
        return tp if isinstance(tp, list) else []

    def save(self, payload: Any) -> dict:
        """Check (:meth:`check`, then the georef stage's reader), write atomically keeping a backup."""
        with self._lock:
            doc = self.check(payload)
            kept = self._kept_track_picks()
            if "track_picks" not in doc and kept:  # a save of the points alone keeps the file's track picks
                doc["track_picks"] = kept
            if not doc.get("track_picks"):
                doc.pop("track_picks", None)
            path, backup = save_control_points(self.path, doc, self.project.frame)
        return {"saved": str(path), "backup": str(backup) if backup else None, "n": len(doc["points"]),
                "n_picks": sum(len(p.get("pixels", {})) for p in doc["points"]),
                "n_track_picks": sum(len(t.get("pixels") or []) for t in doc.get("track_picks", []))}

    # -- georef --------------------------------------------------------------------------------------------
    def run_georef(self) -> dict:
        """Run the georef stage in-process (under the incident's lock; it writes out/georef/cameras.json and
        stats.json) and summarise it for the page."""
        from ..georef.stage import run_georef

        project = self.project
        t0 = time.perf_counter()
        notes = self.layout_notes()
        with self._lock, project.lock():
            try:
                result = run_georef(project, lambda fraction, message="": None)
            except WorkbenchError as exc:  # the stage's message, then what the picks' layout says
                raise InputError(str(exc) + "".join(f". {n}" for n in notes)) from None
            stats = {**dict(result.stats), "stage": "georef", "duration_s": round(time.perf_counter() - t0, 3),
                     "run_by": "picker"}
            project.write_json(project.stage_dir("georef") / "stats.json", stats)
        doc = project.read_json(result.outputs["cameras"])
        return {**self.summary(doc, stats), "layout_notes": notes}

    def layout_notes(self) -> list[str]:
        """What the saved control points' layout says before a georef, per photo of the incident's photo set:
        too few to place it on its own (how many more), points nearly on one line in the scene, or picks crowded
        into a small part of the photo."""
        if not self.path.is_file():
            return []
        cps = load_control_points(self.path, self.project.frame)
        out = []
        for photo, (w, h) in self.image_sizes().items():
            pts = [cp for cp in cps if photo in cp.pixels]
            n = len(pts)
            if 0 < n < MIN_POINTS_ALONE:
                out.append(f"{photo}: {n} control point(s) picked in it; placing it on its own needs 3 and checking "
                           f"them a 4th (2 with the camera's GPS position, 1 with GPS and a compass direction): pick "
                           f"{MIN_POINTS_ALONE - n} more, spread over the photo")
            if n < 3:
                continue
            X = np.array([cp.enu for cp in pts])
            sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
            if sv[1] < COLLINEAR_RATIO * sv[0]:
                out.append(f"{photo}: its {n} control points lie nearly on one line in the scene (spread across it "
                           f"{sv[1] / math.sqrt(n):.2f} m for {sv[0] / math.sqrt(n):.1f} m along it): add points off "
                           f"that line")
            uv = np.array([cp.pixels[photo] for cp in pts])
            span = np.ptp(uv, axis=0) / np.array([w, h])
            if span[0] * span[1] < MIN_PHOTO_SPAN:
                out.append(f"{photo}: the picks cover {100 * span[0]:.0f} % x {100 * span[1]:.0f} % of the photo: "
                           f"points spread over it place the camera better")
        return out

    def summary(self, doc: dict, stats: dict) -> dict:
        """Residuals (px and m, flagged where the stage warns), each camera's placement (scene frame, project CRS,
        WGS84, optical axis azimuth and tilt, map pixel) and 1-sigma / 95 % figures."""
        from ..georef.options import GeorefOptions

        opts, frame = GeorefOptions(), self.project.frame
        g = doc.get("georegistration") or {}
        try:
            sigma = {cp.name: cp.sigma_m for cp in load_control_points(self.path, frame)}
        except (InputError, OSError):
            sigma = {}
        res = []
        for r in g.get("residuals") or []:
            # does not fit: an outlier, behind the camera, or off its ray by more than 3 times the point's own
            # 1-sigma (at least the stage's warn_point_m) and by more than the stage's warn_point_px in the photo
            e_px, e_m = r.get("error_px"), r.get("error_m")
            limit_m = max(opts.warn_point_m, FLAG_SIGMAS * sigma.get(r.get("point"), 0.0))
            flagged = (e_px is None or not r.get("inlier", True)
                       or (e_m is not None and e_m > limit_m and e_px > opts.warn_point_px))
            res.append({"point": r.get("point"), "view": r.get("view"), "uv": r.get("uv"),
                        "residual_px": r.get("residual_px"), "error_px": e_px, "error_m": e_m,
                        "inlier": r.get("inlier", True), "flagged": bool(flagged), "limit_m": limit_m})
        unc = g.get("view_uncertainty") or {}
        cov6 = g.get("covariance_world_rotation_centre")
        cams = []
        for v in doc.get("views", []):
            M = np.asarray(v["cam_from_world"], float)
            c = np.asarray(v["center_enu"], float)
            en = frame.crs_from_enu(c)
            geo = frame.wgs84_from_enu(c)
            az, tilt = _azimuth_tilt(M)
            cam = {"name": v["name"], "centre_enu": c.tolist(), "centre_crs": [float(x) for x in en],
                   "lon": float(geo[0]), "lat": float(geo[1]), "azimuth_deg": az, "tilt_deg": tilt,
                   "map_uv": self._map_uv(float(en[0]), float(en[1]))}
            C = None
            if cov6 is not None:
                C6 = np.asarray(cov6, float)
                C, sr = C6[3:, 3:], float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(C6[:3, :3]).max(), 0.0))))
                cam["sigma_rotation_deg"] = sr
            elif isinstance(unc.get(v["name"]), dict) and unc[v["name"]].get("cov_centre_enu_m2") is not None:
                u = unc[v["name"]]
                C = np.asarray(u["cov_centre_enu_m2"], float)
                sr = u.get("sigma_rotation_deg")
                cam["sigma_rotation_deg"] = float(np.max(sr)) if sr is not None else None
            if C is not None:
                C = 0.5 * (C + C.T)
                cam["sigma_centre_enu_m"] = np.sqrt(np.clip(np.diag(C), 0, None)).tolist()
                cam["cov_centre_enu_m2"] = C.tolist()
                # the 95 % ellipsoid's longest semi-axis: sqrt(chi2_3(0.95) * largest eigenvalue)
                cam["ci95_centre_max_m"] = float(np.sqrt(CHI2_3_95 * max(np.linalg.eigvalsh(C).max(), 0.0)))
            cams.append(cam)
        return {"route": doc.get("route"), "frame": doc.get("frame", "scene"), "rms_px": g.get("rms_px"),
                "rms_m": g.get("rms_m"), "n_points": g.get("n_points"), "n_outliers": g.get("n_outliers"),
                "residuals": res, "cameras": cams, "priors": g.get("priors"),
                "warnings": stats.get("warnings", []), "duration_s": stats.get("duration_s"),
                "limits": {"warn_point_px": opts.warn_point_px, "warn_point_m": opts.warn_point_m,
                           "flag_sigmas": FLAG_SIGMAS}}
