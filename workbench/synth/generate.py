"""``workbench synth``: generate a complete incident with ground truth, deterministic for a seed.

Writes into an incident folder (through :class:`~workbench.project.Project` paths, atomically):
the DEM GeoTIFF, building footprints and the railway line the train ran on (``layers/`` or a regional ``terrain/``
folder), ``project.toml``,
``camera_profile.json``, the photos (``photos/panorama`` from one position, the camera only turning;
``photos/multiview`` from places around the site), instance masks and ``truth/ground_truth.json``
(carriage poses and their place on the track, camera poses and intrinsics, every marked point's true pixel and
visibility in every photo). The format is in ``docs/formats.md``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import tomli_w
from PIL import Image
from shapely.geometry import Point, Polygon

from ..core.camera import CameraIntrinsics, look_at, project_world
from ..core.frames import SceneFrame, hpr_from_rotation
from ..core.geometry import rot_z
from ..core.io import atomic_write, atomic_write_text, to_json
from ..core.settings import SETTINGS_FILE, parse_settings
from ..errors import WorkbenchError
from ..files.buildings import write_buildings_geojson
from ..files.dem import TerrainModel
from ..files.exif import write_jpeg
from ..render.lens import render_photo
from ..render.offscreen import OffscreenScene, SceneMesh
from ..rolling_stock import load_library
from ..terrain.extrude import building_meshes
from .buildings import make_buildings
from .control_points import PIXEL_SIGMA_PX, write_control_points
from .layout import HELD_OFFSET_MAX_M, lay_consist
from .scenarios import SCENARIOS, plan_consist
from .terrain import make_terrain, write_dem_geotiff
from .track import carriage_track_truth, write_track_layer

log = logging.getLogger(__name__)

GENERATOR_VERSION = 4
SENSOR_WIDTH_MM = 23.5  # APS-C, for the EXIF focal length


@dataclass(frozen=True, kw_only=True)
class SynthOptions:
    scenario: str = "spuyten-duyvil"
    seed: int = 1
    n_cars: int | None = None  # None: the scenario's consist; fewer (tests) or more
    photo_width: int = 1600
    photo_height: int = 1200
    hfov_deg: float = 50.0  # nominal horizontal field of view of the camera
    distortion: tuple[float, float, float, float, float] = (-0.08, 0.012, 0.0004, -0.0003, 0.0)  # k1 k2 p1 p2 k3
    n_panorama: int | None = None  # None: 5..8, enough to cover the consist with ~40% overlap
    n_multiview: int = 12  # 0: no multi-position set
    terrain_size_m: float = 500.0
    terrain_resolution_m: float = 1.0
    layers_dir: str = "layers"  # where the DEM and buildings go, relative to the incident folder
    supersample: int = 2

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise WorkbenchError(f"unknown scenario {self.scenario!r}; choose one of {sorted(SCENARIOS)}")
        if self.n_cars is not None and not (1 <= self.n_cars <= 40):
            raise WorkbenchError(f"--cars {self.n_cars}: give 1 to 40 carriages")
        if not (64 <= self.photo_width <= 8000 and 48 <= self.photo_height <= 6000):
            raise WorkbenchError(f"photo size {self.photo_width}x{self.photo_height} is out of range")
        if self.n_panorama is not None and not (2 <= self.n_panorama <= 12):
            raise WorkbenchError(f"--panorama {self.n_panorama}: give 2 to 12 photos")
        if not (0 <= self.n_multiview <= 40):
            raise WorkbenchError(f"--multiview {self.n_multiview}: give 0 to 40 photos")
        if not (100.0 <= self.terrain_size_m <= 5000.0):
            raise WorkbenchError(f"--terrain-size {self.terrain_size_m:g}: give 100 to 5000 m (the cameras stand up to "
                                 f"the ground's edge less 40 m)")

    def spec_hash(self) -> str:
        blob = json.dumps({**asdict(self), "version": GENERATOR_VERSION}, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# ---------------------------------------------------------------------------------------------------
def camera_rotation(bearing_deg: float, elevation_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """``cam_from_world`` rotation for a camera looking along compass ``bearing_deg``, tilted up by
    ``elevation_deg`` and rolled clockwise (as seen by the photographer) by ``roll_deg``."""
    b, e = np.deg2rad(bearing_deg), np.deg2rad(elevation_deg)
    fwd = np.array([np.sin(b) * np.cos(e), np.cos(b) * np.cos(e), np.sin(e)])
    R = look_at(np.zeros(3), fwd)[:3, :3]
    return rot_z(np.deg2rad(roll_deg)) @ R


def _pose(R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ centre
    return M


def _inside_any(xy: np.ndarray, polygons, margin: float) -> bool:
    p = Point(float(xy[0]), float(xy[1]))
    return any(Polygon(poly).buffer(margin).contains(p) for poly in polygons)


class _Site:
    """What camera placement needs to know about the site (ENU)."""

    def __init__(self, terrain_model, water_enu, building_polys_enu, half_size: float):
        self.tm = terrain_model
        self.water = [water_enu] if water_enu is not None and len(water_enu) >= 3 else []
        self.buildings = building_polys_enu
        self.half = half_size

    def ok(self, xy: np.ndarray, margin: float = 25.0) -> bool:
        if np.any(np.abs(xy) > self.half - margin):
            return False
        if _inside_any(xy, self.water, 3.0) or _inside_any(xy, self.buildings, 4.0):
            return False
        return bool(np.isfinite(self.tm.height_at(xy[None])[0]))

    def ground(self, xy: np.ndarray) -> float:
        return float(self.tm.height_at(np.asarray(xy, float)[None])[0])


def _marked_points_world(placed) -> np.ndarray:
    return np.vstack([p.world_from_carriage.apply(np.array(list(p.ctype.marked_points.values()))) for p in placed])


def visible_fraction(scene, centre: np.ndarray, points: np.ndarray) -> float:
    """Share of ``points`` (n, 3) that a camera at ``centre`` sees unoccluded (ray casts against the scene)."""
    import open3d as o3d

    rs, _ = scene._raycaster()
    d = points - centre
    dist = np.linalg.norm(d, axis=1)
    rays = np.empty((len(points), 6), np.float32)
    rays[:, :3] = centre
    rays[:, 3:] = d / dist[:, None]
    t = rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return float(np.mean(t >= dist - (0.05 + 0.01 * dist)))


def _car_corners(placed) -> np.ndarray:
    pts = []
    for p in placed:
        bb = np.asarray(p.ctype.bounding_box())
        corners = np.array([[x, y, z] for x in bb[:, 0] for y in bb[:, 1] for z in bb[:, 2]])
        pts.append(p.world_from_carriage.apply(corners))
    return np.vstack(pts)


def plan_panorama(placed, site: _Site, scene, opts: SynthOptions, rng) -> tuple[np.ndarray, list]:
    """One camera position about 1.1 consist extents away, on high ground; 5-8 photos turning about it."""
    corners = _car_corners(placed)
    centre = corners.mean(axis=0)
    extent = float(np.max(np.linalg.norm(corners[:, None, :2] - corners[None, :, :2], axis=2)))
    dist = float(np.clip(0.8 * extent, 50.0, site.half - 40.0))
    targets = _marked_points_world(placed)
    best = None
    for a in np.arange(0.0, 360.0, 10.0):
        d = np.array([np.sin(np.deg2rad(a)), np.cos(np.deg2rad(a))])
        for f in (1.0, 0.8):
            xy = centre[:2] + d * dist * f
            if not site.ok(xy):
                continue
            g = site.ground(xy)
            # standing on the ground, or raised (embankment, bridge, aerial ladder)
            for z in (g + 1.7, max(g + 1.7, centre[2] + 15.0)):
                # a raised view sees the jackknifed cars from above; a ground view must be clearly better
                score = visible_fraction(scene, np.array([xy[0], xy[1], z]), targets) - (0.15 if z - g < 2 else 0.0)
                if best is None or score > best[0]:
                    best = (score, xy, z)
    if best is None:
        raise WorkbenchError("synth: found no place for the panorama camera on this terrain; try another seed")
    _, xy, z = best
    cam = np.array([xy[0], xy[1], z])
    rel = corners - cam
    bearings = np.rad2deg(np.arctan2(rel[:, 0], rel[:, 1]))
    mid = np.rad2deg(np.arctan2(*(centre - cam)[:2]))
    rel_b = (bearings - mid + 180.0) % 360.0 - 180.0
    lo, hi = rel_b.min() - 4.0, rel_b.max() + 4.0
    step = opts.hfov_deg * 0.6  # 40 % overlap
    n = opts.n_panorama or int(np.clip(np.ceil(max(hi - lo - opts.hfov_deg, 0) / step) + 1, 5, 8))
    span = max(hi - lo - opts.hfov_deg, (n - 1) * 0.2 * opts.hfov_deg)
    span = min(span, (n - 1) * step)
    yaws = mid + (lo + hi) / 2 + np.linspace(-span / 2, span / 2, n)
    elev = np.rad2deg(np.arctan2(centre[2] - cam[2], np.linalg.norm((centre - cam)[:2])))
    views = []
    for k, yaw in enumerate(yaws):
        R = camera_rotation(yaw + rng.normal(0, 0.5), elev + rng.normal(0, 1.0), rng.normal(0, 1.0))
        views.append({"name": f"pano_{k:02d}", "cam_from_world": _pose(R, cam)})
    return cam, views


def plan_multiview(placed, site: _Site, scene, opts: SynthOptions, rng) -> list:
    """Photos from places around the site: walking distance on the ground, a few from a drone."""
    corners = _car_corners(placed)
    centre = corners.mean(axis=0)
    centres = np.array([p.world_from_carriage.translation for p in placed])
    cov = np.cov((corners[:, :2] - centre[:2]).T)
    evals, evecs = np.linalg.eigh(cov)
    a = 1.3 * np.sqrt(evals[1]) + 20.0
    b = 1.3 * np.sqrt(evals[0]) + 20.0
    views = []
    tries = 0
    while len(views) < opts.n_multiview and tries < 400:
        tries += 1
        th = 2 * np.pi * (len(views) + rng.uniform(-0.3, 0.3)) / opts.n_multiview + 0.37 * (tries // opts.n_multiview)
        direction = evecs @ np.array([a * np.cos(th), b * np.sin(th)])
        xy = None
        for scale in rng.uniform(1.0, 1.4) * np.array([1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4]):
            cand = centre[:2] + direction * scale
            if np.min(np.linalg.norm(centres[:, :2] - cand, axis=1)) < 18.0:
                break  # too close to the wreck to see it: give up this direction
            if site.ok(cand, margin=12.0):
                xy = cand
                break
        if xy is None:
            continue
        drone = len(views) % 4 == 3
        z = site.ground(xy) + (rng.uniform(15.0, 30.0) if drone else 1.7)
        cam = np.array([xy[0], xy[1], z])
        nearest = np.argsort(np.linalg.norm(centres[:, :2] - xy, axis=1))[:3]
        if visible_fraction(scene, cam, _marked_points_world([placed[i] for i in nearest])) < 0.4:
            continue  # the wreck is hidden from here (terrain, buildings)
        near = centres[nearest].mean(axis=0)
        target = 0.6 * near + 0.4 * centre + rng.normal(0, 2.0, 3)
        target[2] = max(target[2], centre[2]) + 1.0
        d = target - cam
        bearing = np.rad2deg(np.arctan2(d[0], d[1]))
        elev = np.rad2deg(np.arctan2(d[2], np.linalg.norm(d[:2])))
        R = camera_rotation(bearing, elev, rng.normal(0, 1.5))
        views.append({"name": f"view_{len(views):02d}", "cam_from_world": _pose(R, cam)})
    if len(views) < opts.n_multiview:
        raise WorkbenchError(f"synth: placed only {len(views)} of {opts.n_multiview} multi-view cameras; try "
                             f"another seed or fewer photos")
    return views


# ---------------------------------------------------------------------------------------------------
def visibility_tolerance_m(depth_m: float, focal_px: float) -> float:
    """How much nearer than a point a surface may be and the point still count as visible (metres)."""
    return 0.05 + 2.0 * depth_m / focal_px


def observe(placed, intr: CameraIntrinsics, cam_from_world: np.ndarray, depth: np.ndarray) -> dict:
    """True pixel and visibility of every marked point in one photo.

    Visible: inside the image, in front of the camera, and nothing nearer in the rendered depth buffer at
    the point's pixel than the point itself, less a tolerance of 5 cm plus two pixel footprints (a surface
    seen obliquely spans that much depth within one pixel).
    """
    out = {}
    h, w = depth.shape
    for p in placed:
        names = list(p.ctype.marked_points)
        pts = p.world_from_carriage.apply(np.array([p.ctype.marked_points[n] for n in names]))
        uv, z = project_world(intr, cam_from_world, pts)
        rec = {}
        for name, (u, v), zz in zip(names, uv, z):
            in_front = bool(zz > 0.1)
            in_img = bool(in_front and intr.in_image(np.array([[u, v]]))[0])
            visible = False
            if in_img:
                iu, iv = min(max(int(round(u)), 0), w - 1), min(max(int(round(v)), 0), h - 1)
                visible = bool(depth[iv, iu] >= zz - visibility_tolerance_m(zz, intr.fx))
            rec[name] = {"uv": [float(u), float(v)] if in_front else None, "depth_m": float(zz),
                         "in_image": in_img, "visible": visible}
        out[p.number] = rec
    return out


def _ids_png(instance: np.ndarray) -> np.ndarray:
    m = np.full(instance.shape, 255, np.uint8)
    ok = instance >= 0
    m[ok] = instance[ok].astype(np.uint8)
    return m


# ---------------------------------------------------------------------------------------------------
def _is_synthetic(settings_path: Path) -> bool:
    """Was this project.toml written by `workbench synth` (a sample whose photos are not committed)?"""
    try:
        return bool(tomllib.loads(settings_path.read_text(encoding="utf-8")).get("incident", {}).get("synthetic"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
        return False


def _write_control_points(root: Path) -> None:
    """control_points.json from the truth (cheap: no rendering; kept when already up to date)."""
    write_control_points(root)


def _keep_if_generated(root: Path, truth_path: Path, opts: SynthOptions) -> bool:
    """When ``root`` is generated with these options, every photo in place: refresh its control points, True."""
    try:
        old = json.loads(truth_path.read_text())
        photos_ok = all((root / ph["photo"]).is_file() for ph in old.get("photos", []))
        # an incident generated before the railway layer was written: generate it afresh (the same photos)
        rail = old.get("layers", {}).get("railways")
        complete = photos_ok and bool(rail) and (root / rail).is_file()
        if old.get("generator", {}).get("spec_hash") == opts.spec_hash() and complete:
            log.info("synth: %s is already generated with these options; nothing to do", root)
            _write_control_points(root)
            return True
    except (json.JSONDecodeError, KeyError, TypeError):
        pass  # an unreadable old truth file: generate afresh
    return False


@dataclass
class _Layers:
    """The site's layers as generated and written: terrain, buildings, and the scene frame they set."""

    st: object  # the SynthTerrain
    frame: SceneFrame
    h0: float  # the height of the scene origin
    tm: object  # the TerrainModel read back from the written DEM
    buildings: list
    dem_path: Path
    bld_path: Path
    ortho_path: Path
    rail_path: Path


def _make_layers(root: Path, scn, opts: SynthOptions) -> _Layers:
    """The DEM, the building footprints, the orthophoto and the railway line, written under ``opts.layers_dir``."""
    frame0 = SceneFrame(scn.crs, scn.lat, scn.lon, 0.0)
    st = make_terrain(scn.terrain, frame0, size_m=opts.terrain_size_m, resolution_m=opts.terrain_resolution_m,
                      seed=opts.seed)
    layers = root / opts.layers_dir
    dem_path = layers / f"{scn.id}_dem.tif"
    bld_path = layers / f"{scn.id}_buildings.geojson"
    ortho_path = layers / f"{scn.id}_ortho.jpg"
    rail_path = layers / f"{scn.id}_railways.geojson"
    write_dem_geotiff(dem_path, st)
    tm0 = TerrainModel.from_geotiff(dem_path, frame0)
    h0 = round(float(tm0.height_at(np.zeros((1, 2)))[0]), 2)
    frame = SceneFrame(scn.crs, scn.lat, scn.lon, h0)
    tm = TerrainModel.from_geotiff(dem_path, frame)
    buildings = make_buildings(scn.terrain, st, frame, seed=opts.seed)
    write_buildings_geojson(bld_path, buildings, scn.crs)
    atomic_write(ortho_path, lambda p: st.texture.convert("RGB").save(p, quality=90))
    write_track_layer(rail_path, st, frame0, scn.id)
    return _Layers(st, frame, h0, tm, buildings, dem_path, bld_path, ortho_path, rail_path)


def _lay_out_consist(scn, lay: _Layers, opts: SynthOptions, rng) -> list:
    """The scenario's consist, derailed along the track, coming to rest around the scene origin."""
    types = load_library()
    plans = plan_consist(scn, types, rng, opts.n_cars)
    track = np.asarray(lay.st.track_enu, float)
    seg = np.linalg.norm(np.diff(track[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s_origin = float(s[np.argmin(np.linalg.norm(track[:, :2], axis=1))])
    total = sum(p.ctype.length_m for p in plans)
    front_s = float(np.clip(s_origin + 0.3 * total, 0.0, s[-1]))
    lateral = float(rng.uniform(*scn.lateral_m) * rng.choice([-1.0, 1.0]))
    return lay_consist(plans, lay.tm, track, front_s_m=front_s, lateral_m=lateral, rng=rng)


def _camera_intrinsics(opts: SynthOptions) -> CameraIntrinsics:
    """The synthetic camera: ``opts.hfov_deg`` across, principal point a little off centre, real distortion."""
    w, h = opts.photo_width, opts.photo_height
    fx = (w / 2.0) / np.tan(np.deg2rad(opts.hfov_deg) / 2.0)
    k1, k2, p1, p2, k3 = opts.distortion
    return CameraIntrinsics(width=w, height=h, fx=fx, fy=fx, cx=(w - 1) / 2.0 + 0.013 * w,
                            cy=(h - 1) / 2.0 - 0.011 * h, k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)


def _build_scene(lay: _Layers, placed, w: int, h: int):
    """The scene to render: textured terrain, buildings, the carriages (each its instance id), the sun."""
    scene = OffscreenScene(w, h)
    scene.add(SceneMesh("terrain", lay.tm.mesh(texture=lay.st.texture)))
    for i, m in enumerate(building_meshes(lay.buildings, lay.tm, lay.frame)):
        scene.add(SceneMesh(f"building_{i}", m))
    for i, p in enumerate(placed):
        mesh = p.ctype.mesh(car_number=p.number).copy()
        mesh.apply_transform(p.world_from_carriage.matrix)
        scene.add(SceneMesh(f"car_{p.number}", mesh, instance_id=i))
    # low winter/spring sun from the south-east
    az, el = np.deg2rad(150.0), np.deg2rad(35.0)
    scene.set_sun(-np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)]))
    return scene


def _site(lay: _Layers, opts: SynthOptions) -> _Site:
    bpolys = [lay.frame.enu_from_crs(np.column_stack([np.asarray(b["footprint_crs"]),
                                                      np.zeros(len(b["footprint_crs"]))]))[:, :2]
              for b in lay.buildings]
    return _Site(lay.tm, lay.st.water_polygon_enu, bpolys, opts.terrain_size_m / 2.0)


def _render_photos(root: Path, scn, scene, intr: CameraIntrinsics, all_views: list, placed, opts: SynthOptions,
                   progress: Callable[[float, str], None]) -> list:
    """Render, write (photo with EXIF, instance mask) and observe every view; their truth records, in order."""
    date = _dt.datetime.fromisoformat(scn.date + "T07:30:00")
    w, fx = intr.width, intr.fx

    def write_photo(k: int, group: str, view: dict, res) -> dict:
        rel = f"photos/{group}/{view['name']}.jpg"
        stamp = (date + _dt.timedelta(seconds=20 * k)).strftime("%Y:%m:%d %H:%M:%S")
        write_jpeg(root / rel, res.color, focal_length_mm=fx * SENSOR_WIDTH_MM / w, sensor_width_mm=SENSOR_WIDTH_MM,
                   extra={"DateTimeOriginal": stamp})
        mask_rel = f"truth/masks/{view['name']}.png"
        atomic_write(root / mask_rel, lambda p, m=_ids_png(res.instance): Image.fromarray(m).save(p))
        M = view["cam_from_world"]
        return {"photo": rel, "set": group, "mask": mask_rel, "intrinsics": intr.to_dict(), "cam_from_world": M,
                "center_enu": -M[:3, :3].T @ M[:3, 3], "observations": observe(placed, intr, M, res.depth)}

    # two photos at a time: the ray caster is multi-threaded, but the shading is numpy, mostly on one core; the
    # renders are independent, and each photo is the same as rendered alone
    photos = []
    scene.prepare()  # built once, before the threads share it
    with ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1))) as pool:
        renders = pool.map(lambda gv: render_photo(scene, intr, gv[1]["cam_from_world"], supersample=opts.supersample),
                           all_views)
        for k, ((group, view), res) in enumerate(zip(all_views, renders)):
            progress(0.25 + 0.7 * k / len(all_views), f"photo {k + 1}/{len(all_views)}")
            photos.append(write_photo(k, group, view, res))
    return photos


def _carriages_truth(placed, frame: SceneFrame) -> list:
    """Each carriage's true pose (matrix, ENU, CRS, WGS84, heading/pitch/roll), coupler gap and marked points."""
    cars = []
    for i, p in enumerate(placed):
        M = p.world_from_carriage.matrix
        hd, pt, rl = hpr_from_rotation(M[:3, :3])
        origin = M[:3, 3]
        body_centre = p.world_from_carriage.apply(np.asarray(p.ctype.bounding_box()).mean(axis=0))
        gap = None
        if i + 1 < len(placed):
            a = p.world_from_carriage.apply(p.ctype.coupler_rear)
            b = placed[i + 1].world_from_carriage.apply(placed[i + 1].ctype.coupler_front)
            gap = float(np.linalg.norm(b - a))
        cars.append({
            "number": p.number, "type": p.ctype.id, "index": i, "instance_id": i, "state": p.state,
            "world_from_carriage": M, "position_enu": origin, "body_centre_enu": body_centre,
            "position_crs": frame.crs_from_enu(origin), "position_wgs84": frame.wgs84_from_enu(origin),
            "heading_deg": hd, "pitch_deg": pt, "roll_deg": rl,
            "coupling_to_next": p.coupling_to_next, "coupler_gap_to_next_m": gap,
            "min_terrain_clearance_m": p.min_clearance_m,
            "marked_points_enu": {n: p.world_from_carriage.apply(x) for n, x in p.ctype.marked_points.items()},
        })
    return cars


def _write_settings(root: Path, settings_path: Path, scn, opts: SynthOptions, lay: _Layers, intr: CameraIntrinsics,
                    placed, pano_centre: np.ndarray) -> None:
    """camera_profile.json and project.toml (validated before it is written)."""
    profile = {"model": "brown", "source": "synthetic camera (known exactly)", "intrinsics": intr.to_dict(),
               "sensor_width_mm": SENSOR_WIDTH_MM}
    atomic_write_text(root / "camera_profile.json", to_json(profile))
    settings = {
        "incident": {"name": scn.title, "date": _dt.date.fromisoformat(scn.date), "synthetic": True,
                     "description": f"Synthetic incident: scenario {scn.id}, seed {opts.seed}. Photos are renders; "
                                    f"the truth is in truth/ground_truth.json."},
        "location": {"lat": scn.lat, "lon": scn.lon, "height_m": lay.h0, "crs": scn.crs},
        "terrain": {"dem": os.path.relpath(lay.dem_path, root), "buildings": os.path.relpath(lay.bld_path, root),
                    "railways": os.path.relpath(lay.rail_path, root), "dem_vertical_accuracy_m": 0.25, "aoi_radius_m": opts.terrain_size_m / 2.0 - 5.0},
        "consist": [{"number": p.number, "type": p.ctype.id,
                     **({"coupling_to_next": p.coupling_to_next} if p.coupling_to_next else {})} for p in placed],
        "camera": {"source": "calibrated", "profile": "camera_profile.json", "photos": "photos/panorama",
                   "position_enu": [float(x) for x in pano_centre]},
        # the control points this generator writes (write_control_points) are the true pixels plus this noise:
        # stated, so that the georegistration's covariance is that of the picks it fits
        "georef": {"pick_sigma_px": PIXEL_SIGMA_PX},
        # the couplers' play the layout drew the held couplings' offsets from: stated, so that the solve's coupler
        # prior is the generator's (the default, 5 cm, made its intervals wider than the truth's 3 cm warrants)
        "solver": {"slack_held_m": HELD_OFFSET_MAX_M},
    }
    parse_settings(settings, str(settings_path))  # what we write must validate
    header = ("# Incident settings written by `workbench synth` (see docs/formats.md).\n"
              f"# scenario = {scn.id}, seed = {opts.seed}\n\n")
    atomic_write_text(settings_path, header + tomli_w.dumps(settings))


def generate_incident(root: Path, opts: SynthOptions, *, force: bool = False,
                      progress: Callable[[float, str], None] = lambda f, m="": None) -> dict:
    """Generate (or, when already generated with the same options, keep) a synthetic incident in ``root``."""
    root = Path(root)
    truth_path = root / "truth" / "ground_truth.json"
    settings_path = root / SETTINGS_FILE
    if truth_path.is_file() and not force and _keep_if_generated(root, truth_path, opts):
        return {"skipped": True, "truth": str(truth_path)}
    if settings_path.is_file() and not truth_path.is_file() and not force and not _is_synthetic(settings_path):
        raise WorkbenchError(f"{settings_path}: exists and is not a synthetic incident; `workbench synth` will not "
                             f"overwrite it (use an empty folder, or --force)")

    scn = SCENARIOS[opts.scenario]
    rng = np.random.default_rng(opts.seed)
    progress(0.02, "terrain")
    lay = _make_layers(root, scn, opts)
    progress(0.10, "consist")
    placed = _lay_out_consist(scn, lay, opts, rng)
    progress(0.2, "cameras")
    intr = _camera_intrinsics(opts)
    progress(0.25, "scene")
    scene = _build_scene(lay, placed, intr.width, intr.height)
    site = _site(lay, opts)
    pano_centre, pano_views = plan_panorama(placed, site, scene, opts, rng)
    multi_views = plan_multiview(placed, site, scene, opts, rng) if opts.n_multiview else []
    all_views = [("panorama", v) for v in pano_views] + [("multiview", v) for v in multi_views]
    photos = _render_photos(root, scn, scene, intr, all_views, placed, opts, progress)

    progress(0.96, "ground truth")
    cars = _carriages_truth(placed, lay.frame)
    for car, on_track in zip(cars, carriage_track_truth(placed, lay.st, scn.id)):
        car["track"] = on_track
    truth = {
        "generator": {"name": "workbench synth", "version": GENERATOR_VERSION, "spec_hash": opts.spec_hash(),
                      "options": asdict(opts)},
        "scenario": {"id": scn.id, "title": scn.title},
        "frame": {"crs": scn.crs, "lat": scn.lat, "lon": scn.lon, "height_m": lay.h0},
        "layers": {"dem": os.path.relpath(lay.dem_path, root), "buildings": os.path.relpath(lay.bld_path, root),
                   "ortho": os.path.relpath(lay.ortho_path, root), "railways": os.path.relpath(lay.rail_path, root)},
        "carriages": cars,
        "panorama_center_enu": pano_centre,
        "photos": photos,
    }
    _write_settings(root, settings_path, scn, opts, lay, intr, placed, pano_centre)
    atomic_write_text(truth_path, to_json(truth))  # last: its presence marks a complete incident
    progress(0.98, "control points")
    _write_control_points(root)
    progress(1.0, "done")
    return {"skipped": False, "truth": str(truth_path), "photos": len(photos), "carriages": len(cars)}
