"""Levelling a relative scene from the carriages that stand on their wheels (docs/solver.md, "Relative scenes").

An incident with no survey is solved in a provisional frame anchored at the camera (the georef stage's relative
route). Nothing in the photo says which way is up except the carriages themselves: a car standing on its wheels
on straight, level track has its floor horizontal, so its z axis is the vertical. This module takes the solved
poses, finds the cars that agree on an up direction (the upright ones; a car lying on its side or tipped over
disagrees and is left out), averages their z axes weighted by their covariance, and returns the rotation about
the camera that makes that average vertical, with the y axis along the reference photo's centre ray (its
viewing direction).

The levelling's uncertainty is what the data allow: each car's tilt from its fit, plus ``sigma_car_deg`` of its
own (suspension, a wheel off the rail, uneven ballast; independent car to car), plus ``sigma_common_deg`` that
no number of cars averages away (the grade and cant of the track they stand on). When three or more cars are used
and they scatter more than that model says, the covariance is inflated by the excess (the Birge ratio).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.geometry import rotation_between, skew
from .camera_term import add_pose_covariance, camera_pose_jacobian

__all__ = ["Levelling", "UprightCar", "level_from_carriages", "add_levelling_uncertainty"]

UPRIGHT_TOL_DEG = 10.0    # cars whose z axes agree within this are taken to stand on the same track
# a photo is held within this of level: an "up" farther from the camera's is a car on its side
CAMERA_TILT_MAX_DEG = 35.0
CAMERA_LEVEL_SIGMA_DEG = 5.0  # the fallback's sigma when no car stands on its wheels (the photo taken level)


@dataclass(frozen=True)
class UprightCar:
    """A solved carriage as the levelling sees it: ``R`` (3, 3) its rotation in the provisional frame,
    ``cov_rotation`` (3, 3) rad^2 of its scene rotation vector (None: not known)."""

    number: str
    R: np.ndarray
    cov_rotation: np.ndarray | None = None


@dataclass
class Levelling:
    """``world_from_provisional`` (4, 4): the rotation about the origin (the camera) into the levelled frame;
    ``cov_rotation`` (3, 3) rad^2: the levelled frame's error (a scene rotation vector, levelled frame): its tilt,
    and the turn about z that comes with it (y follows the camera's ray projected on the level); the cars used
    and left out; a note."""

    world_from_provisional: np.ndarray
    cov_rotation: np.ndarray
    used: list[str]
    left_out: list[str]
    method: str  # "carriages" | "camera"
    note: str
    facts: dict = field(default_factory=dict)
    # where the photo's GPS and compass placed the levelled scene (the solve stage's): world_from_levelled (4, 4),
    # cov (6, 6), centre_enu (3,), record; None: the scene stays relative
    placement: dict | None = None
    # car number -> (3, 3): how the levelled frame turns (its scene rotation vector) when that car's solved rotation
    # moves (its scene rotation vector), both in the levelled frame; the cars used only (a car's own tilt feeds the
    # frame): :meth:`frame_turn`
    tilt_response: dict[str, np.ndarray] = field(default_factory=dict)
    # (3, 3): how the levelled frame turns when the camera's forward direction (the ray its y follows) moves, both in
    # the levelled frame (a turn about z, mostly); None: not computed
    forward_response: np.ndarray | None = None

    def frame_turn(self, car_turns: dict[str, np.ndarray]) -> np.ndarray:
        """(3, k): the levelled frame's rotation vector (levelled frame) when the cars used turn by ``car_turns``
        (car number -> (3, k), their scene rotation vectors in the levelled frame), to first order: their ups move
        the weighted mean up, and the frame follows (the tilt, and the turn about z it brings). Cars not used, or
        not named, move nothing."""
        k = next((np.shape(v)[1] for v in car_turns.values() if np.ndim(v) == 2), 1)
        out = np.zeros((3, k))
        for number, T in self.tilt_response.items():
            d = car_turns.get(number)
            if d is not None:
                out += T @ np.asarray(d, float).reshape(3, -1)
        return out

    @property
    def sigma_tilt_deg(self) -> list[float]:
        return np.degrees(np.sqrt(np.clip(np.diag(self.cov_rotation)[:2], 0.0, None))).tolist()

    def to_dict(self) -> dict:
        return {"method": self.method, "cars_used": self.used, "cars_left_out": self.left_out,
                "sigma_tilt_deg": self.sigma_tilt_deg, "cov_rotation_rad2": self.cov_rotation.tolist(),
                "world_from_provisional": self.world_from_provisional.tolist(), "note": self.note, **self.facts}


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """(3, 2) an orthonormal basis of the plane normal to ``u``."""
    e = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(u, e)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(u, b1)])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def _upright_set(ups: np.ndarray, camera_up: np.ndarray) -> list[int]:
    """Indices of the largest group of cars whose z axes agree within UPRIGHT_TOL_DEG, among the groups whose
    up is within CAMERA_TILT_MAX_DEG of the camera's (empty: no car stands on its wheels)."""
    best: list[int] = []
    best_spread = math.inf
    for i in range(len(ups)):
        group = [j for j in range(len(ups)) if _angle_deg(ups[i], ups[j]) <= UPRIGHT_TOL_DEG]
        mean = ups[group].sum(axis=0)
        mean /= np.linalg.norm(mean)
        if _angle_deg(mean, camera_up) > CAMERA_TILT_MAX_DEG:
            continue
        spread = float(np.mean([_angle_deg(mean, ups[j]) for j in group]))
        if len(group) > len(best) or (len(group) == len(best) and spread < best_spread):
            best, best_spread = group, spread
    return best


def _frame(up: np.ndarray, camera_forward: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_provisional: ``up`` to +z, then the camera's forward direction turned to +y."""
    R = rotation_between(up, [0.0, 0.0, 1.0])
    f = R @ np.asarray(camera_forward, float)
    yaw = math.atan2(f[0], f[1])  # turning by +yaw about z takes (sin yaw, cos yaw) to +y
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    M = np.eye(4)
    M[:3, :3] = Rz @ R
    return M


def _frame_jacobian(u: np.ndarray, camera_forward: np.ndarray) -> np.ndarray:
    """(3, 2): how a step of the estimated up ``u`` (in :func:`_tangent_basis`) turns the levelled frame, as a
    scene rotation vector in that frame: the tilt itself, and the turn about z it brings, since y follows the
    camera's ray projected on the new level (a numerical derivative; a small rotation's vector is the skew part
    of R)."""
    B = _tangent_basis(u)
    M = _frame(u, camera_forward)
    J = np.zeros((3, 2))
    h = 1e-6
    for k in range(2):
        Mk = _frame(u + h * B[:, k], camera_forward)
        dR = Mk[:3, :3] @ M[:3, :3].T
        J[:, k] = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / h
    return J


def _forward_jacobian(u: np.ndarray, camera_forward: np.ndarray) -> np.ndarray:
    """(3, 3): how the levelled frame turns (a scene rotation vector in that frame) when ``camera_forward`` moves,
    the move expressed in the levelled frame (a numerical derivative, as :func:`_frame_jacobian`)."""
    M = _frame(u, camera_forward)
    J = np.zeros((3, 3))
    h = 1e-6
    for k in range(3):
        dR = _frame(u, np.asarray(camera_forward, float) + h * M[:3, :3].T[:, k])[:3, :3] @ M[:3, :3].T
        J[:, k] = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / h
    return J


def _frame_covariance(u: np.ndarray, camera_forward: np.ndarray, cov_u: np.ndarray) -> np.ndarray:
    """(3, 3) rad^2: the levelled frame's error (:func:`_frame_jacobian`) from an error of the estimated up ``u``
    of covariance ``cov_u`` (2, 2) in :func:`_tangent_basis`."""
    J = _frame_jacobian(u, camera_forward)
    return J @ cov_u @ J.T


def level_from_carriages(cars: list[UprightCar], camera_up: np.ndarray, camera_forward: np.ndarray, *,
                         sigma_car_deg: float = 0.5, sigma_common_deg: float = 0.5) -> Levelling:
    """The levelled frame of a relative scene (module docstring). ``camera_up`` (3,): the reference camera's up
    (-y of the camera) and ``camera_forward`` (3,) its optical axis, both in the provisional frame."""
    cam_up = np.asarray(camera_up, float) / np.linalg.norm(camera_up)
    ups = np.array([np.asarray(c.R, float)[:, 2] for c in cars]) if cars else np.zeros((0, 3))
    idx = _upright_set(ups, cam_up) if len(cars) else []
    s_car, s_common = math.radians(sigma_car_deg), math.radians(sigma_common_deg)
    if not idx:
        cov = _frame_covariance(cam_up, camera_forward, math.radians(CAMERA_LEVEL_SIGMA_DEG) ** 2 * np.eye(2))
        why = ("no solved carriage stands on its wheels" if cars else "no carriage was solved")
        return Levelling(_frame(cam_up, camera_forward), cov, [], [c.number for c in cars], "camera",
                         f"{why}: the scene is levelled as if the photo had been held level (sigma "
                         f"{CAMERA_LEVEL_SIGMA_DEG:g} deg); pitch and roll are only as good as that",
                         forward_response=_forward_jacobian(cam_up, camera_forward))
    u = ups[idx].sum(axis=0)
    u /= np.linalg.norm(u)
    covs = []
    for i in idx:
        ui = ups[i]
        C = s_car ** 2 * (np.eye(3) - np.outer(ui, ui))
        Cr = cars[i].cov_rotation
        if Cr is not None and np.all(np.isfinite(Cr)):
            K = skew(ui)  # d(up) = d_theta x up = -[up]x d_theta
            C = C + K @ np.asarray(Cr, float) @ K.T
        covs.append(C)
    for _ in range(5):  # information-weighted mean on the sphere (Gauss-Newton in the tangent plane)
        B = _tangent_basis(u)
        Ws = [np.linalg.inv(B.T @ C @ B) for C in covs]
        ds = [B.T @ (ups[i] - u) for i in idx]
        info = sum(Ws)
        d = np.linalg.solve(info, sum(W @ di for W, di in zip(Ws, ds)))
        u = u + B @ d
        u /= np.linalg.norm(u)
        if np.linalg.norm(d) < 1e-12:
            break
    B = _tangent_basis(u)
    Ws = [np.linalg.inv(B.T @ C @ B) for C in covs]
    info = sum(Ws)
    cov_u = np.linalg.inv(info)
    M = _frame(u, camera_forward)
    # the mean up's response to each car's turn (d up_i = -[up_i]x d_theta_i, provisional frame), carried to the
    # frame's turn, both in the levelled frame (d_theta_provisional = R^T d_theta_levelled)
    Jf = _frame_jacobian(u, camera_forward)
    response = {cars[i].number: Jf @ cov_u @ W @ B.T @ (-skew(ups[i])) @ M[:3, :3].T for i, W in zip(idx, Ws)}
    ds = [B.T @ (ups[i] - u) for i in idx]
    chi2 = float(sum(di @ W @ di for W, di in zip(Ws, ds)))
    dof = 2 * (len(idx) - 1)
    birge = math.sqrt(chi2 / dof) if dof >= 4 else 1.0
    if birge > 1.0:
        cov_u *= birge ** 2
    cov_u += s_common ** 2 * np.eye(2)
    cov = Jf @ cov_u @ Jf.T
    left = [cars[i].number for i in range(len(cars)) if i not in idx]
    note = (f"levelled from {len(idx)} carriage(s) standing on their wheels ({', '.join(cars[i].number for i in idx)})"
            + (f"; left out as not upright: {', '.join(left)}" if left else ""))
    facts = {"chi2": chi2, "dof": dof, "birge_ratio": birge, "sigma_car_deg": sigma_car_deg,
             "sigma_common_deg": sigma_common_deg,
             "camera_tilt_deg": _angle_deg(u, cam_up)}
    return Levelling(M, 0.5 * (cov + cov.T), [cars[i].number for i in idx], left, "carriages", note, facts,
                     tilt_response=response, forward_response=_forward_jacobian(u, camera_forward))


def add_levelling_uncertainty(res: Any, lev: Levelling) -> list[str]:
    """Add the levelling's error to every carriage's covariance, in place, where the scene stays in the levelled
    frame (the camera at the origin), and return the numbers of the carriages changed.

    A carriage's error in the levelled frame is its fit's plus the frame's turn about the camera, ``e_i = d_i +
    A_i d_phi`` (:func:`~workbench.solve.camera_term.camera_pose_jacobian`), and the frame's turn comes partly from
    the same fit: ``d_phi = sum_j T_j d_theta_j + d_common`` (``T_j`` the :attr:`Levelling.tilt_response` of the
    cars used, ``d_common`` the track's tilt, the cars' own and any Birge excess). So beside ``A_i C_phi A_i^T``
    (``lev.cov_rotation``, which counts the cars used as independent) the fit's correlations enter: between the
    cars used (``T_j C_jk T_k^T``, j != k) and between a car and the frame its own tilt feeds (``A_i sum_j T_j
    C_ji`` and its transpose); ``C`` is the fit's joint covariance (``res.covariance``). Where a car's tilt feeds
    the frame its levelled tilt is the difference of the two: roll's sigma about 6 % (up to 15 %) below the
    independent sum with three cars, the track's 0.5 deg as the common term."""
    C = np.asarray(res.covariance, float) if res.covariance is not None else None
    order = {name: i for i, name in enumerate(res.covariance_order or [])}
    col = {c.number: order.get(f"{c.number}.omega_x") for c in res.carriages}
    used = [n for n in lev.tilt_response if C is not None and col.get(n) is not None]
    cov_frame = np.asarray(lev.cov_rotation, float).copy()
    for j in used:
        for k in used:
            if j != k:
                cov_frame += lev.tilt_response[j] @ C[col[j]:col[j] + 3, col[k]:col[k] + 3] @ lev.tilt_response[k].T
    extra = {}
    for c in res.carriages:
        if c.world_from_carriage is None:
            continue
        A = camera_pose_jacobian(np.asarray(c.world_from_carriage, float), np.zeros(3))[:, :3]
        X = A @ cov_frame @ A.T
        i = col.get(c.number)
        if i is not None and used:
            K = A @ sum(lev.tilt_response[j] @ C[col[j]:col[j] + 3, i:i + 6] for j in used)  # (6, 6)
            X = X + K + K.T
        extra[c.number] = X
    return list(add_pose_covariance(res, extra))
