"""Fast synthetic consist problems (no rendering) for the solver's tests and benchmark.

N carriages (types cycling through shoreliner, p32ac-dm, amfleet-i, acs-64) laid as a jackknifed chain on a
flat or gently sloped plane, resting on it (wheels on the plane, to within the coupling slack). Held couplings
have true offsets drawn uniformly in the ball |T| <= ``slack_m`` — the distribution the solver's offset prior
N(0, (slack/sqrt 5)^2) per axis stands for (a disc in the plane would have per-axis sd slack/2 in the plane,
wider than the prior, and bias the solver at low noise); broken ones are
pulled apart by 1-3 m and carry no link. One camera about 1.1 train lengths from the consist's centre, ~10 m
above the plane, looking at the consist, 4000x3000 px, f ~ 3000 px, small radial distortion. Each carriage
shows the 7 marked points "as a photo shows them": those on the faces most turned towards the camera (the
side facing it and the nearer end); ``n_points`` may also be a sequence (one count per carriage, cycled), for
consists whose carriages show different numbers of points. Pixel noise is Gaussian with ``pixel_sigma_px`` per
coordinate. All randomness comes from ``seed``.

:func:`redraw` keeps a problem's geometry (camera, rotations, the first carriage, the visible points) and draws
new held-coupling offsets and new pixel noise: many noise draws of one geometry separate an estimator's bias
from its spread.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from ..core.camera import CameraIntrinsics, look_at, project_world
from ..core.geometry import rot_z, rotation_between
from ..rolling_stock import get_type
from .model import CarriageInput, ChainLink, View
from .terrain import surface_samples, wheel_points

TYPE_CYCLE = ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64")


class PlaneTerrain:
    """Terrain z = z0 + a x + b y (scene ENU), with the ``height_at`` interface of the terrain model."""

    def __init__(self, a: float = 0.0, b: float = 0.0, z0: float = 0.0) -> None:
        self.a, self.b, self.z0 = float(a), float(b), float(z0)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        return self.z0 + self.a * xy[:, 0] + self.b * xy[:, 1]

    @property
    def normal(self) -> np.ndarray:
        n = np.array([-self.a, -self.b, 1.0])
        return n / np.linalg.norm(n)


class DemWithError:
    """A DEM of the simulated ground with the error a terrain contact states: the plane ``ground`` (its
    ``height_at``) raised under each carriage by ``ground_m`` (n,), m (the ground that carriage stands on: its
    wheels' height over the plane; 0: the plane), plus one height error per carriage (``errors_m`` (n,), m), exact
    within ``radii_m`` (n,) of that carriage's centre (``centres_xy`` (n, 2), scene m: its wheels' reach), and
    between the carriages the errors blended by inverse squared distance to those discs (continuous: no step for
    a lowest point or a slope to fall on). Independent per carriage, as the contact term takes a DEM's error
    (``terrain_sigma_m`` per carriage); the ``height_at`` interface of the terrain model."""

    def __init__(self, ground: PlaneTerrain, centres_xy: np.ndarray, errors_m: np.ndarray,
                 radii_m: np.ndarray, ground_m: np.ndarray | None = None) -> None:
        self.ground = ground
        self.centres_xy = np.asarray(centres_xy, dtype=float).reshape(-1, 2)
        self.errors_m = np.asarray(errors_m, dtype=float).reshape(-1)
        self.radii_m = np.asarray(radii_m, dtype=float).reshape(-1)
        n = len(self.centres_xy)
        self.ground_m = np.zeros(n) if ground_m is None else np.asarray(ground_m, dtype=float).reshape(-1)
        if len(self.errors_m) != n or len(self.radii_m) != n or len(self.ground_m) != n:
            raise ValueError(f"{self.centres_xy.shape=}, {self.errors_m.shape=}, {self.radii_m.shape=}, "
                             f"{self.ground_m.shape=}: one error, radius and ground height per carriage")

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        dist = np.sqrt(((xy[:, None, :] - self.centres_xy[None]) ** 2).sum(-1))  # (m, n)
        gap = np.maximum(dist - self.radii_m[None], 0.0)
        inside = gap <= 0.0
        w = 1.0 / np.maximum(gap, 1e-9) ** 2
        e = self.errors_m + self.ground_m
        err = (w @ e) / w.sum(axis=1)
        own = np.where(inside, dist, np.inf).argmin(axis=1)  # inside a disc: that carriage's error (the nearest)
        err = np.where(inside.any(axis=1), e[own], err)
        return self.ground.height_at(xy) + err


@dataclass
class SimProblem:
    carriages: list[CarriageInput]
    links: list[ChainLink]
    views: list[View]
    truth: list[np.ndarray]  # world_from_carriage (4, 4) per carriage
    offsets: list[np.ndarray]  # true coupler offsets T per link (front -> rear)
    terrain: PlaneTerrain
    pixel_sigma_px: float
    clean_pixels: list[dict] = field(default_factory=list)  # per carriage: point -> noiseless (u, v)


def simulate_consist(n_cars: int = 6, *, seed: int = 0, pixel_sigma_px: float = 1.0, slack_m: float = 0.03,
                     broken: tuple[int, ...] = (), slope_deg: float = 2.0, n_points: int | Sequence[int] = 7,
                     width: int = 4000, height: int = 3000, focal_px: float = 3000.0,
                     distortion: tuple[float, float] = (-0.02, 0.004), jackknife_deg: tuple[float, float] = (4.0, 25.0),
                     distance_factor: float = 1.1, camera_height_m: float = 10.0,
                     max_distance_m: float | None = None, hfov_deg: float = 60.0) -> SimProblem:
    """A synthetic consist problem. ``broken``: link indices i (between cars i and i+1) that are broken.

    One photo from ``distance_factor`` train lengths away sees the whole consist. With ``max_distance_m`` the
    camera stands no farther than that and, when the consist does not fit one photo, turns: a panorama of
    photos (``hfov_deg`` wide, the focal set to match, ~40 % overlap) from one place, each carriage observed in
    the photo where it is nearest the centre (how a long freight train is photographed)."""
    rng = np.random.default_rng(seed)
    types = [get_type(TYPE_CYCLE[i % len(TYPE_CYCLE)]) for i in range(n_cars)]
    az = rng.uniform(0, 2 * np.pi)
    sl = np.tan(np.deg2rad(slope_deg)) * rng.uniform(0.3, 1.0)
    terrain = PlaneTerrain(sl * np.cos(az), sl * np.sin(az), 0.0)
    Rp = rotation_between([0.0, 0.0, 1.0], terrain.normal)  # scene up to the plane's normal
    n = terrain.normal
    yaw = rng.uniform(0, 2 * np.pi)
    poses, offsets = [], []
    R = Rp @ rot_z(yaw)
    t = np.zeros(3)
    poses.append((R, t))
    for i in range(1, n_cars):
        Ra, ta = poses[-1]
        a_ct, b_ct = types[i - 1], types[i]
        sign = rng.choice([-1.0, 1.0])
        yaw = yaw + sign * np.deg2rad(rng.uniform(*jackknife_deg))
        if (i - 1) in broken:
            yaw += rng.normal(0, np.deg2rad(15))
        Rb = Rp @ rot_z(yaw)
        if (i - 1) in broken:
            r, phi = rng.uniform(1.0, 3.0), rng.uniform(0, 2 * np.pi)
            T = Rp @ np.array([r * np.cos(phi), r * np.sin(phi), 0.0])
        else:  # uniform in the ball |T| <= slack: the model the solver's offset prior stands for
            u = rng.normal(size=3)
            T = slack_m * rng.uniform() ** (1.0 / 3.0) * u / np.linalg.norm(u)
        tb = ta + Ra @ a_ct.coupler_rear + T - Rb @ b_ct.coupler_front
        poses.append((Rb, tb))
        offsets.append(T)
    truth = []
    for R, t in poses:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, t
        truth.append(M)
    origins = np.array([M[:3, 3] for M in truth])
    centre = origins.mean(0)
    total = float(sum(ct.length_m for ct in types))
    xy = origins[:, :2] - centre[:2]
    if len(origins) > 1:
        _, _, Vt = np.linalg.svd(xy, full_matrices=False)
        d = Vt[0]
    else:
        d = truth[0][:2, 0]
    perp = np.array([-d[1], d[0]]) * rng.choice([-1.0, 1.0])
    dist = distance_factor * total if max_distance_m is None else min(distance_factor * total, max_distance_m)
    eye_xy = centre[:2] + perp * dist
    eye = np.array([*eye_xy, float(terrain.height_at(eye_xy[None])[0]) + camera_height_m])
    if max_distance_m is not None:
        focal_px = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    f = focal_px * (1.0 + rng.uniform(-0.02, 0.02))
    intr = CameraIntrinsics(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2 + rng.uniform(-10, 10),
                            cy=(height - 1) / 2 + rng.uniform(-10, 10), k1=distortion[0], k2=distortion[1])
    # bearings (about the vertical through the eye) of the carriages; photos spaced to cover them
    body = np.array([M[:3, :3] @ np.array([0.0, 0.0, ct.height_m / 2]) + M[:3, 3] for ct, M in zip(types, truth)])
    rel = body[:, :2] - eye[:2]
    az_c = np.arctan2(rel[:, 1], rel[:, 0])
    az0 = np.arctan2(*(centre[:2] - eye[:2])[::-1])
    daz = (az_c - az0 + np.pi) % (2 * np.pi) - np.pi
    span = float(daz.max() - daz.min())
    step = np.deg2rad(hfov_deg) * 0.6
    n_views = 1 if max_distance_m is None else max(1, int(np.ceil((span + np.deg2rad(hfov_deg) * 0.2) / step)))
    mids = [0.5 * (daz.max() + daz.min())] if n_views == 1 else \
        list(np.linspace(daz.min() + 0.4 * step, daz.max() - 0.4 * step, n_views))
    views = []
    for j, m in enumerate(mids):
        a = az0 + m
        tgt = eye + np.array([np.cos(a), np.sin(a), 0.0]) * dist
        tgt[2] = centre[2] + 1.5 if n_views == 1 else tgt[2] - camera_height_m + 1.5
        if n_views == 1:
            tgt = centre + n * 1.5
        views.append(View(name="photo" if n_views == 1 else f"photo_{j + 1:02d}", intrinsics=intr,
                          cam_from_world=look_at(eye, tgt)))
    counts = [int(n_points)] * n_cars if np.ndim(n_points) == 0 else \
        [int(list(n_points)[i % len(n_points)]) for i in range(n_cars)]
    carriages, clean = [], []
    for i, (ct, M) in enumerate(zip(types, truth)):
        R, t = M[:3, :3], M[:3, 3]
        view = views[int(np.argmin([abs(daz[i] - m) for m in mids]))]
        cam_from_world = view.cam_from_world
        vc = eye - (R @ np.array([0.0, 0.0, ct.height_m / 2]) + t)
        vc /= np.linalg.norm(vc)
        names = list(ct.marked_points)
        score = []
        for nm in names:
            s = max(float((R @ ct.face_normal(fc)) @ vc) for fc in ct.marked_point_faces[nm])
            score.append(s)
        order = np.argsort(-np.array(score), kind="stable")[:counts[i]]
        chosen = [names[j] for j in order]
        P = np.array([ct.marked_points[nm] for nm in chosen])
        uv, depth = project_world(intr, cam_from_world, P @ R.T + t)
        noisy = uv + rng.normal(0.0, pixel_sigma_px, uv.shape)
        if not (np.all(depth > 0) and np.all(intr.in_image(noisy, margin=1.0))):
            raise RuntimeError(f"simulate_consist(seed={seed}): car {i} is not fully in the image")
        clean.append({nm: tuple(map(float, uv[j])) for j, nm in enumerate(chosen)})
        carriages.append(CarriageInput(number=f"{100 + i}", carriage_type=ct,
                                       observations={view.name: {nm: tuple(map(float, noisy[j]))
                                                                 for j, nm in enumerate(chosen)}}))
    links = [ChainLink(i, i + 1, None if i in broken else slack_m) for i in range(n_cars - 1)]
    return SimProblem(carriages, links, views, truth, offsets, terrain, pixel_sigma_px, clean)


def redraw(sim: SimProblem, seed: int, pixel_sigma_px: float | None = None, offsets: bool = True) -> SimProblem:
    """The same geometry (camera, carriage rotations, first carriage's pose, the visible points of each carriage)
    with new held-coupling offsets (uniform in the ball |T| <= slack, as :func:`simulate_consist` draws them;
    ``offsets=False`` keeps them) and new pixel noise (``pixel_sigma_px``, default the problem's). Broken links
    keep their offsets. All randomness comes from ``seed``."""
    rng = np.random.default_rng(seed)
    sigma = sim.pixel_sigma_px if pixel_sigma_px is None else float(pixel_sigma_px)
    types = [c.carriage_type for c in sim.carriages]
    slack = {L.front: L.slack_m for L in sim.links}
    truth = [sim.truth[0].copy()]
    new_off = []
    for i in range(1, len(types)):
        Ra, ta = truth[-1][:3, :3], truth[-1][:3, 3]
        Rb = sim.truth[i][:3, :3]
        T = sim.offsets[i - 1]
        if offsets and slack.get(i - 1) is not None:
            u = rng.normal(size=3)
            T = slack[i - 1] * rng.uniform() ** (1.0 / 3.0) * u / np.linalg.norm(u)
        M = np.eye(4)
        M[:3, :3] = Rb
        M[:3, 3] = ta + Ra @ types[i - 1].coupler_rear + T - Rb @ types[i].coupler_front
        truth.append(M)
        new_off.append(np.asarray(T, float))
    vidx = {v.name: v for v in sim.views}
    carriages, clean = [], []
    for car, M in zip(sim.carriages, truth):
        ct = car.carriage_type
        obs = {}
        cl = {}
        for vname, pts in car.observations.items():
            view = vidx[vname]
            names = list(pts)
            P = np.array([ct.marked_points[nm] for nm in names])
            uv, _ = project_world(view.intrinsics, view.cam_from_world, P @ M[:3, :3].T + M[:3, 3])
            noisy = uv + rng.normal(0.0, sigma, uv.shape)
            obs[vname] = {nm: tuple(map(float, noisy[j])) for j, nm in enumerate(names)}
            cl.update({nm: tuple(map(float, uv[j])) for j, nm in enumerate(names)})
        carriages.append(CarriageInput(number=car.number, carriage_type=ct, observations=obs))
        clean.append(cl)
    return replace(sim, carriages=carriages, truth=truth, offsets=new_off, pixel_sigma_px=sigma, clean_pixels=clean)


def dem_with_error(sim: SimProblem, sigma_m: float, seed: int, ground: str = "carriages") -> DemWithError:
    """The DEM a solve of ``sim`` is given when its terrain is known to ``sigma_m`` per carriage: the ground plus
    N(0, ``sigma_m``) per carriage (:class:`DemWithError`, drawn from ``seed``), exact out to its wheels (their
    farthest reach from the carriage's origin plus 0.5 m). ``ground``: ``"carriages"`` (default), the ground each
    carriage stands on: the plane raised under it by its wheels' height over the plane at the truth (the
    couplers' play, drawn in 3-D by :func:`simulate_consist`, lifts or sinks the carriages off the plane by a
    random walk along the consist, 0-3 cm; a carriage on its wheels stands on the ground, so the DEM's error is
    its stated error about where the wheels are); ``"plane"``: the plane itself, so the DEM's error about the
    wheels is the stated error plus that walk."""
    if not (np.isfinite(sigma_m) and sigma_m >= 0):
        raise ValueError(f"dem_with_error: sigma_m = {sigma_m!r}; expected a non-negative height error in metres")
    if ground not in ("carriages", "plane"):
        raise ValueError(f"dem_with_error: ground = {ground!r}; expected 'carriages' or 'plane'")
    centres = np.array([M[:2, 3] for M in sim.truth])  # each carriage's origin, midway between its couplers
    radii, lift = [], []
    for c, M in zip(sim.carriages, sim.truth):
        W = wheel_points(surface_samples(c.carriage_type, 400))
        radii.append(float(np.linalg.norm(W[:, :2], axis=1).max()) + 0.5)
        Xw = W @ M[:3, :3].T + M[:3, 3]
        lift.append(float(np.mean(Xw[:, 2] - sim.terrain.height_at(Xw[:, :2]))))
    errors = np.random.default_rng(seed).normal(0.0, sigma_m, len(sim.truth))
    return DemWithError(sim.terrain, centres, errors, np.array(radii),
                        np.array(lift) if ground == "carriages" else None)
