"""The scene to export: the solved carriages, the terrain and the buildings, gathered once for every format.

Everything here is in the scene frame (``world``: the incident's ENU frame, metres; see ``docs/conventions.md``)
until a writer converts it. The writers convert *exactly per vertex* with :class:`~workbench.core.frames.SceneFrame`
(ENU -> WGS84 or ENU -> project CRS), never by adding an offset: the ENU frame is not the CRS grid shifted.

* the carriages are the one scene model of :mod:`workbench.files.scene` (:class:`SceneCarriage`), which the
  renders, the report and the viewer use too.
* :func:`decimate_terrain` keeps the terrain at full resolution near the carriages (so a carriage resting on the
  ground still rests on it in every export) and simplifies the rest (quadric error, the seam held exactly).
* :func:`build_scene` puts it all together for a :class:`~workbench.project.Project`.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import trimesh

from ..core.frames import SceneFrame
from ..core.options import Range, check_options
from ..errors import InputError
from ..files.scene import SceneCarriage, scene_carriages

if TYPE_CHECKING:  # pragma: no cover
    from ..project import Project

log = logging.getLogger(__name__)

#: ``gltf_from_enu``: glTF is y-up. glTF +X = east, +Y = up, +Z = south (= -north). A proper rotation (det +1).
GLTF_FROM_ENU = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    """What the export writes and how large it may get.

    ``terrain_max_faces``: the terrain is simplified to about this many triangles (0: keep every triangle);
    ``full_resolution_margin_m``: terrain within this horizontal distance of a carriage keeps every DEM triangle;
    ``texture_max_px``: the terrain texture's longest side is capped to this; ``livery_max_px`` likewise for the
    carriages' livery atlases; ``jpeg_quality`` for the re-encoded textures; ``tiles``: also write Cesium 3D Tiles.
    """

    terrain_max_faces: Annotated[int, Range(ge=1000, also=(0,))] = 150_000
    full_resolution_margin_m: Annotated[float, Range(ge=0.0, le=1000.0)] = 20.0
    texture_max_px: Annotated[int, Range(ge=64, le=16384)] = 2048
    livery_max_px: Annotated[int, Range(ge=64, le=16384)] = 1024
    jpeg_quality: Annotated[int, Range(ge=10, le=100)] = 85
    tiles: bool = True

    def __post_init__(self) -> None:
        check_options(self, "export options")


@dataclass(kw_only=True)
class TerrainSurface:
    """The terrain as exported: ``vertices`` (n, 3) ENU metres, ``faces`` (m, 3) counter-clockwise seen from above;
    either ``uv`` (n, 2) into ``texture`` (origin top-left, as glTF) or ``colors`` (n, 3) floats in [0, 1]."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: Any = None  # PIL image
    texture_source: str | None = None
    colors: np.ndarray | None = None
    full_resolution: np.ndarray | None = None  # (m,) bool: faces kept exactly from the terrain stage's mesh
    info: dict = field(default_factory=dict)


@dataclass(kw_only=True)
class ExportScene:
    frame: SceneFrame
    carriages: list[SceneCarriage]
    left_out: list[dict]
    terrain: TerrainSurface | None
    buildings: list[trimesh.Trimesh]  # one closed mesh per building, ENU metres
    title: str = ""
    date: str = ""
    solution_status: str = ""
    relative: dict | None = None  # the solution's frame record when the scene is relative (no survey)
    _jpegs: dict = field(default_factory=dict, repr=False)  # (id(image), max_px, quality) -> (image, bytes)

    def jpeg(self, image: Any, max_px: int, quality: int) -> bytes:
        """``cap_image(image, max_px)`` encoded as JPEG of ``quality``, once per image object and settings: the glTF
        and the KMZ embed the same livery atlases (the same bytes; capping them took 0.08 s each)."""
        key = (id(image), int(max_px), int(quality))
        if key not in self._jpegs:  # (the image is kept with its bytes: its id is not reused meanwhile)
            buf = io.BytesIO()
            cap_image(image, max_px).save(buf, format="JPEG", quality=quality)
            self._jpegs[key] = (image, buf.getvalue())
        return self._jpegs[key][1]

    def georeference(self) -> dict:
        """The georeference recorded in every export (JSON-ready); a relative scene says it has none."""
        if self.relative is not None:
            return {"frame": "relative", "crs": None, "origin_wgs84": None,
                    "scene_frame": self.relative.get("axes", "local levelled frame at the camera, metres"),
                    "note": "not georeferenced: no control points, no known cameras, no GPS (docs/gis.md, "
                            "\"Relative incidents\")", "units": "metres"}
        f = self.frame
        o = f.origin_crs
        epsg = f.crs.to_epsg()
        return {
            "scene_frame": "local East-North-Up tangent frame, metres (docs/conventions.md)",
            "origin_wgs84": [f.lon_deg, f.lat_deg, f.height_m],
            "origin_wgs84_order": "longitude deg, latitude deg, height m",
            "crs": f"EPSG:{epsg}" if epsg else f.crs.to_string(),
            "crs_name": f.crs.name,
            "origin_crs": [float(o[0]), float(o[1]), float(o[2])],
            "origin_crs_order": "easting m, northing m, height m",
            "height_datum": "the DEM's vertical datum (used as ellipsoidal height in the ENU conversion)",
            "grid_convergence_deg": f.grid_convergence_deg(),
            "units": "metres",
        }


# ---------------------------------------------------------------------------------------------------------
# solution.json
# ---------------------------------------------------------------------------------------------------------
# ---------------------------------------------------------------------------------------------------------
# terrain
# ---------------------------------------------------------------------------------------------------------
def _segment_distance_xy(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Horizontal distance (n,) of points (n, 2) to the segment a-b (2,)."""
    d = b - a
    t = np.clip(((points - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * d), axis=1)


def near_carriages(points_xy: np.ndarray, carriages: list[SceneCarriage], margin_m: float) -> np.ndarray:
    """(n,) bool: points (n, 2) ENU within ``margin_m`` (horizontally) of a carriage's body (its centre line
    widened by half its width)."""
    near = np.zeros(len(points_xy), dtype=bool)
    for c in carriages:
        ends = c.world_from_carriage.apply(np.array([[c.length_m / 2, 0.0, 0.0], [-c.length_m / 2, 0.0, 0.0]]))
        near |= _segment_distance_xy(points_xy, ends[0, :2], ends[1, :2]) <= margin_m + c.width_m / 2
    return near


def decimate_terrain(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray, max_faces: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Simplify a terrain mesh to about ``max_faces`` triangles, keeping the faces flagged in ``keep`` exactly.

    vertices (n, 3) metres, faces (m, 3), keep (m,) bool. The other faces are simplified with a quadric-error
    decimation (pyfqmr) that holds their border vertices fixed, so the seam with the kept faces has no crack.
    Returns (vertices (n', 3), faces (m', 3), kept (m',) bool: the faces taken over unchanged, info dict).
    """
    V = np.asarray(vertices, dtype=float)
    F = np.asarray(faces, dtype=np.int64)
    keep = np.asarray(keep, dtype=bool)
    info = {"faces_in": int(len(F)), "faces_kept_exactly": int(keep.sum())}
    far = F[~keep]
    budget = max_faces - int(keep.sum())
    if max_faces == 0 or len(F) <= max_faces or len(far) == 0 or budget < 100:
        info.update(faces_out=int(len(F)), simplified=False)
        return V, F, keep.copy(), info
    import pyfqmr

    used = np.unique(far)
    remap = -np.ones(len(V), dtype=np.int64)
    remap[used] = np.arange(len(used))
    s = pyfqmr.Simplify()
    s.setMesh(V[used], remap[far].astype(np.int32))
    s.simplify_mesh(target_count=int(budget), aggressiveness=7, preserve_border=True, verbose=False)
    DV, DF, _ = s.getMesh()
    DV = np.asarray(DV, dtype=float)
    DF = np.asarray(DF, dtype=np.int64)
    # Merge: the kept faces' vertices, then the simplified part's; border vertices coincide exactly.
    kept_faces = F[keep]
    kv = np.unique(kept_faces)
    kremap = -np.ones(len(V), dtype=np.int64)
    kremap[kv] = np.arange(len(kv))
    allV = np.vstack([V[kv], DV])
    allF = np.vstack([kremap[kept_faces], DF + len(kv)])
    # weld identical positions (the seam) so the surface is one connected mesh
    _, first, inverse = np.unique(np.round(allV, 9), axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    newV = allV[first[order]]
    newF = rank[inverse.reshape(-1)][allF]
    kept = np.zeros(len(newF), dtype=bool)
    kept[: len(kept_faces)] = True
    info.update(faces_out=int(len(newF)), simplified=True)
    return newV, newF, kept, info


def _height_colors(z: np.ndarray) -> np.ndarray:
    """(n, 3) float colours in [0, 1] for heights z (n,) metres: a hypsometric ramp."""
    from matplotlib import colormaps

    lo, hi = float(np.min(z)), float(np.max(z))
    t = (z - lo) / max(hi - lo, 1e-6)
    return np.asarray(colormaps["terrain"](0.25 + 0.6 * t))[:, :3]


def find_orthophoto(project: "Project") -> tuple[Path, Path] | None:
    """(orthophoto image, DEM whose extent it covers) for the project, or None (see
    :func:`workbench.terrain.stage.orthophoto_path`)."""
    t = project.settings.terrain
    if not t.dem:
        return None
    ortho = project.orthophoto_path()
    return (ortho, project.path(t.dem)) if ortho is not None else None


def texture_uv(vertices_enu: np.ndarray, frame: SceneFrame, dem_path: Path) -> np.ndarray:
    """UV (n, 2), origin top-left (glTF), of ENU vertices (n, 3) in an image north-up over the DEM's bounds
    (in the DEM's own CRS). Converted exactly per vertex: ENU -> WGS84 -> DEM CRS."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(dem_path) as src:
        left, bottom, right, top = src.bounds
        dem_crs = src.crs.to_wkt() if src.crs else None
    if dem_crs is None:
        raise InputError(f"{dem_path}: the DEM has no CRS; cannot place the orthophoto on the terrain")
    geo = frame.wgs84_from_enu(np.asarray(vertices_enu, dtype=float))
    tr = Transformer.from_crs("EPSG:4326", dem_crs, always_xy=True)
    x, y = tr.transform(geo[:, 0], geo[:, 1])
    return np.column_stack([(np.asarray(x) - left) / (right - left), (top - np.asarray(y)) / (top - bottom)])


def cap_image(image: Any, max_px: int) -> Any:
    """The PIL image, RGB, its longest side at most ``max_px`` (Lanczos)."""
    from PIL import Image

    im = image.convert("RGB")
    w, h = im.size
    s = max_px / max(w, h)
    if s < 1.0:
        im = im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.Resampling.LANCZOS, reducing_gap=2.0)
    return im


def build_terrain(mesh: trimesh.Trimesh, frame: SceneFrame, carriages: list[SceneCarriage],
                  options: ExportOptions, ortho: tuple[Path, Path] | None) -> TerrainSurface:
    """The exported terrain from the terrain stage's mesh (ENU): simplified away from the carriages, with the
    orthophoto as texture when there is one, else colours by height."""
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces, dtype=np.int64)
    centroids = V[F].mean(axis=1)
    keep = near_carriages(centroids[:, :2], carriages, options.full_resolution_margin_m)
    V, F, kept, info = decimate_terrain(V, F, keep, options.terrain_max_faces)
    surface = TerrainSurface(vertices=V, faces=F, full_resolution=kept, info=info)
    if ortho is not None:
        from PIL import Image

        image_path, dem_path = ortho
        try:
            with Image.open(image_path) as im:
                surface.texture = cap_image(im, options.texture_max_px)
        except OSError as exc:
            raise InputError(f"{image_path}: cannot read the orthophoto ({exc})") from None
        surface.uv = texture_uv(V, frame, dem_path)
        surface.texture_source = str(image_path)
    else:
        surface.colors = _height_colors(V[:, 2])
    return surface


def split_buildings(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """One mesh per building: the connected parts (through shared vertex positions, to 1 mm) of the terrain
    stage's merged buildings mesh, each with its vertices welded; ordered by their lowest corner."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if len(F) == 0:
        return []
    _, first, inverse = np.unique(np.round(V, 3), axis=0, return_index=True, return_inverse=True)
    W, WF = V[first], inverse.reshape(-1)[F]
    n = len(W)
    rows = np.concatenate([WF[:, 0], WF[:, 1], WF[:, 2]])
    cols = np.concatenate([WF[:, 1], WF[:, 2], WF[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    face_label = label[WF[:, 0]]
    parts = []
    for lab in np.unique(face_label):
        f = WF[face_label == lab]
        used = np.unique(f)
        remap = np.full(n, -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        parts.append(trimesh.Trimesh(W[used], remap[f], process=False))
    return sorted(parts, key=lambda m: tuple(np.round(m.bounds[0], 3)))


def ground_heights(terrain: TerrainSurface | None, xy: np.ndarray) -> np.ndarray:
    """Terrain heights (n,) at ENU points xy (n, 2) on the exported terrain mesh; NaN where there is none."""
    xy = np.asarray(xy, dtype=float)
    out = np.full(len(xy), np.nan)
    if terrain is None or len(xy) == 0:
        return out
    V, F = terrain.vertices, terrain.faces
    # candidate faces: those whose horizontal bounding box contains a query (few queries, local meshes)
    tri = V[F]
    lo, hi = tri[:, :, :2].min(axis=1), tri[:, :, :2].max(axis=1)
    for k, p in enumerate(xy):
        cand = np.nonzero(np.all((lo <= p + 1e-9) & (hi >= p - 1e-9), axis=1))[0]
        for f in cand:
            a, b, c = tri[f]
            m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
            det = np.linalg.det(m)
            if abs(det) < 1e-12:
                continue
            u, v = np.linalg.solve(m, p - a[:2])
            if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9:
                out[k] = a[2] + u * (b[2] - a[2]) + v * (c[2] - a[2])
                break
    return out


# ---------------------------------------------------------------------------------------------------------
def build_scene(project: "Project", options: ExportOptions | None = None) -> ExportScene:
    """Gather the export scene of a project: ``out/solve/solution.json``, ``out/terrain/terrain.ply`` and
    ``buildings.ply`` (when the terrain stage wrote them), and the carriage models with their liveries."""
    options = options or ExportOptions()
    frame = project.frame
    types = project.carriage_types()
    sol = project.solution("export")
    cars, left = scene_carriages(sol, types)
    doc = sol.doc
    if not cars:
        raise InputError(f"{sol.path}: no carriage has a pose (all left out); nothing to export")
    tdir = project.stage_dir("terrain")
    terrain = None
    if (tdir / "terrain.ply").is_file() and not sol.relative:
        mesh = trimesh.load(tdir / "terrain.ply", process=False, force="mesh")
        terrain = build_terrain(mesh, frame, cars, options, find_orthophoto(project))
    buildings: list[trimesh.Trimesh] = []
    if (tdir / "buildings.ply").is_file() and not sol.relative:
        buildings = split_buildings(trimesh.load(tdir / "buildings.ply", process=False, force="mesh"))
    s = project.settings
    return ExportScene(frame=frame, carriages=cars, left_out=left, terrain=terrain, buildings=buildings,
                       title=s.incident.name, date=str(s.incident.date), solution_status=str(doc.get("status", "")),
                       relative=doc["frame"] if sol.relative else None)
