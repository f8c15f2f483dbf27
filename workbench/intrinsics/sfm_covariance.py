"""The SfM poses' own uncertainty after bundle adjustment, to first order, as a shared factor per model.

Bundle adjustment's information on the photos' poses, the shared cameras' intrinsics it refined and the 3-D points
is ``J^T J / sigma^2`` (``J`` the reprojection Jacobian of every observation, ``sigma`` the pixel error estimated
from the adjustment's own residuals with its degrees of freedom). The points are eliminated (Schur complement),
leaving the reduced information ``S`` on the poses and intrinsics. ``S`` is singular along the model's 7-dof
similarity (the gauge: the model has no scale, position or orientation of its own), so a covariance of the poses
exists only in a chosen gauge. The one chosen here is **the camera centres' own similarity**: of every pose error
the similarity that best fits the centres' errors (least squares) is taken out (the S-transformation
``P = I - G (G^T W G)^-1 G^T W``, ``G`` the similarity's motion of the poses, ``W`` selecting the centres), so
what is stated is the error of the poses relative to one another, as the georef stage's similarity leaves it when
it fits the model to the control points (that similarity absorbs a common motion of the model; what it absorbs
exactly depends on where the control points lie: taking it as the centres' similarity is the first-order
approximation, right when the control points are spread as the photos' view of the scene).

The pose error of view ``v`` is parametrised as in ``georegistration.pose_uncertainty`` (docs/formats.md), but in
the model frame: the rotation vector of ``model_from_cam`` applied on the left (rad, model frame), then the
centre's error (model units). The joint covariance of the model's views (``6 N x 6 N``, rank ``6 N - 7`` at most)
is written as a factor ``L`` (``6 N x r``: ``C = L L^T``), each view's 6 rows of it as its ``pose_factor``: the
views' errors are ``F_v z`` with one ``z ~ N(0, I_r)`` shared by the model's views, which keeps their correlation
(views of one model are not independent: a scale drift moves them together). The factor keeps the ``r`` largest
eigen-directions (all of them up to ``max_rank``) and states the share of the trace it keeps.

The Jacobian is by central differences, per parameter kind for all observations at once (each observation
depends on one pose, one point and its camera's intrinsics). References: Triggs et al., "Bundle adjustment: a
modern synthesis" (2000), section 9 (gauge freedom, S-transformations); Förstner & Wrobel, "Photogrammetric
Computer Vision" (2016), section 4.5.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_so3, skew

log = logging.getLogger(__name__)

__all__ = ["SfmPoseCovariance", "pose_covariance", "intrinsic_parameters"]

PARAMETRISATION = ("each view's error: [rotation vector of model_from_cam (rad, model frame, applied on the left), "
                   "centre (model units)] = pose_factor @ z, z ~ N(0, I_r) shared by the model's views; gauge: the "
                   "camera centres' own least-squares similarity taken out")


@dataclass
class SfmPoseCovariance:
    """A model's pose covariance: ``factor[name]`` (6, r) per view (``C_v = F_v F_v^T``; the model's views share
    ``z``), ``intrinsics_factor[name]`` (len(params), r): the rows of the view's camera's refined intrinsics
    (``params``, in :class:`CameraIntrinsics` units: pixels for ``f``, ``fx``, ``fy``, ``cx``, ``cy``) in the same
    factor, so that a pose error and the intrinsics error that comes with it (a focal error compensated by a
    shift along the optical axis) stay together; empty when no intrinsics were refined; and the figures of the
    estimate (``stats``)."""

    factor: dict[str, np.ndarray]
    stats: dict = field(default_factory=dict)
    intrinsics_factor: dict[str, np.ndarray] = field(default_factory=dict)
    params: tuple[str, ...] = ()

    def marginal(self, name: str) -> np.ndarray:
        """(6, 6) covariance of one view's pose error."""
        F = self.factor[name]
        return F @ F.T


def intrinsic_parameters(model: str, refine_focal: bool, refine_principal_point: bool,
                         refine_extra: bool) -> list[str]:
    """The intrinsics bundle adjustment refined, as the fields of :class:`CameraIntrinsics` they move (``f`` moves
    ``fx`` and ``fy`` together: COLMAP's single-focal models)."""
    focal = {"SIMPLE_PINHOLE": ["f"], "SIMPLE_RADIAL": ["f"], "RADIAL": ["f"]}.get(model, ["fx", "fy"])
    extra = {"SIMPLE_RADIAL": ["k1"], "RADIAL": ["k1", "k2"], "OPENCV": ["k1", "k2", "p1", "p2"]}.get(model, [])
    return (focal if refine_focal else []) + (["cx", "cy"] if refine_principal_point else []) + \
        (extra if refine_extra else [])


def _moved(intr: CameraIntrinsics, name: str, h: float) -> CameraIntrinsics:
    return intr.moved((name,), np.array([h]))


def _project(R: np.ndarray, c: np.ndarray, X: np.ndarray, cam_of: np.ndarray,
             intr: list[CameraIntrinsics]) -> np.ndarray:
    """Pixels (n, 2) of points ``X`` (n, 3) seen by cameras of rotations ``R`` (n, 3, 3: cam_from_model) and centres
    ``c`` (n, 3), each observation with its intrinsics ``intr[cam_of[i]]``."""
    q = np.einsum("nij,nj->ni", R, X - c)
    out = np.empty((len(q), 2))
    for k, K in enumerate(intr):
        m = cam_of == k
        if m.any():
            out[m] = K.project(q[m])
    return out


def _jacobians(R: np.ndarray, c: np.ndarray, X: np.ndarray, cam_of: np.ndarray, intr: list[CameraIntrinsics],
               params: list[str], scale: float):
    """Per observation: d(pixel)/d(pose) (n, 2, 6), d(pixel)/d(point) (n, 2, 3) and d(pixel)/d(its camera's
    intrinsics) (n, 2, len(params)), by central differences."""
    n = len(X)
    Jc, Jp, Jk = np.zeros((n, 2, 6)), np.zeros((n, 2, 3)), np.zeros((n, 2, len(params)))
    hr, ht = 1e-6, 1e-6 * scale
    for j in range(3):
        e = np.zeros(3)
        e[j] = hr
        # a rotation on the left of model_from_cam = R^T: R' = R Exp(-e)
        up, dn = R @ exp_so3(-e), R @ exp_so3(e)
        Jc[:, :, j] = (_project(up, c, X, cam_of, intr) - _project(dn, c, X, cam_of, intr)) / (2 * hr)
        e = np.zeros(3)
        e[j] = ht
        Jc[:, :, 3 + j] = (_project(R, c + e, X, cam_of, intr) - _project(R, c - e, X, cam_of, intr)) / (2 * ht)
        Jp[:, :, j] = (_project(R, c, X + e, cam_of, intr) - _project(R, c, X - e, cam_of, intr)) / (2 * ht)
    for j, name in enumerate(params):
        ref = abs(getattr(intr[0], "fx" if name == "f" else name))
        h = 1e-6 * max(ref, 1.0) if name in ("f", "fx", "fy", "cx", "cy") else 1e-6
        up = [_moved(K, name, h) for K in intr]
        dn = [_moved(K, name, -h) for K in intr]
        Jk[:, :, j] = (_project(R, c, X, cam_of, up) - _project(R, c, X, cam_of, dn)) / (2 * h)
    return Jc, Jp, Jk


def _reduced_information(Jc, Jp, Jk, img, pt, cam_of, n_img: int, n_pt: int, n_cam: int):
    """The information on (poses, intrinsics) with the points eliminated (Schur complement), unit pixel sigma:
    (D, D) dense, D = 6 n_img + n_cam n_k."""
    n, nk = len(img), Jk.shape[2]
    D = 6 * n_img + n_cam * nk
    cols_c = np.concatenate([6 * img[:, None] + np.arange(6), 6 * n_img + nk * cam_of[:, None] + np.arange(nk)],
                            axis=1)  # (n, 6 + nk)
    A = np.concatenate([Jc, Jk], axis=2)  # (n, 2, 6 + nk)
    rows = 2 * np.arange(n)[:, None] + np.arange(2)
    Ac = sp.csr_matrix((A.reshape(-1), (np.repeat(rows.reshape(-1), A.shape[2]),
                                        np.tile(cols_c, (1, 2)).reshape(-1))), shape=(2 * n, D))
    Bp = sp.csr_matrix((Jp.reshape(-1), (np.repeat(rows.reshape(-1), 3),
                                         np.tile(3 * pt[:, None] + np.arange(3), (1, 2)).reshape(-1))),
                       shape=(2 * n, 3 * n_pt))
    Hcc = (Ac.T @ Ac).toarray()
    Hcp = (Ac.T @ Bp).tocsr()
    blocks = np.zeros((n_pt, 3, 3))
    np.add.at(blocks, pt, np.einsum("nai,naj->nij", Jp, Jp))
    inv = np.linalg.inv(blocks + 1e-12 * np.trace(blocks, axis1=1, axis2=2)[:, None, None] * np.eye(3))
    bi = np.repeat(3 * np.arange(n_pt), 9) + np.tile(np.repeat(np.arange(3), 3), n_pt)
    bj = np.repeat(3 * np.arange(n_pt), 9) + np.tile(np.tile(np.arange(3), 3), n_pt)
    Hpp_inv = sp.csr_matrix((inv.reshape(-1), (bi, bj)), shape=(3 * n_pt, 3 * n_pt))
    Y = Hcp @ Hpp_inv
    S = Hcc - (Y @ Hcp.T).toarray()
    return 0.5 * (S + S.T)


def _gauge(centres: np.ndarray, D: int) -> tuple[np.ndarray, np.ndarray]:
    """The similarity's motion of the poses ``G`` (D, 7: log scale, rotation, translation about the model origin)
    and the weights ``W`` (D,) selecting the centres (1) over the rotations and intrinsics (0)."""
    G = np.zeros((D, 7))
    W = np.zeros(D)
    for i, c in enumerate(centres):
        G[6 * i:6 * i + 3, 1:4] = np.eye(3)
        G[6 * i + 3:6 * i + 6, 0] = c
        G[6 * i + 3:6 * i + 6, 1:4] = -skew(c)
        G[6 * i + 3:6 * i + 6, 4:7] = np.eye(3)
        W[6 * i + 3:6 * i + 6] = 1.0
    return G, W


def _held_variances(params: list[str], prior_sd: dict[str, float], n_img: int, n_cam: int) -> dict[int, float]:
    """The held parameters' indices in the (poses, intrinsics) vector and their priors' variances."""
    return {6 * n_img + len(params) * k + j: prior_sd[name] ** 2
            for j, name in enumerate(params) if name in prior_sd for k in range(n_cam)}


def _generalised_inverse(S: np.ndarray, G: np.ndarray, held: dict[int, float]) -> np.ndarray:
    """A generalised inverse of the reduced information ``S`` (D, D; its null space the gauge ``G``), with the
    ``held`` parameters (index -> variance) as *consider* parameters: the adjustment did not estimate them (they
    were held at a prior), so the data do not narrow them; their error ``d`` moves the estimated rest by
    ``B d``, ``B = -S_aa^+ S_ah`` (the estimate's response), and the covariance is ``[[C_aa + B V B^T, B V],
    [V B^T, V]]`` with ``C_aa = S_aa^+`` (the rest's, the held ones exact) and ``V`` the priors' variances."""
    D = len(S)
    h = np.array(sorted(held), dtype=int)
    a = np.setdiff1d(np.arange(D), h)
    Ga = G[a]
    alpha = float(np.trace(S[np.ix_(a, a)])) / len(a) / max(float(np.mean(np.sum(Ga * Ga, axis=0))), 1e-300)
    Xa = np.linalg.inv(S[np.ix_(a, a)] + alpha * Ga @ Ga.T)  # S_aa's null space is the gauge (G's rows of h are 0)
    if not len(h):
        return Xa
    V = np.diag([held[i] for i in h])
    B = -Xa @ S[np.ix_(a, h)]
    X = np.zeros((D, D))
    X[np.ix_(a, a)] = Xa + B @ V @ B.T
    X[np.ix_(a, h)] = B @ V
    X[np.ix_(h, a)] = (B @ V).T
    X[np.ix_(h, h)] = V
    return X


def pose_covariance(names: list[str], cam_from_model: np.ndarray, camera_index: np.ndarray,
                    intrinsics: list[CameraIntrinsics], obs_image: np.ndarray, obs_point: np.ndarray,
                    obs_uv: np.ndarray, points: np.ndarray, params: list[str], max_rank: int = 96,
                    prior_sd: dict[str, float] | None = None) -> SfmPoseCovariance:
    """The covariance of an SfM model's poses (module docstring).

    ``names`` (N,) and ``cam_from_model`` (N, 4, 4) of its views, ``camera_index`` (N,): each view's camera in
    ``intrinsics`` (pixel convention of docs/conventions.md); observations: view index ``obs_image`` (n,), point
    index ``obs_point`` (n,), pixel ``obs_uv`` (n, 2); ``points`` (P, 3) model frame; ``params``: the intrinsics
    the adjustment refined (:func:`intrinsic_parameters`), taken as unknowns too (their error moves the poses);
    ``prior_sd``: those of ``params`` the adjustment held at a prior value that is itself uncertain (a focal held
    at the EXIF's, ``{"f": sigma_px}``), each with that prior's 1-sigma, taken as *consider* parameters
    (:func:`_generalised_inverse`): the held value's error, and the pose error it causes, are in the covariance (a
    held parameter with no stated sigma is left out of ``params``: taken as exact).
    Raises ValueError when the observations cannot fix the poses."""
    t0 = time.perf_counter()
    M = np.asarray(cam_from_model, float)
    n_img, n_pt, n_cam = len(names), len(points), len(intrinsics)
    img, pt = np.asarray(obs_image, int), np.asarray(obs_point, int)
    if len(img) < 10 or n_img < 2:
        raise ValueError(f"{len(img)} observations in {n_img} views: too few for a pose covariance")
    centres = np.einsum("nji,nj->ni", M[:, :3, :3], -M[:, :3, 3])
    scale = float(np.median(np.linalg.norm(centres - np.median(centres, axis=0), axis=1))) or 1.0
    cam_of = np.asarray(camera_index, int)[img]
    R, c = M[img, :3, :3], centres[img]
    X = np.asarray(points, float)[pt]
    r = (_project(R, c, X, cam_of, intrinsics) - np.asarray(obs_uv, float)).reshape(-1)
    Jc, Jp, Jk = _jacobians(R, c, X, cam_of, intrinsics, params, scale)
    D = 6 * n_img + n_cam * len(params)
    prior_sd = {k: float(v) for k, v in (prior_sd or {}).items() if k in params}
    if any(not (np.isfinite(v) and v > 0) for v in prior_sd.values()):
        raise ValueError(f"a prior's sigma must be finite and positive: {prior_sd}")
    dof = len(r) - (3 * n_pt + D - len(prior_sd) * n_cam - 7)  # a held parameter was not fitted
    if dof <= 0 or not np.all(np.isfinite(r)):
        raise ValueError(f"{len(r)} residuals for {len(r) - dof} free parameters: no pose covariance")
    sigma = float(np.sqrt(np.sum(r * r) / dof))
    S = _reduced_information(Jc, Jp, Jk, img, pt, cam_of, n_img, n_pt, n_cam) / sigma ** 2
    G, W = _gauge(centres, D)
    X_g = _generalised_inverse(S, G, _held_variances(params, prior_sd, n_img, n_cam))
    P = np.eye(D) - G @ np.linalg.solve(G.T @ (W[:, None] * G), (G * W[:, None]).T)
    C = P @ X_g @ P.T
    C = 0.5 * (C + C.T)
    if not np.all(np.isfinite(C)):  # a degenerate model (e.g. two views and a focal run off): no covariance to state
        raise ValueError(f"the {n_img} views' observations do not fix their poses (the covariance is not finite)")
    Cp = C[:6 * n_img, :6 * n_img]
    # the factor of the poses and the intrinsics together (the intrinsics rows scaled to be comparable with the
    # poses' for the truncation, then scaled back): L L^T = C up to the directions left out
    nk = len(params)
    u = np.ones(D)
    if nk:
        k_scale = np.sqrt(np.clip(np.diag(C)[6 * n_img:], 1e-300, None))
        p_scale = float(np.sqrt(max(np.mean(np.diag(Cp)), 1e-300)))
        u[6 * n_img:] = k_scale / p_scale
    ev, V = np.linalg.eigh(C / np.outer(u, u))
    order = np.argsort(ev)[::-1]
    ev, V = np.clip(ev[order], 0.0, None), V[:, order]
    keep = min(max_rank, int(np.sum(ev > 1e-12 * max(ev[0], 1e-300))))
    L = (V[:, :keep] * np.sqrt(ev[:keep])) * u[:, None]
    factor = {n: L[6 * i:6 * i + 6] for i, n in enumerate(names)}
    cam_idx = np.asarray(camera_index, int)
    k_factor = {n: L[6 * n_img + nk * cam_idx[i]:6 * n_img + nk * (cam_idx[i] + 1)] for i, n in enumerate(names)} \
        if nk else {}
    sd = np.sqrt(np.clip(np.diag(Cp), 0.0, None)).reshape(n_img, 6)
    k_sd = np.sqrt(np.clip(np.diag(C)[6 * n_img:], 0.0, None))
    stats = {"parametrisation": PARAMETRISATION, "rank": keep,
             "trace_share_kept": float(np.sum(ev[:keep]) / max(float(np.sum(ev)), 1e-300)),
             "sigma_px": sigma, "n_observations": int(len(img)), "n_points": int(n_pt), "dof": int(dof),
             "intrinsics_refined": [p for p in params if p not in prior_sd],
             "intrinsics_held_uncertain": prior_sd,
             "sigma_intrinsics": {f"{p}[{k}]" if n_cam > 1 else p: float(k_sd[k * len(params) + j])
                                  for k in range(n_cam) for j, p in enumerate(params)},
             "max_sigma_rotation_deg": float(np.degrees(sd[:, :3].max())),
             "max_sigma_centre_model": float(sd[:, 3:].max()), "time_s": round(time.perf_counter() - t0, 3)}
    log.info("sfm: pose covariance of %d views from %d observations (sigma %.2f px): up to %.3f deg, %.4f model units",
             n_img, len(img), sigma, stats["max_sigma_rotation_deg"], stats["max_sigma_centre_model"])
    return SfmPoseCovariance(factor, stats, k_factor, tuple(params))


def reconstruction_pose_covariance(rec, names_by_id: dict[int, str], intrinsics_of, params: list[str],
                                   max_rank: int = 96, prior_sd: dict[str, float] | None = None
                                   ) -> SfmPoseCovariance:
    """:func:`pose_covariance` of a pycolmap ``Reconstruction``'s registered images (``names_by_id``: image id ->
    view name), every observation of a 3-D point (COLMAP's pixels moved to docs/conventions.md's by -0.5), the
    cameras' intrinsics from ``intrinsics_of(camera)``."""
    ids = sorted(names_by_id)
    cam_ids = sorted({rec.image(i).camera_id for i in ids})
    cam_index = {c: k for k, c in enumerate(cam_ids)}
    M = np.zeros((len(ids), 4, 4))
    for k, i in enumerate(ids):
        M[k, :3, :] = np.asarray(rec.image(i).cam_from_world().matrix())
        M[k, 3, 3] = 1.0
    pos = {i: k for k, i in enumerate(ids)}
    pids = sorted(rec.point3D_ids())
    pidx = {p: k for k, p in enumerate(pids)}
    img, pt, uv = [], [], []
    for i in ids:
        im = rec.image(i)
        for p2 in im.points2D:
            if p2.has_point3D() and p2.point3D_id in pidx:
                img.append(pos[i])
                pt.append(pidx[p2.point3D_id])
                uv.append(np.asarray(p2.xy, float) - 0.5)
    X = np.array([rec.point3D(p).xyz for p in pids], float).reshape(-1, 3)
    return pose_covariance([names_by_id[i] for i in ids], M,
                           np.array([cam_index[rec.image(i).camera_id] for i in ids]),
                           [intrinsics_of(rec.camera(c)) for c in cam_ids], np.asarray(img), np.asarray(pt),
                           np.asarray(uv).reshape(-1, 2), X, params, max_rank, prior_sd)
