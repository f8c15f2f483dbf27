"""A small textured scene rendered by ray casting, with exact cameras: ground truth for SfM tests and benchmarks.

The scene is a textured ground plane (z = 0) and a few textured upright boxes (stand-ins for carriages)
in a world frame of metres (z up). Photos are rendered through :class:`CameraIntrinsics` *with* its Brown
distortion (each pixel's ray is the exact inverse of :meth:`CameraIntrinsics.project`), so an SfM result can
be checked for focal, distortion and camera positions. Cameras stand on an arc around the scene looking at
its centre (multi-view) -- the geometry SfM needs, with 15-25 degrees between neighbours.

Fast (numpy only): 10 photos of 480x360 take about a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import zoom

from ..core.camera import CameraIntrinsics, look_at
from ..files.exif import write_jpeg


@dataclass(frozen=True)
class _Quad:
    origin: np.ndarray  # (3,) a corner
    u: np.ndarray  # (3,) edge vector (texture x)
    v: np.ndarray  # (3,) edge vector (texture y)
    texture: np.ndarray  # (n, n, 3) float 0..255
    normal: np.ndarray  # (3,) outward unit normal (faces seen from behind are culled)


def _texture(rng: np.random.Generator, n: int = 512, cells: tuple[int, ...] = (6, 20, 48)) -> np.ndarray:
    """Random texture (n, n, 3), values 0..255: band-limited luminance blobs with hard edges (SIFT finds them
    at several scales; nothing finer than a few texels, so no aliasing) under a soft colour tint."""
    def field(c: int) -> np.ndarray:
        f = zoom(rng.normal(0.0, 1.0, (c + 1, c + 1)), n / c, order=1)[:n, :n]
        return f / (f.std() + 1e-9)

    lum = sum(field(c) * a for c, a in zip(cells, (0.6, 1.0, 0.8)))
    lum = np.tanh(1.5 * lum)  # hard-ish edges
    img = 128.0 + 90.0 * lum[:, :, None] * np.ones(3)
    tint = np.stack([field(3) for _ in range(3)], axis=2)
    img += 25.0 * tint
    for _ in range(40):  # hard-edged discs
        cx, cy, r = rng.uniform(0, n), rng.uniform(0, n), rng.uniform(0.01, 0.03) * n
        x0, x1, y0, y1 = int(max(cx - r, 0)), int(min(cx + r + 1, n)), int(max(cy - r, 0)), int(min(cy + r + 1, n))
        yy, xx = np.ogrid[y0:y1, x0:x1]
        img[y0:y1, x0:x1][(xx - cx) ** 2 + (yy - cy) ** 2 < r * r] = rng.uniform(10, 245, 3)
    return np.clip(img, 0, 255)


def make_scene(seed: int = 0) -> list[_Quad]:
    """Ground 60 x 60 m and three boxes (about 20 x 3 x 4 m), world frame metres, z up."""
    rng = np.random.default_rng(seed)
    quads = [_Quad(np.array([-30.0, -30.0, 0.0]), np.array([60.0, 0, 0]), np.array([0, 60.0, 0]),
                   _texture(rng, 1024, (10, 40, 100)), np.array([0.0, 0.0, 1.0]))]
    boxes = [((-8.0, -3.0), 20.0, 3.0, 4.0, 0.3), ((5.0, 6.0), 18.0, 3.0, 3.5, -0.6), ((-2.0, 10.0), 8.0, 4.0, 6.0, 0.1)]
    for (x, y), L, W, H, yaw in boxes:
        c, s = np.cos(yaw), np.sin(yaw)
        ex, ey, ez = np.array([c, s, 0.0]) * L, np.array([-s, c, 0.0]) * W, np.array([0, 0, H])
        o = np.array([x, y, 0.0]) - ex / 2 - ey / 2
        faces = [(o, ex, ez), (o + ey, ex, ez), (o, ey, ez), (o + ex, ey, ez), (o + ez, ex, ey)]
        box_centre = o + (ex + ey + ez) / 2
        for fo, fu, fv in faces:
            n = np.cross(fu, fv)
            n /= np.linalg.norm(n)
            if n @ (fo + (fu + fv) / 2 - box_centre) < 0:
                n = -n
            quads.append(_Quad(fo, fu, fv, _texture(rng, 256, (3, 10, 24)), n))
    return quads


def arc_cameras(n: int, *, radius_m: float = 26.0, arc_deg: float = 140.0, height_m: float = 6.0,
                seed: int = 0) -> list[np.ndarray]:
    """``n`` cam_from_world (4, 4) on an arc around the scene, looking at its centre, slightly jittered."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = np.deg2rad(-arc_deg / 2 + arc_deg * i / max(n - 1, 1) + rng.uniform(-3, 3))
        r = radius_m * rng.uniform(0.85, 1.15)
        eye = np.array([r * np.cos(a), r * np.sin(a), height_m + rng.uniform(-2.0, 4.0)])
        target = np.array([0.0, 2.0, 1.5]) + rng.normal(0, 1.5, 3)
        out.append(look_at(eye, target))
    return out


def pixel_rays(intr: CameraIntrinsics) -> np.ndarray:
    """(h * w, 3) unit rays in the camera frame of every pixel centre, row-major (distortion inverted)."""
    vv, uu = np.mgrid[0:intr.height, 0:intr.width].astype(float)
    return intr.rays(np.column_stack([uu.ravel(), vv.ravel()]))


def render(quads: list[_Quad], intr: CameraIntrinsics, cam_from_world: np.ndarray,
           sky=(150.0, 190.0, 230.0), rays_cam: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) uint8 photo of the scene through ``intr`` (with its distortion) at ``cam_from_world``.

    ``rays_cam``: :func:`pixel_rays` of ``intr``, to reuse between photos.
    """
    h, w = intr.height, intr.width
    if rays_cam is None:
        rays_cam = pixel_rays(intr)
    M = np.asarray(cam_from_world, dtype=float)
    R, t = M[:3, :3], M[:3, 3]
    eye = -R.T @ t
    d = rays_cam @ R  # world directions (rows)
    best = np.full(len(d), np.inf)
    colour = np.tile(np.asarray(sky, dtype=float), (len(d), 1))
    for q in quads:
        if (eye - q.origin) @ q.normal <= 0:
            continue  # seen from behind
        n = np.cross(q.u, q.v)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((q.origin - eye) @ n) / denom
        p = eye + s[:, None] * d
        rel = p - q.origin
        a = rel @ q.u / (q.u @ q.u)
        b = rel @ q.v / (q.v @ q.v)
        hit = (s > 0.1) & (s < best) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        if not hit.any():
            continue
        tex = q.texture
        tn = tex.shape[0] - 1
        x, y = a[hit] * tn, b[hit] * tn  # bilinear lookup, all channels at once
        x0 = np.clip(np.floor(x).astype(int), 0, tn - 1)
        y0 = np.clip(np.floor(y).astype(int), 0, tn - 1)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        colour[hit] = ((tex[y0, x0] * (1 - fx) + tex[y0, x0 + 1] * fx) * (1 - fy)
                       + (tex[y0 + 1, x0] * (1 - fx) + tex[y0 + 1, x0 + 1] * fx) * fy)
        best[hit] = s[hit]
    return np.clip(colour, 0, 255).astype(np.uint8).reshape(h, w, 3)


def write_multiview_set(folder: Path, n: int = 10, *, width: int = 480, height: int = 360, hfov_deg: float = 55.0,
                        k1: float = -0.08, k2: float = 0.012, seed: int = 0, exif: bool = True) -> dict:
    """Render ``n`` photos ``mv_00.jpg``... into ``folder`` (with EXIF focal tags of a 6.17 mm wide sensor
    when ``exif``); returns the truth: ``{"intrinsics": {...}, "photos": [{"name", "cam_from_world", "center"}]}``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    f = width / 2.0 / np.tan(np.deg2rad(hfov_deg) / 2.0)
    intr = CameraIntrinsics(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2.0 + 3.0,
                            cy=(height - 1) / 2.0 - 2.0, k1=k1, k2=k2)
    quads = make_scene(seed)
    rays = pixel_rays(intr)
    photos = []
    sensor_mm = 6.17
    for i, M in enumerate(arc_cameras(n, seed=seed)):
        name = f"mv_{i:02d}.jpg"
        img = render(quads, intr, M, rays_cam=rays)
        if exif:
            write_jpeg(folder / name, img, focal_length_mm=f * sensor_mm / width, sensor_width_mm=sensor_mm,
                       quality=95)
        else:
            Image.fromarray(img).save(folder / name, quality=95)
        photos.append({"name": name, "cam_from_world": M.tolist(), "center": (-M[:3, :3].T @ M[:3, 3]).tolist()})
    return {"intrinsics": intr.to_dict(), "photos": photos}
