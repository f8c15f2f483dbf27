"""The rolling-stock library: shipped carriage types plus user-defined ones, one TOML file each."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ..core.layout import LIBRARY_TYPES_DIR
from ..errors import SettingsError, UnknownModelType
from . import mesh_type
from .geometry import FACE_NORMALS, Part, anchor_point, bogie_boxes, build_parts, equipment_box
from .spec import POINT_TOLERANCE_M, AnySpec, CarriageSpec, MeshCarriageSpec, load_spec

if TYPE_CHECKING:  # trimesh takes seconds to import: loaded when a mesh is built, not to list or check types
    import trimesh  # (and the livery, PIL's drawing and fonts: loaded where a livery is painted)

    from .livery import Atlas

TYPES_DIR = LIBRARY_TYPES_DIR


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
    midway between the coupler faces, at top-of-rail height. Parametric (the body built from the dimensions) or
    a mesh type (the model read from a mesh file, :mod:`.mesh_type`); both answer the same questions.
    """

    def __init__(self, spec: AnySpec, source_path: Path) -> None:
        self.spec = spec
        self.source_path = Path(source_path)
        # the type's identity, as its file states it
        self.id: str = spec.id
        self.name: str = spec.name
        self.operator: str = spec.operator
        self.kind: str = spec.kind
        self.default_car_number: str = spec.default_car_number
        self._lock = threading.Lock()
        self._parts: list[Part] | None = None
        self._mesh_cache: dict[tuple[str, bool], trimesh.Trimesh] = {}
        self._loaded = mesh_type.load_mesh(spec, self.source_path) if self.is_mesh_type else None
        # its size (metres): over the coupler faces; over the body ends, the body's width and the model's top above
        # the top of rail (a mesh type: the mesh's extents)
        self.length_m = float(spec.dimensions.length_over_couplers_m)
        if self._loaded is not None:
            lo, hi = self._loaded.bounds
            self.body_length_m, self.width_m, self.height_m = float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(hi[2])
        else:
            d = spec.dimensions
            self.body_length_m, self.width_m, self.height_m = map(float, (d.body_length_m, d.width_m, d.height_m))
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
        if self._loaded is not None:  # every point, the anchored couplers too: the file is the model
            mesh_type.check_points(self.source_path, spec, pts, self._loaded.vertices, self._loaded.faces)
        else:
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
        m = self.mesh(textured=False)
        V, F = np.asarray(m.vertices), np.asarray(m.faces)
        for i, mp in explicit:
            dist = mesh_type.surface_distance(V, F, np.asarray(mp.xyz, dtype=float))
            if dist > POINT_TOLERANCE_M:
                raise SettingsError(
                    f"{self.source_path}: 'marked_points[{i}].xyz' = {list(mp.xyz)!r} ({mp.name!r}): the point is "
                    f"{dist:.3f} m from the model's surface, more than the {POINT_TOLERANCE_M * 1000:.0f} mm allowed; "
                    "give a point on the body (e.g. a corner) or use an 'anchor'"
                )

    # -- identity and dimensions ------------------------------------------------------------------------
    @property
    def is_mesh_type(self) -> bool:
        """Whether the model is a mesh file (``[mesh]``) rather than built from the dimensions."""
        return isinstance(self.spec, MeshCarriageSpec)

    @property
    def has_reference_imagery(self) -> bool:
        """Whether the automatic finder may search photos for this type: a parametric type whose ``[livery]`` is
        its real appearance (given in the file, ``reference`` true). Mesh types and types without a livery, or
        whose livery only colours the drawing (``reference = false``), have none: their cars need hand picks."""
        return isinstance(self.spec, CarriageSpec) and self.spec.has_livery and self.spec.livery.reference

    def _mesh_bounds(self) -> np.ndarray:
        return self._loaded.bounds.copy()

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
        """The closed parts the model is made of (a mesh type: one part, the file's mesh)."""
        with self._lock:
            if self._parts is None:
                if self._loaded is not None:
                    import trimesh

                    m = trimesh.Trimesh(vertices=self._loaded.vertices, faces=self._loaded.faces, process=False)
                    self._parts = [Part(m, "body", "mesh")]
                else:
                    self._parts = build_parts(self.spec)
            return self._parts

    def mesh(self, car_number: str = "", textured: bool = True) -> trimesh.Trimesh:
        """Mesh in the carriage frame (a copy; the original is cached per car number).

        Untextured: the parts concatenated with shared vertices (each part closed, outward normals).
        Textured: every triangle has its own three vertices, with UVs into the car's livery atlas
        (a PIL image in ``mesh.visual.material.image``); ``car_number`` ("" = the type's default) is painted
        on both sides and both ends. A mesh type: UVs into a palette of the file's colours (no number painted).
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

        if self._loaded is not None:
            return trimesh.Trimesh(vertices=self._loaded.vertices, faces=self._loaded.faces, process=False)
        meshes = [p.mesh for p in self.parts()]
        m = trimesh.util.concatenate(meshes)
        return trimesh.Trimesh(vertices=m.vertices, faces=m.faces, process=False)

    def _build_textured(self, number: str) -> trimesh.Trimesh:
        import trimesh
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import SimpleMaterial

        if self._loaded is not None:
            mesh = mesh_type.textured_mesh(self._loaded)
            mesh.metadata["carriage_type"] = self.id
            mesh.metadata["car_number"] = number
            return mesh
        from .livery import paint_atlas  # (PIL's drawing and fonts: only where a livery is painted)

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
        """(atlas layout, PIL image) of the livery for ``car_number`` (a parametric type's only)."""
        if self._loaded is not None:
            raise ValueError(f"{self.id}: a mesh type has no livery atlas")
        from .livery import Atlas

        m = self.mesh(car_number, textured=True)
        return Atlas(self.spec), m.visual.material.image

    def bounding_box(self) -> np.ndarray:
        """(2, 3) min / max corners of the whole model (couplers included) in the carriage frame."""
        if self._loaded is not None:  # the coupler faces too, where the file has no couplers
            lo, hi = self._mesh_bounds()
            ends = np.array([self.coupler_front, self.coupler_rear])
            return np.array([np.minimum(lo, ends.min(axis=0)), np.maximum(hi, ends.max(axis=0))])
        return np.array(self.mesh(textured=False).bounds, dtype=float)

    def collision_boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Axis-aligned boxes (centre (3,), half extents (3,)) in the carriage frame: the body (without
        couplers), each bogie, and the underframe equipment between the bogies. A mesh type: one box, the
        mesh's bounds (running gear and any couplers in the file included)."""
        if self._loaded is not None:
            lo, hi = self._mesh_bounds()
            return [((lo + hi) / 2, (hi - lo) / 2)]
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
        to ``n`` points; so the result has ``max(n, number of vertices)`` rows. Deterministic for a seed.
        A mesh type (often many thousand vertices): the vertices of its convex hull, which hold the lowest point
        in any attitude, topped up to ``n`` (:func:`.mesh_type.hull_samples`)."""
        if self._loaded is not None:
            return mesh_type.hull_samples(self._loaded.vertices, self._loaded.faces, n, seed)
        m = self.mesh(textured=False)
        verts = np.unique(np.round(np.asarray(m.vertices), 9), axis=0)
        extra = max(0, int(n) - len(verts))
        if extra == 0:
            return verts
        import trimesh

        pts, _ = trimesh.sample.sample_surface(m, extra, seed=seed)
        return np.vstack([verts, np.asarray(pts)])


# --------------------------------------------------------------------------------------------------------
_cache: dict[Path, tuple[tuple, CarriageType]] = {}
_spec_cache: dict[Path, tuple[int, AnySpec]] = {}
_cache_lock = threading.Lock()


def _stamp(path: Path, spec: AnySpec | None) -> tuple:
    """When the type file (and a mesh type's mesh file) last changed."""
    stamp = (path.stat().st_mtime_ns,)
    if isinstance(spec, MeshCarriageSpec):
        f = mesh_type.mesh_file(spec, path)
        stamp += (f.stat().st_mtime_ns if f.is_file() else None,)
    return stamp


def _load_type(path: Path) -> CarriageType:
    path = Path(path).resolve()
    with _cache_lock:
        hit = _cache.get(path)
        checked = _spec_cache.get(path)
    if hit is not None and hit[0] == _stamp(path, hit[1].spec):
        return hit[1]
    # the file as :func:`load_specs` read and checked it, when unchanged since; else read now
    spec = checked[1] if checked is not None and checked[0] == path.stat().st_mtime_ns else load_spec(path)
    ct = CarriageType(spec, path)
    with _cache_lock:
        _cache[path] = (_stamp(path, spec), ct)
    return ct


def _type_files(extra_dirs: Iterable[Path | str]) -> list[Path]:
    """The type files in load order: the shipped ones, then each extra folder's ``*.toml`` (a missing folder:
    :class:`SettingsError`)."""
    files = []
    for folder in [TYPES_DIR, *[Path(d) for d in extra_dirs]]:
        if not folder.is_dir():
            raise SettingsError(f"{folder}: rolling-stock folder not found")
        files += sorted(folder.glob("*.toml"))
    return files


def load_library(extra_dirs: Iterable[Path | str] = ()) -> dict[str, CarriageType]:
    """All carriage types: the shipped ones, then one per ``*.toml`` in each of ``extra_dirs`` (in order).

    A user type with the id of an earlier one replaces it. A bad file raises :class:`SettingsError` naming
    the file and the key; a missing extra folder raises :class:`SettingsError` too.
    """
    lib: dict[str, CarriageType] = {}
    for path in _type_files(extra_dirs):
        ct = _load_type(path)
        lib[ct.id] = ct
    return lib


def load_specs(extra_dirs: Iterable[Path | str] = ()) -> dict[str, tuple[AnySpec, Path]]:
    """Every type's validated file, ``id -> (spec, path)``, in :func:`load_library`'s order and precedence,
    without building a model: what a listing needs. The checks that need the model (an ``xyz`` marked point on
    its surface, a mesh type's mesh file) are :func:`load_library`'s."""
    specs: dict[str, tuple[AnySpec, Path]] = {}
    for path in _type_files(extra_dirs):
        path = path.resolve()
        stamp = path.stat().st_mtime_ns
        with _cache_lock:
            hit = _spec_cache.get(path)
        if hit is None or hit[0] != stamp:  # read and checked once per change of the file
            hit = (stamp, load_spec(path))
            with _cache_lock:
                _spec_cache[path] = hit
        specs[hit[1].id] = (hit[1], path)
    return specs


def get_type(type_id: str, extra_dirs: Iterable[Path | str] = ()) -> CarriageType:
    """The carriage type called ``type_id`` (case-insensitive); :class:`UnknownModelType` if there is none. Every
    type file is read and checked (:func:`load_specs`), only this one's model is built."""
    specs = load_specs(extra_dirs)
    key = str(type_id).strip().lower()
    if key not in specs:
        raise UnknownModelType(
            f"unknown carriage type {type_id!r}; known types: {', '.join(sorted(specs))}. "
            "Add a type by writing its TOML file into the incident's rolling_stock/ folder."
        )
    return _load_type(specs[key][1])
