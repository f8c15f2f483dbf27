"""The chain parametrisation: a step's parameter vector ``x`` and the poses it stands for.

Per chain the parameters are the first carriage's translation, every carriage's rotation increment (when the
step frees rotations) and every link's coupler offset, so that each follower's translation is eliminated
through the chain and the bound ``|T| <= slack`` holds exactly (``docs/solver.md``, "Parametrisation").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.geometry import exp_so3, left_jacobian_so3, skew
from .loss import robust_half_cost
from .model import SolveOptions
from .problem import SQRT5, Car, Chains, Poses, Problem
from .terrain import Contact

_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def sphere_basis(d: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector d."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(d, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(d, b1)])


@dataclass
class Unpacked:
    """The poses at a parameter vector, each link's offset, and (when asked) the derivatives: ``D`` car -> d t /
    d chain params (3, size of its chain), ``Jl`` (N, 3, 3) the left Jacobians of the rotation increments."""

    poses: Poses
    links: list[list[np.ndarray]]
    D: dict[int, np.ndarray]
    Jl: np.ndarray | None


class ChainLayout:
    """Maps the parameter vector of a step to poses (and focal) with d t / d params per carriage.

    Per chain: the first carriage's translation (3), the rotation increments (3 per carriage, when free),
    and per link either ``"free"`` (the offset T itself, 3 parameters; the active-set driver keeps it inside
    the ball) or ``"sphere"`` (the constraint active: ``T = s Exp_d0(B a)``, 2 parameters, exactly on the
    sphere |T| = s). Then the log-focal of each focal group.
    """

    def __init__(self, chains: Chains, rot_free: bool, focal_views: list[list[int]], cars: list[Car], ref: Poses,
                 modes: list[list[str]] | None = None, prior_px: float = 1.0):
        self.chains, self.slacks, self.rot_free = chains.members, chains.slacks, rot_free
        self.prior_px = float(prior_px)  # the configured pixel sigma: coupler prior rows are T * prior_px / sigma_T
        self.focal_views = list(focal_views)
        self.cars = cars
        self.R_ref, self.f_ref = ref.R.copy(), ref.f.copy()
        self.modes = modes if modes is not None else [["free"] * (len(ch) - 1) for ch in self.chains]
        self._place_parameters(ref.t)
        self._index_links()

    def _place_parameters(self, t_ref: np.ndarray) -> None:
        """Offsets of each chain's and link's parameters, and the start ``x0`` (the reference poses)."""
        R_ref, cars = self.R_ref, self.cars
        self.off, self.size, self.link_off, self.sphere = [], [], [], []
        n = 0
        x0 = []
        for c, ch in enumerate(self.chains):
            self.off.append(n)
            m = 3 + (3 * len(ch) if self.rot_free else 0)
            x0.append(t_ref[ch[0]])
            if self.rot_free:
                x0.append(np.zeros(3 * len(ch)))
            lo, sph = [], []
            for j in range(len(ch) - 1):
                a, b = cars[ch[j]], cars[ch[j + 1]]
                T = (t_ref[ch[j + 1]] + R_ref[ch[j + 1]] @ b.c_front) - (t_ref[ch[j]] + R_ref[ch[j]] @ a.c_rear)
                lo.append(m)
                if self.modes[c][j] == "sphere":
                    nT = float(np.linalg.norm(T))
                    d0 = T / nT if nT > 0 else np.array([1.0, 0.0, 0.0])
                    sph.append((d0, sphere_basis(d0)))
                    x0.append(np.zeros(2))
                    m += 2
                else:
                    sph.append(None)
                    x0.append(T)
                    m += 3
            self.link_off.append(lo)
            self.sphere.append(sph)
            self.size.append(m)
            n += m
        self.f_off = n
        n += len(self.focal_views)
        x0.append(np.zeros(len(self.focal_views)))
        self.n = n
        self.x0 = np.concatenate([np.asarray(v, float).reshape(-1) for v in x0]) if x0 else np.zeros(0)

    def _index_links(self) -> None:
        """Index arrays over every link of every chain, in chain order (unpack works on all links at once)."""
        chains, slacks, cars = self.chains, self.slacks, self.cars
        self.chain_of = {}
        for c, ch in enumerate(chains):
            for j, k in enumerate(ch):
                self.chain_of[k] = (c, j)
        self.rot_cars = [k for ch in chains for k in ch] if self.rot_free else []
        self.rot_idx = np.array([self.off[c] + 3 + 3 * j + i for c, ch in enumerate(chains) for j in range(len(ch))
                                 for i in range(3)], dtype=int) if self.rot_free else np.zeros(0, int)
        links = [(c, j) for c, ch in enumerate(chains) for j in range(len(ch) - 1)]
        self._link_a = np.array([chains[c][j] for c, j in links], dtype=int)  # front carriage of the link
        self._link_b = np.array([chains[c][j + 1] for c, j in links], dtype=int)  # rear carriage
        self._c_rear = np.array([cars[chains[c][j]].c_rear for c, j in links], dtype=float).reshape(-1, 3)
        self._c_front = np.array([cars[chains[c][j + 1]].c_front for c, j in links], dtype=float).reshape(-1, 3)
        self.link_col = [self.off[c] + self.link_off[c][j] for c, j in links]  # first column of its parameters
        is_sph = np.array([self.sphere[c][j] is not None for c, j in links], dtype=bool)
        self._free = np.nonzero(~is_sph)[0]
        self._free_cols = np.array([self.link_col[i] for i in self._free], dtype=int).reshape(-1, 1) + np.arange(3)
        self._sph = np.nonzero(is_sph)[0]
        self._sph_cols = np.array([self.link_col[i] for i in self._sph], dtype=int).reshape(-1, 1) + np.arange(2)
        self._sph_d0 = np.array([self.sphere[c][j][0] for c, j in (links[i] for i in self._sph)]).reshape(-1, 3)
        self._sph_B = np.array([self.sphere[c][j][1] for c, j in (links[i] for i in self._sph)]).reshape(-1, 3, 2)
        self._sph_s = np.array([slacks[c][j] for c, j in (links[i] for i in self._sph)], dtype=float)
        self.link_sph = is_sph
        self.link_w = np.where(is_sph, 2, 3)  # parameters per link
        # coupler prior rows: T * prior_px / sigma_T, sigma_T = slack / sqrt 5
        self.link_scale = np.array([self.prior_px * SQRT5 / slacks[c][j] for c, j in links], dtype=float)
        self._chain_links = np.cumsum([0] + [len(ch) - 1 for ch in chains])  # chain c: links [c_, c_ + 1)

    def _link_offsets(self, x: np.ndarray) -> list[np.ndarray]:
        """Sets ``self.T`` (L, 3) and ``self.GT_pad`` (L, 3, 3) (d T / d link params, a sphere link's third
        column zero) of every link; returns d T / d link params per link (3, 3 or 2)."""
        nl = len(self._link_a)
        T = np.empty((nl, 3))
        GT: list[np.ndarray] = [_EYE3] * nl
        GT_pad = np.zeros((nl, 3, 3))
        GT_pad[self._free] = _EYE3
        T[self._free] = x[self._free_cols]
        if len(self._sph):
            # exponential chart of the sphere at d0 (covers every direction): T = s (cos|v| d0 + sinc|v| v), v = B a
            d0, B, s = self._sph_d0, self._sph_B, self._sph_s
            v = np.einsum("nij,nj->ni", B, x[self._sph_cols])
            th = np.linalg.norm(v, axis=1)
            small = th < 1e-6
            ths = np.where(small, 1.0, th)
            c1 = np.where(small, 1.0 - th * th / 6.0, np.sin(ths) / ths)
            c2 = np.where(small, -1.0 / 3.0 + th * th / 30.0, (ths * np.cos(ths) - np.sin(ths)) / ths**3)
            T[self._sph] = s[:, None] * (np.cos(th)[:, None] * d0 + c1[:, None] * v)
            G = (c1[:, None, None] * (_EYE3 - d0[:, :, None] * v[:, None, :]) + c2[:, None, None] * v[:, :, None]
                 * v[:, None, :]) @ B * s[:, None, None]
            GT_pad[self._sph, :, :2] = G
            for i, g in zip(self._sph, G):
                GT[i] = g
        self.T, self.GT_pad = T, GT_pad
        return GT

    def unpack(self, x: np.ndarray, with_derivs: bool | str = True) -> Unpacked:
        """Poses, focal, offsets at ``x``. ``with_derivs``: True also the dense chain derivatives ``D`` (O(N^2)
        for a long chain) and the left Jacobians; ``"local"`` only the left Jacobians (what the structured
        solver needs); False neither. Also sets ``self.GT[c][j] = (column, d T / d link params)``, ``self.T``
        and ``self.GT_pad`` (see :meth:`_link_offsets`)."""
        R = self.R_ref.copy()
        t = np.zeros((len(self.cars), 3))
        D: dict[int, np.ndarray] = {}  # car -> (3, size_c): d t / d chain params
        Jl = np.tile(_EYE3, (len(self.cars), 1, 1)) if with_derivs else None
        if self.rot_free and self.rot_cars:  # all rotations at once
            dl = x[self.rot_idx].reshape(-1, 3)
            R[self.rot_cars] = exp_so3(dl) @ self.R_ref[self.rot_cars]
            if with_derivs:
                Jl[self.rot_cars] = left_jacobian_so3(dl)
        GT = self._link_offsets(x)
        T = self.T
        ra = np.einsum("nij,nj->ni", R[self._link_a], self._c_rear)
        rb = np.einsum("nij,nj->ni", R[self._link_b], self._c_front)
        step = ra + T - rb  # t_b - t_a of every link
        T_links: list[list[np.ndarray]] = []
        self.GT = []
        for c, ch in enumerate(self.chains):
            o = self.off[c]
            l0, l1 = self._chain_links[c], self._chain_links[c + 1]
            t[ch[0]] = x[o:o + 3]
            if l1 > l0:
                t[ch[1:]] = x[o:o + 3] + np.cumsum(step[l0:l1], axis=0)
            T_links.append(list(T[l0:l1]))
            self.GT.append([(self.link_col[i], GT[i]) for i in range(l0, l1)])
            if with_derivs is True:
                self._chain_derivatives(c, GT, ra, rb, Jl, D)
        f = self.f_ref.copy()
        for i, grp in enumerate(self.focal_views):
            for v_ in grp:
                f[v_] = self.f_ref[v_] * math.exp(x[self.f_off + i])
        return Unpacked(Poses(R, t, f), T_links, D, Jl)

    def _chain_derivatives(self, c: int, GT: list[np.ndarray], ra: np.ndarray, rb: np.ndarray, Jl: np.ndarray,
                           D: dict[int, np.ndarray]) -> None:
        """d t / d chain params of every carriage of chain ``c`` into ``D`` (a link or rotation moves every
        carriage behind it)."""
        ch = self.chains[c]
        l0 = self._chain_links[c]
        Dk = np.zeros((3, self.size[c]))
        Dk[:, 0:3] = _EYE3
        D[ch[0]] = Dk
        for j in range(len(ch) - 1):
            i = l0 + j
            lo = self.link_off[c][j]
            Dk = Dk.copy()
            Dk[:, lo:lo + GT[i].shape[1]] += GT[i]
            if self.rot_free:
                ja = 3 + 3 * j
                Dk[:, ja:ja + 3] += -skew(ra[i]) @ Jl[ch[j]]
                Dk[:, ja + 3:ja + 6] += skew(rb[i]) @ Jl[ch[j + 1]]
            D[ch[j + 1]] = Dk

    def poses(self, x: np.ndarray) -> Poses:
        """The poses and focal at ``x``."""
        return self.unpack(x, with_derivs=False).poses


def residuals_and_jacobian(prob: Problem, lay: ChainLayout, x: np.ndarray, contact: Contact | None, jac: bool):
    """The stacked residuals (weighted pixels, contact rows, coupler prior rows) at ``x`` and, with ``jac``, their
    dense Jacobian in ``x`` (used by the active set's multiplier test and for costs, not by the solver)."""
    up = lay.unpack(x, with_derivs=True)
    R, t, f, D, Jl = up.poses.R, up.poses.t, up.poses.f, up.D, up.Jl
    uv, Xw, JX, Jf = prob.project(R, t, f, jac=jac)
    w = prob.w
    r = ((uv - prob.uv) * w[:, None]).reshape(-1)
    cars_c = contact.cars if contact is not None else []
    rc = np.zeros(len(cars_c))
    if cars_c:
        rc, a_c, q_c, on_c = contact.rows(R[cars_c], t[cars_c])
    T_all = [(c, j, T) for c, Tl in enumerate(up.links) for j, T in enumerate(Tl)]
    rp = np.concatenate([T * (lay.prior_px * SQRT5 / lay.slacks[c][j]) for c, j, T in T_all]) if T_all else np.zeros(0)
    res = np.concatenate([r, rc, rp])
    if not jac:
        return res, None
    M = len(prob.P)
    J = np.zeros((2 * M + len(cars_c) + len(rp), lay.n))
    row0 = 2 * M + len(cars_c)
    for i, (c, j, T) in enumerate(T_all):
        col, GT = lay.GT[c][j]
        J[row0 + 3 * i:row0 + 3 * i + 3, col:col + GT.shape[1]] = GT * (lay.prior_px * SQRT5 / lay.slacks[c][j])
    JXw = JX * w[:, None, None]
    for k in prob.active:
        c, j = lay.chain_of[k]
        o, m = lay.off[c], lay.size[c]
        idx = prob.by_car[k]
        rows = np.concatenate([2 * idx, 2 * idx + 1])
        Jk = np.concatenate([JXw[idx, 0, :], JXw[idx, 1, :]], axis=0)  # (2n, 3)
        J[rows, o:o + m] = Jk @ D[k]
        if lay.rot_free:
            q = prob.P[idx] @ R[k].T  # R p
            Jr = -np.einsum("nab,nbc->nac", JXw[idx], skew(q)) @ Jl[k]  # (n, 2, 3)
            ro = o + 3 + 3 * j
            J[rows, ro:ro + 3] += np.concatenate([Jr[:, 0, :], Jr[:, 1, :]], axis=0)
    for i, grp in enumerate(lay.focal_views):
        idx = prob.rows_of_views(grp)
        col = lay.f_off + i
        J[2 * idx, col] = Jf[idx, 0] * w[idx] * f[prob.view[idx]]
        J[2 * idx + 1, col] = Jf[idx, 1] * w[idx] * f[prob.view[idx]]
    for i, k in enumerate(cars_c):
        if not on_c[i]:
            continue
        a, q = a_c[i], q_c[i]  # d residual / d X, R s
        c, j = lay.chain_of[k]
        o, m = lay.off[c], lay.size[c]
        row = 2 * M + i
        J[row, o:o + m] = a @ D[k]
        if lay.rot_free:
            ro = o + 3 + 3 * j
            J[row, ro:ro + 3] += -(a @ skew(q)) @ Jl[k]
    return res, J


def full_cost(prob: Problem, cars: list[Car], chains: Chains, poses: Poses, contact: Contact | None,
              options: SolveOptions) -> float:
    """The cost step 4 minimises (pixels, coupler prior, terrain contact, robust loss) at ``poses``."""
    lay = ChainLayout(chains, True, [], cars, poses, None, options.pixel_sigma_px)
    r, _ = residuals_and_jacobian(prob, lay, lay.x0, contact, False)
    if options.robust_loss == "linear":
        return float(0.5 * np.sum(r**2))
    # the robust cost here is half the one the solver minimises (kept as it was: only compared with itself)
    return float(0.5 * np.sum(robust_half_cost(r, options.robust_loss, options.loss_scale_px)))
