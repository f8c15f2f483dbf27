"""Buildings as meshes in the scene frame: footprints extruded from the terrain to their height, with facades,
windows and roofs coloured by kind (the GeoJSON route of the terrain stage; CityJSON is in ``buildings.py``)."""

from __future__ import annotations

import hashlib

import numpy as np
import shapely
import trimesh
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from ..core.frames import SceneFrame
from ..errors import InputError
from ..files.dem import TerrainModel

__all__ = ["building_meshes", "sample_points"]


def sample_points(poly: Polygon, spacing: float) -> np.ndarray:
    """(n, 2) the polygon's corners and a grid of ``spacing`` inside it."""
    minx, miny, maxx, maxy = poly.bounds
    gx, gy = np.meshgrid(np.arange(minx, maxx + spacing, spacing), np.arange(miny, maxy + spacing, spacing))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    inside = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    return np.vstack([np.asarray(poly.exterior.coords)[:-1], pts[inside]])


# ----------------------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------------------
_FACADES = {
    "house": [(236, 230, 214), (190, 92, 70), (205, 200, 190), (170, 150, 120), (150, 160, 170)],
    "apartment": [(150, 90, 70), (200, 180, 150), (175, 170, 160), (130, 80, 65)],
    "warehouse": [(176, 178, 174), (200, 190, 165), (120, 135, 150), (160, 150, 140)],
}
_ROOFS = {"house": [(80, 70, 68), (120, 60, 50), (70, 72, 78)], "apartment": [(60, 60, 62), (90, 88, 85)],
          "warehouse": [(150, 152, 150), (110, 112, 115), (70, 70, 72)]}
# kind: (bay width, floor height, window u interval, window v interval)
_WINDOWS = {"house": (3.5, 2.9, (0.3, 0.7), (0.35, 0.8)), "apartment": (3.2, 3.0, (0.2, 0.8), (0.3, 0.8)),
            "warehouse": (6.0, 4.5, (0.2, 0.8), (0.62, 0.86))}
_GLASS = (52, 64, 78)
_DOOR = (72, 74, 78)


def _pick(options: list, key: str, salt: str) -> tuple:
    h = int(hashlib.sha256(f"{key}:{salt}".encode()).hexdigest()[:8], 16)
    return options[h % len(options)]


def building_meshes(buildings: list[dict], terrain_model: TerrainModel, frame: SceneFrame) -> list[trimesh.Trimesh]:
    """One mesh per building (ENU metres, vertex colours): walls from the lowest terrain under the footprint up to
    ``base_m + height_m`` (datum), with window/door bands on the facades and a flat roof."""
    out = []
    cell = float(min(abs(terrain_model.transform.a), abs(terrain_model.transform.e)))
    for b in buildings:
        ring = np.asarray(b["footprint_crs"], dtype=float)[:, :2]
        if len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]
        kind = str(b.get("kind", "house"))
        if kind not in _WINDOWS:
            kind = "house"
        bid = str(b["id"])
        height = float(b["height_m"])
        # Ground under the footprint (ENU up).
        enu0 = frame.enu_from_crs(np.column_stack([ring, np.zeros(len(ring))]))
        poly = orient(Polygon(enu0[:, :2]), sign=1.0)  # counter-clockwise seen from above
        samples = sample_points(poly, max(min(cell, 2.0), 0.25))
        zg = terrain_model.height_at(samples)
        ground = float(np.nanmin(zg)) if np.any(np.isfinite(zg)) else None
        # Roof corners: exact ENU of (E, N, base + height) when base_m is known.
        if not _is_ccw(enu0[:, :2]):
            ring = ring[::-1]
        if b.get("base_m") is not None:
            top = frame.enu_from_crs(np.column_stack([ring, np.full(len(ring), float(b["base_m"]) + height)]))
            if ground is None:
                ground = float(top[:, 2].min()) - height
            if top[:, 2].min() < ground + 2.0:  # base_m far below this terrain: keep the building standing
                top[:, 2] += ground + height - top[:, 2].min()
        else:
            if ground is None:
                raise InputError(f"building {bid} lies outside the terrain and has no base_m")
            top = frame.enu_from_crs(np.column_stack([ring, np.zeros(len(ring))]))
            top[:, 2] = ground + height
        bottom_z = ground - 0.2  # sink a little so no gap shows on sloping ground
        facade = _pick(_FACADES[kind], bid, "facade")
        roof = _pick(_ROOFS[kind], bid, "roof")
        V: list[np.ndarray] = []
        C: list[tuple] = []
        bay_w, floor_h, (wu0, wu1), (wv0, wv1) = _WINDOWS[kind]
        n = len(top)
        for i in range(n):
            p0, p1 = top[i], top[(i + 1) % n]
            e = p1[:2] - p0[:2]
            length = float(np.hypot(*e))
            if length < 1e-6:
                continue
            nb = max(1, int(round(length / bay_w)))
            ub = np.unique(np.clip(np.concatenate([np.arange(nb + 1) / nb] + [(k + np.array([wu0, wu1])) / nb
                                                                               for k in range(nb)]), 0, 1))
            z_base = min(p0[2], p1[2]) - height
            nf = max(1, int((height + 1e-6) // floor_h))
            fh = height / nf
            vb = [bottom_z] + [z_base + (k + t) * fh for k in range(nf) for t in (0.0, wv0, wv1)]
            vb = np.unique(np.clip(np.array(vb + [z_base + height]), bottom_z, None))
            for a in range(len(ub) - 1):
                um = 0.5 * (ub[a] + ub[a + 1])
                bay = min(int(um * nb), nb - 1)
                in_win_u = wu0 < um * nb - bay < wu1
                xa, xb = p0[:2] + e * ub[a], p0[:2] + e * ub[a + 1]
                za_top = p0[2] + (p1[2] - p0[2]) * ub[a]
                zb_top = p0[2] + (p1[2] - p0[2]) * ub[a + 1]
                for k in range(len(vb) - 1):
                    lo, hi = vb[k], vb[k + 1]
                    vm = 0.5 * (lo + hi) - z_base
                    if lo >= z_base + height - 1e-9:
                        continue
                    floor = int(vm // fh) if vm >= 0 else -1
                    fv = vm / fh - floor
                    colour = facade
                    if floor >= 0 and in_win_u and wv0 < fv < wv1:
                        colour = _GLASS
                    if kind == "warehouse" and floor == 0 and bay % 3 == 1 and fv < 0.75 and i % 2 == 0:
                        colour = _DOOR if in_win_u else colour
                    hi_a = za_top if k == len(vb) - 2 else hi
                    hi_b = zb_top if k == len(vb) - 2 else hi
                    # counter-clockwise footprint -> outward normals with this winding
                    V.append(np.array([[xa[0], xa[1], lo], [xb[0], xb[1], lo], [xb[0], xb[1], hi_b],
                                       [xa[0], xa[1], lo], [xb[0], xb[1], hi_b], [xa[0], xa[1], hi_a]]))
                    C.extend([colour] * 6)
        # Roof (constrained triangulation of the footprint).
        tris = shapely.constrained_delaunay_triangles(Polygon(top[:, :2]))
        roof_v = []
        for tri in shapely.get_parts(tris):
            xy = np.asarray(tri.exterior.coords)[:3]
            xy = xy if _ccw(xy) else xy[::-1]
            roof_v.append(np.column_stack([xy, _roof_z(top, xy)]))
        for rv in roof_v:
            V.append(rv)
            C.extend([roof] * 3)
        verts = np.vstack(V)
        faces = np.arange(len(verts)).reshape(-1, 3)
        colours = np.column_stack([np.asarray(C, dtype=np.uint8), np.full(len(C), 255, np.uint8)])
        m = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colours, process=False)
        m.metadata["name"] = bid
        m.metadata["kind"] = kind
        out.append(m)
    return out


def _ccw(xy: np.ndarray) -> bool:
    a, b, c = xy[0], xy[1], xy[2]
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0


def _is_ccw(ring: np.ndarray) -> bool:
    """Whether ``ring`` (k, 2) runs counter-clockwise (shoelace)."""
    x, y = ring[:, 0], ring[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0


def _roof_z(top: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Roof height at xy: the nearest roof corner's (corners differ by millimetres of earth curvature)."""
    d = np.linalg.norm(top[None, :, :2] - xy[:, None, :], axis=2)
    return top[np.argmin(d, axis=1), 2]
