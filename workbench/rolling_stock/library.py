"""The rolling-stock library: shipped carriage types plus user-defined ones, one TOML file each."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ..errors import SettingsError, UnknownModelType
from .geometry import FACE_NORMALS, Part, anchor_point, bogie_boxes, build_parts, equipment_box
from .livery import Atlas, paint_atlas
from .spec import CarriageSpec, load_spec

if TYPE_CHECKING:  # trimesh takes seconds to import: loaded when a mesh is built, not to list or check types
    import trimesh

TYPES_DIR = Path(__file__).with_name("types")


def _classify(part: Part, normals: np.ndarray) -> np.ndarray:
    """Atlas region of each face of a part, from its outward normal."""
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    out = np.empty(len(normals), dtype=object)
    side = np.where(ny >= 0, "left", "right")
    end = np.where(nx >= 0, "front", "rear")
    if part.kind == "body":
        is_end = (np.abs(nx) >= 0.3) & (np.abs(nx) >= np.abs(ny))
        is_under = ~is_end & (nz < -0.5)
        is_side = ~is_end & ~is_under & (np.abs(ny) >= nz)
        out[:] = "roof"
        out[is_side] = side[is_side]
    else:
        is_under = np.abs(nz) > 0.5
        is_end = ~is_under & (np.abs(nx) >= np.abs(ny))
        out[:] = side
    out[is_end] = end[is_end]
    out[is_under] = "under"
    return out


class CarriageType:
    """One carriage type: dimensions, marked points and (cached) meshes in the carriage frame.

    Carriage frame: metres; x forward (towards the front coupler), y left, z up; origin on the centre line
    midway between the coupler faces, at top-of-rail height.
    """

    def __init__(self, spec: CarriageSpec, source_path: Path) -> None:
        self.spec = spec
        self.source_path = Path(source_path)
        self._lock = threading.Lock()
        self._parts: list[Part] | None = None
        self._mesh_cache: dict[tuple[str, bool], trimesh.Trimesh] = {}
        pts: dict[str, np.ndarray] = {}
        faces: dict[str, tuple[str, ...]] = {}
        for mp in spec.marked_points:
            if mp.anchor is not None:
                xyz, fs = anchor_point(spec, mp.anchor)
            else:
                xyz, fs = np.array(mp.xyz, dtype=float), tuple(mp.faces)
            pts[mp.name] = xyz
            faces[mp.name] = fs
        self.marked_points: dict[str, np.ndarray] = pts
        self._check_explicit_points()
        self.marked_point_faces: dict[str, tuple[str, ...]] = faces
        self.marked_point_normals: dict[str, np.ndarray] = {
            n: (lambda v: v / np.linalg.norm(v))(sum(FACE_NORMALS[f] for f in fs)) for n, fs in faces.items()
        }

    def _check_explicit_points(self) -> None:
        """Explicit ``xyz`` marked points must lie on the model's surface (anchors do by construction)."""
        explicit = [(i, mp) for i, mp in enumerate(self.spec.marked_points) if mp.xyz is not None]
        if not explicit:
            return
        import trimesh

        tri = self.mesh(textured=False).triangles
        for i, mp in explicit:
            p = np.asarray(mp.xyz, dtype=float)
            q = trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), axis=0))
            dist = float(np.min(np.linalg.norm(q - p, axis=1)))
            if dist > 0.005:
                raise SettingsError(
                    f"{self.source_path}: 'marked_points[{i}].xyz' = {list(mp.xyz)!r}: the point is {dist:.3f} m "
                    "off the model's surface; give a point on the body (e.g. a corner) or use an 'anchor'"
                )

    # -- identity and dimensions ------------------------------------------------------------------------
    @property
    def id(self) -> str:
        return self.spec.id

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def operator(self) -> str:
        return self.spec.operator

    @property
    def kind(self) -> str:
        return self.spec.kind

    @property
    def default_car_number(self) -> str:
        return self.spec.default_car_number

    @property
    def length_m(self) -> float:
        """Length over the coupler faces."""
        return float(self.spec.dimensions.length_over_couplers_m)

    @property
    def body_length_m(self) -> float:
        return float(self.spec.dimensions.body_length_m)

    @property
    def width_m(self) -> float:
        return float(self.spec.dimensions.width_m)

    @property
    def height_m(self) -> float:
        return float(self.spec.dimensions.height_m)

    @property
    def coupler_front(self) -> np.ndarray:
        return np.array([self.length_m / 2, 0.0, self.spec.dimensions.coupler_height_m])

    @property
    def coupler_rear(self) -> np.ndarray:
        return np.array([-self.length_m / 2, 0.0, self.spec.dimensions.coupler_height_m])

    @staticmethod
    def face_normal(face: str) -> np.ndarray:
        """Nominal outward normal of a named face ("left", "right", "front", "rear", "roof")."""
        return FACE_NORMALS[face].copy()

    def __repr__(self) -> str:
        return f"CarriageType({self.id!r}, {self.length_m:.2f} m, from {self.source_path})"

    # -- geometry -----------------------------------------------------------------------------------------
    def parts(self) -> list[Part]:
        with self._lock:
            if self._parts is None:
                self._parts = build_parts(self.spec)
            return self._parts

    def mesh(self, car_number: str = "", textured: bool = True) -> trimesh.Trimesh:
        """Mesh in the carriage frame (a copy; the original is cached per car number).

        Untextured: the parts concatenated with shared vertices (each part closed, outward normals).
        Textured: every triangle has its own three vertices, with UVs into the car's livery atlas
        (a PIL image in ``mesh.visual.material.image``); ``car_number`` ("" = the type's default) is painted
        on both sides and both ends.
        """
        number = car_number or self.spec.default_car_number
        key = (number if textured else "", bool(textured))
        with self._lock:
            cached = self._mesh_cache.get(key)
        if cached is None:
            cached = self._build_textured(number) if textured else self._build_plain()
            with self._lock:
                self._mesh_cache[key] = cached
        return cached.copy()

    def _build_plain(self) -> trimesh.Trimesh:
        import trimesh

        meshes = [p.mesh for p in self.parts()]
        m = trimesh.util.concatenate(meshes)
        return trimesh.Trimesh(vertices=m.vertices, faces=m.faces, process=False)

    def _build_textured(self, number: str) -> trimesh.Trimesh:
        import trimesh
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import SimpleMaterial

        atlas, image = paint_atlas(self.spec, number)
        verts, uvs = [], []
        for part in self.parts():
            tri = part.mesh.triangles  # (F, 3, 3)
            regions = _classify(part, part.mesh.face_normals)
            uv = np.empty((len(tri), 3, 2))
            for region in set(regions):
                sel = regions == region
                uv[sel] = atlas.uv(region, tri[sel].reshape(-1, 3)).reshape(-1, 3, 2)
            verts.append(tri.reshape(-1, 3))
            uvs.append(uv.reshape(-1, 2))
        V = np.vstack(verts)
        UV = np.vstack(uvs)
        F = np.arange(len(V)).reshape(-1, 3)
        material = SimpleMaterial(image=image, diffuse=[255, 255, 255, 255], ambient=[255, 255, 255, 255],
                                  specular=[40, 40, 40, 255], glossiness=10.0)
        mesh = trimesh.Trimesh(vertices=V, faces=F, visual=TextureVisuals(uv=UV, material=material), process=False)
        mesh.metadata["carriage_type"] = self.id
        mesh.metadata["car_number"] = number
        return mesh

    def texture(self, car_number: str = "") -> tuple[Atlas, "object"]:
        """(atlas layout, PIL image) of the livery for ``car_number``."""
        m = self.mesh(car_number, textured=True)
        return Atlas(self.spec), m.visual.material.image

    def bounding_box(self) -> np.ndarray:
        """(2, 3) min / max corners of the whole model (couplers included) in the carriage frame."""
        return np.array(self.mesh(textured=False).bounds, dtype=float)

    def collision_boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Axis-aligned boxes (centre (3,), half extents (3,)) in the carriage frame: the body (without
        couplers), each bogie, and the underframe equipment between the bogies."""
        d = self.spec.dimensions
        lo = np.array([-d.body_length_m / 2, -d.width_m / 2, d.body_bottom_m])
        hi = np.array([d.body_length_m / 2, d.width_m / 2, d.height_m])
        boxes = [(lo, hi), *bogie_boxes(self.spec)]
        eq = equipment_box(self.spec)
        if eq is not None:
            boxes.append(eq)
        return [((a + b) / 2, (b - a) / 2) for a, b in boxes]

    def sample_surface(self, n: int, seed: int = 0) -> np.ndarray:
        """Points on the mesh surface: every (unique) mesh vertex, topped up with area-uniform random samples
        to ``n`` points; so the result has ``max(n, number of vertices)`` rows. Deterministic for a seed."""
        m = self.mesh(textured=False)
        verts = np.unique(np.round(np.asarray(m.vertices), 9), axis=0)
        extra = max(0, int(n) - len(verts))
        if extra == 0:
            return verts
        import trimesh

        pts, _ = trimesh.sample.sample_surface(m, extra, seed=seed)
        return np.vstack([verts, np.asarray(pts)])


# --------------------------------------------------------------------------------------------------------
_cache: dict[Path, tuple[float, CarriageType]] = {}
_cache_lock = threading.Lock()


def _load_type(path: Path) -> CarriageType:
    path = Path(path).resolve()
    mtime = path.stat().st_mtime
    with _cache_lock:
        hit = _cache.get(path)
        if hit is not None and hit[0] == mtime:
            return hit[1]
    ct = CarriageType(load_spec(path), path)
    with _cache_lock:
        _cache[path] = (mtime, ct)
    return ct


def load_library(extra_dirs: Iterable[Path | str] = ()) -> dict[str, CarriageType]:
    """All carriage types: the shipped ones, then one per ``*.toml`` in each of ``extra_dirs`` (in order).

    A user type with the id of an earlier one replaces it. A bad file raises :class:`SettingsError` naming
    the file and the key; a missing extra folder raises :class:`SettingsError` too.
    """
    lib: dict[str, CarriageType] = {}
    dirs = [TYPES_DIR, *[Path(d) for d in extra_dirs]]
    for folder in dirs:
        if not folder.is_dir():
            raise SettingsError(f"{folder}: rolling-stock folder not found")
        for path in sorted(folder.glob("*.toml")):
            ct = _load_type(path)
            lib[ct.id] = ct
    return lib


def get_type(type_id: str, extra_dirs: Iterable[Path | str] = ()) -> CarriageType:
    """The carriage type called ``type_id`` (case-insensitive); :class:`UnknownModelType` if there is none."""
    lib = load_library(extra_dirs)
    key = str(type_id).strip().lower()
    if key not in lib:
        raise UnknownModelType(
            f"unknown carriage type {type_id!r}; known types: {', '.join(sorted(lib))}. "
            "Add a type by writing its TOML file into the incident's rolling_stock/ folder."
        )
    return lib[key]
