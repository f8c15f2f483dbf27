"""Cesium 3D Tiles 1.1: ``tiles/tileset.json`` with one tile whose content is the scene's GLB.

3D Tiles takes glTF content as y-up and turns it z-up (glTF (x, y, z) -> tile (x, -z, y)), which brings our glTF
axes (east, up, south) back to the scene's ENU axes; the root ``transform`` then maps ENU to ECEF (EPSG:4978):
columns east, north, up unit vectors and the origin, column-major as 3D Tiles stores matrices. Heights are the
DEM's, treated as ellipsoidal (docs/conventions.md): over a geoid-based globe terrain the scene sits off by the
local geoid undulation (docs/exports.md).
"""

from __future__ import annotations

import numpy as np
from pyproj import Transformer

from ..core.frames import SceneFrame
from ..core.geometry import orthonormal
from .scene import ExportScene


def ecef_from_enu(frame: SceneFrame) -> np.ndarray:
    """(4, 4) ``ecef_from_enu``: ENU metres -> ECEF (EPSG:4978) metres, exact (ENU is a rigid image of ECEF)."""
    tr = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    geo = frame.wgs84_from_enu(np.vstack([np.zeros(3), np.eye(3)]))
    x, y, z = tr.transform(geo[:, 0], geo[:, 1], geo[:, 2])
    P = np.column_stack([x, y, z])
    A = (P[1:] - P[0]).T
    M = np.eye(4)
    M[:3, :3] = orthonormal(A)  # the ENU axes in ECEF: a rotation up to rounding
    M[:3, 3] = P[0]
    return M


def scene_bounds_enu(scene: ExportScene) -> tuple[np.ndarray, np.ndarray]:
    pts = []
    if scene.terrain is not None:
        pts.append(scene.terrain.vertices)
    for b in scene.buildings:
        pts.append(np.asarray(b.vertices, dtype=float))
    for c in scene.carriages:
        pts.append(c.world_from_carriage.apply(np.asarray(c.mesh(textured=False).vertices, dtype=float)))
    allp = np.vstack(pts)
    return allp.min(axis=0), allp.max(axis=0)


def tileset_document(scene: ExportScene, content_uri: str) -> dict:
    """The ``tileset.json`` document: one leaf tile with ``content_uri`` (the GLB, relative to the tileset)."""
    lo, hi = scene_bounds_enu(scene)
    c, h = (lo + hi) / 2, (hi - lo) / 2 + 0.01
    box = [*c.tolist(), float(h[0]), 0.0, 0.0, 0.0, float(h[1]), 0.0, 0.0, 0.0, float(h[2])]
    M = ecef_from_enu(scene.frame)
    return {
        "asset": {"version": "1.1", "generator": "train-wreck-workbench export",
                  "extras": {"georeference": scene.georeference()}},
        "geometricError": float(np.linalg.norm(hi - lo)),
        "root": {
            "transform": [float(x) for x in M.T.reshape(-1)],  # column-major
            "boundingVolume": {"box": [float(x) for x in box]},
            "geometricError": 0.0,
            "refine": "REPLACE",
            "content": {"uri": content_uri},
        },
    }
