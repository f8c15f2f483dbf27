"""Off-screen rendering of ENU scenes on Open3D's Filament renderer (Vulkan; lavapipe on the CPU).

Conventions follow ``workbench/core/camera.py``: camera x right, y down, z forward, ``cam_from_world``
(4, 4) with ``p_cam = R @ p_world + t``, and pixel (0, 0) is the **centre** of the top-left pixel.
Open3D's ``setup_camera(K, ...)`` treats pixel (0, 0) as the top-left *corner* of the image (measured: a
point lands half a pixel up-left of ``K @ X``), so :meth:`OffscreenScene.render` adds half a pixel to the
principal point it hands over. Open3D also ignores the skew term of ``K``; skewed and distorted cameras
go through :func:`workbench.render.lens.render_photo`.

Every :meth:`OffscreenScene.render` gives

* colour: one rasterised pass (Filament, lit, textured, tone-mapped), rendered ``supersample`` x larger
  and area-averaged down;
* depth and instance: rays cast through the exact pixel centres against the same triangles (Open3D's
  Embree ``RaycastingScene``), so they are exact, unblended, and cheap (~0.2 s for 1600 x 1200);
  depth is metres along the camera z axis, ``inf`` where nothing is hit.

Open3D cannot hold two ``OffscreenRenderer`` at once in one process (destroying either aborts the
process), so one module-level renderer is shared by all scenes and re-created only when the canvas
size changes; a scene re-uploads its geometry when another scene used the renderer in between.
"""

from __future__ import annotations

import ctypes.util
import glob
import hashlib
import os
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from ..errors import RenderError
from .ahead import shaded_ahead

_MAX_CANVAS = 16384
PASS_THREADS = 2  # threads for the sub-pixel passes of a supersampled ray-traced render

_INSTALL_HINT = ("install the Vulkan/EGL runtime, e.g. on Debian/Ubuntu: "
                 "`apt-get install libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1` "
                 "(mesa-vulkan-drivers provides lavapipe, a CPU Vulkan driver)")

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


class _Traced:
    """A render's array that may be traced late (``depth``, ``instance``): reading or setting it first runs the
    render's pending trace (which sets both), then reads or sets ``_<name>``."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = "_" + name

    def __get__(self, render: RenderResult | None, owner: type | None = None):
        if render is None:
            return self
        render._trace()
        return getattr(render, self.slot)

    def __set__(self, render: RenderResult, value: np.ndarray) -> None:
        render._trace()
        setattr(render, self.slot, value)


class RenderResult:
    """A render: ``color`` (h, w, 3) uint8 RGB; ``depth`` (h, w) float32 metres along camera z, inf where nothing;
    ``instance`` (h, w) int32 instance id, -1 for background / non-instance objects.

    Depth and instance may be given as ``traced``, a function returning both: they are then cast when one of
    them is first read (most renders are pictures whose depth and ids nobody reads; the scene's triangles are
    bound when the render is made, so a later change of the scene does not change them)."""

    depth = _Traced()
    instance = _Traced()

    def __init__(self, color: np.ndarray, depth: np.ndarray | None = None, instance: np.ndarray | None = None, *,
                 traced=None) -> None:
        if traced is None and (depth is None or instance is None):
            raise ValueError("RenderResult needs depth and instance, or traced")
        self.color = color
        self._depth, self._instance, self._traced = depth, instance, traced
        self._lock = threading.Lock()

    def _trace(self) -> None:
        with self._lock:
            if self._traced is not None:
                self._depth, self._instance = self._traced()
                self._traced = None


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
    """The shared renderer, with a canvas of at least ``width`` x ``height``.

    Renders use the canvas's top-left corner; the canvas is re-created (slow, and each new one compiles
    shaders again) only when it is too small, or more than 4 times the area needed.
    """
    if _Canvas.renderer is not None:
        cw, ch = _Canvas.size
        if cw >= width and ch >= height and cw * ch <= 4 * width * height:
            return _Canvas.renderer
        if cw * ch <= 4 * width * height:  # grow, keeping room for the sizes used so far
            width, height = max(width, cw), max(height, ch)
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
    return r


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
    # each corner's sum of its kept neighbours' weighted normals, added in order (as np.add.at adds them: the same
    # sums, 10 times faster)
    ci, w_kept = corner_idx[keep], fn_w[nb_face[keep]]
    acc = np.column_stack([np.bincount(ci, weights=w_kept[:, k], minlength=3 * F) for k in range(3)])
    n = np.linalg.norm(acc, axis=1, keepdims=True)
    acc = np.where(n > 0, acc / np.maximum(n, 1e-300), fn[corner_f])
    return acc.reshape(F, 3, 3)


# Open3D caches GPU textures by the address of the o3d.geometry.Image; once an Image is freed, a new one at
# the same address picks up a stale texture and the next render_to_image can hang forever (seen with
# lavapipe). So texture images are kept alive for the whole process, shared by content.
_TEXTURES: dict[tuple, object] = {}


def _texture_handle(tex: np.ndarray):
    import open3d as o3d

    key = (tex.shape, hashlib.blake2b(tex.tobytes(), digest_size=16).hexdigest())
    img = _TEXTURES.get(key)
    if img is None:
        img = _TEXTURES[key] = o3d.geometry.Image(np.ascontiguousarray(tex))
    return img


def _linear_from_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=float), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


_SRGB_TO_LINEAR = _linear_from_srgb(np.arange(256) / 255.0).astype(np.float32)  # per 8-bit sRGB value


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


def _material_base_color(visual, textured: bool) -> np.ndarray:
    """Colour factor of a trimesh material: glTF's baseColorFactor multiplies the texture; a SimpleMaterial's
    diffuse colour (trimesh defaults it to grey 0.4) is only used when there is no texture."""
    mat = getattr(visual, "material", None)
    for attr in (("baseColorFactor",) if textured else ("baseColorFactor", "diffuse", "main_color")):
        c = getattr(mat, attr, None) if mat is not None else None
        if c is not None:
            c = np.asarray(c, dtype=float).reshape(-1)
            if c.size >= 3:
                return (c[:3] / 255.0) if c.max() > 1.0 else c[:3]
    return np.ones(3)


def to_open3d(item: SceneMesh):
    """(Open3D mesh with per-corner normals/colours/UVs, lit material) for one SceneMesh."""
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
        mat.albedo_img = _texture_handle(tex)
        base = _material_base_color(visual, True)
        mat.base_color = [float(base[0]), float(base[1]), float(base[2]), 1.0]
    else:
        colors = None
        if kind == "vertex":
            colors = np.asarray(visual.vertex_colors, dtype=float)[:, :3][Fa].reshape(-1, 3) / 255.0
        elif kind == "face":
            colors = np.repeat(np.asarray(visual.face_colors, dtype=float)[:, :3] / 255.0, 3, axis=0)
        elif kind == "texture":
            colors = np.tile(_material_base_color(visual, False), (3 * F, 1))
        if colors is None:
            colors = np.full((3 * F, 3), 0.7)
        # Filament takes vertex colours as linear while textures are decoded from sRGB: linearise them.
        colors = _linear_from_srgb(colors)
        m.vertex_colors = o3d.utility.Vector3dVector(colors)
        mat.base_color = [1.0, 1.0, 1.0, 1.0]

    return m, mat


# ----------------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------------
class OffscreenScene:
    """A set of meshes in world (ENU) coordinates, a sun and a sky, rendered to ``width`` x ``height``."""

    def __init__(self, width: int, height: int, *, background_rgb=(0.62, 0.74, 0.88), supersample: int = 2,
                 engine: str = "raytrace") -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size {width}x{height} must be positive")
        if int(supersample) < 1:
            raise ValueError(f"supersample={supersample} must be >= 1")
        self.width, self.height = int(width), int(height)
        self.background_rgb = tuple(float(c) for c in background_rgb)
        self.supersample = int(supersample)
        self._items: dict[str, tuple[SceneMesh, object, object]] = {}
        self._sun = _Sun()
        self._version = 0
        self._rays = None  # (version, RaycastingScene, instance id per geometry id)
        self._rays_lock = threading.Lock()  # renders of one scene may run in several threads
        if engine not in ("raytrace", "filament"):
            raise ValueError(f"engine={engine!r}: choose 'raytrace' or 'filament'")
        self.engine = engine
        self._shading: dict[str, _ShadingData] = {}

    # -- content ---------------------------------------------------------------------------------------
    def add(self, item: SceneMesh) -> None:
        if not isinstance(item, SceneMesh):
            raise TypeError(f"expected a SceneMesh, got {type(item).__name__}")
        if item.name in self._items:
            raise ValueError(f"a mesh named {item.name!r} is already in the scene")
        if int(item.instance_id) < -1:
            raise ValueError(f"{item.name!r}: instance_id={item.instance_id} must be >= 0, or -1 for none")
        m, mat = to_open3d(item) if self.engine == "filament" else (None, None)
        self._items[item.name] = (item, m, mat)
        self._shading[item.name] = shaded_ahead(item.mesh) or _ShadingData.of(item)  # (computed ahead: the same)
        self._version += 1

    def remove(self, name: str) -> None:
        del self._items[name]
        del self._shading[name]
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

    # -- ray casting (depth, instance) -----------------------------------------------------------------
    def prepare(self) -> None:
        """Build the ray-casting scene now (it is built on the first render otherwise): call before several threads
        render the same scene."""
        self._raycaster()

    def _raycaster(self):
        with self._rays_lock:
            return self._build_raycaster()

    def _build_raycaster(self):
        if self._rays is not None and self._rays[0] == self._version:
            return self._rays[1], self._rays[2]
        import open3d as o3d

        rs = o3d.t.geometry.RaycastingScene()
        inst = []
        self._gid_names = {}
        for item, _m, _mat in self._items.values():
            V = np.ascontiguousarray(item.mesh.vertices, dtype=np.float32)
            F = np.ascontiguousarray(item.mesh.faces, dtype=np.uint32)
            gid = rs.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F))
            inst.append((gid, int(item.instance_id)))
            self._gid_names[gid] = item.name
        lut = np.full(max([g for g, _ in inst], default=-1) + 2, -1, dtype=np.int32)  # last entry: miss
        for g, i in inst:
            lut[g] = i
        self._rays = (self._version, rs, lut)
        return rs, lut

    def trace(self, cam_from_world: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays through undistorted normalised coordinates ``xy`` (..., 2) of a camera.

        Returns (depth along camera z in metres, ``inf`` on a miss; instance id, -1 on a miss or for
        non-instance objects), both shaped like ``xy[..., 0]``. Triangles are hit from either side."""
        return self.tracer()(cam_from_world, xy)

    def tracer(self):
        """:meth:`trace` bound to the scene's triangles as they are now (a later change of the scene does not
        change what it casts against)."""
        if not self._items:
            return _trace_nothing
        rs, lut = self._raycaster()
        return lambda cam_from_world, xy: _trace(rs, lut, cam_from_world, xy)

    # -- rasterised colour -----------------------------------------------------------------------------
    def _load(self, r) -> None:
        key = (id(self), self._version)
        if _Canvas.owner == key:
            return
        r.scene.clear_geometry()
        for name, (_item, m, mat) in self._items.items():
            r.scene.add_geometry(name, m, mat)
        _Canvas.owner = key

    def render_color(self, K: np.ndarray, cam_from_world: np.ndarray, width: int, height: int,
                     supersample: int) -> np.ndarray:
        """The lit colour image (height, width, 3) uint8 of the pinhole view ``K`` (no skew)."""
        K = np.asarray(K, dtype=float)
        M = np.asarray(cam_from_world, dtype=float)
        s = int(supersample)
        W, H = width * s, height * s
        if max(W, H) > _MAX_CANVAS:
            raise ValueError(f"render of {width}x{height} at supersample {s} exceeds the {_MAX_CANVAS} px canvas limit")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if self.engine == "raytrace":
            return self.raytrace_color(M, lambda uv: np.column_stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy]),
                                       width, height, s)
        with _Canvas.lock:
            r = _get_renderer(W, H)
            self._load(r)
            view = r.scene.view
            view.set_post_processing(True)
            view.set_antialiasing(True)
            view.set_sample_count(1)
            view.set_shadowing(self._sun.shadows)
            r.scene.set_background([*self.background_rgb, 1.0])
            sun = self._sun
            low = r.scene.scene
            low.set_sun_light(sun.direction.astype(np.float32), np.asarray(sun.color, np.float32), sun.intensity)
            low.enable_sun_light(True)
            low.enable_indirect_light(True)
            low.set_indirect_light_intensity(sun.ambient_intensity)
            # s x larger with pixel centres kept: c' = (c + 0.5) s - 0.5; and Open3D puts pixel (0, 0)'s
            # centre at (0.5, 0.5), so it gets c' + 0.5.
            Kc = np.array([[fx * s, 0.0, (cx + 0.5) * s], [0.0, fy * s, (cy + 0.5) * s], [0.0, 0.0, 1.0]])
            CW, CH = _Canvas.size
            r.setup_camera(Kc, M, CW, CH)  # the image is the canvas's top-left W x H corner
            color = np.asarray(r.render_to_image())[:H, :W, :3]
        if s > 1:
            color = cv2.resize(color, (width, height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(color, dtype=np.uint8)

    def render(self, K: np.ndarray, cam_from_world: np.ndarray, *, size: tuple[int, int] | None = None,
               supersample: int | None = None) -> RenderResult:
        """Render the pinhole view ``K`` (no skew, no distortion) from ``cam_from_world`` (4, 4).

        ``size``: (width, height) of this render if not the scene's own. ``supersample``: colour is rendered
        this many times larger and area-averaged down (default: the scene's)."""
        K = np.asarray(K, dtype=float)
        M = np.asarray(cam_from_world, dtype=float)
        if K.shape != (3, 3) or M.shape != (4, 4):
            raise ValueError(f"K.shape={K.shape}, cam_from_world.shape={M.shape}; expected (3, 3) and (4, 4)")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(M))):
            raise ValueError("K and cam_from_world must be finite")
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1]):
            raise ValueError("render() takes a pinhole K without skew; use workbench.render.lens.render_photo "
                             "for skewed or distorted cameras")
        w, h = (self.width, self.height) if size is None else (int(size[0]), int(size[1]))
        s = self.supersample if supersample is None else int(supersample)
        if s < 1:
            raise ValueError(f"supersample={s} must be >= 1")
        color = self.render_color(K, M, w, h, s)
        trace = self.tracer()

        def traced() -> tuple[np.ndarray, np.ndarray]:
            u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
            return trace(M, np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], axis=-1))

        return RenderResult(color, traced=traced)


def _trace_nothing(cam_from_world: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    shape = np.shape(xy)[:-1]
    return np.full(shape, np.inf, np.float32), np.full(shape, -1, np.int32)


def _trace(rs, lut: np.ndarray, cam_from_world: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`OffscreenScene.trace` against the ray-casting scene ``rs`` (instance id per geometry id: ``lut``)."""
    import open3d as o3d

    M = np.asarray(cam_from_world, dtype=float)
    xy = np.asarray(xy, dtype=float)
    shape = xy.shape[:-1]
    R, t = M[:3, :3], M[:3, 3]
    centre = -R.T @ t
    d_cam = np.concatenate([xy.reshape(-1, 2), np.ones((xy[..., 0].size, 1))], axis=1)
    d_world = d_cam @ R  # R.T @ d for each row; z component in camera = 1, so t_hit = camera z
    rays = np.empty((len(d_world), 6), dtype=np.float32)
    rays[:, :3] = centre
    rays[:, 3:] = d_world
    ans = rs.cast_rays(o3d.core.Tensor(rays))
    depth = ans["t_hit"].numpy().astype(np.float32)
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    hit = np.isfinite(depth) & (gid >= 0) & (gid < len(lut) - 1)
    depth = np.where(hit, depth, np.inf).astype(np.float32)
    instance = np.where(hit, lut[np.where(hit, gid, len(lut) - 1)], -1).astype(np.int32)
    return depth.reshape(shape), instance.reshape(shape)


# ----------------------------------------------------------------------------------------------------------
# Ray-traced colour (the default engine): Open3D's Embree ray caster, shaded on the CPU
# ----------------------------------------------------------------------------------------------------------
@dataclass
class _ShadingData:
    """What the ray tracer needs of one mesh: per-corner normals, and per-corner UVs + texture or colours."""

    corner_normals: np.ndarray  # (F, 3, 3)
    corner_uv: np.ndarray | None  # (F, 3, 2), trimesh convention: v = 0 at the image's bottom row
    texture: np.ndarray | None  # (H, W, 3) float32, linear
    corner_colors: np.ndarray | None  # (F, 3, 3) float32, linear

    @classmethod
    def of(cls, item: SceneMesh) -> "_ShadingData":
        mesh = item.mesh
        V = np.asarray(mesh.vertices, dtype=float)
        Fa = np.asarray(mesh.faces, dtype=np.int64)
        if len(Fa) == 0:
            raise ValueError(f"SceneMesh {item.name!r} has no faces")
        normals = _corner_normals(V, Fa).astype(np.float32)
        visual = mesh.visual
        kind = getattr(visual, "kind", None)
        tex = _texture_image(visual) if kind == "texture" else None
        uv = getattr(visual, "uv", None) if kind == "texture" else None
        if tex is not None and uv is not None and len(uv) == len(V):
            base = _material_base_color(visual, True)
            lin = (_SRGB_TO_LINEAR[tex] * np.asarray(base, dtype=np.float32)).astype(np.float32) \
                if tex.dtype == np.uint8 else (_linear_from_srgb(tex.astype(np.float32) / 255.0) * base).astype(np.float32)
            return cls(normals, np.asarray(uv, dtype=np.float32)[Fa], lin, None)
        colors = None
        if kind == "vertex":
            colors = np.asarray(visual.vertex_colors, dtype=float)[:, :3][Fa] / 255.0
        elif kind == "face":
            colors = np.repeat(np.asarray(visual.face_colors, dtype=float)[:, None, :3] / 255.0, 3, axis=1)
        elif kind == "texture":
            colors = np.broadcast_to(_material_base_color(visual, False), (len(Fa), 3, 3))
        if colors is None:
            colors = np.full((len(Fa), 3, 3), 0.7)
        return cls(normals, None, None, _linear_from_srgb(colors).astype(np.float32))


shading_data = _ShadingData.of  # (public: what a scene computes of a mesh added to it; render.ahead keeps some)


def _sample_bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup; ``uv`` (n, 2) in [0, 1] with v = 0 at the bottom row (trimesh/glTF-flipped)."""
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0.0, w - 1.0)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0.0, h - 1.0)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    # img[y, x] of the four neighbours, gathered from the flattened texture (the same values, fewer passes)
    flat = img.reshape(h * w, -1)
    r0, r1 = y0 * w, y1 * w
    gx = 1 - fx
    top = flat.take(r0 + x0, axis=0) * gx + flat.take(r0 + x1, axis=0) * fx
    bot = flat.take(r1 + x0, axis=0) * gx + flat.take(r1 + x1, axis=0) * fx
    return top * (1 - fy) + bot * fy


def _srgb_from_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def _raytrace_shade(self: "OffscreenScene", cam_from_world: np.ndarray, xy: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Linear-light colour (n, 3) seen along the rays through undistorted normalised coordinates ``xy`` (n, 2), and
    which rays hit a surface (n,) bool. Keeps no state: renders may run in several threads."""
    import open3d as o3d

    M = np.asarray(cam_from_world, dtype=float)
    R, t = M[:3, :3], M[:3, 3]
    centre = -R.T @ t
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R  # world directions, camera z = 1
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    # sky: the background colour (sRGB, linearised; the tone curve below maps it back to itself)
    horizon = _linear_from_srgb(np.asarray(self.background_rgb, dtype=float))
    out = np.broadcast_to(horizon.astype(np.float32), (len(xy), 3)).copy()
    if not self._items:
        return out, np.zeros(len(xy), bool)
    rs, _lut = self._raycaster()
    rays = np.empty((len(d), 6), dtype=np.float32)
    rays[:, :3] = centre
    rays[:, 3:] = dn
    ans = rs.cast_rays(o3d.core.Tensor(rays))
    thit = ans["t_hit"].numpy()
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    bary = ans["primitive_uvs"].numpy().astype(np.float32)  # hit = (1-u-v) v0 + u v1 + v v2
    hit = np.isfinite(thit) & np.isin(gid, list(self._gid_names))
    idx = np.nonzero(hit)[0]
    if len(idx) == 0:
        return out, hit
    w = np.column_stack([1.0 - bary[idx, 0] - bary[idx, 1], bary[idx, 0], bary[idx, 1]]).astype(np.float32)
    albedo = np.zeros((len(idx), 3), np.float32)
    normal = np.zeros((len(idx), 3), np.float32)
    # the hits grouped by geometry: one stable sort instead of a mask over every hit per geometry (the same
    # hits, in the same order)
    g_hit = gid[idx]
    order = np.argsort(g_hit, kind="stable")
    g_sorted = g_hit[order]
    for g, name in self._gid_names.items():
        lo, hi = np.searchsorted(g_sorted, [g, g + 1])
        if lo == hi:
            continue
        sel = order[lo:hi]
        sd = self._shading[name]
        p = prim[idx[sel]]
        ws = w[sel]  # (n, 3) barycentric weights of the three corners
        normal[sel] = np.einsum("nij,ni->nj", sd.corner_normals[p], ws)
        if sd.texture is not None:
            uv = np.einsum("nij,ni->nj", sd.corner_uv[p], ws)
            albedo[sel] = _sample_bilinear(sd.texture, uv)
        else:
            albedo[sel] = np.einsum("nij,ni->nj", sd.corner_colors[p], ws)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    view = dn[idx].astype(np.float32)
    flip = np.sum(normal * view, axis=1) > 0  # seen from behind: shade the side facing the camera
    normal[flip] *= -1
    sun = self._sun
    to_sun = -np.asarray(sun.direction, dtype=np.float32)
    lam = np.clip(normal @ to_sun, 0.0, None)
    lit = np.nonzero(lam > 0)[0]
    vis = np.zeros(len(idx), np.float32)
    if sun.shadows and len(lit):
        pts = centre + dn[idx[lit]] * thit[idx[lit], None]
        srays = np.empty((len(lit), 6), dtype=np.float32)
        srays[:, :3] = pts + normal[lit] * 0.03
        srays[:, 3:] = to_sun
        occ = rs.test_occlusions(o3d.core.Tensor(srays)).numpy().astype(bool)
        vis[lit] = (~occ).astype(np.float32)
    else:
        vis[lit] = 1.0
    sun_rgb = np.asarray(sun.color, np.float32) * (sun.intensity / 90_000.0)
    sky = np.float32(0.5 * sun.ambient_intensity / 40_000.0) * (0.6 + 0.4 * normal[:, 2:3])
    radiance = albedo * (sun_rgb * (lam * vis)[:, None] + sky)
    # a little aerial perspective
    haze = (1.0 - np.exp(-thit[idx] / 4000.0))[:, None].astype(np.float32)
    radiance = radiance * (1 - haze) + horizon.astype(np.float32) * haze
    out[idx] = radiance
    return out, hit


def _raytrace_color(self: "OffscreenScene", cam_from_world: np.ndarray, xy_of_uv, width: int, height: int,
                    supersample: int) -> np.ndarray:
    """Supersampled ray-traced colour (height, width, 3) uint8. ``xy_of_uv`` maps pixel coordinates (n, 2) of the
    output image (pixel (0, 0) = centre of the top-left pixel) to undistorted normalised coordinates."""
    s = int(supersample)
    offs = (np.arange(s) + 0.5) / s - 0.5
    acc = np.zeros((height * width, 3), np.float32)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    base = np.column_stack([u.ravel(), v.ravel()])
    def one_pass(o: tuple[float, float]) -> np.ndarray:
        xy = xy_of_uv(base + [o[1], o[0]])
        ok = np.all(np.isfinite(xy), axis=1)
        col = np.broadcast_to(_linear_from_srgb(np.asarray(self.background_rgb, float)).astype(np.float32),
                              (len(xy), 3)).copy()
        shaded, hit = _raytrace_shade(self, cam_from_world, xy[ok])
        # exposure and a soft shoulder on lit surfaces; the sky keeps its colour
        shaded[hit] = shaded[hit] * 1.15 / (1.0 + 0.22 * shaded[hit])
        col[ok] = shaded
        return col

    passes = [(oy, ox) for oy in offs for ox in offs]
    if len(passes) > 1 and threading.current_thread() is threading.main_thread():
        # the sub-pixel passes on two threads (each computed as alone, summed in their order: the same picture);
        # not where the caller already renders several pictures at once on threads
        from concurrent.futures import ThreadPoolExecutor

        self.prepare()
        with ThreadPoolExecutor(max_workers=PASS_THREADS) as pool:
            cols = list(pool.map(one_pass, passes))
    else:
        cols = [one_pass(o) for o in passes]
    for col in cols:
        acc += col
    acc /= s * s
    return (np.round(_srgb_from_linear(acc) * 255.0)).astype(np.uint8).reshape(height, width, 3)


OffscreenScene.raytrace_color = _raytrace_color
