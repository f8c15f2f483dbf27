"""Mesh types: a carriage model read from a mesh file (glTF/GLB, OBJ or STL, e.g. a manufacturer's CAD export),
put into the carriage frame and checked against the type file (the format and every bound: :mod:`.spec`,
"Mesh types").

The file is read with trimesh: every triangle of every node (a glTF's node transforms applied), scaled by
``mesh.unit_m`` and moved by ``mesh.carriage_from_file``. Each triangle keeps the colour the file gives it
(material colour, texture sampled at its vertices, vertex or face colours; else ``mesh.color``): the textured
mesh the renderers and exporters draw carries them as a small palette texture.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import SettingsError
from .spec import (MESH_HALF_WIDTH_M, MESH_LOWEST_Z_M, MESH_MAX_TRIANGLES, MESH_TOP_Z_M, MESH_X_MARGIN_M,
                   POINT_TOLERANCE_M, MeshCarriageSpec)

if TYPE_CHECKING:
    import trimesh
    from PIL import Image

PALETTE_BLOCK_PX = 16  # one colour per 16 x 16 px block: JPEG's blocks (and chroma subsampling) stay inside it
PALETTE_MAX_COLOURS = 256


@dataclass(frozen=True)
class LoadedMesh:
    path: Path  # the mesh file
    vertices: np.ndarray  # (V, 3) carriage frame, metres
    faces: np.ndarray  # (F, 3) int
    face_rgb: np.ndarray  # (F, 3) uint8
    bounds: np.ndarray  # (2, 3) min / max corner of the triangles' vertices


def mesh_file(spec: MeshCarriageSpec, type_path: Path) -> Path:
    """The mesh file of a mesh type (``mesh.file``, relative to the type file)."""
    p = Path(spec.mesh.file)
    return p if p.is_absolute() else Path(type_path).parent / p


def carriage_from_file(spec: MeshCarriageSpec, type_path: Path) -> np.ndarray:
    """``mesh.carriage_from_file`` (4, 4), checked: a rotation (orthonormal, determinant +1, within 1e-6) and a
    translation in metres; identity when not given."""
    if spec.mesh.carriage_from_file is None:
        return np.eye(4)
    M = np.asarray(spec.mesh.carriage_from_file, dtype=float)
    key = "mesh.carriage_from_file"
    if not np.all(np.isfinite(M)):
        raise SettingsError(f"{type_path}: '{key}': every entry must be a finite number")
    if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-9):
        raise SettingsError(f"{type_path}: '{key}' last row = {M[3].tolist()}: must be [0, 0, 0, 1]")
    R = M[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > 1e-6 or np.linalg.det(R) < 0:
        raise SettingsError(
            f"{type_path}: '{key}': the 3 x 3 part must be a rotation (orthonormal within 1e-6, determinant +1; "
            f"found |RᵀR - I| = {off:.2g}, determinant {np.linalg.det(R):.6g}); put a scale in 'mesh.unit_m', and a "
            "mirror cannot be used (it turns the faces inside out)")
    return M


def _material_colour(material) -> np.ndarray | None:
    """A material's own colour (glTF's baseColorFactor, an OBJ .mtl's diffuse), None when it gives none."""
    for attr in ("baseColorFactor", "diffuse"):
        c = getattr(material, attr, None)
        if c is not None and np.size(c) >= 3:
            return np.asarray(c, dtype=float).reshape(-1)[:3]
    return None


def _face_colours(geom, default: np.ndarray) -> np.ndarray:
    """(F, 3) uint8 colour of each triangle of one trimesh geometry: the texture sampled at its vertices, the
    material's colour, the vertex or face colours; ``default`` where the file gives none."""
    n = len(geom.faces)
    vis = geom.visual
    try:
        if getattr(vis, "kind", None) == "texture":
            image = getattr(vis.material, "image", None) or getattr(vis.material, "baseColorTexture", None)
            if vis.uv is not None and image is not None:
                vc = np.asarray(vis.to_color().vertex_colors)  # the texture at each vertex
                if vc.ndim == 2 and len(vc) == len(geom.vertices):
                    return np.round(vc[np.asarray(geom.faces)][:, :, :3].mean(axis=1)).astype(np.uint8)
            c = _material_colour(vis.material)
            return np.tile(np.clip(np.round(c), 0, 255).astype(np.uint8), (n, 1)) if c is not None else \
                np.tile(default, (n, 1))
        if getattr(vis, "kind", None) in ("face", "vertex"):
            c = np.asarray(vis.face_colors)[:, :3]
            if len(c) == n:
                return c.astype(np.uint8)
    except (ValueError, IndexError, AttributeError, TypeError):  # a visual trimesh cannot convert: the default
        pass
    return np.tile(default, (n, 1))


def _read(path: Path, type_path: Path, default_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (file units), faces and face colours of every triangle in the file."""
    import trimesh

    try:
        scene = trimesh.load(path, force="scene", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises assorted errors on a broken file: name the file
        raise SettingsError(f"{type_path}: 'mesh.file' = {path.name!r}: cannot read this mesh ({type(exc).__name__}: "
                            f"{exc}); export it again as glTF/GLB, OBJ or STL") from None
    verts, faces, cols = [], [], []
    n = 0
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        g = scene.geometry.get(name)
        if not isinstance(g, trimesh.Trimesh) or len(g.faces) == 0:
            continue  # lines, points: not a surface
        V = np.asarray(g.vertices, dtype=float) @ transform[:3, :3].T + transform[:3, 3]
        F = np.asarray(g.faces, dtype=np.int64)
        if np.linalg.det(transform[:3, :3]) < 0:  # a mirroring node: keep the faces turned outwards
            F = F[:, ::-1]
        verts.append(V)
        faces.append(F + n)
        cols.append(_face_colours(g, default_rgb))
        n += len(V)
    if not faces:
        raise SettingsError(f"{type_path}: 'mesh.file' = {path.name!r}: no triangles in this file")
    return np.vstack(verts), np.vstack(faces), np.vstack(cols)


def load_mesh(spec: MeshCarriageSpec, type_path: Path) -> LoadedMesh:
    """The mesh of a mesh type in the carriage frame, checked against the bounds of :mod:`.spec` ("Mesh types");
    :class:`SettingsError` naming the type file, the key, the value and the bound."""
    path = mesh_file(spec, type_path)
    if not path.is_file():
        raise SettingsError(f"{type_path}: 'mesh.file' = {spec.mesh.file!r}: not found ({path}); the path is "
                            "relative to the type file")
    M = carriage_from_file(spec, type_path)
    default = np.array([int(spec.mesh.color[i:i + 2], 16) for i in (1, 3, 5)], dtype=np.uint8)
    V, F, C = _read(path, type_path, default)
    if len(F) > MESH_MAX_TRIANGLES:
        raise SettingsError(f"{type_path}: 'mesh.file' = {spec.mesh.file!r}: {len(F)} triangles, more than the "
                            f"{MESH_MAX_TRIANGLES} allowed; simplify (decimate) the export")
    V = (spec.mesh.unit_m * V) @ M[:3, :3].T + M[:3, 3]
    if not np.all(np.isfinite(V)):
        raise SettingsError(f"{type_path}: 'mesh.file' = {spec.mesh.file!r}: vertices that are not finite numbers")
    tri = V[F]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = area2 > 1e-12  # degenerate triangles (zero area) carry no surface and no normal
    F, C = F[keep], C[keep]
    # one vertex where the file repeats it (STL always does, glTF at UV seams): a closed mesh is watertight;
    # the triangles keep their order (and so their colours)
    import trimesh

    m = trimesh.Trimesh(vertices=V, faces=F, process=False)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    V, F = np.asarray(m.vertices, dtype=float), np.asarray(m.faces, dtype=np.int64)
    used = V[np.unique(F)]
    check_extent(spec, type_path, used)
    return LoadedMesh(path, V, F, C, np.array([used.min(axis=0), used.max(axis=0)]))


def check_extent(spec: MeshCarriageSpec, type_path: Path, V: np.ndarray) -> None:
    """The mesh's extent in the carriage frame against the type's length (the frame and the units right)."""
    L = spec.dimensions.length_over_couplers_m
    lo, hi = V.min(axis=0), V.max(axis=0)
    hint = "check 'mesh.unit_m' (the file's units) and 'mesh.carriage_from_file' (its axes and origin)"
    where = f"{type_path}: 'mesh.file' = {spec.mesh.file!r} in the carriage frame spans x {lo[0]:.3f} .. " \
            f"{hi[0]:.3f}, y {lo[1]:.3f} .. {hi[1]:.3f}, z {lo[2]:.3f} .. {hi[2]:.3f} m"
    if hi[0] > L / 2 + MESH_X_MARGIN_M or lo[0] < -L / 2 - MESH_X_MARGIN_M:
        raise SettingsError(f"{where}: it must lie within {MESH_X_MARGIN_M} m of the coupler faces, |x| <= "
                            f"length_over_couplers_m / 2 + {MESH_X_MARGIN_M} = {L / 2 + MESH_X_MARGIN_M:.3f} m; {hint}")
    if hi[0] - lo[0] < 0.5 * L:
        raise SettingsError(f"{where}: it must span at least half of length_over_couplers_m = {L} m in x; {hint}")
    if not MESH_LOWEST_Z_M[0] <= lo[2] <= MESH_LOWEST_Z_M[1]:
        raise SettingsError(f"{where}: its lowest point must lie between {MESH_LOWEST_Z_M[0]} and "
                            f"{MESH_LOWEST_Z_M[1]} m (z = 0: the top of the rail, where the wheels touch); {hint}")
    if not MESH_TOP_Z_M[0] <= hi[2] <= MESH_TOP_Z_M[1]:
        raise SettingsError(f"{where}: its top must lie between {MESH_TOP_Z_M[0]} and {MESH_TOP_Z_M[1]} m above "
                            f"the rail; {hint}")
    if max(hi[1], -lo[1]) > MESH_HALF_WIDTH_M:
        raise SettingsError(f"{where}: it must lie within {MESH_HALF_WIDTH_M} m of the centre line (|y|); {hint}")


def surface_distance(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> float:
    """Exact distance of ``point`` from the triangle mesh (the nearest triangle centroid bounds the search)."""
    import trimesh

    tri = vertices[faces]
    p = np.asarray(point, dtype=float)
    ub = float(np.min(np.linalg.norm(tri.mean(axis=1) - p, axis=1)))  # a centroid is on the surface
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    box_d = np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi)), axis=1)
    near = tri[box_d <= ub + 1e-12]
    q = trimesh.triangles.closest_point(near, np.repeat(p[None], len(near), axis=0))
    return float(np.min(np.linalg.norm(q - p, axis=1)))


def check_points(type_path: Path, spec, points: dict[str, np.ndarray], vertices: np.ndarray, faces: np.ndarray,
                 only: set[str] | None = None) -> None:
    """Every marked point (or those in ``only``) within :data:`POINT_TOLERANCE_M` of the mesh; the error names
    the point, where it is and how far from the mesh."""
    for i, mp in enumerate(spec.marked_points):
        if only is not None and mp.name not in only:
            continue
        p = points[mp.name]
        dist = surface_distance(vertices, faces, p)
        if dist > POINT_TOLERANCE_M:
            given = f"xyz = {list(mp.xyz)!r}" if mp.xyz is not None else f"anchor {mp.anchor!r} at {p.round(4).tolist()}"
            raise SettingsError(
                f"{type_path}: 'marked_points[{i}]' ({mp.name!r}, {given}): the point is {dist:.3f} m from the "
                f"model's surface, more than the {POINT_TOLERANCE_M * 1000:.0f} mm allowed; give a point on the "
                "model (e.g. a corner of the body)")


def palette_texture(face_rgb: np.ndarray) -> tuple[np.ndarray, "Image.Image"]:
    """UVs (F, 2) of each triangle's colour in a palette image, and the image: one 16 x 16 px block per colour
    (at most 256 colours: more are quantised)."""
    from PIL import Image

    rgb = np.asarray(face_rgb, dtype=np.uint8)
    colours, inverse = np.unique(rgb, axis=0, return_inverse=True)
    step = 8
    while len(colours) > PALETTE_MAX_COLOURS:  # quantise, coarser until they fit
        q = (rgb // step) * step + step // 2
        colours, inverse = np.unique(q, axis=0, return_inverse=True)
        step *= 2
    inverse = np.asarray(inverse).reshape(-1)
    g = int(np.ceil(np.sqrt(len(colours))))
    b = PALETTE_BLOCK_PX
    img = np.empty((g * b, g * b, 3), dtype=np.uint8)
    img[:] = colours[0]  # (the blocks no colour uses)
    for k, c in enumerate(colours):
        r, col = divmod(k, g)
        img[r * b:(r + 1) * b, col * b:(col + 1) * b] = c
    r, col = np.divmod(inverse, g)
    size = g * b
    uv = np.column_stack([(col * b + b / 2) / size, 1.0 - (r * b + b / 2) / size])
    return uv, Image.fromarray(img)


def textured_mesh(loaded: LoadedMesh) -> "trimesh.Trimesh":
    """Every triangle with its own three vertices, UVs into the palette of the triangles' colours."""
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import SimpleMaterial

    uv_face, image = palette_texture(loaded.face_rgb)
    V = loaded.vertices[loaded.faces].reshape(-1, 3)
    UV = np.repeat(uv_face, 3, axis=0)
    F = np.arange(len(V)).reshape(-1, 3)
    material = SimpleMaterial(image=image, diffuse=[255, 255, 255, 255], ambient=[255, 255, 255, 255],
                              specular=[40, 40, 40, 255], glossiness=10.0)
    return trimesh.Trimesh(vertices=V, faces=F, visual=TextureVisuals(uv=UV, material=material), process=False)


def hull_samples(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Points on the mesh for the terrain contact: the vertices of its convex hull (the lowest point in any
    attitude is one of them), topped up with area-uniform samples of the surface to ``n``."""
    import trimesh
    from scipy.spatial import QhullError

    used = np.unique(np.round(vertices[np.unique(faces)], 9), axis=0)
    try:
        hull = trimesh.convex.convex_hull(used)
        pts = np.unique(np.round(np.asarray(hull.vertices), 9), axis=0)
    except (QhullError, ValueError):  # qhull refuses a flat mesh (all points in one plane): every vertex then
        pts = used
    extra = max(0, int(n) - len(pts))
    if extra == 0:
        return pts
    m = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    s, _ = trimesh.sample.sample_surface(m, extra, seed=seed)
    return np.vstack([pts, np.asarray(s)])
