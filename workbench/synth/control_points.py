"""Synthetic ground control points for a synthetic incident: ``control_points.json`` from its truth and layers.

Landmarks a person could survey and click: building roof corners and the corners where their walls meet the
ground (from the buildings layer), and marks on the ground beside the wreck (track-side features). Each is
written in the project CRS ``[E, N, h]`` with its true pixel in every photo where it is visible (inside the
image, in front of the camera, and not hidden by the terrain, a building or a carriage: checked by casting a
ray from the camera centre against those meshes), plus 0.5 px Gaussian noise (fixed seed). The choice keeps
up to ``per_photo`` points per photo (as many as the view allows), spread over the image.

:func:`write_control_points` needs only the incident folder (its ``truth/ground_truth.json`` and the layers it
names); it re-renders nothing, so it also runs on samples whose photos are already generated.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import trimesh

from ..core.camera import CameraIntrinsics, project_world
from ..core.frames import SceneFrame
from ..core.geometry import rot_x, rot_y, rot_z
from ..core.io import atomic_write_text, to_json
from ..core.layout import CONTROL_POINTS_FILE as FILE_NAME
from ..errors import InputError
from ..files.buildings import read_buildings_geojson
from ..files.control_points import STANDARD_GAUGE_M, TrackPick
from ..files.railways import read_railways
from ..files.dem import TerrainModel
from ..rolling_stock import get_type
from ..terrain.extrude import building_meshes

log = logging.getLogger(__name__)

__all__ = ["control_points_document", "write_control_points", "track_picks_document", "PIXEL_SIGMA_PX"]

PIXEL_SIGMA_PX = 0.5


def _truth(root: Path) -> dict:
    p = root / "truth" / "ground_truth.json"
    if not p.is_file():
        raise InputError(f"{p}: not found; synthetic control points are made only for synthetic incidents "
                         f"(`workbench synth`)")
    return json.loads(p.read_text(encoding="utf-8"))


def _roof_corners(mesh) -> np.ndarray:
    """(k, 3) corners of a building's flat roof (the vertices of its upward-facing top triangles)."""
    n = mesh.face_normals
    top = mesh.vertices[:, 2].max()
    f = mesh.faces[(n[:, 2] > 0.99) & (mesh.triangles_center[:, 2] > top - 0.5)]
    if len(f) == 0:
        return np.zeros((0, 3))
    v = mesh.vertices[np.unique(f)]
    _, idx = np.unique(np.round(v, 3), axis=0, return_index=True)
    return v[np.sort(idx)]


def _scene_meshes(root: Path, truth: dict, frame: SceneFrame):
    """(terrain model, [building meshes], [carriage meshes]) in the scene frame."""
    layers = truth.get("layers", {})
    dem = root / layers["dem"]
    tm = TerrainModel.from_geotiff(dem, frame)
    blds = []
    if layers.get("buildings") and (root / layers["buildings"]).is_file():
        blds = building_meshes(read_buildings_geojson(root / layers["buildings"]), tm, frame)
    extra = [root / "rolling_stock"] if (root / "rolling_stock").is_dir() else []
    cars = []
    for c in truth["carriages"]:
        m = get_type(c["type"], extra_dirs=extra).mesh(car_number=c["number"], textured=False).copy()
        m.apply_transform(np.asarray(c["world_from_carriage"], float))
        cars.append(m)
    return tm, blds, cars, trimesh


def _ground_marks(truth: dict, tm) -> list[tuple[str, np.ndarray]]:
    """Marks on the ground beside each carriage (track-side features a surveyor would pick)."""
    out = []
    for c in truth["carriages"]:
        M = np.asarray(c["world_from_carriage"], float)
        fwd = M[:3, 0].copy()
        fwd[2] = 0
        nf = np.linalg.norm(fwd)
        fwd = fwd / nf if nf > 1e-6 else np.array([1.0, 0.0, 0.0])
        left = np.array([-fwd[1], fwd[0], 0.0])
        o = M[:3, 3]
        for k, (a, b) in enumerate(((6.0, 7.0), (-6.0, -8.0), (-9.0, 6.5), (8.0, -6.0),
                                    (0.0, 5.5), (2.0, -5.0), (-3.0, 11.0), (4.0, -12.0))):
            xy = o[:2] + a * fwd[:2] + b * left[:2]
            z = tm.height_at(xy[None])[0]
            if np.isfinite(z):
                out.append((f"ground_{c['number']}_{k}", np.array([xy[0], xy[1], z])))
    return out


def _raycaster(meshes):
    """An Open3D ray-casting scene of ``meshes`` (trimesh-like: vertices, faces)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
    return scene


def _visible(scene, ph: dict, P: np.ndarray, max_range_m: float, margin_px: float = 8.0
             ) -> tuple[np.ndarray, np.ndarray]:
    """(visible (k,), true pixel (k, 2), NaN where not) of the points ``P`` (k, 3) in the truth's photo ``ph``:
    in front, inside the image by ``margin_px``, within ``max_range_m``, and not hidden (a ray from the camera
    centre hits nothing before the point, to a tolerance of 5 cm plus 2 px at its distance)."""
    import open3d as o3d

    intr = CameraIntrinsics.from_dict(ph["intrinsics"])
    uv, depth = project_world(intr, np.asarray(ph["cam_from_world"], float), P)
    c = np.asarray(ph["center_enu"], float)
    d = P - c
    dist = np.linalg.norm(d, axis=1)
    cand = (depth > 1.0) & (dist < max_range_m) & np.all(np.isfinite(uv), axis=1)
    cand &= intr.in_image(np.nan_to_num(uv, nan=-1e9), margin=margin_px)
    vis = np.zeros(len(P), bool)
    out = np.full((len(P), 2), np.nan)
    if not cand.any():
        return vis, out
    rays = np.zeros((int(cand.sum()), 6), np.float32)
    rays[:, :3] = c
    rays[:, 3:] = d[cand] / dist[cand, None]
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = t >= dist[cand] - (0.05 + 2.0 * dist[cand] / intr.fx)
    idx = np.nonzero(cand)[0][ok]
    vis[idx] = True
    out[idx] = uv[idx]
    return vis, out


def track_picks_document(root: str | Path, *, rails: tuple[str, ...] = ("left", "right"), per_rail: int = 12,
                         sigma_px: float = PIXEL_SIGMA_PX, seed: int = 0, spacing_m: float = 1.0,
                         max_range_m: float = 250.0, photo_set: str | None = "panorama") -> list[dict]:
    """``track_picks`` entries (docs/gis.md) for a synthetic incident: points on the rails (or the centre line) of
    the track its layer holds (the file's top-of-rail heights; rails at (gauge + head) / 2 from the centre line,
    as georef reads them), every ``spacing_m`` along the line, projected into each photo of ``photo_set`` (None:
    every photo) where visible (:func:`_visible`), ``per_rail`` of them spread evenly along what is seen, with
    Gaussian noise of ``sigma_px`` (seed ``seed``)."""
    root = Path(root)
    truth = _truth(root)
    fr = truth["frame"]
    frame = SceneFrame(fr["crs"], fr["lat"], fr["lon"], fr["height_m"])
    layer = read_railways(root / truth["layers"]["railways"], frame)
    if layer is None:
        raise InputError(f"{root}: the truth's railway layer holds no line")
    line = layer.lines[0]
    tm, blds, cars, _ = _scene_meshes(root, truth, frame)
    scene = _raycaster([tm.mesh(), *blds, *cars])
    rng = np.random.default_rng(seed)
    out = []
    for ph in truth["photos"]:
        if photo_set is not None and ph["set"] != photo_set:
            continue
        for rail in rails:
            off = TrackPick("", "", rail, STANDARD_GAUGE_M, np.zeros((0, 2))).offset_m
            P = line.rail_polyline(off, spacing_m)
            vis, uv = _visible(scene, ph, P, max_range_m, margin_px=4.0)
            idx = np.nonzero(vis)[0]
            if len(idx) < 2:
                continue
            pick = idx[np.unique(np.linspace(0, len(idx) - 1, min(per_rail, len(idx))).round().astype(int))]
            w, h = ph["intrinsics"]["width"], ph["intrinsics"]["height"]
            noisy = np.clip(uv[pick] + rng.normal(0.0, sigma_px, (len(pick), 2)), -0.5, [w - 0.5, h - 0.5])
            out.append({"photo": Path(ph["photo"]).name, "line": line.id, "rail": rail,
                        "pixels": [[round(float(a), 2), round(float(b), 2)] for a, b in noisy]})
    return out


def control_points_document(root: str | Path, *, per_photo: int = 8, sigma_px: float = PIXEL_SIGMA_PX,
                            seed: int = 0, max_range_m: float = 350.0) -> dict:
    """The ``control_points.json`` document (docs/gis.md) of a synthetic incident, from its truth."""
    root = Path(root)
    truth = _truth(root)
    fr = truth["frame"]
    frame = SceneFrame(fr["crs"], fr["lat"], fr["lon"], fr["height_m"])
    tm, blds, cars, trimesh = _scene_meshes(root, truth, frame)

    names: list[str] = []
    pts: list[np.ndarray] = []
    kinds: list[str] = []
    for m in blds:
        bid = str(m.metadata.get("name", "b"))
        for j, c in enumerate(_roof_corners(m)):
            names.append(f"roof_{bid}_{j}")
            pts.append(c)
            kinds.append("roof_corner")
            zg = tm.height_at(c[None, :2])[0]  # the same corner where the wall meets the ground
            if np.isfinite(zg):
                names.append(f"base_{bid}_{j}")
                pts.append(np.array([c[0], c[1], zg]))
                kinds.append("wall_base_corner")
    for n, p in _ground_marks(truth, tm):
        names.append(n)
        pts.append(p)
        kinds.append("ground_mark")
    if not pts:
        raise InputError(f"{root}: no landmarks (no buildings and no terrain under the carriages)")
    P = np.array(pts)

    scene = _raycaster([tm.mesh(), *blds, *cars])
    photos = truth["photos"]
    vis = np.zeros((len(photos), len(P)), bool)
    uvs = np.full((len(photos), len(P), 2), np.nan)
    for i, ph in enumerate(photos):
        vis[i], uvs[i] = _visible(scene, ph, P, max_range_m)

    # choose: per photo, up to per_photo points (counting ones already chosen), spread over the image,
    # preferring points seen in more photos of the same set (SfM needs two views to triangulate)
    sets = [ph["set"] for ph in photos]
    chosen: set[int] = set()
    for i, ph in enumerate(photos):
        same = np.array([s == ph["set"] for s in sets])
        n_views = vis[same].sum(axis=0)
        have = [k for k in chosen if vis[i, k]]
        avail = [k for k in np.nonzero(vis[i])[0] if k not in chosen]
        while len(have) < per_photo and avail:
            if have:
                dmin = np.min(np.linalg.norm(uvs[i, avail][:, None, :] - uvs[i, have][None, :, :], axis=2), axis=1)
            else:
                dmin = np.full(len(avail), 1e9)
            score = np.minimum(dmin, 400.0) + 60.0 * np.minimum(n_views[avail], 4)
            k = avail.pop(int(np.argmax(score)))
            have.append(k)
            chosen.add(k)
    rng = np.random.default_rng(seed)
    crs_xyz = frame.crs_from_enu(P)
    out_points = []
    for k in sorted(chosen):
        pix = {}
        for i, ph in enumerate(photos):
            if vis[i, k]:
                uv = uvs[i, k] + rng.normal(0.0, sigma_px, 2)
                pix[Path(ph["photo"]).name] = [round(float(uv[0]), 2), round(float(uv[1]), 2)]
        out_points.append({"name": names[k], "kind": kinds[k],
                           "coords": [round(float(x), 3) for x in crs_xyz[k]], "sigma_m": 0.05, "pixels": pix})
    gen = truth.get("generator", {})
    return {"crs": fr["crs"],
            "description": (f"Synthetic control points made from the truth of this incident (generator spec "
                            f"{gen.get('spec_hash', '?')}): true pixels + {sigma_px} px noise, seed {seed}; "
                            f"visibility checked by ray casting against terrain, buildings and carriages."),
            "points": out_points}


def write_control_points(root: str | Path, *, per_photo: int = 8, sigma_px: float = PIXEL_SIGMA_PX, seed: int = 0,
                         force: bool = False, track_picks: bool = False, track_sigma_px: float = PIXEL_SIGMA_PX
                         ) -> Path:
    """Write ``<root>/control_points.json`` for a synthetic incident (atomically); returns its path.

    Kept as it is when it was already written for the same truth (same generator spec hash, and track picks when
    asked for) unless ``force``. ``track_picks``: also the true picks of the rails in the panorama's photos
    (:func:`track_picks_document`, noise ``track_sigma_px``, seed ``seed``); off by default, so the samples'
    georegistration stays that of their landmarks (docs/gis.md, "Track picks").
    """
    root = Path(root)
    path = root / FILE_NAME
    truth = _truth(root)
    spec = truth.get("generator", {}).get("spec_hash", "?")
    if path.is_file() and not force:
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
            if f"spec {spec})" in str(old.get("description", "")) and (bool(old.get("track_picks")) or not track_picks):
                log.info("%s is up to date", path)
                return path
            if "Synthetic control points" not in str(old.get("description", "")):
                log.info("%s was not written by the generator; kept", path)
                return path
        except (json.JSONDecodeError, UnicodeDecodeError):
            pass
    doc = control_points_document(root, per_photo=per_photo, sigma_px=sigma_px, seed=seed)
    if track_picks:
        doc["track_picks"] = track_picks_document(root, sigma_px=track_sigma_px, seed=seed)
        doc["description"] += f" Track picks: the rails in the panorama's photos, true pixels + {track_sigma_px} px."
    atomic_write_text(path, to_json(doc))
    log.info("wrote %s (%d control points)", path, len(doc["points"]))
    return path


# ----------------------------------------------------------------------------------------------------------
# Stand-ins for the stitch and sfm stages' outputs, made from the truth (for tests of georegistration)
# ----------------------------------------------------------------------------------------------------------
def true_world_from_pano(root: str | Path) -> np.ndarray:
    """(3, 3) a natural ``world_from_pano`` for the truth's panorama: camera-like axes (x right, y down) with z along
    the sources' mean horizontal viewing direction, so a spherical panorama does not wrap around."""
    truth = _truth(Path(root))
    axes = np.array([np.asarray(ph["cam_from_world"], float)[2, :3] for ph in truth["photos"]
                     if ph["set"] == "panorama"])
    if len(axes) == 0:
        raise InputError(f"{root}: the truth has no panorama photos")
    z = axes.mean(axis=0)
    z[2] = 0.0
    z /= np.linalg.norm(z)
    y = np.array([0.0, 0.0, -1.0])
    x = np.cross(y, z)
    return np.column_stack([x, y, z])  # columns: pano axes in the world


def true_panorama_model(root: str | Path, world_from_pano: np.ndarray | None = None) -> dict:
    """A ``panorama.json`` (the stitch stage's format, spherical projection) for the truth's panorama photos.

    ``world_from_pano`` (3, 3) rotation of the panorama frame in the scene (default :func:`true_world_from_pano`);
    each source's ``cam_from_pano = cam_from_world[:3, :3] @ world_from_pano``. Scale = the photos' focal (px per
    radian); offset and size enclose every source photo.
    """
    root = Path(root)
    truth = _truth(root)
    Rwp = true_world_from_pano(root) if world_from_pano is None else np.asarray(world_from_pano, float)[:3, :3]
    sources, warped = [], []
    scale = None
    for ph in truth["photos"]:
        if ph["set"] != "panorama":
            continue
        R = np.asarray(ph["cam_from_world"], float)[:3, :3]
        cam_from_pano = R @ Rwp
        intr = CameraIntrinsics.from_dict(ph["intrinsics"])
        scale = scale or float(intr.fx)
        w, h = intr.width, intr.height
        t = np.linspace(0.0, 1.0, 17)
        border = np.vstack([np.column_stack([t * (w - 1), np.zeros_like(t)]),
                            np.column_stack([t * (w - 1), np.full_like(t, h - 1)]),
                            np.column_stack([np.zeros_like(t), t * (h - 1)]),
                            np.column_stack([np.full_like(t, w - 1), t * (h - 1)])])
        d = intr.rays(border) @ cam_from_pano  # pano_from_cam = cam_from_pano.T
        warped.append(np.column_stack([np.arctan2(d[:, 0], d[:, 2]), np.pi / 2 + np.arcsin(np.clip(d[:, 1], -1, 1))]))
        sources.append({"name": Path(ph["photo"]).name, "image": ph["photo"], "intrinsics": ph["intrinsics"],
                        "cam_from_pano": cam_from_pano.tolist()})
    if not sources:
        raise InputError(f"{root}: the truth has no panorama photos")
    W = np.vstack(warped) * scale
    lo, hi = W.min(axis=0), W.max(axis=0)
    return {"projection": "spherical", "scale": scale, "offset": [float(lo[0]), float(lo[1])],
            "width": int(np.ceil(hi[0] - lo[0])) + 1, "height": int(np.ceil(hi[1] - lo[1])) + 1,
            "sources": sources, "intrinsics_source": "calibrated"}


def true_reconstruction(root: str | Path, world_from_model: np.ndarray, photo_set: str = "multiview") -> dict:
    """A ``reconstruction.json``-like document (the sfm stage's format) for the truth's ``photo_set`` photos,
    expressed in a model frame given by the similarity ``world_from_model`` (4, 4; scale in its upper-left block)."""
    root = Path(root)
    truth = _truth(root)
    S = np.asarray(world_from_model, float)
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    Rs, ts = S[:3, :3] / s, S[:3, 3]
    images = []
    for ph in truth["photos"]:
        if ph["set"] != photo_set:
            continue
        M = np.asarray(ph["cam_from_world"], float)
        C = np.eye(4)
        C[:3, :3] = M[:3, :3] @ Rs
        C[:3, 3] = (M[:3, :3] @ ts + M[:3, 3]) / s
        images.append({"name": Path(ph["photo"]).name, "image": ph["photo"], "intrinsics": ph["intrinsics"],
                       "cam_from_model": C.tolist()})
    if not images:
        raise InputError(f"{root}: the truth has no {photo_set!r} photos")
    return {"images": images, "points": {"xyz": []}, "intrinsics_source": "sfm"}


def similarity(scale: float, euler_zyx_deg, t) -> np.ndarray:
    """A 4x4 similarity (``world_from_model``): ``scale`` times the rotation of Euler angles (degrees) about the
    fixed z, y, x axes in turn (``Rx Ry Rz``: SciPy's extrinsic ``"zyx"``), then the translation ``t`` (3,)."""
    az, ay, ax = np.radians(np.asarray(euler_zyx_deg, dtype=float))
    S = np.eye(4)
    S[:3, :3] = scale * (rot_x(ax) @ rot_y(ay) @ rot_z(az))
    S[:3, 3] = t
    return S


def split_reconstruction(root: str | Path, groups: list[list[str]], world_from_models: list[np.ndarray]) -> dict:
    """A ``reconstruction.json`` (true cameras) whose main model holds the photos of ``groups[0]`` and whose
    separate models hold ``groups[1:]``, each in its own model frame (``world_from_models[i]``): how SfM reports
    photos it could not join to the main model."""
    docs = [true_reconstruction(root, S) for S in world_from_models]
    pick = [[im for im in d["images"] if im["name"] in g] for d, g in zip(docs, groups)]
    missing = [sorted(set(g) - {im["name"] for im in p}) for p, g in zip(pick, groups)]
    if any(missing):
        raise InputError(f"{root}: photos not in the truth's multi-view set: {missing}")
    unreg = [{"name": im["name"], "reason": "registered only in a separate model", "model": k}
             for k, p in enumerate(pick[1:]) for im in p]
    return {"images": pick[0], "unregistered": unreg, "points": {"xyz": []}, "intrinsics_source": "sfm",
            "models": [{"images": p, "points": {"xyz": []}, "stats": {}} for p in pick[1:]]}


def wrong_camera_reconstruction(root: str | Path, names: list[str], lone: str, world_from_model: np.ndarray, *,
                                f_scale: float, dcx: float, dcy: float) -> dict:
    """The true cameras of ``names`` but ``lone`` in one model frame, with SfM's shared camera wrong (focal scaled
    by ``f_scale``, principal point moved by ``(dcx, dcy)`` px), and ``lone`` left unregistered."""
    rec = split_reconstruction(root, [[n for n in names if n != lone]], [world_from_model])
    for im in rec["images"]:
        it = im["intrinsics"]
        im["intrinsics"] = {**it, "fx": it["fx"] * f_scale, "fy": it["fy"] * f_scale, "cx": it["cx"] + dcx,
                            "cy": it["cy"] + dcy}
    rec["unregistered"] = [{"name": lone, "reason": "too few verified matches with the registered photos"}]
    return rec

