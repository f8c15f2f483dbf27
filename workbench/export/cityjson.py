"""The scene as CityJSON 2.0 (``scene.city.json``), in the project CRS.

* the terrain (as exported: simplified away from the carriages) is one ``TINRelief`` (``CompositeSurface``,
  LoD 1) of triangles;
* each building (a connected part of the terrain stage's buildings mesh) is a ``Building`` (``MultiSurface``,
  LoD 1) of triangles;
* each carriage is a ``GenericCityObject`` (``MultiSurface``, LoD 2: the rolling-stock model posed) with its
  number, type, status, pose and 95% half widths as attributes.

Vertices are converted exactly, one by one, ENU -> project CRS (:meth:`SceneFrame.crs_from_enu`) and stored as
integers with ``transform`` (scale 1 mm, translate = the minimum corner). ``metadata.referenceSystem`` is the
project CRS (horizontal); heights are in the DEM's vertical datum.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .geojson import carriage_properties
from .scene import ExportScene

SCALE_M = 0.001


def _crs_url(scene: ExportScene) -> str:
    epsg = scene.frame.crs.to_epsg()
    if epsg is None:
        return scene.frame.crs.to_string()
    return f"https://www.opengis.net/def/crs/EPSG/0/{epsg}"


class _Vertices:
    """Collects vertices (project CRS, metres); returns their indices."""

    def __init__(self) -> None:
        self.parts: list[np.ndarray] = []
        self.n = 0

    def add(self, crs_xyz: np.ndarray) -> np.ndarray:
        a = np.asarray(crs_xyz, dtype=float)
        self.parts.append(a)
        idx = np.arange(self.n, self.n + len(a))
        self.n += len(a)
        return idx

    def all(self) -> np.ndarray:
        return np.vstack(self.parts) if self.parts else np.zeros((0, 3))


def _triangles(idx: np.ndarray, faces: np.ndarray) -> list:
    """Boundaries of a MultiSurface/CompositeSurface of triangles: [[[i, j, k]], ...]."""
    tri = idx[np.asarray(faces, dtype=np.int64)]
    return [[[int(a), int(b), int(c)]] for a, b, c in tri]


def _drop_degenerate(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces whose three (rounded to the file's millimetre) vertices are distinct."""
    q = np.round(np.asarray(vertices) / SCALE_M).astype(np.int64)
    F = np.asarray(faces, dtype=np.int64)
    a, b, c = q[F[:, 0]], q[F[:, 1]], q[F[:, 2]]
    ok = np.any(a != b, axis=1) & np.any(b != c, axis=1) & np.any(a != c, axis=1)
    return F[ok]


def cityjson_document(scene: ExportScene) -> dict:
    """The CityJSON 2.0 document (a JSON-ready dict)."""
    f = scene.frame
    verts = _Vertices()
    objects: dict[str, Any] = {}
    if scene.terrain is not None:
        V = f.crs_from_enu(scene.terrain.vertices)
        idx = verts.add(V)
        faces = _drop_degenerate(V, scene.terrain.faces)
        objects["terrain"] = {"type": "TINRelief",
                              "attributes": {"source": "DEM (terrain stage)", "faces": int(len(faces))},
                              "geometry": [{"type": "CompositeSurface", "lod": "1",
                                            "boundaries": _triangles(idx, faces)}]}
    for i, b in enumerate(scene.buildings):
        V = f.crs_from_enu(np.asarray(b.vertices, dtype=float))
        idx = verts.add(V)
        faces = _drop_degenerate(V, b.faces)
        zmin, zmax = float(V[:, 2].min()), float(V[:, 2].max())
        objects[f"building-{i + 1}"] = {
            "type": "Building", "attributes": {"measuredHeight": round(zmax - zmin, 3)},
            "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": _triangles(idx, faces)}]}
    for car in scene.carriages:
        m = car.mesh(textured=False)
        V = f.crs_from_enu(car.world_from_carriage.apply(np.asarray(m.vertices, dtype=float)))
        idx = verts.add(V)
        faces = _drop_degenerate(V, m.faces)
        attrs = {k: v for k, v in carriage_properties(car, f).items() if v is not None}
        attrs["body_centre_crs"] = [round(float(x), 4) for x in f.crs_from_enu(car.body_centre_enu[None])[0]]
        objects[f"car-{car.number}"] = {
            "type": "GenericCityObject", "attributes": attrs,
            "geometry": [{"type": "MultiSurface", "lod": "2", "boundaries": _triangles(idx, faces)}]}
    allv = verts.all()
    translate = np.floor(allv.min(axis=0)) if len(allv) else np.zeros(3)
    ints = np.round((allv - translate) / SCALE_M).astype(np.int64)
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    metadata = {"title": scene.title or "scene", "referenceSystem": _crs_url(scene),
                "geographicalExtent": [round(float(x), 3) for x in (*lo, *hi)]}
    if scene.date:
        metadata["referenceDate"] = scene.date
    return {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [SCALE_M] * 3, "translate": [float(x) for x in translate]},
        "metadata": metadata,
        "CityObjects": objects,
        "vertices": ints.tolist(),
    }
