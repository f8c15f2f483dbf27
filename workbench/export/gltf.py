"""The scene as one glTF 2.0 binary (``scene.glb``): terrain, buildings and the carriages with their liveries.

Axes (docs/exports.md): glTF is y-up, so every position is written in glTF axes
``p_gltf = GLTF_FROM_ENU @ p_enu``: glTF +X = east, +Y = up, +Z = south (= -north), metres, origin at the scene
origin. The georeference (origin in WGS84 and in the project CRS, the CRS, the axis change) is in
``asset.extras.georeference`` and, copied, in ``scenes[0].extras.georeference``.

Nodes: ``scene`` (root) -> ``terrain``, ``buildings``, ``carriages`` -> one node per carriage named
``car <number>`` whose translation/rotation is ``GLTF_FROM_ENU @ world_from_carriage @ GLTF_FROM_ENU.T`` and whose
mesh is the carriage model in the carriage frame written in glTF axes (x forward, y up, z right), so an identity
node shows it upright. Its extras hold the number, type, pose and uncertainty. Textures are embedded (JPEG).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pygltflib as gl
import trimesh

from ..core.geometry import quaternion_xyzw_from_matrix
from ..files.scene import SceneCarriage
from .scene import GLTF_FROM_ENU, ExportOptions, ExportScene

log = logging.getLogger(__name__)

_FLOAT, _UINT = gl.FLOAT, gl.UNSIGNED_INT
_CLAMP = 33071  # CLAMP_TO_EDGE
_LINEAR, _LINEAR_MIPMAP = 9729, 9987


class _GlbBuilder:
    """Accumulates buffer views, accessors, images and materials into one binary buffer."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.g = gl.GLTF2(asset=gl.Asset(version="2.0", generator="train-wreck-workbench export"),
                          buffers=[], bufferViews=[], accessors=[], meshes=[], nodes=[], materials=[],
                          textures=[], images=[], samplers=[gl.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP,
                                                                      wrapS=_CLAMP, wrapT=_CLAMP)], scenes=[])

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data),
                                                target=target))
        self.blob.extend(data)
        return len(self.g.bufferViews) - 1

    def accessor(self, array: np.ndarray, *, indices: bool = False, minmax: bool = False) -> int:
        if indices:
            a = np.ascontiguousarray(array, dtype=np.uint32).reshape(-1)
            acc = gl.Accessor(bufferView=self.view(a.tobytes(), gl.ELEMENT_ARRAY_BUFFER), componentType=_UINT,
                              count=int(a.size), type=gl.SCALAR)
        else:
            a = np.ascontiguousarray(array, dtype=np.float32)
            kind = {2: gl.VEC2, 3: gl.VEC3, 4: gl.VEC4}[a.shape[1]]
            acc = gl.Accessor(bufferView=self.view(a.tobytes(), gl.ARRAY_BUFFER), componentType=_FLOAT,
                              count=int(len(a)), type=kind)
            if minmax:
                acc.min = [float(x) for x in a.min(axis=0)]
                acc.max = [float(x) for x in a.max(axis=0)]
        self.g.accessors.append(acc)
        return len(self.g.accessors) - 1

    def texture(self, jpeg: bytes) -> int:
        """A texture from the JPEG bytes of its image (``ExportScene.jpeg``)."""
        self.g.images.append(gl.Image(bufferView=self.view(jpeg), mimeType="image/jpeg"))
        self.g.textures.append(gl.Texture(sampler=0, source=len(self.g.images) - 1))
        return len(self.g.textures) - 1

    def material(self, name: str, *, texture: int | None = None, color=(1.0, 1.0, 1.0, 1.0),
                 double_sided: bool = False) -> int:
        pbr = gl.PbrMetallicRoughness(baseColorFactor=[float(c) for c in color], metallicFactor=0.0,
                                      roughnessFactor=0.9)
        if texture is not None:
            pbr.baseColorTexture = gl.TextureInfo(index=texture)
        self.g.materials.append(gl.Material(name=name, pbrMetallicRoughness=pbr, doubleSided=double_sided))
        return len(self.g.materials) - 1

    def mesh(self, name: str, positions: np.ndarray, normals: np.ndarray, faces: np.ndarray, material: int, *,
             uv: np.ndarray | None = None, colors: np.ndarray | None = None) -> int:
        attrs = gl.Attributes(POSITION=self.accessor(positions, minmax=True), NORMAL=self.accessor(normals))
        if uv is not None:
            attrs.TEXCOORD_0 = self.accessor(uv)
        if colors is not None:
            attrs.COLOR_0 = self.accessor(colors)
        prim = gl.Primitive(attributes=attrs, indices=self.accessor(faces, indices=True), material=material)
        self.g.meshes.append(gl.Mesh(name=name, primitives=[prim]))
        return len(self.g.meshes) - 1

    def node(self, name: str, **kw: Any) -> int:
        self.g.nodes.append(gl.Node(name=name, **kw))
        return len(self.g.nodes) - 1

    def finish(self) -> bytes:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.g.buffers.append(gl.Buffer(byteLength=len(self.blob)))
        self.g.set_binary_blob(bytes(self.blob))
        return b"".join(self.g.save_to_bytes())


def _unit_normals(n: np.ndarray) -> np.ndarray:
    n = np.asarray(n, dtype=float)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    bad = norm[:, 0] < 1e-12
    n = n / np.where(norm < 1e-12, 1.0, norm)
    n[bad] = [0.0, 0.0, 1.0]
    return n


def _flat(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (3m, 3), normals (3m, 3), faces (m, 3)): one vertex triple per triangle, flat normals."""
    tri = np.asarray(mesh.triangles, dtype=float).reshape(-1, 3)
    normals = np.repeat(_unit_normals(mesh.face_normals), 3, axis=0)
    return tri, normals, np.arange(len(tri)).reshape(-1, 3)


def carriage_node_trs(car: SceneCarriage) -> tuple[list[float], list[float]]:
    """(translation (3,), rotation quaternion xyzw (4,)) of a carriage's node, glTF axes."""
    R = GLTF_FROM_ENU @ car.world_from_carriage.rotation @ GLTF_FROM_ENU.T
    t = GLTF_FROM_ENU @ car.world_from_carriage.translation
    q = quaternion_xyzw_from_matrix(R)  # x, y, z, w: glTF's order
    return [float(x) for x in t], [float(x) for x in q]


def carriage_extras(car: SceneCarriage) -> dict:
    return {
        "number": car.number, "type": car.type_id, "type_name": car.type_name, "status": car.status,
        "heading_deg": car.heading_deg, "pitch_deg": car.pitch_deg, "roll_deg": car.roll_deg,
        "ci95_body_centre_m": car.ci95_body_centre_m, "ci95_hpr_deg": car.ci95_hpr_deg,
        "body_centre_carriage": [float(x) for x in car.body_centre_carriage],
        "body_centre_enu": [float(x) for x in car.body_centre_enu],
        "world_from_carriage": car.world_from_carriage.matrix.tolist(),
        "mesh_axes": "carriage frame in glTF axes: +X forward, +Y up, +Z right (carriage -y)",
        "doubtful": bool(car.doubt), "doubt": car.doubt or None,
    }


def glb_bytes(scene: ExportScene, options: ExportOptions) -> tuple[bytes, dict]:
    """The GLB file's bytes and statistics."""
    G = GLTF_FROM_ENU
    b = _GlbBuilder()
    children: list[int] = []
    stats: dict[str, Any] = {}
    if scene.terrain is not None:
        t = scene.terrain
        tm = trimesh.Trimesh(t.vertices, t.faces, process=False)
        normals = _unit_normals(np.asarray(tm.vertex_normals)) @ G.T
        if t.texture is not None:
            mat = b.material("terrain", texture=b.texture(scene.jpeg(t.texture, options.texture_max_px,
                                                                        options.jpeg_quality)))
            m = b.mesh("terrain", t.vertices @ G.T, normals, t.faces, mat, uv=t.uv)
        else:
            mat = b.material("terrain")
            m = b.mesh("terrain", t.vertices @ G.T, normals, t.faces, mat, colors=t.colors)
        children.append(b.node("terrain", mesh=m, extras={"what": "terrain (DEM), scene ENU in glTF axes"}))
        stats["terrain_faces"] = int(len(t.faces))
    if scene.buildings:
        merged = trimesh.util.concatenate(scene.buildings)
        V, N, F = _flat(merged)
        mat = b.material("buildings", color=(0.78, 0.76, 0.72, 1.0))
        m = b.mesh("buildings", V @ G.T, N @ G.T, F, mat)
        children.append(b.node("buildings", mesh=m, extras={"count": len(scene.buildings)}))
        stats["buildings"] = len(scene.buildings)
    car_nodes = []
    for car in scene.carriages:
        V, N, F = _flat(car.mesh(textured=True))
        uv = np.asarray(car.mesh(textured=True).visual.uv, dtype=float)
        uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])  # trimesh: origin bottom-left; glTF: top-left
        image = car.mesh(textured=True).visual.material.image
        tex = b.texture(scene.jpeg(image, options.livery_max_px, options.jpeg_quality))
        mat = b.material(f"livery {car.number}", texture=tex, double_sided=True)
        m = b.mesh(f"{car.type_id} {car.number}", V @ G.T, N @ G.T, F, mat, uv=uv)
        tr, q = carriage_node_trs(car)
        car_nodes.append(b.node(f"car {car.number}", mesh=m, translation=tr, rotation=q, extras=carriage_extras(car)))
    children.append(b.node("carriages", children=car_nodes))
    georef = {**scene.georeference(), "gltf_from_enu": G.tolist(),
              "axes": "glTF +X = east, +Y = up, +Z = south (-north); p_gltf = gltf_from_enu @ p_enu",
              "where": "asset.extras.georeference (copied in scenes[0].extras.georeference)"}
    root = b.node("scene", children=children)
    b.g.scenes.append(gl.Scene(name=scene.title or "scene", nodes=[root], extras={"georeference": georef}))
    b.g.scene = 0
    b.g.asset.extras = {"georeference": georef, "incident": scene.title, "date": scene.date}
    data = b.finish()
    stats.update(carriages=len(car_nodes), bytes=len(data))
    return data, stats
