"""The ``render`` stage: off-screen pictures of the reconstructed scene, for the report and for people.

Writes under ``out/render/``:

* ``overview.png``: the whole scene from above and beside the camera's side of the wreck;
* ``map.png``: a top-down map (true north up, scene frame), the railway lines (``terrain.railways``), carriages
  outlined and numbered, the camera(s), a scale bar and a north arrow with grid north beside it;
* ``photo_<view>.png``: each photo with the reconstruction seen from the photo's own camera (through its
  lens model) blended over it, carriages outlined in their colours; ``photo_<view>_ids.png`` the carriage
  ids of that render (8-bit: the carriage's index in ``solution.json``, 255 = none);
* ``car_<number>.png``: a close-up of every carriage with a pose;
* ``orbit.gif`` (an animation around the scene) and ``orbit_sheet.png`` (some of its frames);
* ``renders.json``: the index of all of them (kind, file, size, camera, time), read by the report.

Renders use :class:`workbench.render.OffscreenScene`, by default its CPU ray tracer (Open3D's Embree
``RaycastingScene``); ``WORKBENCH_RENDER_ENGINE=filament`` selects Open3D's Filament rasteriser (Vulkan; on
a GPU, or lavapipe on the CPU). The scene is read only from files (see :mod:`workbench.report.scene`).
"""

from __future__ import annotations

import logging
import math
import os
import time
import warnings
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from ..core.camera import look_at
from ..core.stage_api import Progress, StageResult
from ..core.track import RailwayLine
from ..errors import RenderError, WorkbenchWarning
from ..project import Project
from ..files.scene import SceneCarriage
from .scene import IncidentScene, camera_glyph, car_color, load_scene, scene_layers

log = logging.getLogger(__name__)

ENGINE_ENV = "WORKBENCH_RENDER_ENGINE"
DEBIAN_PACKAGES = "libgl1 libegl1 libgomp1 libusb-1.0-0 libvulkan1 mesa-vulkan-drivers"

# sizes (width, height) px and supersampling of each kind of render
OVERVIEW_SIZE = (1120, 700)
MAP_SIZE = (900, 900)
CLOSEUP_SIZE = (600, 375)
ORBIT_SIZE = (480, 300)
ORBIT_FRAMES = 12
PHOTO_MAX_WIDTH = 960
HFOV_DEG = 45.0
SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG = 150.0, 40.0


def _engine() -> str:
    engine = os.environ.get(ENGINE_ENV, "raytrace")
    if engine not in ("raytrace", "filament"):
        raise RenderError(f"{ENGINE_ENV}={engine!r}: choose 'raytrace' (CPU) or 'filament' (Vulkan)")
    return engine


def _require_open3d() -> None:
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError) as exc:  # a missing shared library shows up as an ImportError/OSError
        raise RenderError(f"Open3D cannot be loaded ({exc}); install its system libraries, on Debian/Ubuntu: "
                          f"`apt-get install -y {DEBIAN_PACKAGES}`") from None


def _pinhole(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def fit_distance(radius: float, width: int, height: int, hfov_deg: float = HFOV_DEG, margin: float = 1.1) -> float:
    """Distance at which a sphere of ``radius`` fills the narrower field of view."""
    hf = math.radians(hfov_deg) / 2.0
    vf = math.atan(math.tan(hf) * height / width)
    return margin * radius / math.sin(min(hf, vf))


def view_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the target towards the eye: compass azimuth (clockwise from north), elevation above horizon."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])


def viewer_azimuth(sc: IncidentScene, centre: np.ndarray) -> float:
    """Compass azimuth from the scene centre towards the photo cameras (where people stood), else south-east."""
    if not sc.cameras:
        return 135.0
    d = np.mean([c.center_enu for c in sc.cameras], axis=0) - centre
    if np.hypot(d[0], d[1]) < 1.0:
        return 135.0
    return math.degrees(math.atan2(d[0], d[1])) % 360.0


class SceneRenderer:
    """An :class:`OffscreenScene` holding the incident's layers; renders named views."""

    def __init__(self, sc: IncidentScene, *, engine: str | None = None, camera_glyphs: bool = True) -> None:
        _require_open3d()
        from ..render.offscreen import OffscreenScene, SceneMesh

        self.sc = sc
        self.scene = OffscreenScene(*OVERVIEW_SIZE, background_rgb=(0.70, 0.80, 0.91), supersample=2,
                                    engine=engine or _engine())
        if sc.terrain is not None:
            self.scene.add(SceneMesh("terrain", sc.terrain))
        if sc.buildings is not None:
            self.scene.add(SceneMesh("buildings", sc.buildings))
        if sc.track is not None:
            self.scene.add(SceneMesh("track", sc.track))
        for c in sc.carriages:
            self.scene.add(SceneMesh(f"car_{c.number}", sc.carriage_mesh(c), instance_id=c.index))
        self.centre, self.radius = sc.focus()
        self._glyphs: list[str] = []
        if camera_glyphs:
            size = float(np.clip(0.05 * self.radius, 1.5, 8.0))
            for i, cam in enumerate(sc.cameras):
                name = f"camera_{i}"
                self.scene.add(SceneMesh(name, camera_glyph(cam, size)))
                self._glyphs.append(name)
        az, el = math.radians(SUN_AZIMUTH_DEG), math.radians(SUN_ELEVATION_DEG)
        self.scene.set_sun(-np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)]))

    def without_glyphs(self) -> None:
        for n in self._glyphs:
            self.scene.remove(n)
        self._glyphs = []

    def render(self, cam_from_world: np.ndarray, size: tuple[int, int], *, K: np.ndarray | None = None,
               supersample: int = 2):
        w, h = size
        K = _pinhole(w, h) if K is None else K
        return self.scene.render(K, cam_from_world, size=(w, h), supersample=supersample)

    def view_from(self, target: np.ndarray, radius: float, azimuth_deg: float, elevation_deg: float,
                  size: tuple[int, int], *, margin: float = 1.1) -> np.ndarray:
        """``cam_from_world`` of a camera looking at ``target`` from (azimuth, elevation), framing ``radius``."""
        eye = np.asarray(target, float) + view_direction(azimuth_deg, elevation_deg) * fit_distance(radius, *size,
                                                                                                  margin=margin)
        return look_at(eye, target)


# ----------------------------------------------------------------------------------------------------------
# Individual pictures
# ----------------------------------------------------------------------------------------------------------
def top_down_camera(centre_en: np.ndarray, half_extent_m: float, size_px: int, ground_z: float,
                    height_m: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(K, cam_from_world, metres per pixel at ``ground_z``) of a near-orthographic, north-up camera far above."""
    # high enough that tall things lean little, low enough that the renderer's aerial haze stays faint
    height_m = max(300.0, 6.0 * half_extent_m) if height_m is None else float(height_m)
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # x east, y south (image down), z down
    eye = np.array([centre_en[0], centre_en[1], ground_z + height_m])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    f = height_m * size_px / (2.0 * half_extent_m)
    K = np.array([[f, 0.0, (size_px - 1) / 2.0], [0.0, f, (size_px - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, M, 2.0 * half_extent_m / size_px


def _nice_length(max_m: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``max_m``."""
    k = 10 ** math.floor(math.log10(max_m))
    for m in (5, 2, 1):
        if m * k <= max_m:
            return m * k
    return k


def _draw_railways(ax, railways: Sequence[RailwayLine], extent: tuple[float, float, float, float], pe) -> None:
    """The railway lines, dashed over a white halo, with chainage ticks (metres, on the left of the direction of
    increasing chainage) every round number of metres."""
    x0, x1, y0, y1 = extent
    W = x1 - x0
    step = _nice_length(W / 4.0)
    for k, line in enumerate(railways):
        P = line.points_enu
        ax.plot(P[:, 0], P[:, 1], color=(0.12, 0.12, 0.12), linewidth=1.3, linestyle=(0, (6, 2)),
                path_effects=[pe.withStroke(linewidth=3.2, foreground=(1, 1, 1, 0.85))],
                label="railway line (centre), chainage in m" if k == 0 else None, zorder=2)
        first = math.ceil(line.chainage_origin_m / step) * step
        for ch in np.arange(first, line.chainage_origin_m + line.length_m + 1e-9, step):
            xy, bearing = line.at(float(ch))
            if not (x0 < xy[0] < x1 and y0 < xy[1] < y1):
                continue
            b = math.radians(bearing)
            left = np.array([-math.cos(b), math.sin(b)])
            tip = xy + 0.018 * W * left
            ax.plot([xy[0], tip[0]], [xy[1], tip[1]], color=(0.12, 0.12, 0.12), linewidth=1.0, zorder=2)
            ax.annotate(f"{ch:g}", tip, xytext=tuple(4 * left), textcoords="offset points", fontsize=6,
                        color=(0.12, 0.12, 0.12), ha="center", va="center", zorder=2,
                        path_effects=[pe.withStroke(linewidth=2, foreground="white")])


def draw_map(path: Path, image: np.ndarray, extent: tuple[float, float, float, float], sc: IncidentScene,
             convergence_deg: float, crs_name: str, frame_note: str, railways: Sequence[RailwayLine] = (),
             relative: bool = False) -> None:
    """A map figure: the top-down render with the railway lines (chainage ticks), carriage outlines and numbers,
    cameras, scale bar, north arrows; ``relative``: a plan of a scene with no georeference (the arrow is the
    camera's direction, not north)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patheffects as pe
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrow, Polygon, Rectangle

    x0, x1, y0, y1 = extent
    fig, ax = plt.subplots(figsize=(7.0, 7.0), dpi=150)
    ax.imshow(image, extent=extent, origin="upper", interpolation="bilinear")
    halo = [pe.withStroke(linewidth=3, foreground="white")]
    _draw_railways(ax, railways, extent, pe)
    for c in sc.carriages:
        col = np.array(car_color(c.index)) / 255.0
        fp = c.footprint_enu()
        ax.add_patch(Polygon(fp, closed=True, fill=False, edgecolor=col, linewidth=1.6))
        ax.plot(*c.front_enu()[:2], marker="o", color=col, markersize=3.5)
        ctr = fp.mean(axis=0)
        ax.annotate(c.number, ctr, xytext=(6, 6), textcoords="offset points", fontsize=8, fontweight="bold",
                    color=col, path_effects=halo)
    for cam in sc.cameras:
        ce = cam.center_enu
        if not (x0 <= ce[0] <= x1 and y0 <= ce[1] <= y1):
            continue
        fwd = cam.cam_from_world[2, :3]
        ang = math.atan2(fwd[1], fwd[0])
        half = math.atan(0.5 * cam.intrinsics.width / cam.intrinsics.fx)
        L = 0.12 * (x1 - x0)
        wedge = [ce[:2], ce[:2] + L * np.array([math.cos(ang + half), math.sin(ang + half)]),
                 ce[:2] + L * np.array([math.cos(ang - half), math.sin(ang - half)])]
        ax.add_patch(Polygon(wedge, closed=True, facecolor=(0.9, 0.15, 0.15, 0.18), edgecolor=(0.9, 0.15, 0.15),
                             linewidth=0.8))
        ax.plot(ce[0], ce[1], marker="^", color=(0.85, 0.1, 0.1), markersize=7, markeredgecolor="white")
    if sc.cameras:
        ax.plot([], [], marker="^", color=(0.85, 0.1, 0.1), linestyle="none", label="camera (photo position)")
    ax.plot([], [], color="k", marker="o", markersize=3, linewidth=1.2, label="carriage outline, dot = front")
    ax.legend(loc="best", fontsize=7, framealpha=0.85)
    # scale bar (bottom left)
    W = x1 - x0
    L = _nice_length(W / 3.2)
    bx, by = x0 + 0.05 * W, y0 + 0.05 * (y1 - y0)
    bh = 0.012 * (y1 - y0)
    ax.add_patch(Rectangle((bx - 0.01 * W, by - 2.2 * bh), L + 0.02 * W, 6.2 * bh, facecolor=(1, 1, 1, 0.8),
                           edgecolor="none"))
    for i in range(4):
        ax.add_patch(Rectangle((bx + i * L / 4, by), L / 4, bh, facecolor="k" if i % 2 == 0 else "white",
                               edgecolor="k", linewidth=0.6))
    for f in (0.0, 0.5, 1.0):
        ax.text(bx + f * L, by + 1.6 * bh, f"{f * L:g}", ha="center", va="bottom", fontsize=7)
    ax.text(bx + L, by - 0.8 * bh, "metres", ha="right", va="top", fontsize=7)
    # north arrows (top right): true north (scene +y) and grid north
    marks = np.vstack([np.vstack([c.footprint_enu() for c in sc.carriages]) if sc.carriages else np.zeros((0, 2)),
                       np.array([cam.center_enu[:2] for cam in sc.cameras]).reshape(-1, 2)])
    corners = [(x1 - 0.08 * W, y1 - 0.2 * (y1 - y0)), (x0 + 0.08 * W, y1 - 0.2 * (y1 - y0))]
    clear = [float(np.min(np.linalg.norm(marks - np.array(q), axis=1))) if len(marks) else 1.0 for q in corners]
    nx, ny = corners[int(np.argmax(clear))]
    al = 0.1 * (y1 - y0)
    ax.add_patch(Rectangle((nx - 0.055 * W, ny - 0.03 * W), 0.11 * W, al + 0.11 * W, facecolor=(1, 1, 1, 0.8),
                           edgecolor="none"))
    ax.add_patch(FancyArrow(nx, ny, 0, al, width=0.012 * W, head_width=0.035 * W, head_length=0.035 * W,
                            length_includes_head=True, color="k"))
    ax.text(nx, ny + al + 0.01 * W, "camera" if relative else "N", ha="center", va="bottom",
            fontsize=8 if relative else 11, fontweight="bold")
    if not relative:
        g = math.radians(convergence_deg)
        ax.plot([nx, nx + al * 0.8 * math.sin(g)], [ny, ny + al * 0.8 * math.cos(g)], color=(0.2, 0.2, 0.8),
                linewidth=0.9, linestyle="--")
        ax.text(nx, ny - 0.012 * W, f"GN {convergence_deg:+.2f}°", ha="center", va="top", fontsize=6,
                color=(0.2, 0.2, 0.8))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    if relative:
        ax.set_xlabel("right of the camera (m)", fontsize=8)
        ax.set_ylabel("ahead of the camera, along the photo's centre ray (m)", fontsize=8)
        ax.set_title(f"Plan view, RELATIVE (not georeferenced; up is the camera's direction, not north). {frame_note}",
                     fontsize=8)
    else:
        ax.set_xlabel("east of the reference point (m)", fontsize=8)
        ax.set_ylabel("north of the reference point (m)", fontsize=8)
        ax.set_title(f"Site plan: true north up; grid north ({crs_name}) dashed. {frame_note}", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    from ..core.io import atomic_write

    atomic_write(path, lambda p: fig.savefig(p, dpi=150))
    plt.close(fig)


def blend_photo(photo: np.ndarray, render: np.ndarray, ids: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """The photo with the rendered carriages blended over it (``alpha``) and each outlined in its colour.

    ``photo``, ``render``: (h, w, 3) uint8; ``ids``: (h, w) carriage index, -1 for none.
    """
    import cv2

    out = photo.astype(np.float32).copy()
    car = ids >= 0
    out[car] = (1 - alpha) * out[car] + alpha * render[car].astype(np.float32)
    out = out.astype(np.uint8)
    for k in np.unique(ids[car]):
        m = (ids == k).astype(np.uint8)
        edge = cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        out[edge] = car_color(int(k))
    return out


def _font(size_px: int, bold: bool = True):
    from matplotlib import font_manager
    from PIL import ImageFont

    path = font_manager.findfont(font_manager.FontProperties(family="DejaVu Sans", weight="bold" if bold else "normal"))
    return ImageFont.truetype(path, size_px)


def label_carriages(color: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, sc: IncidentScene,
                    lift_m: float = 4.0) -> np.ndarray:
    """Car numbers in boxes of the car's colour above each carriage of a pinhole render (h, w, 3) uint8."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(color)
    draw = ImageDraw.Draw(img)
    font = _font(max(12, color.shape[1] // 70))
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    for c in sc.carriages:
        base = c.body_centre_enu
        top = base + np.array([0.0, 0.0, lift_m])
        pc = np.array([R @ base + t, R @ top + t])
        if np.any(pc[:, 2] <= 0):
            continue
        uv = (K @ (pc / pc[:, 2:3]).T).T[:, :2]
        (u0, v0), (u1, v1) = uv
        if not (0 <= u1 < color.shape[1] and 0 <= v1 < color.shape[0]):
            continue
        col = car_color(c.index)
        draw.line([(u0, v0), (u1, v1)], fill=col, width=2)
        text = c.number
        left, tp, r, b = draw.textbbox((0, 0), text, font=font)
        w, h = r - left, b - tp
        box = (u1 - w / 2 - 5, v1 - h - 8, u1 + w / 2 + 5, v1)
        draw.rounded_rectangle(box, radius=4, fill=(255, 255, 255), outline=col, width=2)
        draw.text((u1 - w / 2 - left, v1 - h - 4 - tp), text, font=font, fill=(20, 20, 20))
    return np.asarray(img)


def _write_png(project: Project, path: Path, image: np.ndarray) -> Path:
    """Write an (h, w, 3) or (h, w) uint8 image as PNG, atomically, with fast compression (renders are big)."""
    from PIL import Image

    img = Image.fromarray(np.ascontiguousarray(image))
    return project.write_with(path, lambda p: img.save(p, format="PNG", compress_level=1))


def _latlon(lat: float, lon: float, nd: int = 5) -> str:
    return f"{abs(lat):.{nd}f}° {'N' if lat >= 0 else 'S'}, {abs(lon):.{nd}f}° {'E' if lon >= 0 else 'W'}"


def _read_rgb(path: Path, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        if im.size != tuple(size):
            im = im.resize(size, Image.Resampling.LANCZOS)
        return np.asarray(im)


# ----------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------
def _closeup_azimuth(c: SceneCarriage, towards_deg: float) -> tuple[float, float]:
    """(azimuth, elevation) of a close-up: 35° off square to the carriage side nearest the photographer; a carriage
    lying on its side is seen from above its upturned side, from the roof's direction."""
    R = c.world_from_carriage.rotation
    left, up = R[:, 1], R[:, 2]
    if abs(left[2]) > 0.85:  # on its side (|roll| above about 60°): the up-facing side is +y (left) or -y
        roof_az = math.degrees(math.atan2(up[0], up[1])) % 360.0
        return (roof_az + 20.0) % 360.0, 55.0
    left_az = math.degrees(math.atan2(left[0], left[1])) % 360.0
    d = (towards_deg - left_az + 180.0) % 360.0 - 180.0
    base = left_az if abs(d) <= 90.0 else (left_az + 180.0) % 360.0
    return (base + 35.0) % 360.0, 28.0


RENDER_THREADS = 2  # renders in flight at once (ray tracer only): Embree casts on every core, the shading on one


def _timed_iter(sr: "SceneRenderer", tasks: list):
    """``(task(), seconds)`` of each task, in order, as an iterator: the tasks run on two threads with the CPU ray
    tracer (started at once; each picture is the same as rendered alone), one by one with Filament."""
    def timed(task):
        t0 = time.perf_counter()
        return task(), time.perf_counter() - t0

    if sr.scene.engine != "raytrace" or len(tasks) < 2:
        return (timed(t) for t in tasks)
    from concurrent.futures import ThreadPoolExecutor

    sr.scene.prepare()  # built once, before the threads share it
    pool = ThreadPoolExecutor(max_workers=RENDER_THREADS)
    futures = [pool.submit(timed, t) for t in tasks]
    pool.shutdown(wait=False)  # the threads end when the queue is done

    def results():
        try:
            for f in futures:
                yield f.result()
        finally:
            for f in futures:
                f.cancel()
    return results()


class _RenderRun:
    """One run of the render stage: each picture rendered, written under ``out`` and recorded (``renders.json``'s
    index, the time by kind, the stage's outputs), in the stage's order."""

    def __init__(self, project: Project, progress: Progress, out: Path, sc: IncidentScene, sr: SceneRenderer):
        self.project, self.progress, self.out, self.sc, self.sr = project, progress, out, sc, sr
        self.index: list[dict] = []
        self.railways: dict = {}
        self.timings: dict[str, float] = {}
        self.outputs: dict[str, Path] = {}
        self.az0 = viewer_azimuth(sc, sr.centre)
        self.n_steps = 3 + len(sc.carriages) + len(sc.cameras)
        self.map_view: tuple | None = None  # the map's render (_map_render), made beside the overview
        self.step = 0

    def tick(self, msg: str) -> None:
        self.step += 1
        self.progress(min(self.step / self.n_steps, 0.99), msg)

    def record(self, kind: str, name: str, path: Path, t0: float, **extra) -> None:
        dt = time.perf_counter() - t0
        self.timings[kind] = self.timings.get(kind, 0.0) + dt
        self.outputs[name] = path
        self.index.append({"kind": kind, "name": name, "path": self.project.relative(path), "time_s": round(dt, 3),
                           **extra})

    def overview(self) -> None:
        """The overview (its sub-pixel passes on two threads), with the map's render on a third thread meanwhile:
        both need the camera glyphs, which the other pictures leave out."""
        sr = self.sr
        self.tick("overview")
        t0 = time.perf_counter()
        M = sr.view_from(sr.centre, sr.radius, self.az0 + 25.0, 32.0, OVERVIEW_SIZE, margin=0.8)
        from concurrent.futures import ThreadPoolExecutor

        if sr.scene.engine == "raytrace":
            sr.scene.prepare()  # built once, before the threads share it
        with ThreadPoolExecutor(max_workers=1) as pool:
            map_render = pool.submit(self._map_render) if sr.scene.engine == "raytrace" else None
            res = sr.render(M, OVERVIEW_SIZE)
            p = _write_png(self.project, self.out / "overview.png",
                           label_carriages(res.color, _pinhole(*OVERVIEW_SIZE), M, self.sc))
            self.record("overview", "overview", p, t0, width=OVERVIEW_SIZE[0], height=OVERVIEW_SIZE[1],
                        cam_from_world=M)
            self.map_view = map_render.result() if map_render is not None else self._map_render()

    def _map_render(self) -> tuple:
        """(colour of the map's top-down render, its extent, metres per pixel, seconds)."""
        t0 = time.perf_counter()
        sc, sr = self.sc, self.sr
        pts = [c.footprint_enu() for c in sc.carriages] + [np.array([c.center_enu[:2] for c in sc.cameras])
                                                          if sc.cameras else np.zeros((0, 2))]
        P = np.vstack([q for q in pts if len(q)]) if any(len(q) for q in pts) else np.zeros((1, 2))
        lo, hi = P.min(axis=0), P.max(axis=0)
        centre_en = 0.5 * (lo + hi)
        half = float(max(0.5 * np.max(hi - lo) * 1.12 + 6.0, 25.0))
        K, Mt, mpp = top_down_camera(centre_en, half, MAP_SIZE[0], float(sr.centre[2]))
        res = sr.render(Mt, MAP_SIZE, K=K, supersample=1)
        extent = (centre_en[0] - half, centre_en[0] + half, centre_en[1] - half, centre_en[1] + half)
        return res.color, extent, mpp, time.perf_counter() - t0

    def top_down_map(self) -> None:
        """The map: the carriages and cameras from above (rendered beside the overview), with a scale bar, north
        and the grid convergence."""
        sc, project = self.sc, self.project
        self.tick("map")
        if self.map_view is None:  # not rendered beside the overview
            self.map_view = self._map_render()
        color, extent, mpp, dt = self.map_view
        t0 = time.perf_counter() - dt
        relative = (sc.solution.get("frame") or {}).get("kind") == "relative"
        conv = 0.0 if relative else project.frame.grid_convergence_deg()
        map_path = self.out / "map.png"
        crs_name = project.settings.location.crs
        with warnings.catch_warnings(record=True) as caught:  # a layer with no railway line: in the stage's stats
            warnings.simplefilter("always", WorkbenchWarning)
            layer = None if relative else project.railways(heights=False)  # not in a relative scene's frame
        self.railways = {"file": project.settings.terrain.railways, "lines": len(layer.lines) if layer else 0,
                         "warnings": [str(w.message) for w in caught if issubclass(w.category, WorkbenchWarning)]}
        note = ("Origin at the camera." if relative else
                f"Reference point {_latlon(project.settings.location.lat, project.settings.location.lon)}.")
        draw_map(map_path, color, extent, sc, conv, crs_name, note,
                 railways=layer.lines if layer is not None else (), relative=relative)
        self.record("map", "map", map_path, t0, extent_enu=list(extent), metres_per_px=mpp, grid_convergence_deg=conv,
                    crs=crs_name)

    def _photo_task(self, cam, scale: float, intr):
        """The work of one photo overlay (render, blend, write both pictures), for a render thread."""
        from ..render.lens import render_photo

        def task() -> dict:
            res = render_photo(self.sr.scene, intr, cam.cam_from_world, supersample=1)
            photo = _read_rgb(cam.image, (intr.width, intr.height))
            stem = Path(cam.name).stem
            p = _write_png(self.project, self.out / f"photo_{stem}.png", blend_photo(photo, res.color, res.instance))
            ids = np.where(res.instance >= 0, res.instance, 255).astype(np.uint8)
            pid = _write_png(self.project, self.out / f"photo_{stem}_ids.png", ids)
            return {"stem": stem, "path": p, "ids": pid, "pixels": {str(int(k)): int(n) for k, n in
                                                                      zip(*np.unique(res.instance[res.instance >= 0],
                                                                                     return_counts=True))}}
        return task

    def _closeup_task(self, c: SceneCarriage):
        """The work of one close-up (its view, render, write), for a render thread."""
        sr = self.sr

        def task() -> dict:
            r = 0.5 * float(np.linalg.norm(c.bbox_carriage[1] - c.bbox_carriage[0]))
            az, el = _closeup_azimuth(c, self.az0)
            M = sr.view_from(c.body_centre_enu, r, az, el, CLOSEUP_SIZE, margin=1.0)
            res = sr.render(M, CLOSEUP_SIZE)
            return {"path": _write_png(self.project, self.out / f"car_{c.number}.png", res.color), "az": az, "el": el}
        return task

    def _orbit_task(self, k: int):
        sr = self.sr

        def task() -> np.ndarray:
            M = sr.view_from(sr.centre, sr.radius, self.az0 + 360.0 * k / ORBIT_FRAMES, 30.0, ORBIT_SIZE, margin=0.8)
            return sr.render(M, ORBIT_SIZE, supersample=1).color
        return task

    def pictures(self) -> None:
        """The map's figure, the photo overlays, the close-ups and the orbit, all but the map without the camera
        glyphs: their renders (each written by the thread that made it) on the render threads from one queue, the
        orbit's frames first so that its GIF is made while the others render; the map drawn here meanwhile; each
        recorded in the stage's order (photos, close-ups, orbit)."""
        sc, sr, project = self.sc, self.sr, self.project
        sr.without_glyphs()
        observed_views = {v for c in sc.solution.get("carriages", []) for v in (c.get("observations") or {})}
        present = []  # (camera, scale, the photo's camera at the overlay's size)
        for cam in sc.cameras:
            if cam.image is None or not cam.image.is_file():
                log.warning("render: photo of view %s not found (%s); no overlay for it", cam.name, cam.image)
                continue
            scale = min(1.0, PHOTO_MAX_WIDTH / cam.intrinsics.width)
            present.append((cam, scale, cam.intrinsics.scaled(scale) if scale < 1.0 else cam.intrinsics))
        tasks = [self._orbit_task(k) for k in range(ORBIT_FRAMES)] + \
                [self._photo_task(*p) for p in present] + [self._closeup_task(c) for c in sc.carriages]
        t0 = time.perf_counter()
        results = _timed_iter(sr, tasks)
        self.top_down_map()
        frames = []
        for k in range(ORBIT_FRAMES):
            frame, _dt = next(results)
            self.progress(min((self.step + k / ORBIT_FRAMES) / self.n_steps, 0.99),
                          f"orbit frame {k + 1}/{ORBIT_FRAMES}")
            frames.append(frame)
        orbit = self._write_orbit(frames)
        t_orbit = time.perf_counter() - t0
        for (cam, scale, intr), (r, dt) in zip(present, [next(results) for _ in present]):
            self.tick(f"photo {cam.name}")
            self.outputs[f"photo_{r['stem']}_ids"] = r["ids"]
            self.record("photo", f"photo_{r['stem']}", r["path"], time.perf_counter() - dt, view=cam.name,
                        width=intr.width, height=intr.height, scale=scale, ids=project.relative(r["ids"]),
                        observed=cam.name in observed_views, carriage_pixels=r["pixels"])
        for c, (r, dt) in zip(sc.carriages, [next(results) for _ in sc.carriages]):
            self.tick(f"close-up {c.number}")
            self.record("closeup", f"car_{c.number}", r["path"], time.perf_counter() - dt, carriage=c.number,
                        width=CLOSEUP_SIZE[0], height=CLOSEUP_SIZE[1], azimuth_deg=r["az"], elevation_deg=r["el"])
        self.tick("orbit")
        gif, sp, sheet_az = orbit
        self.record("orbit", "orbit", gif, time.perf_counter() - t_orbit, frames=ORBIT_FRAMES, width=ORBIT_SIZE[0],
                    height=ORBIT_SIZE[1], sheet=project.relative(sp), sheet_azimuths_deg=sheet_az[:6])

    def _write_orbit(self, frames: list[np.ndarray]) -> tuple[Path, Path, list[float]]:
        """The orbit's GIF and its sheet of six frames: (gif, sheet, the sheet's azimuths)."""
        from PIL import Image

        project, az0 = self.project, self.az0
        gif = self.out / "orbit.gif"
        imgs = [Image.fromarray(f) for f in frames]
        project.write_with(gif, lambda q: imgs[0].save(q, format="GIF", save_all=True, append_images=imgs[1:],
                                                       duration=250, loop=0))
        sel = frames[:: max(1, ORBIT_FRAMES // 6)][:6]
        h, w = sel[0].shape[:2]
        sheet = np.full((2 * h + 6, 3 * w + 12, 3), 255, np.uint8)
        for i, f in enumerate(sel):
            r_, c_ = divmod(i, 3)
            sheet[r_ * (h + 6):r_ * (h + 6) + h, c_ * (w + 6):c_ * (w + 6) + w] = f
        sp = _write_png(project, self.out / "orbit_sheet.png", sheet)
        self.outputs["orbit_sheet"] = sp
        sheet_az = [(az0 + 360.0 * k / ORBIT_FRAMES) % 360.0
                    for k in range(0, ORBIT_FRAMES, max(1, ORBIT_FRAMES // 6))]
        return gif, sp, sheet_az


_AHEAD: dict = {}  # what ahead() read in this process: {"root": the incident's folder, "layers": scene_layers}


def ahead(project: Project) -> Iterator[None]:
    """``StageSpec.ahead``: the stage's work that needs no solution, one step per item, done in the stage's process
    while the correspond stage runs (``runner``): Open3D and matplotlib imported, each carriage's textured model
    built (the carriage type keeps it: the scene's carriages are copies of it), the terrain, buildings and track
    read (:func:`scene_layers`) and their shading data computed (``render.ahead``). :func:`run_render` takes what
    was done (the runner stops the steps at the stage's turn); every picture is the same as without. The consist's
    carriages are built in its order: which ones the solution poses is not known yet."""
    _require_open3d()
    from ..render.ahead import remember
    from ..render.offscreen import SceneMesh, shading_data

    yield
    import matplotlib  # the map's figure (draw_map), drawn while the other pictures render

    matplotlib.use("Agg")
    import matplotlib.patheffects  # noqa: F401
    import matplotlib.pyplot  # noqa: F401

    _font(12)  # (matplotlib's font list, read once)
    yield
    types = project.carriage_types()
    for car in project.settings.consist:
        types[car.number].mesh(car.number, textured=True)
        yield
    layers: dict = {}
    _AHEAD.clear()
    _AHEAD.update(root=project.root, layers=layers)  # each layer there once read (the stage reads those not there)
    for name, mesh in scene_layers(project, textured=True):
        layers[name] = mesh
        yield
    for name, mesh in layers.items():
        if mesh is not None and len(mesh.faces):
            remember(mesh, shading_data(SceneMesh(name, mesh)))
            yield


def run_render(project: Project, progress: Progress) -> StageResult:
    t_all = time.perf_counter()
    out = project.stage_dir("render")
    progress(0.0, "reading the scene")
    layers = _AHEAD.pop("layers", None) if _AHEAD.pop("root", None) == project.root else None
    _AHEAD.clear()
    sc = load_scene(project, layers=layers)
    sr = SceneRenderer(sc)
    run = _RenderRun(project, progress, out, sc, sr)
    run.overview()
    run.pictures()

    total = time.perf_counter() - t_all
    idx = {"engine": sr.scene.engine, "renders": run.index, "time_s": round(total, 3),
           "focus_enu": sr.centre, "focus_radius_m": sr.radius, "viewer_azimuth_deg": run.az0}
    run.outputs["renders"] = project.write_json(out / "renders.json", idx)
    progress(1.0, "done")
    return StageResult(outputs=run.outputs, stats={
        "engine": sr.scene.engine, "n_renders": len(run.index), "n_carriages": len(sc.carriages),
        "n_photos": sum(1 for r in run.index if r["kind"] == "photo"),
        "time_by_kind_s": {k: round(v, 3) for k, v in run.timings.items()},
        "terrain_textured": bool(sc.terrain is not None and getattr(sc.terrain.visual, "kind", None) == "texture"),
        "railways": run.railways,
    })
