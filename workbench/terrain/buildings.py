"""Buildings to triangle meshes in the scene frame, standing on the terrain.

Two inputs (docs/gis.md):

* **GeoJSON footprints with heights** (docs/formats.md "Terrain layers"): a FeatureCollection whose ``crs``
  member names the project CRS; every feature a Polygon with ``height_m`` (> 0) and optional ``base_m``.
  Extruded from the lowest terrain under the footprint to ``base_m + height_m`` (or ground + ``height_m``).
* **CityJSON** (1.x and 2.0, as cities publish them): ``Building`` and ``BuildingPart`` objects, LoD1 or LoD2
  ``Solid`` / ``MultiSolid`` / ``CompositeSolid`` / ``MultiSurface`` / ``CompositeSurface`` geometry, vertices
  decoded with the file's ``transform`` (``scale``, ``translate``), CRS from ``metadata.referenceSystem``
  (a compound CRS such as EPSG:7415 = RD New + NAP uses its horizontal part). Every surface (with holes) is
  triangulated; vertices go CRS -> WGS84 -> ENU exactly (:func:`enu_from_layer_coords`). An object with only
  LoD0 footprints is extruded by its ``measuredHeight``; one with neither is an error naming it.
  With a terrain model, each building is moved vertically so its lowest vertex sits on the lowest terrain under
  it (``stand_on_terrain``): the city model's height datum need not be the DEM's. The shifts are reported, and
  a large median shift is warned about (:class:`BuildingsDatumMismatch`).
"""

from __future__ import annotations

import json
import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ..core.frames import SceneFrame, enu_from_layer_coords
from ..errors import InputError, WorkbenchWarning

log = logging.getLogger(__name__)

__all__ = ["BuildingsResult", "BuildingsDatumMismatch", "read_buildings", "cityjson_meshes", "geojson_meshes",
           "is_cityjson"]

BUILDING_TYPES = ("Building", "BuildingPart")
MAX_DISTANCE_M = 20_000.0
DATUM_WARN_M = 2.0


class BuildingsDatumMismatch(WorkbenchWarning):
    """The buildings' own ground heights differ from the terrain's by more than a couple of metres."""


@dataclass
class BuildingsResult:
    """Meshes (ENU metres, one per building or part), and what was done while reading."""

    meshes: list[trimesh.Trimesh]
    info: dict = field(default_factory=dict)

    def merged(self) -> trimesh.Trimesh | None:
        return trimesh.util.concatenate(self.meshes) if self.meshes else None


def is_cityjson(path: Path) -> bool:
    name = path.name.lower()
    if name.endswith((".city.json", ".cityjson")):
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096).decode("utf-8", "ignore")
    except OSError:
        return False
    return '"CityJSON"' in head


def read_buildings(path: str | Path, frame: SceneFrame, terrain_model=None, *, lod: str | float | None = None,
                   stand_on_terrain: bool = True) -> BuildingsResult:
    """Read a buildings layer (GeoJSON footprints or CityJSON, by content) into meshes in ``frame``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"buildings file {path} does not exist; fix terrain.buildings or put the file there")
    if is_cityjson(path):
        return cityjson_meshes(path, frame, terrain_model, lod=lod, stand_on_terrain=stand_on_terrain)
    return geojson_meshes(path, frame, terrain_model)


# ----------------------------------------------------------------------------------------------------------
# GeoJSON footprints
# ----------------------------------------------------------------------------------------------------------
def geojson_meshes(path: Path, frame: SceneFrame, terrain_model) -> BuildingsResult:
    """GeoJSON footprints with heights (docs/formats.md) -> extruded meshes standing on ``terrain_model``."""
    from ..files.buildings import read_buildings_geojson
    from .extrude import building_meshes

    if terrain_model is None:
        raise InputError(f"buildings file {path}: GeoJSON footprints need a terrain to stand on; set terrain.dem")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"buildings file {path} is not valid GeoJSON ({exc})") from None
    feats = doc.get("features") if isinstance(doc, dict) else None
    for i, f in enumerate(feats or []):
        props = (f or {}).get("properties") or {}
        if props.get("height_m") is None:
            fid = props.get("id", (f or {}).get("id", f"#{i}"))
            raise InputError(f"buildings file {path}: feature {fid} has no height_m; give every building its height "
                             f"above its base in metres (from LiDAR, a city model, or storeys x 3 m), or remove it")
    blds = read_buildings_geojson(path, expect_crs=frame.crs.to_string())
    meshes = building_meshes(blds, terrain_model, frame)
    return BuildingsResult(meshes, {"format": "geojson", "n_buildings": len(blds), "n_meshes": len(meshes)})


# ----------------------------------------------------------------------------------------------------------
# CityJSON
# ----------------------------------------------------------------------------------------------------------
def _crs_from_reference_system(value: Any, where: str) -> str:
    if not value:
        raise InputError(f"{where}: no metadata.referenceSystem, so its coordinates cannot be placed; add it (e.g. "
                         f"\"https://www.opengis.net/def/crs/EPSG/0/7415\", or `cjio {where} crs_assign 7415 save "
                         f"...`)")
    s = str(value).strip()
    for sep in ("/EPSG/0/", "EPSG::", "EPSG:"):
        if sep in s:
            code = s.split(sep)[-1].strip("/ ")
            if code.isdigit():
                return f"EPSG:{code}"
    return s


def _lod_value(g: dict) -> float:
    try:
        return float(str(g.get("lod", 0)))
    except ValueError:
        return 0.0


def _surfaces(geom: dict) -> list[list[list[int]]]:
    """Every surface (a list of rings of vertex indices, the first the outer one) of a CityJSON geometry."""
    t, b = geom.get("type"), geom.get("boundaries") or []
    if t in ("MultiSurface", "CompositeSurface"):
        return list(b)
    if t == "Solid":
        return [s for shell in b for s in shell]
    if t in ("MultiSolid", "CompositeSolid"):
        return [s for solid in b for shell in solid for s in shell]
    return []


def _triangulate_surface(rings: list[np.ndarray]) -> np.ndarray:
    """Triangles (k, 3) of indices into ``np.vstack(rings)`` for one planar-ish polygon with holes (3-D rings)."""
    import shapely
    from shapely.geometry import Polygon

    outer = rings[0]
    n = len(outer)
    if n < 3:
        return np.zeros((0, 3), int)
    if n == 3 and len(rings) == 1:
        return np.array([[0, 1, 2]])
    # Newell normal, then a 2-D frame in the polygon's plane
    allv = np.vstack(rings)
    nrm = np.zeros(3)
    for i in range(n):
        a, b = outer[i], outer[(i + 1) % n]
        nrm += np.array([(a[1] - b[1]) * (a[2] + b[2]), (a[2] - b[2]) * (a[0] + b[0]), (a[0] - b[0]) * (a[1] + b[1])])
    if np.linalg.norm(nrm) < 1e-12:
        return np.zeros((0, 3), int)
    nrm /= np.linalg.norm(nrm)
    u = np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    c = allv.mean(axis=0)
    uv = np.column_stack([(allv - c) @ u, (allv - c) @ v])
    offs = np.cumsum([0] + [len(r) for r in rings])
    poly = Polygon(uv[offs[0]:offs[1]], [uv[offs[k]:offs[k + 1]] for k in range(1, len(rings))])
    if not poly.is_valid:
        poly = poly.buffer(0)
    if poly.is_empty or poly.area <= 0:
        return np.zeros((0, 3), int)
    tris = shapely.get_parts(shapely.constrained_delaunay_triangles(poly))
    if len(tris) == 0:
        return np.zeros((0, 3), int)
    from scipy.spatial import cKDTree

    tree = cKDTree(uv)
    pts = np.array([np.asarray(t.exterior.coords)[:3] for t in tris])  # (k, 3, 2)
    _, idx = tree.query(pts.reshape(-1, 2))
    out = idx.reshape(-1, 3)
    # keep the winding of the original ring (normal nrm): triangle normals must agree with it
    tri3 = allv[out]
    tn = np.cross(tri3[:, 1] - tri3[:, 0], tri3[:, 2] - tri3[:, 0])
    flip = tn @ nrm < 0
    out[flip] = out[flip][:, [0, 2, 1]]
    return out[(out[:, 0] != out[:, 1]) & (out[:, 1] != out[:, 2]) & (out[:, 0] != out[:, 2])]


def cityjson_meshes(path: Path, frame: SceneFrame, terrain_model=None, *, lod: str | float | None = None,
                    stand_on_terrain: bool = True, colour: tuple[int, int, int] = (205, 200, 190),
                    roof_colour: tuple[int, int, int] = (120, 70, 60)) -> BuildingsResult:
    """A CityJSON file's buildings -> one mesh per ``Building``/``BuildingPart`` with geometry, in ENU metres.

    ``lod``: the level of detail to use (e.g. ``"2.2"``); default: the highest each object has.
    """
    where = f"buildings file {path}"
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{where} is not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "CityJSON":
        raise InputError(f"{where} is not a CityJSON file (no \"type\": \"CityJSON\")")
    crs = _crs_from_reference_system((doc.get("metadata") or {}).get("referenceSystem"), str(path))
    V = np.asarray(doc.get("vertices") or [], dtype=float).reshape(-1, 3)
    tr = doc.get("transform")
    if tr:
        V = V * np.asarray(tr.get("scale", [1, 1, 1]), float) + np.asarray(tr.get("translate", [0, 0, 0]), float)
    objs = doc.get("CityObjects") or {}
    wanted = None if lod is None else float(str(lod))
    chosen: list[tuple[str, dict, dict]] = []
    no_height = []
    for oid, obj in objs.items():
        if obj.get("type") not in BUILDING_TYPES:
            continue
        geoms = [g for g in obj.get("geometry") or [] if g.get("type") != "GeometryInstance"]
        if not geoms:
            if obj.get("type") == "Building" and obj.get("children"):
                continue  # its parts carry the geometry
            no_height.append(oid)
            continue
        if wanted is not None:
            cand = [g for g in geoms if abs(_lod_value(g) - wanted) < 1e-6] or \
                   [g for g in geoms if _lod_value(g) <= wanted]
        else:
            cand = geoms
        if not cand:
            cand = geoms
        g = max(cand, key=_lod_value)
        chosen.append((oid, obj, g))
    if not chosen:
        raise InputError(f"{where}: no Building or BuildingPart with geometry (object types: "
                         f"{sorted({o.get('type') for o in objs.values()})})")
    used = np.unique(np.concatenate([np.asarray([i for s in _surfaces(g) for r in s for i in r] or [0], int)
                                     for _, _, g in chosen]))
    if len(V) == 0 or used.max() >= len(V):
        raise InputError(f"{where}: a geometry refers to vertex {int(used.max())} but the file has {len(V)} vertices")
    enu = np.full_like(V, np.nan)
    enu[used] = enu_from_layer_coords(V[used], crs, frame, where)
    dist = np.linalg.norm(enu[used, :2], axis=1)
    if float(np.median(dist)) > MAX_DISTANCE_M:
        raise InputError(f"{where}: its buildings lie {np.median(dist) / 1000:.1f} km from the incident (median; CRS "
                         f"{crs}); it is the wrong file, or its referenceSystem is wrong, or location.* is")
    meshes, shifts, skipped, lods = [], [], [], []
    for oid, obj, g in chosen:
        surfs = _surfaces(g)
        attrs = obj.get("attributes") or {}
        if _lod_value(g) < 1.0 or not surfs:
            h = attrs.get("measuredHeight")
            if not (isinstance(h, (int, float)) and h > 0) or not surfs:
                no_height.append(oid)
                continue
            surfs = _extrude_lod0(surfs, V, float(h))
            mesh = _mesh_from_surfaces(surfs, None, crs, frame, where, colour, roof_colour)
        else:
            mesh = _mesh_from_surfaces(surfs, enu, crs, frame, where, colour, roof_colour)
        if mesh is None:
            skipped.append(oid)
            continue
        if terrain_model is not None and stand_on_terrain:
            zg = terrain_model.height_at(mesh.vertices[:, :2])
            if not np.any(np.isfinite(zg)):
                skipped.append(oid)
                continue
            shift = float(np.nanmin(zg) - mesh.vertices[:, 2].min())
            mesh.vertices[:, 2] += shift
            shifts.append(shift)
        mesh.metadata["name"] = str(oid)
        mesh.metadata["lod"] = str(g.get("lod"))
        lods.append(str(g.get("lod")))
        meshes.append(mesh)
    if no_height:
        raise InputError(f"{where}: {len(no_height)} building(s) have no height (no LoD1+ solid and no "
                         f"measuredHeight), e.g. {no_height[:3]}; add measuredHeight (metres) or LoD1 geometry, or "
                         f"remove them")
    info: dict[str, Any] = {"format": "cityjson", "version": doc.get("version"), "crs": crs,
                            "n_buildings": len(meshes), "n_outside_terrain": len(skipped),
                            "lods": sorted(set(lods))}
    if skipped:
        log.warning("%s: %d building(s) outside the terrain were left out", where, len(skipped))
    if shifts:
        med = float(np.median(shifts))
        info["vertical_shift_m"] = {"median": med, "min": float(np.min(shifts)), "max": float(np.max(shifts))}
        if abs(med) > DATUM_WARN_M:
            msg = (f"{where}: buildings were moved by {med:+.2f} m (median) to stand on the terrain; the city model's "
                   f"height datum ({crs}) may differ from the DEM's; check both are in the same vertical datum")
            log.warning(msg)
            warnings.warn(msg, BuildingsDatumMismatch, stacklevel=2)
    return BuildingsResult(meshes, info)


def _extrude_lod0(surfs: list, V: np.ndarray, height: float) -> list[np.ndarray]:
    """LoD0 footprint surfaces -> 3-D surfaces (as coordinate rings, CRS units) of a prism ``height`` tall."""
    out = []
    for s in surfs:
        ring = V[np.asarray(s[0], int)]
        top = ring.copy()
        top[:, 2] += height
        out.append([ring[::-1]])
        out.append([top])
        for i in range(len(ring)):
            j = (i + 1) % len(ring)
            out.append([np.array([ring[i], ring[j], top[j], top[i]])])
    return out


def _mesh_from_surfaces(surfs, enu: np.ndarray | None, crs: str, frame: SceneFrame, where: str,
                        colour, roof_colour) -> trimesh.Trimesh | None:
    """Triangulate surfaces (vertex-index rings when ``enu`` is given, else coordinate rings in ``crs``)."""
    verts, faces, cols = [], [], []
    base = 0
    for s in surfs:
        if enu is not None:
            rings = [enu[np.asarray(r, int)] for r in s if len(r) >= 3]
        else:
            rings = [enu_from_layer_coords(np.asarray(r, float), crs, frame, where) for r in s if len(r) >= 3]
        if not rings or len(rings[0]) < 3:
            continue
        tri = _triangulate_surface(rings)
        if len(tri) == 0:
            continue
        allv = np.vstack(rings)
        verts.append(allv)
        faces.append(tri + base)
        tv = allv[tri]
        nz = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
        nn = np.linalg.norm(nz, axis=1)
        up = np.where(nn > 0, nz[:, 2] / np.maximum(nn, 1e-12), 0.0)
        c = np.where((up > 0.3)[:, None], np.asarray(roof_colour), np.asarray(colour))
        cols.append(np.repeat(c, 3, axis=0))
        base += len(allv)
    if not faces:
        return None
    F = np.vstack(faces)
    Vx = np.vstack(verts)
    C = np.vstack(cols).astype(np.uint8)
    # one vertex per face corner so each face keeps its colour
    VV = Vx[F.reshape(-1)]
    FF = np.arange(len(VV)).reshape(-1, 3)
    rgba = np.column_stack([C, np.full(len(C), 255, np.uint8)])
    return trimesh.Trimesh(vertices=VV, faces=FF, vertex_colors=rgba, process=False)
