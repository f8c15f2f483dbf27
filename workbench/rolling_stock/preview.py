"""Quick-look renders of a textured carriage model (Open3D off-screen; headless through Vulkan/lavapipe).

    python -m workbench.rolling_stock.preview /tmp/rolling_stock_look [type ...]

writes ``<type>_views.png`` (four views: front-left, rear-right, front and side) and ``<type>_atlas.png``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import RenderError
from .library import CarriageType, load_library


def to_open3d(mesh):
    """A textured trimesh (as built by :meth:`CarriageType.mesh`) as an Open3D legacy TriangleMesh."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=float))
    m.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32))
    uv = np.asarray(mesh.visual.uv, dtype=float)[np.asarray(mesh.faces).reshape(-1)]
    # trimesh's UVs (v = 0 at the bottom of the image) and the unflipped image render correctly in
    # Open3D's rendering API (checked visually: lettering reads the right way round on every face)
    m.triangle_uvs = o3d.utility.Vector2dVector(uv)
    m.triangle_material_ids = o3d.utility.IntVector(np.zeros(len(mesh.faces), dtype=np.int32))
    m.compute_triangle_normals()
    m.compute_vertex_normals()
    return m


_RENDERER = None  # Open3D allows one off-screen renderer per process: keep and reuse it


def render_views(ct: CarriageType, car_number: str = "", size: tuple[int, int] = (960, 540)) -> Image.Image:
    try:
        import open3d as o3d
        from open3d.visualization import rendering
    except Exception as exc:  # pragma: no cover - depends on the machine
        raise RenderError(f"Open3D rendering is not available: {exc}") from None
    mesh = ct.mesh(car_number)
    om = to_open3d(mesh)
    global _RENDERER
    try:
        if _RENDERER is None or _RENDERER[1] != tuple(size):
            _RENDERER = (rendering.OffscreenRenderer(*size), tuple(size))
    except Exception as exc:  # pragma: no cover
        raise RenderError(f"cannot start the off-screen renderer: {exc}") from None
    r = _RENDERER[0]
    r.scene.clear_geometry()
    mat = rendering.MaterialRecord()
    mat.shader = "defaultLit"
    tex = np.ascontiguousarray(np.asarray(mesh.visual.material.image.convert("RGB")))
    mat.albedo_img = o3d.geometry.Image(tex)
    r.scene.add_geometry("car", om, mat)
    r.scene.set_background([0.72, 0.8, 0.9, 1.0])
    r.scene.scene.set_sun_light([-0.3, -0.5, -0.8], [1.0, 1.0, 1.0], 60000)
    r.scene.scene.enable_sun_light(True)
    r.scene.scene.enable_indirect_light(True)
    r.scene.scene.set_indirect_light_intensity(45000)
    L, H = ct.length_m, ct.height_m
    c = np.array([0.0, 0.0, H / 2])
    views = [
        (np.array([L * 0.75, L * 0.55, H * 1.2]), c + [L * 0.1, 0, 0]),  # front-left
        (np.array([-L * 0.75, -L * 0.55, H * 1.5]), c - [L * 0.1, 0, 0]),  # rear-right
        (np.array([L / 2 + 9.0, -2.5, 2.2]), np.array([L / 2, 0.0, H / 2])),  # front, close
        (np.array([0.0, L * 0.85, 2.0]), c),  # left side, broadside
    ]
    tiles = []
    for eye, target in views:
        r.setup_camera(45.0, target.tolist(), eye.tolist(), [0, 0, 1])
        tiles.append(Image.fromarray(np.asarray(r.render_to_image())))
    w, h = size
    out = Image.new("RGB", (2 * w, 2 * h))
    for k, t in enumerate(tiles):
        out.paste(t, ((k % 2) * w, (k // 2) * h))
    return out


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "/tmp/rolling_stock_look")
    out.mkdir(parents=True, exist_ok=True)
    lib = load_library()
    for tid in argv[1:] or sorted(lib):
        ct = lib[tid]
        ct.mesh().visual.material.image.save(out / f"{tid}_atlas.png")
        render_views(ct).save(out / f"{tid}_views.png")
        print(out / f"{tid}_views.png")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
