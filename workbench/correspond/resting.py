"""Hypotheses of a carriage's pose put on the terrain (the chain/terrain pose search, :mod:`.search`).

The pitch at which a car coupled at an anchor keeps its other coupler as high above the ground, a pose lowered
or raised until its lowest collision-box corner touches the terrain, and a pose moved along its coupler's line
of sight to where it touches it. Scene frame (ENU, metres), ``world_from_carriage`` (4, 4) and
``cam_from_carriage`` (4, 4) as in ``docs/conventions.md``; ``terrain``: ``Project.terrain_model()`` or None.
Where many poses or headings are put down at once, the terrain is read once for all of them: the heights of
points do not depend on which others are asked with them, so each result is the one-by-one result.
"""

from __future__ import annotations

import numpy as np

from ..rolling_stock import CarriageType


def pitch_on_terrain(a, yaw: float, L: float, terrain) -> float:
    """Pitch (rad) at which the other coupler stands as high above the terrain as the anchored one; ``a``: the
    anchor (``search.Anchor``: ``world`` (3,) the anchored coupler in the scene frame, ``end`` "front" / "rear")."""
    if terrain is None:
        return 0.0
    h_a = terrain.height_at(a.world[None, :2])[0]
    if not np.isfinite(h_a):
        return 0.0
    clear = a.world[2] - h_a
    sign = -1.0 if a.end == "front" else 1.0  # the other coupler lies behind the front one, ahead of the rear one
    p = 0.0
    for _ in range(4):
        other = a.world + sign * L * np.array([np.cos(p) * np.cos(yaw), np.cos(p) * np.sin(yaw), np.sin(p)])
        h = terrain.height_at(other[None, :2])[0]
        if not np.isfinite(h):
            return p
        s = np.clip(sign * (h + clear - a.world[2]) / L, -0.5, 0.5)
        p = float(np.arcsin(s))
    return p


def pitches_on_terrain(a, yaws: list[float], L: float, terrain) -> list[float]:
    """:func:`pitch_on_terrain` at each heading, the terrain read once per step for all of them (the same
    arithmetic per heading; the terrain's heights of points do not depend on which others are asked with them)."""
    if terrain is None:
        return [0.0] * len(yaws)
    h_a = terrain.height_at(a.world[None, :2])[0]
    if not np.isfinite(h_a):
        return [0.0] * len(yaws)
    clear = a.world[2] - h_a
    sign = -1.0 if a.end == "front" else 1.0
    p = [0.0] * len(yaws)
    live = list(range(len(yaws)))  # the headings still iterating
    for _ in range(4):
        if not live:
            break
        others = [a.world + sign * L * np.array([np.cos(p[k]) * np.cos(yaws[k]), np.cos(p[k]) * np.sin(yaws[k]),
                                                 np.sin(p[k])]) for k in live]
        hs = terrain.height_at(np.array([o[:2] for o in others]))
        still = []
        for k, h in zip(live, hs):
            if not np.isfinite(h):
                continue  # (returns p as it is)
            sv = np.clip(sign * (h + clear - a.world[2]) / L, -0.5, 0.5)
            p[k] = float(np.arcsin(sv))
            still.append(k)
        live = still
    return p


def rested(Ws: list[np.ndarray], corners: np.ndarray, terrain) -> list[np.ndarray]:
    """:func:`rest` of each pose, the terrain read once for all of their corners."""
    if terrain is None or not Ws:
        return list(Ws)
    Ps = [(W[:3, :3] @ corners.T).T + W[:3, 3] for W in Ws]
    hs = terrain.height_at(np.vstack([P[:, :2] for P in Ps]))
    out = []
    for k, (W, P) in enumerate(zip(Ws, Ps)):
        h = hs[k * len(corners):(k + 1) * len(corners)]
        if not np.any(np.isfinite(h)):
            out.append(W)
            continue
        W = W.copy()
        W[2, 3] -= float(np.nanmin(P[:, 2] - h))
        out.append(W)
    return out


def collision_corners(ct: CarriageType) -> np.ndarray:
    """(n, 3) carriage-frame corners of the car's collision boxes (body, bogies, equipment)."""
    out = []
    for c, h in ct.collision_boxes():
        for sx in (-1, 1):
            for sy in (-1, 1):
                for sz in (-1, 1):
                    out.append(c + h * [sx, sy, sz])
    return np.array(out)


def rest(W: np.ndarray, corners: np.ndarray, terrain) -> np.ndarray:
    """world_from_carriage moved vertically so that its lowest corner touches the terrain (as it is without)."""
    if terrain is None:
        return W
    P = (W[:3, :3] @ corners.T).T + W[:3, 3]
    h = terrain.height_at(P[:, :2])
    if not np.any(np.isfinite(h)):
        return W
    W = W.copy()
    W[2, 3] -= float(np.nanmin(P[:, 2] - h))
    return W


def rest_on_ray(cam_from_carriage: np.ndarray, c: np.ndarray, cam_from_world: np.ndarray, corners: np.ndarray,
                 terrain, reach_m: float) -> np.ndarray:
    """The pose moved along the line of sight of its coupler ``c`` (the photo keeps the coupler where it is)
    to where its lowest corner touches the terrain, within ``reach_m``: the depth that an image position leaves
    open."""
    if terrain is None:
        return cam_from_carriage
    world_from_cam = np.linalg.inv(cam_from_world)
    X = cam_from_carriage[:3, :3] @ c + cam_from_carriage[:3, 3]

    def at(sc):
        M = cam_from_carriage.copy()
        M[:3, 3] += (sc - 1.0) * X
        return M

    def clearance(sc):
        W = world_from_cam @ at(sc)
        P = (W[:3, :3] @ corners.T).T + W[:3, 3]
        h = terrain.height_at(P[:, :2])
        return float(np.nanmin(P[:, 2] - h)) if np.any(np.isfinite(h)) else np.nan

    d = float(np.linalg.norm(X))
    lo, hi = 1.0 - reach_m / d, 1.0 + reach_m / d  # within the anchor's reach along the line of sight
    g_lo, g_hi = clearance(lo), clearance(hi)
    if not (np.isfinite(g_lo) and np.isfinite(g_hi)) or np.sign(g_lo) == np.sign(g_hi):
        return cam_from_carriage  # no contact along the ray within the range: leave it
    while (hi - lo) * d > 1e-3:  # to a millimetre along the line of sight
        mid = 0.5 * (lo + hi)
        g = clearance(mid)
        if not np.isfinite(g):
            break
        if np.sign(g) == np.sign(g_lo):
            lo, g_lo = mid, g
        else:
            hi = mid
    return at(0.5 * (lo + hi))


__all__ = ["pitch_on_terrain", "pitches_on_terrain", "rest", "rested", "collision_corners", "rest_on_ray"]
