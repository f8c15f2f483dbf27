"""Off-screen rendering of ENU scenes on Open3D's Filament renderer (Vulkan; lavapipe on the CPU).

Conventions follow ``workbench/core/camera.py``: camera x right, y down, z forward, ``cam_from_world``
(4, 4) with ``p_cam = R @ p_world + t``, and pixel (0, 0) is the **centre** of the top-left pixel.
Open3D's ``setup_camera(K, ...)`` treats pixel (0, 0) as the top-left *corner* of the image (measured: a
point lands half a pixel up-left of ``K @ X``), so :meth:`OffscreenScene.render` adds half a pixel to the
principal point it hands over. Open3D also ignores the skew term of ``K``; skewed and distorted cameras
go through :func:`workbench.render.lens.render_photo`.

Every :meth:`OffscreenScene.render` makes three passes on one shared renderer:

* colour: lit, textured, tone-mapped, rendered ``supersample`` x larger and area-downsampled;
* instance: unlit flat colours that encode ``instance_id + 1`` (MSAA and post-processing off), sampled
  at the exact final pixel centres (no blending across object edges);
* depth: the depth buffer of the same pass, metres along the camera z axis, ``inf`` where nothing.

Open3D cannot hold two ``OffscreenRenderer`` at once in one process (destroying either aborts the
process), so one module-level renderer is shared by all scenes and re-created only when the canvas
size changes; a scene re-uploads its geometry when another scene used the renderer in between.
"""

from __future__ import annotations

import ctypes.util
import glob
import os
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from ..errors import RenderError

_INSTALL_HINT = ("install the Vulkan/EGL runtime, e.g. on Debian/Ubuntu: "
                 "`apt-get install libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1` "
                 "(mesa-vulkan-drivers provides lavapipe, a CPU Vulkan driver)")

# Instance ids are encoded as (id + 1) in base _LEVELS over the three colour channels; code 0 = none.
_LEVELS = 9
MAX_INSTANCE_ID = _LEVELS ** 3 - 2

_SHOW_COLOR = "c:"
_SHOW_ID = "i:"


@dataclass
class SceneMesh:
    """One mesh of a scene, in world (ENU) coordinates.

    ``mesh.visual`` is either ``TextureVisuals`` (UV + PIL image, as trimesh loads glTF/OBJ; trimesh's
    UV origin is the bottom-left of the image) or ``ColorVisuals`` (per-vertex or per-face colours).
    ``instance_id >= 0`` marks objects that need an instance mask (carriages); -1 for everything else.
    """

    name: str
    mesh: trimesh.Trimesh
    instance_id: int = -1


@dataclass
class RenderResult:
    color: np.ndarray  # (h, w, 3) uint8 RGB
    depth: np.ndarray  # (h, w) float32 metres along camera z, inf where nothing
    instance: np.ndarray  # (h, w) int32 instance id, -1 for background / non-instance objects


@dataclass
class _Sun:
    direction: np.ndarray = field(default_factory=lambda: _unit(np.array([0.35, 0.6, -0.72])))
    intensity: float = 90_000.0  # lux
    color: tuple[float, float, float] = (1.0, 0.97, 0.92)
    ambient_intensity: float = 40_000.0  # image-based (sky) light
    shadows: bool = True


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"direction {v} has no length")
    return v / n


# ----------------------------------------------------------------------------------------------------------
# The shared renderer
# ----------------------------------------------------------------------------------------------------------
class _Canvas:
    """The one Open3D OffscreenRenderer of the process, of a fixed size."""

    renderer = None
    size: tuple[int, int] | None = None
    owner: tuple[int, int] | None = None  # (id(scene), scene version) whose geometry is loaded
    levels_out: np.ndarray | None = None  # the 8-bit output of each instance-code level (calibrated)
    lock = threading.RLock()


def _check_vulkan() -> None:
    if os.environ.get("WORKBENCH_SKIP_VULKAN_CHECK"):
        return
    if ctypes.util.find_library("vulkan") is None:
        raise RenderError(f"off-screen rendering needs the Vulkan loader (libvulkan.so.1), not found; {_INSTALL_HINT}")
    icd_dirs = ["/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d"]
    if not os.environ.get("VK_ICD_FILENAMES") and not os.environ.get("VK_DRIVER_FILES") \
            and not any(glob.glob(os.path.join(d, "*.json")) for d in icd_dirs):
        raise RenderError(f"off-screen rendering found no Vulkan driver (no ICD file in {', '.join(icd_dirs)}); "
                          f"{_INSTALL_HINT}")


def _get_renderer(width: int, height: int):
    """The shared renderer with a canvas of exactly ``width`` x ``height`` (re-created on size change)."""
    if _Canvas.renderer is not None and _Canvas.size == (width, height):
        return _Canvas.renderer
    _check_vulkan()
    from open3d.visualization import rendering

    if _Canvas.renderer is not None:
        _Canvas.renderer.scene.clear_geometry()
        _Canvas.renderer = None
        import gc

        gc.collect()
    try:
        r = rendering.OffscreenRenderer(int(width), int(height))
    except Exception as exc:  # noqa: BLE001 - Open3D raises RuntimeError with varying text
        raise RenderError(f"could not create an off-screen renderer ({exc}); {_INSTALL_HINT}") from exc
    _Canvas.renderer, _Canvas.size, _Canvas.owner = r, (int(width), int(height)), None
    if _Canvas.levels_out is None:
        _Canvas.levels_out = _calibrate_levels(r, int(width), int(height))
    return r


def _code_levels_in() -> np.ndarray:
    # Inputs roughly evenly spaced after the (sRGB-like) output curve of the unlit pass.
    return (np.arange(_LEVELS) / (_LEVELS - 1)) ** (1.0 / 2.2)


def _id_pass_settings(r) -> None:
    r.scene.view.set_post_processing(False)
    r.scene.view.set_sample_count(1)
    r.scene.set_background([0.0, 0.0, 0.0, 1.0])


def _calibrate_levels(r, width: int, height: int) -> np.ndarray:
    """Render one flat quad per code level through the instance pass; return each level's 8-bit output."""
    import open3d as o3d
    from open3d.visualization import rendering

    r.scene.clear_geometry()
    _id_pass_settings(r)
    n = _LEVELS
    f = 100.0
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    probes = []
    for k, v in enumerate(_code_levels_in()):
        # a quad covering a small square of the canvas around its probe pixel
        u = width * (k + 0.5) / n
        x0, x1 = (u - 2.0 - width / 2) / f, (u + 2.0 - width / 2) / f
        y0, y1 = -2.0 / f, 2.0 / f
        verts = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]], dtype=float) * 10.0
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                      o3d.utility.Vector3iVector(np.array([[0, 2, 1], [0, 3, 2], [0, 1, 2], [0, 2, 3]])))
        mat = rendering.MaterialRecord()
        mat.shader = "defaultUnlit"
        mat.base_color = [float(v), float(v), float(v), 1.0]
        r.scene.add_geometry(f"calib{k}", m, mat)
        probes.append((int(round(height / 2.0)), int(round(u))))
    r.setup_camera(K, np.eye(4), width, height)
    img = np.asarray(r.render_to_image())
    r.scene.clear_geometry()
    out = np.array([float(img[py, px, 0]) for py, px in probes])
    if np.any(np.diff(out) < 4):
        raise RenderError(f"instance-mask calibration failed: flat colours render as {out.tolist()} (not distinct)")
    return out


def _decode_table(levels_out: np.ndarray) -> np.ndarray:
    """Byte value -> level index (nearest calibrated level)."""
    b = np.arange(256, dtype=float)
    return np.argmin(np.abs(b[:, None] - levels_out[None, :]), axis=1).astype(np.int32)


# ----------------------------------------------------------------------------------------------------------
# trimesh -> Open3D
# ----------------------------------------------------------------------------------------------------------
def _corner_normals(vertices: np.ndarray, faces: np.ndarray, crease_deg: float = 35.0) -> np.ndarray:
    """Per-corner normals (F, 3, 3): smooth across edges flatter than ``crease_deg``, hard across sharper ones."""
    tri = vertices[faces]
    fn_w = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area-weighted face normals
    norm = np.linalg.norm(fn_w, axis=1, keepdims=True)
    fn = np.divide(fn_w, norm, out=np.zeros_like(fn_w), where=norm > 0)
    F = len(faces)
    corner_v = faces.reshape(-1)
    corner_f = np.repeat(np.arange(F), 3)
    order = np.argsort(corner_v, kind="stable")
    faces_by_v = corner_f[order]
    deg = np.bincount(corner_v, minlength=len(vertices))
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    d = deg[corner_v]  # valence of each corner's vertex
    corner_idx = np.repeat(np.arange(3 * F), d)
    offs = np.arange(d.sum()) - np.repeat(np.cumsum(d) - d, d)
    nb_face = faces_by_v[start[corner_v][corner_idx] + offs]
    own = fn[corner_f[corner_idx]]
    keep = np.einsum("ij,ij->i", own, fn[nb_face]) >= np.cos(np.deg2rad(crease_deg))
    acc = np.zeros((3 * F, 3))
    np.add.at(acc, corner_idx[keep], fn_w[nb_face[keep]])
    n = np.linalg.norm(acc, axis=1, keepdims=True)
    acc = np.where(n > 0, acc / np.maximum(n, 1e-300), fn[corner_f])
    return acc.reshape(F, 3, 3)


def _texture_image(visual) -> np.ndarray | None:
    mat = getattr(visual, "material", None)
    if mat is None:
        return None
    img = getattr(mat, "image", None)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
    if img is None:
        return None
    arr = np.asarray(img.convert("RGB") if hasattr(img, "convert") else img)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    return np.ascontiguousarray(arr[..., :3].astype(np.uint8))


def _material_base_color(visual) -> np.ndarray:
    mat = getattr(visual, "material", None)
    for attr in ("baseColorFactor", "diffuse", "main_color"):
        c = getattr(mat, attr, None) if mat is not None else None
        if c is not None:
            c = np.asarray(c, dtype=float).reshape(-1)
            if c.size >= 3:
                return (c[:3] / 255.0) if c.max() > 1.0 else c[:3]
    return np.ones(3)


def _to_open3d(item: SceneMesh):
    """(colour mesh, colour material, id mesh, id material) for one SceneMesh."""
    import open3d as o3d
    from open3d.visualization import rendering

    mesh = item.mesh
    V = np.asarray(mesh.vertices, dtype=float)
    Fa = np.asarray(mesh.faces, dtype=np.int64)
    if len(Fa) == 0:
        raise ValueError(f"SceneMesh {item.name!r} has no faces")
    F = len(Fa)
    corners = V[Fa].reshape(-1, 3)
    tris = np.arange(3 * F, dtype=np.int32).reshape(F, 3)
    normals = _corner_normals(V, Fa).reshape(-1, 3)

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(corners), o3d.utility.Vector3iVector(tris))
    m.vertex_normals = o3d.utility.Vector3dVector(normals)
    mat = rendering.MaterialRecord()
    mat.shader = "defaultLit"
    mat.base_roughness = 0.85
    mat.base_metallic = 0.0
    mat.base_reflectance = 0.3
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    tex = _texture_image(visual) if kind == "texture" else None
    uv = getattr(visual, "uv", None) if kind == "texture" else None
    if tex is not None and uv is not None and len(uv) == len(V):
        uv = np.asarray(uv, dtype=float)[Fa].reshape(-1, 2)
        # trimesh and Open3D both put v = 0 at the image's bottom row (checked by test_texture_not_flipped).
        m.triangle_uvs = o3d.utility.Vector2dVector(uv)
        mat.albedo_img = o3d.geometry.Image(tex)
        base = _material_base_color(visual)
        mat.base_color = [float(base[0]), float(base[1]), float(base[2]), 1.0]
    else:
        colors = None
        if kind == "vertex":
            colors = np.asarray(visual.vertex_colors, dtype=float)[:, :3][Fa].reshape(-1, 3) / 255.0
        elif kind == "face":
            colors = np.repeat(np.asarray(visual.face_colors, dtype=float)[:, :3] / 255.0, 3, axis=0)
        elif kind == "texture":
            c = _material_base_color(visual)
            colors = np.tile(c, (3 * F, 1))
        if colors is None:
            colors = np.full((3 * F, 3), 0.7)
        m.vertex_colors = o3d.utility.Vector3dVector(colors)
        mat.base_color = [1.0, 1.0, 1.0, 1.0]

    mid = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(corners), o3d.utility.Vector3iVector(tris))
    mat_id = rendering.MaterialRecord()
    mat_id.shader = "defaultUnlit"
    code = item.instance_id + 1
    lv = _code_levels_in()
    digits = (code // _LEVELS ** 2, (code // _LEVELS) % _LEVELS, code % _LEVELS)
    mat_id.base_color = [float(lv[digits[0]]), float(lv[digits[1]]), float(lv[digits[2]]), 1.0]
    return m, mat, mid, mat_id


# ----------------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------------
class OffscreenScene:
    """A set of meshes in world (ENU) coordinates, a sun and a sky, rendered to ``width`` x ``height``."""

    def __init__(self, width: int, height: int, *, background_rgb=(0.62, 0.74, 0.88), supersample: int = 2) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size {width}x{height} must be positive")
        if int(supersample) < 1:
            raise ValueError(f"supersample={supersample} must be >= 1")
        self.width, self.height = int(width), int(height)
        self.background_rgb = tuple(float(c) for c in background_rgb)
        self.supersample = int(supersample)
        self._items: dict[str, tuple[SceneMesh, tuple]] = {}
        self._sun = _Sun()
        self._version = 0

    # -- content ---------------------------------------------------------------------------------------
    def add(self, item: SceneMesh) -> None:
        if not isinstance(item, SceneMesh):
            raise TypeError(f"expected a SceneMesh, got {type(item).__name__}")
        if item.name in self._items:
            raise ValueError(f"a mesh named {item.name!r} is already in the scene")
        if not (-1 <= int(item.instance_id) <= MAX_INSTANCE_ID):
            raise ValueError(f"{item.name!r}: instance_id={item.instance_id} outside [-1, {MAX_INSTANCE_ID}]")
        self._items[item.name] = (item, _to_open3d(item))
        self._version += 1

    def remove(self, name: str) -> None:
        del self._items[name]
        self._version += 1

    @property
    def names(self) -> list[str]:
        return list(self._items)

    def set_sun(self, direction_enu, intensity: float = 90_000.0, *, ambient_intensity: float = 40_000.0,
                color=(1.0, 0.97, 0.92), shadows: bool = True) -> None:
        """Sun light travelling along ``direction_enu`` (FROM the sun towards the scene, so z < 0 by day).

        ``intensity``: sun illuminance (lux, Filament units; ~100 000 for a clear day).
        ``ambient_intensity``: image-based sky/indirect light, which keeps shadowed sides from going black.
        """
        self._sun = _Sun(direction=_unit(direction_enu), intensity=float(intensity), color=tuple(color),
                         ambient_intensity=float(ambient_intensity), shadows=bool(shadows))

    # -- rendering -------------------------------------------------------------------------------------
    def _load(self, r) -> None:
        key = (id(self), self._version)
        if _Canvas.owner == key:
            return
        r.scene.clear_geometry()
        for name, (_item, (m, mat, mid, mat_id)) in self._items.items():
            r.scene.add_geometry(_SHOW_COLOR + name, m, mat)
            r.scene.add_geometry(_SHOW_ID + name, mid, mat_id)
        _Canvas.owner = key

    def _show(self, r, prefix: str) -> None:
        for name in self._items:
            r.scene.show_geometry(_SHOW_COLOR + name, prefix == _SHOW_COLOR)
            r.scene.show_geometry(_SHOW_ID + name, prefix == _SHOW_ID)

    def render(self, K: np.ndarray, cam_from_world: np.ndarray, *, size: tuple[int, int] | None = None,
               supersample: int | None = None) -> RenderResult:
        """Render the pinhole view ``K`` (no skew, no distortion) from ``cam_from_world``.

        ``size``: (width, height) of this render if not the scene's own. ``supersample``: colour is rendered
        this many times larger and area-averaged down (default: the scene's).
        """
        K = np.asarray(K, dtype=float)
        M = np.asarray(cam_from_world, dtype=float)
        if K.shape != (3, 3) or M.shape != (4, 4):
            raise ValueError(f"K.shape={K.shape}, cam_from_world.shape={M.shape}; expected (3, 3) and (4, 4)")
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or abs(K[1, 0]) > 0 or np.any(K[2] != [0, 0, 1]):
            raise ValueError("render() takes a pinhole K without skew; use workbench.render.lens.render_photo "
                             "for skewed or distorted cameras")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(M))):
            raise ValueError("K and cam_from_world must be finite")
        w, h = (self.width, self.height) if size is None else (int(size[0]), int(size[1]))
        s = self.supersample if supersample is None else int(supersample)
        if s < 1:
            raise ValueError(f"supersample={s} must be >= 1")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        W, H = w * s, h * s
        with _Canvas.lock:
            r = _get_renderer(W, H)
            self._load(r)
            view = r.scene.view

            # -- colour: s x larger, pixel centres kept consistent: c' = (c + 0.5) s - 0.5; Open3D wants +0.5.
            self._show(r, _SHOW_COLOR)
            view.set_post_processing(True)
            view.set_sample_count(1)
            view.set_antialiasing(True)
            view.set_shadowing(self._sun.shadows)
            r.scene.set_background([*self.background_rgb, 1.0])
            sun = self._sun
            low = r.scene.scene
            low.set_sun_light(sun.direction.astype(np.float32), np.asarray(sun.color, np.float32), sun.intensity)
            low.enable_sun_light(True)
            low.enable_indirect_light(True)
            low.set_indirect_light_intensity(sun.ambient_intensity)
            Kc = np.array([[fx * s, 0.0, (cx + 0.5) * s], [0.0, fy * s, (cy + 0.5) * s], [0.0, 0.0, 1.0]])
            r.setup_camera(Kc, M, W, H)
            color = np.asarray(r.render_to_image())[..., :3]
            if s > 1:
                color = cv2.resize(color, (w, h), interpolation=cv2.INTER_AREA)
            color = np.ascontiguousarray(color, dtype=np.uint8)

            # -- instance + depth: canvas pixel s*u is exactly final pixel u's centre; no blending.
            self._show(r, _SHOW_ID)
            _id_pass_settings(r)
            view.set_antialiasing(False)
            view.set_shadowing(False)
            Ki = np.array([[fx * s, 0.0, cx * s + 0.5], [0.0, fy * s, cy * s + 0.5], [0.0, 0.0, 1.0]])
            r.setup_camera(Ki, M, W, H)
            ids = np.asarray(r.render_to_image())[::s, ::s][:h, :w]
            depth = np.asarray(r.render_to_depth_image(z_in_view_space=True), dtype=np.float32)[::s, ::s][:h, :w]
            self._show(r, _SHOW_COLOR)

        table = _decode_table(_Canvas.levels_out)
        code = table[ids[..., 0]] * _LEVELS ** 2 + table[ids[..., 1]] * _LEVELS + table[ids[..., 2]]
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
        instance = (code - 1).astype(np.int32)
        instance[~np.isfinite(depth)] = -1
        return RenderResult(color=color, depth=np.ascontiguousarray(depth), instance=np.ascontiguousarray(instance))
