"""Lay a derailed consist on the terrain: jackknifed carriages, some on their side, couplings held or broken.

Every carriage rests on the ground without penetrating it: free carriages are lowered along gravity
(scene z) onto the terrain mesh; a carriage whose front coupling held hangs from the previous
carriage's rear coupler (plus a small offset within the coupler slack) and is pitched about that
point until it touches the ground. Carriage bodies never overlap each other (oriented-box test).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..core.frames import Rigid, hpr_from_rotation, rotation_from_hpr
from ..core.geometry import boxes_overlap

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CarPlan:
    """What the scenario asks of one carriage (front to rear)."""

    number: str
    ctype: object  # CarriageType
    state: str = "upright"  # upright | tilted | on_side
    roll_deg: float = 0.0  # state roll (on_side: +-90, tilted: +-(10..35))
    jackknife_deg: float = 0.0  # heading change relative to the previous carriage (or the track, for the first)
    coupling_to_next: str | None = "held"  # held | broken | None (last)
    broken_gap_m: float = 3.0  # for a broken coupling to the next car: distance between the coupler faces


@dataclass
class PlacedCar:
    number: str
    ctype: object
    world_from_carriage: Rigid
    state: str
    coupling_to_next: str | None
    coupler_offset_m: np.ndarray | None = None  # this car's front coupler minus previous rear coupler (held only)
    min_clearance_m: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def hpr(self) -> tuple[float, float, float]:
        return hpr_from_rotation(self.world_from_carriage.rotation)


# ---------------------------------------------------------------------------------------------------
def _world_boxes(car_type, pose: Rigid):
    out = []
    for centre, half in car_type.collision_boxes():
        out.append((pose.apply(np.asarray(centre, float)), pose.rotation, np.asarray(half, float)))
    return out


def cars_overlap(a: PlacedCar, b: PlacedCar, margin: float = 0.02) -> bool:
    for c1, R1, h1 in _world_boxes(a.ctype, a.world_from_carriage):
        for c2, R2, h2 in _world_boxes(b.ctype, b.world_from_carriage):
            if boxes_overlap(c1, R1, h1, c2, R2, h2, margin):
                return True
    return False


# ---------------------------------------------------------------------------------------------------
class _Contact:
    """Clearance between a carriage (dense surface samples) and the terrain surface."""

    def __init__(self, terrain, car_type, node_tree, terrain_nodes: np.ndarray, n_samples: int = 3000) -> None:
        self.terrain = terrain
        self.samples = car_type.sample_surface(n_samples, seed=0)
        self.boxes = car_type.collision_boxes()
        self.terrain_nodes = terrain_nodes  # (m, 3) ENU vertices of the terrain mesh
        self.node_tree = node_tree  # KD-tree of their east/north
        bb = np.asarray(car_type.bounding_box())
        self.radius = float(np.linalg.norm(bb[1] - bb[0])) / 2.0 + 1.0
        self.centre = bb.mean(axis=0)

    def clearance(self, R: np.ndarray, t: np.ndarray) -> float:
        """Smallest height of the carriage surface above the terrain (negative: penetration), metres."""
        P = self.samples @ R.T + t
        h = self.terrain.height_at(P[:, :2])
        if np.any(~np.isfinite(h)):
            return -np.inf  # off the DEM: treat as invalid
        c = float(np.min(P[:, 2] - h))
        # terrain nodes inside a carriage box also count as penetration
        near = self.node_tree.query_ball_point((R @ self.centre + t)[:2], self.radius)
        local = (self.terrain_nodes[near] - t) @ R  # carriage frame
        for centre, half in self.boxes:
            # signed distance of each terrain node to the box: > 0 outside, < 0 inside (continuous in the pose)
            q = np.abs(local - centre) - np.asarray(half)
            sdf = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(np.max(q, axis=1), 0.0)
            if len(sdf):
                c = min(c, float(np.min(sdf)))
        return c


def _settle_free(contact: _Contact, heading: float, roll: float, xy: np.ndarray, terrain) -> tuple[np.ndarray, np.ndarray]:
    """Pose of a free carriage: follow the terrain slope, then lower along gravity until it touches."""
    # slope under the carriage: the mean terrain normal around xy
    probe = xy + np.array([[0, 0], [5, 0], [-5, 0], [0, 5], [0, -5]], float)
    nrm = terrain.normal_at(probe).mean(axis=0)
    nrm /= np.linalg.norm(nrm)
    fwd = np.array([np.sin(np.deg2rad(heading)), np.cos(np.deg2rad(heading)), 0.0])
    left = np.array([-fwd[1], fwd[0], 0.0])
    pitch = np.rad2deg(np.arcsin(np.clip(-(nrm @ fwd), -1, 1)))
    slope_roll = np.rad2deg(np.arcsin(np.clip(nrm @ left, -1, 1)))
    R = rotation_from_hpr(heading, pitch, roll + slope_roll)
    t = np.array([xy[0], xy[1], float(terrain.height_at(xy[None])[0]) + 20.0])
    for _ in range(12):  # lowering is exact for the surface samples; a box-node contact may need repeats
        c = contact.clearance(R, t)
        if not np.isfinite(c):
            raise ValueError("carriage off the DEM")
        t[2] -= c
        if abs(c) < 1e-4:
            break
    return R, t


def _settle_pinned(contact: _Contact, heading: float, roll: float, pin: np.ndarray, coupler_local: np.ndarray):
    """Pose of a carriage whose front coupler is pinned at ``pin``: pitch about it until it touches the ground."""

    def pose(pitch: float):
        R = rotation_from_hpr(heading, pitch, roll)
        return R, pin - R @ coupler_local

    lo, hi = -12.0, 12.0  # nose down .. nose up; clearance falls as pitch rises (the rear drops)
    c_lo = contact.clearance(*pose(lo))
    c_hi = contact.clearance(*pose(hi))
    log.debug("pinned: roll=%.1f c_lo=%.3f c_hi=%.3f pin=%s", roll, c_lo, c_hi, pin)
    if not (np.isfinite(c_lo) and np.isfinite(c_hi)) or c_lo < 0 or c_hi > 0:
        return None
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if contact.clearance(*pose(mid)) > 0:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-6:
            break
    return pose(lo)


# the couplers' play (m): a held coupling's offset is drawn uniformly in the ball of this radius, the distribution
# the solver's coupler prior stands for (``solver.slack_held_m``; the generator states it in project.toml)
HELD_OFFSET_MAX_M = 0.03


def lay_consist(plans: list[CarPlan], terrain, track_enu: np.ndarray, *, front_s_m: float, lateral_m: float,
                rng: np.random.Generator, held_offset_max_m: float = HELD_OFFSET_MAX_M) -> list[PlacedCar]:
    """Place the consist. ``front_s_m``: arc length along the track where the front car came to rest;
    ``lateral_m``: its sideways displacement from the track (positive: left of the direction of travel);
    ``held_offset_max_m``: the couplers' play (a held coupling's offset uniform in the ball of that radius)."""
    track = np.asarray(track_enu, float)
    seg = np.diff(track[:, :2], axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    if not (0 <= front_s_m <= s[-1]):
        raise ValueError(f"front_s_m={front_s_m} outside the track (0..{s[-1]:.0f} m)")
    i = int(np.searchsorted(s, front_s_m) - 1)
    i = min(max(i, 0), len(seg) - 1)
    tangent = seg[i] / np.linalg.norm(seg[i])
    base = track[i, :2] + tangent * (front_s_m - s[i])
    left = np.array([-tangent[1], tangent[0]])
    track_heading = np.rad2deg(np.arctan2(tangent[0], tangent[1]))

    nodes = np.asarray(terrain.mesh().vertices)
    tree = cKDTree(nodes[:, :2])
    placed: list[PlacedCar] = []
    for k, plan in enumerate(plans):
        ct = plan.ctype
        contact = _Contact(terrain, ct, tree, nodes)
        result = None
        coupling_changed = False
        notes: list[str] = []
        prev = placed[-1] if placed else None
        held = prev is not None and prev.coupling_to_next == "held"
        # try the planned jackknife and roll first, then smaller/mirrored jackknifes, then less roll
        # (a carriage on its side cannot hang from an upright neighbour's coupler), then let the coupling break
        variants = [(jk_scale * sgn, roll_scale) for roll_scale in (1.0, 0.5, 0.15)
                    for sgn in (1.0, -1.0) for jk_scale in (1.0, 0.75, 0.5)]
        variants += [(1.0, 1.0, "break")]
        for attempt, variant in enumerate(variants):
            jk = plan.jackknife_deg * variant[0]
            roll = plan.roll_deg * variant[1]
            if len(variant) == 3 and held:
                held = False
                coupling_changed = True
                notes.append("the coupling could not hold in any pose tried; it broke")
            if prev is None:
                heading = track_heading + jk
                fwd = np.array([np.sin(np.deg2rad(heading)), np.cos(np.deg2rad(heading))])
                front_xy = base + left * lateral_m
                centre_xy = front_xy - fwd * ct.coupler_front[0]
                R, t = _settle_free(contact, heading, roll, centre_xy, terrain)
                offset = None
            else:
                heading = prev.hpr[0] + jk
                prev_rear = prev.world_from_carriage.apply(prev.ctype.coupler_rear)
                if held:
                    off = rng.normal(size=3)
                    offset = off / np.linalg.norm(off) * held_offset_max_m * rng.uniform() ** (1.0 / 3.0)
                    pose = _settle_pinned(contact, heading, roll, prev_rear + offset, np.asarray(ct.coupler_front))
                    if pose is None:
                        notes.append(f"attempt {attempt}: could not hang from the coupler at jackknife {jk:.0f} deg, "
                                     f"roll {roll:.0f} deg")
                        continue
                    R, t = pose
                else:
                    offset = None
                    prev_heading = np.deg2rad(prev.hpr[0])
                    back = -np.array([np.sin(prev_heading), np.cos(prev_heading)])
                    side = np.array([-back[1], back[0]]) * rng.uniform(-0.5, 0.5)
                    front_xy = prev_rear[:2] + (back + side) / np.linalg.norm(back + side) * plan_gap(plans[k - 1])
                    fwd = np.array([np.sin(np.deg2rad(heading)), np.cos(np.deg2rad(heading))])
                    centre_xy = front_xy - fwd * ct.coupler_front[0]
                    R, t = _settle_free(contact, heading, roll, centre_xy, terrain)
            pose = Rigid(R, t, "world", f"carriage:{plan.number}")
            state = plan.state if abs(roll) > 60 or plan.state != "on_side" else "tilted"
            cand = PlacedCar(plan.number, ct, pose, state, plan.coupling_to_next,
                             coupler_offset_m=offset, min_clearance_m=contact.clearance(R, t), notes=notes)
            clash = [p.number for p in placed[:-1] if cars_overlap(cand, p)]
            if prev is not None and not held and cars_overlap(cand, prev):
                clash.append(prev.number)
            if clash:
                notes.append(f"attempt {attempt}: overlapped {clash} at jackknife {jk:.0f} deg")
                continue
            result = cand
            break
        if coupling_changed and result is not None:
            prev.coupling_to_next = "broken"
        if result is None:
            raise RuntimeError(f"could not lay carriage {plan.number} without overlap or hanging in the air: {notes}")
        placed.append(result)
        log.debug("placed %s: hpr=%s clearance=%.4f", plan.number, np.round(result.hpr, 2), result.min_clearance_m)
    return placed


def plan_gap(plan: CarPlan) -> float:
    return plan.broken_gap_m
