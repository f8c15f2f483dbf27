"""What the picker draws over a photo: a carriage's model edges and its marked points, projected with a camera.

Pure geometry (no file, no request). Pixels follow docs/conventions.md (pixel (0, 0) is the centre of the
top-left pixel); cameras are :class:`workbench.core.camera.CameraIntrinsics` and ``cam_from_world`` (4, 4).

* :func:`model_edges`: the edges of a carriage type's model worth drawing: creases (the faces on either side
  meet at more than :data:`CREASE_DEG`) and every edge between two faces, which the silhouette test needs.
* :func:`outline`: those edges in one photo at one pose: a crease where one of its faces turns to the camera,
  and the silhouette (an edge between a face that turns to the camera and one that turns away), each cut into
  pieces of at most :data:`PIECE_M` so that the lens distortion bends it as the photo does; a piece the car's
  body hides (a line of sight to it crosses the body part first: the running gear under a car seen from above) is
  left out. A mesh type has one part, so only its back faces are culled. Other cars and buildings hide nothing.
* :func:`project_points`: marked points to pixels, None where a point is behind the camera or beyond the
  lens model's reach (:func:`reach`: a Brown polynomial folds back far outside the picture).
* :func:`in_sight`: whether the car's own model hides a point (a line of sight cast against the model, with the
  synthetic truth's tolerance; at a grazing angle it can go either way, and other cars are not considered).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from ..core.camera import CameraIntrinsics

CREASE_DEG = 30.0  # a crease: the two faces meet at more than this
PIECE_M = 0.75  # an edge is drawn as pieces at most this long (the lens bends long straight edges)
MAX_FACES = 20000  # a model with more faces (a detailed mesh type) is outlined by its convex hull
MAX_LINES = 6000  # pieces per carriage and photo at most


@dataclass(frozen=True)
class ModelEdges:
    """Edges of a carriage model in the carriage frame: ends ``a``, ``b`` (n, 3); the two faces' outward normals
    ``n1``, ``n2`` and centres ``c1``, ``c2`` (n, 3); ``crease`` (n,) bool; the model (a ``trimesh.Trimesh``,
    the lines of sight of :func:`in_sight` are cast against it) and ``body``, its body part (the outline's
    occluder; None for a mesh type)."""

    a: np.ndarray
    b: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    crease: np.ndarray
    mesh: object = None
    body: object = None


_edges_cache: dict[tuple, ModelEdges] = {}
_edges_lock = threading.Lock()


def model_edges(ct) -> ModelEdges:
    """The :class:`ModelEdges` of carriage type ``ct`` (cached per type file and its mtime)."""
    src = getattr(ct, "source_path", None)
    try:
        stamp = src.stat().st_mtime_ns if src is not None else 0
    except OSError:
        stamp = 0
    key = (ct.id, str(src), stamp)
    with _edges_lock:
        hit = _edges_cache.get(key)
    if hit is not None:
        return hit
    import trimesh

    m = ct.mesh(textured=False)
    mesh = trimesh.Trimesh(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces), process=True)
    if len(mesh.faces) > MAX_FACES:
        mesh = mesh.convex_hull
    pairs = np.asarray(mesh.face_adjacency)
    ends = np.asarray(mesh.face_adjacency_edges)
    V, N, C = np.asarray(mesh.vertices), np.asarray(mesh.face_normals), np.asarray(mesh.triangles_center)
    angle = np.asarray(mesh.face_adjacency_angles)
    hit = ModelEdges(a=V[ends[:, 0]], b=V[ends[:, 1]], n1=N[pairs[:, 0]], n2=N[pairs[:, 1]], c1=C[pairs[:, 0]],
                     c2=C[pairs[:, 1]], crease=angle > math.radians(CREASE_DEG), mesh=mesh,
                     body=None if ct.is_mesh_type else next((q.mesh for q in ct.parts() if q.name == "body"), None))
    with _edges_lock:
        _edges_cache[key] = hit
    return hit


def reach(intr: CameraIntrinsics) -> float:
    """The largest undistorted normalised radius the lens model is trusted to: 1.25 times that of the photo's
    farthest corner (beyond it a Brown polynomial may fold back into the picture)."""
    corners = np.array([[-0.5, -0.5], [intr.width - 0.5, -0.5], [-0.5, intr.height - 0.5],
                        [intr.width - 0.5, intr.height - 0.5]])
    xy = intr.undistort(intr.normalized_from_pixels(corners))
    r = float(np.max(np.hypot(xy[:, 0], xy[:, 1])))
    return 1.25 * r if math.isfinite(r) and r > 0 else 2.0


def _pixels(intr: CameraIntrinsics, cam_from_world: np.ndarray, X: np.ndarray, limit: float) -> np.ndarray:
    """World points (n, 3) -> pixels (n, 2), NaN behind the camera or beyond ``limit`` (normalised radius)."""
    M = np.asarray(cam_from_world, dtype=float)
    P = np.asarray(X, dtype=float).reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
    z = P[:, 2]
    ok = z > 1e-6
    xy = np.full((len(P), 2), np.nan)
    xy[ok] = P[ok, :2] / z[ok, None]
    xy[~(np.hypot(xy[:, 0], xy[:, 1]) <= limit)] = np.nan
    good = np.all(np.isfinite(xy), axis=1)
    uv = np.full((len(P), 2), np.nan)
    if good.any():
        uv[good] = intr.pixels_from_normalized(intr.distort(xy[good]))
    return uv


def project_points(points: dict[str, np.ndarray], world_from_carriage: np.ndarray, intr: CameraIntrinsics,
                   cam_from_world: np.ndarray) -> dict[str, list[float] | None]:
    """Each marked point (carriage frame) in the photo: ``[u, v]`` rounded to 0.001 px, or None (behind the camera
    or beyond the lens model's reach; a point outside the picture but within reach is given)."""
    names = list(points)
    if not names:
        return {}
    W = np.asarray(world_from_carriage, dtype=float)
    P = np.array([points[n] for n in names], dtype=float)
    uv = _pixels(intr, cam_from_world, P @ W[:3, :3].T + W[:3, 3], reach(intr))
    return {n: ([round(float(uv[i, 0]), 3), round(float(uv[i, 1]), 3)] if np.all(np.isfinite(uv[i])) else None)
            for i, n in enumerate(names)}


def outline(edges: ModelEdges, world_from_carriage: np.ndarray, intr: CameraIntrinsics,
            cam_from_world: np.ndarray) -> list[list[list[float]]]:
    """The model's visible creases and its silhouette in the photo: polylines of pixels (rounded to 0.01 px),
    each one edge; pieces behind the camera or beyond the lens model's reach are left out, and an edge wholly
    outside the picture (by more than half its size) too."""
    W = np.asarray(world_from_carriage, dtype=float)
    R, t = W[:3, :3], W[:3, 3]
    M = np.asarray(cam_from_world, dtype=float)
    centre = -M[:3, :3].T @ M[:3, 3]
    facing1 = np.einsum("ij,ij->i", edges.n1 @ R.T, centre - (edges.c1 @ R.T + t)) > 0
    facing2 = np.einsum("ij,ij->i", edges.n2 @ R.T, centre - (edges.c2 @ R.T + t)) > 0
    keep = (edges.crease & (facing1 | facing2)) | (facing1 != facing2)
    a, b = edges.a[keep] @ R.T + t, edges.b[keep] @ R.T + t
    if not len(a):
        return []
    n = np.clip(np.ceil(np.linalg.norm(b - a, axis=1) / PIECE_M).astype(int), 1, 64)
    if int(n.sum()) > MAX_LINES:  # a dense model: fewer pieces (the ends only)
        n[:] = 1
    limit = reach(intr)
    w, h = intr.width, intr.height
    lines = []
    offsets = np.concatenate([[0], np.cumsum(n + 1)])
    s = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n])
    idx = np.repeat(np.arange(len(a)), n + 1)
    X = a[idx] + s[:, None] * (b[idx] - a[idx])
    uv = _pixels(intr, M, X, limit)
    if edges.body is not None:  # pieces behind the body
        seen = np.all(np.isfinite(uv), axis=1)
        seen[seen] = _clear(edges.body, R.T @ (centre - t), (X[seen] - t) @ R, intr.fx)
        uv[~seen] = np.nan
    for i in range(len(a)):
        seg = uv[offsets[i]:offsets[i + 1]]
        good = np.all(np.isfinite(seg), axis=1)
        # runs of consecutive good samples
        run: list[list[float]] = []
        for j in range(len(seg)):
            if good[j]:
                run.append([round(float(seg[j, 0]), 2), round(float(seg[j, 1]), 2)])
                continue
            if len(run) >= 2:
                lines.append(run)
            run = []
        if len(run) >= 2:
            lines.append(run)
    out = []
    for ln in lines:
        q = np.asarray(ln)
        lo, hi = q.min(axis=0), q.max(axis=0)
        if hi[0] < -0.5 * w or lo[0] > 1.5 * w or hi[1] < -0.5 * h or lo[1] > 1.5 * h:
            continue
        out.append(ln)
    return out




def _clear(mesh, c: np.ndarray, P: np.ndarray, focal_px: float) -> np.ndarray:
    """(n,) whether the lines of sight from ``c`` to points ``P`` (one frame) meet ``mesh`` no nearer than 5 cm
    plus two pixel footprints (``2 distance / focal_px``) before the point."""
    d = P - c
    length = np.linalg.norm(d, axis=1)
    out = np.ones(len(P), dtype=bool)
    if not len(P):
        return out
    from trimesh.ray.ray_triangle import RayMeshIntersector

    hits, rays, _ = RayMeshIntersector(mesh).intersects_location(
        np.repeat(c[None], len(P), axis=0), d / np.maximum(length, 1e-12)[:, None], multiple_hits=True)
    if len(rays):
        dist = np.linalg.norm(hits - c, axis=1)
        near = dist < length[rays] - (0.05 + 2.0 * length[rays] / float(focal_px))
        out[np.unique(rays[near])] = False
    return out


def in_sight(edges: ModelEdges, world_from_carriage: np.ndarray, centre: np.ndarray, points: np.ndarray,
             focal_px: float) -> np.ndarray:
    """(n,) whether the line of sight from the camera ``centre`` (scene frame) to each carriage-frame point
    meets the carriage's own model (:attr:`ModelEdges.mesh`) no nearer than 5 cm plus two pixel footprints
    (``2 distance / focal_px``) before the point, as the synthetic truth's visibility is judged. The car itself
    only: other cars and buildings are not considered."""
    W = np.asarray(world_from_carriage, dtype=float)
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    if edges.mesh is None:
        return np.ones(len(P), dtype=bool)
    return _clear(edges.mesh, W[:3, :3].T @ (np.asarray(centre, dtype=float) - W[:3, 3]), P, focal_px)
