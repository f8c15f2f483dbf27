"""The trust-region core: Levenberg-Marquardt on a chained step, solved through a sparse KKT system.

The step is taken in the chain parameters ``x`` (:class:`.layout.ChainLayout`, so the coupling bound stays
exact) but computed in expanded variables ``z`` (every carriage's own rotation and translation increments, the
link parameters, the focal) subject to the linearised couplings ``C z = 0``: there the Gauss-Newton matrix is
block diagonal and the system costs O(N) per iteration for N carriages. ``docs/solver.md``, "Method".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..core.geometry import skew
from .layout import ChainLayout
from .loss import robust_rho
from .model import SolveOptions
from .problem import Car, Problem
from .terrain import Contact

_EYE3 = np.eye(3)
_EYE3.flags.writeable = False
# the trust-region system of a step is solved dense up to this many unknowns and constraints (a 10-carriage
# step with free rotations has 114): dense LU costs O(n^3), SuperLU O(n) plus a fixed per-call overhead; on
# the benchmark's consists the two break even between 20 (n = 234) and 30 carriages (n = 354)
DENSE_KKT_MAX = 200

# debugging: set to a list to record every evaluation of levenberg_marquardt as
# (nfev, cost, new cost, predicted reduction, lambda, |dx|, scaled gradient)
TRACE: list | None = None


class ExpandedLayout:
    """Index map of the expanded variables ``z`` of a chained step: per carriage its rotation increment (3, when
    free) and translation increment (3), per link its offset parameters (3 free / 2 on the sphere), then the
    log-focal of each estimated focal group; ``xz`` maps the chain parameters ``x`` into ``z``. Also the fixed
    sparsity patterns of the Gauss-Newton matrix ``Hz``, of ``C`` and of the KKT matrix."""

    def __init__(self, lay: ChainLayout):
        self.nr = 3 if lay.rot_free else 0
        self.bs = self.nr + 3
        self._place_variables(lay)
        self._map_chain_parameters(lay)
        self._hessian_pattern(lay)
        self._constraint_pattern(lay)
        self._kkt_pattern()

    def _place_variables(self, lay: ChainLayout) -> None:
        self.zc: dict[int, int] = {}
        n = 0
        for ch in lay.chains:
            for k in ch:
                self.zc[k] = n
                n += self.bs
        self.zl: list[list[tuple[int, int]]] = []
        for c, ch in enumerate(lay.chains):
            row = []
            for j in range(len(ch) - 1):
                w = 2 if lay.sphere[c][j] is not None else 3
                row.append((n, w))
                n += w
            self.zl.append(row)
        self.zf = n
        self.nf = len(lay.focal_views)
        n += self.nf
        self.nz = n

    def _map_chain_parameters(self, lay: ChainLayout) -> None:
        xz = np.empty(lay.n, dtype=int)
        for c, ch in enumerate(lay.chains):
            o = lay.off[c]
            xz[o:o + 3] = self.zc[ch[0]] + self.nr + np.arange(3)
            if lay.rot_free:
                for j, k in enumerate(ch):
                    xz[o + 3 + 3 * j:o + 6 + 3 * j] = self.zc[k] + np.arange(3)
            for j in range(len(ch) - 1):
                z0, w = self.zl[c][j]
                lo = o + lay.link_off[c][j]
                xz[lo:lo + w] = z0 + np.arange(w)
        xz[lay.f_off:lay.f_off + self.nf] = self.zf + np.arange(self.nf)
        self.xz = xz
        self.n_links = sum(len(ch) - 1 for ch in lay.chains)
        self.cars = [k for ch in lay.chains for k in ch]
        self.chain_end = np.concatenate([np.full(len(ch), sum(len(h) for h in lay.chains[:c + 1]))
                                         for c, ch in enumerate(lay.chains)]).astype(int)
        starts = np.cumsum([0] + [len(ch) for ch in lay.chains])[:-1]
        self.first_pos = starts.astype(int)
        self.is_first = np.zeros(len(self.cars), bool)
        self.is_first[self.first_pos] = True
        self.tfirst_x = np.array([lay.off[c] + i for c in range(len(lay.chains)) for i in range(3)], dtype=int)
        self.rot_x = lay.rot_idx
        self.link_rear_pos = np.array([starts[c] + j + 1 for c, ch in enumerate(lay.chains)
                                       for j in range(len(ch) - 1)], dtype=int)
        self.link_list = [(c, j) for c, ch in enumerate(lay.chains) for j in range(len(ch) - 1)]
        # per link (chain order): its parameters' indices in x and in z, padded to 3 (link_mask: the real ones)
        self.link_mask = np.arange(3) < lay.link_w[:, None]  # (L, 3)
        self.link_mask2 = self.link_mask[:, :, None] & self.link_mask[:, None, :]  # (L, 3, 3)
        self.link_x = np.array(lay.link_col, dtype=int).reshape(-1, 1) + np.arange(3)
        self.link_z = np.array([self.zl[c][j][0] for c, j in self.link_list], dtype=int).reshape(-1, 1) + np.arange(3)
        self.car_pos = np.full(len(lay.cars), -1, dtype=int)  # consist index -> position in self.cars
        self.car_pos[self.cars] = np.arange(len(self.cars))

    def _hessian_pattern(self, lay: ChainLayout) -> None:
        bs, nf = self.bs, self.nf
        z0 = np.array([self.zc[k] for k in self.cars], dtype=int)
        ar = np.arange(bs)
        h_rows = [np.repeat(z0[:, None] + ar, bs, axis=1).ravel(), ]
        h_cols = [np.tile(z0[:, None] + ar, (1, bs)).ravel()]
        if nf:
            fr = self.zf + np.arange(nf)
            a = np.repeat(z0[:, None] + ar, nf, axis=1).ravel()
            b = np.tile(fr, len(z0) * bs)
            h_rows += [a, b, np.repeat(fr, nf)]
            h_cols += [b, a, np.tile(fr, nf)]
        for c, j in self.link_list:
            l0, w = self.zl[c][j]
            h_rows.append(np.repeat(l0 + np.arange(w), w))
            h_cols.append(np.tile(l0 + np.arange(w), w))
        self.h_rows = np.concatenate(h_rows)
        self.h_cols = np.concatenate(h_cols)

    def _constraint_pattern(self, lay: ChainLayout) -> None:
        crow, ccol = [], []
        nr = self.nr
        for li, (c, j) in enumerate(self.link_list):
            ka, kb = lay.chains[c][j], lay.chains[c][j + 1]
            l0, w = self.zl[c][j]
            r3 = 3 * li + np.arange(3)
            cols = [self.zc[kb] + nr + np.arange(3), self.zc[ka] + nr + np.arange(3), l0 + np.arange(w)]
            if lay.rot_free:
                cols += [self.zc[ka] + np.arange(3), self.zc[kb] + np.arange(3)]
            for cc in cols:
                crow.append(np.repeat(r3, len(cc)))
                ccol.append(np.tile(cc, 3))
        self.c_rows = np.concatenate(crow) if crow else np.zeros(0, int)
        self.c_cols = np.concatenate(ccol) if ccol else np.zeros(0, int)
        # the C entries of a link, in the order of c_rows / c_cols: I, -I, -GT (3 x w), then -A, -B (rotations)
        nblk = 5 if lay.rot_free else 3
        self.c_mask = np.ones((self.n_links, nblk, 9), dtype=bool)
        self.c_mask[:, 2, :] = np.repeat(self.link_mask, 3, axis=0).reshape(-1, 9)

    def _kkt_pattern(self) -> None:
        # the KKT matrix [[Hz + diag(damping), C^T], [C, 0]]: its entries (Hz, C, C^T, the diagonal) in one list
        nz, nk = self.nz, self.nz + 3 * self.n_links
        self.nk = nk
        k_rows = np.concatenate([self.h_rows, self.c_rows + nz, self.c_cols, np.arange(nz)])
        k_cols = np.concatenate([self.h_cols, self.c_cols, self.c_rows + nz, np.arange(nz)])
        self.dense = nk <= DENSE_KKT_MAX
        if self.dense:
            self.k_flat = k_rows * nk + k_cols
        else:  # compressed-column structure, computed once: each entry's slot in the CSC data (duplicates summed)
            uniq, self.k_slot = np.unique(k_cols * nk + k_rows, return_inverse=True)
            self.k_indices = (uniq % nk).astype(np.int32)
            self.k_indptr = np.searchsorted(uniq // nk, np.arange(nk + 1)).astype(np.int32)

    def kkt(self, h_vals: np.ndarray, c_vals: np.ndarray, damping: np.ndarray) -> np.ndarray | sp.csc_matrix:
        """The KKT matrix (nk, nk) ``[[Hz + diag(damping), C^T], [C, 0]]`` from the values of Hz and C on their
        patterns (:func:`kkt_values`) and the damping (nz,): dense when small (``self.dense``), else CSC."""
        vals = np.concatenate([h_vals, c_vals, c_vals, damping])
        nk = self.nk
        if self.dense:
            return np.bincount(self.k_flat, weights=vals, minlength=nk * nk).reshape(nk, nk)
        data = np.bincount(self.k_slot, weights=vals, minlength=len(self.k_indices))
        return sp.csc_matrix((data, self.k_indices, self.k_indptr), shape=(nk, nk))


@dataclass
class Blocks:
    """The cost and Gauss-Newton blocks in ``z`` at ``x``: per carriage ``Hcar`` (n, bs, bs), ``gcar`` (n, bs),
    carriage-focal ``Hcf``, focal ``Hff``, ``gf``, per link ``Hl`` (L, 3, 3), ``gl`` and the prior's d cost / d T
    ``gTp``; ``R``, ``Jl`` and ``T`` the poses' rotations, left Jacobians and link offsets."""

    x: np.ndarray
    cost: float
    R: np.ndarray
    Jl: np.ndarray
    Hcar: np.ndarray
    gcar: np.ndarray
    Hcf: np.ndarray
    Hff: np.ndarray
    gf: np.ndarray
    Hl: np.ndarray
    gl: np.ndarray
    T: np.ndarray
    gTp: np.ndarray


def _point_jacobians(prob: Problem, lay: ChainLayout, zl: ExpandedLayout, up) -> tuple:
    """Weighted pixel residuals (2M,), d pixel / d carriage block (M, 2, bs) and d pixel / d log-focal (M, 2, nf)."""
    R, t, f, Jl = up.poses.R, up.poses.t, up.poses.f, up.Jl
    uv, Xw, JX, Jf = prob.project(R, t, f, jac=True)
    w = prob.w
    rpix = ((uv - prob.uv) * w[:, None]).reshape(-1)
    JXw = JX * w[:, None, None]
    if lay.rot_free:
        q = Xw - t[prob.car]
        Jr = -np.einsum("nab,nbc,ncd->nad", JXw, skew(q), Jl[prob.car])
        Jpt = np.concatenate([Jr, JXw], axis=2)
    else:
        Jpt = JXw
    Jfp = np.zeros((len(prob.P), 2, zl.nf))
    for i, grp in enumerate(lay.focal_views):
        idx = prob.rows_of_views(grp)
        Jfp[idx, :, i] = Jf[idx] * (w[idx] * f[prob.view[idx]])[:, None]
    return rpix, Jpt, Jfp


def gauss_newton_blocks(prob: Problem, lay: ChainLayout, zl: ExpandedLayout, x: np.ndarray, contact: Contact | None,
                        options: SolveOptions) -> Blocks:
    """Residuals, cost and the Gauss-Newton blocks in ``z`` at ``x``; a robust loss enters as scipy's
    ``least_squares`` does (rows rescaled by sqrt(rho' + 2 rho'' r^2), residuals by rho' / that)."""
    up = lay.unpack(x, with_derivs="local")
    R, t, Jl = up.poses.R, up.poses.t, up.Jl
    M = len(prob.P)
    rpix, Jpt, Jfp = _point_jacobians(prob, lay, zl, up)
    cars_c = contact.cars if contact is not None else []
    rc = np.zeros(len(cars_c))
    Jc = np.zeros((len(cars_c), zl.bs))
    if cars_c:
        rc, a, qk, _ = contact.rows(R[cars_c], t[cars_c])
        Jc[:, zl.nr:] = a
        if lay.rot_free:  # -(a x-matrix(R s)) J_l, i.e. (R s x a)^T J_l
            Jc[:, :3] = np.einsum("ni,nij->nj", np.cross(qk, a), Jl[cars_c])
    s_l = lay.link_scale
    rp = (lay.T * s_l[:, None]).reshape(-1)
    r = np.concatenate([rpix, rc, rp])
    if options.robust_loss == "linear":
        cost = 0.5 * float(r @ r)
        sc = None
    else:
        rho = robust_rho(r, options.robust_loss, options.loss_scale_px)
        cost = 0.5 * float(np.sum(rho[0]))
        js = rho[1] + 2 * rho[2] * r**2
        js = np.sqrt(np.maximum(js, np.finfo(float).eps))
        r = r * rho[1] / js
        sc = js
    rpm = r[:2 * M].reshape(M, 2)
    rcm = r[2 * M:2 * M + len(cars_c)]
    rpr = r[2 * M + len(cars_c):]
    if sc is not None:
        sp_ = sc[:2 * M].reshape(M, 2)
        Jpt = Jpt * sp_[:, :, None]
        Jfp = Jfp * sp_[:, :, None]
        Jc = Jc * sc[2 * M:2 * M + len(cars_c), None]
        scp = sc[2 * M + len(cars_c):]
    nf = zl.nf
    cpos = zl.car_pos[prob.car]
    Hcar = np.zeros((len(zl.cars), zl.bs, zl.bs))
    gcar = np.zeros((len(zl.cars), zl.bs))
    np.add.at(Hcar, cpos, np.einsum("nai,naj->nij", Jpt, Jpt))
    np.add.at(gcar, cpos, np.einsum("nai,na->ni", Jpt, rpm))
    Hcf = np.zeros((len(zl.cars), zl.bs, nf))
    if nf:
        np.add.at(Hcf, cpos, np.einsum("nai,naj->nij", Jpt, Jfp))
    Hff = np.einsum("nai,naj->ij", Jfp, Jfp)
    gf = np.einsum("nai,na->i", Jfp, rpm)
    if cars_c:
        kpos = zl.car_pos[cars_c]
        np.add.at(Hcar, kpos, Jc[:, :, None] * Jc[:, None, :])
        np.add.at(gcar, kpos, Jc * rcm[:, None])
    # the coupler prior rows, all links at once (padded to 3 parameters, see ChainLayout.GT_pad)
    Jp = lay.GT_pad * s_l[:, None, None]  # (L, 3, 3): d rows / d link params
    rpr3 = rpr.reshape(-1, 3)
    gT = rpr3 * s_l[:, None]  # d cost / d T of each link's prior rows
    if sc is not None:
        scp3 = scp.reshape(-1, 3)
        Jp = Jp * scp3[:, :, None]
        gT = gT * scp3
    Hl = np.einsum("nji,njk->nik", Jp, Jp)
    gl = np.einsum("nji,nj->ni", Jp, rpr3)
    return Blocks(x, cost, R, Jl, Hcar, gcar, Hcf, Hff, gf, Hl, gl, lay.T, gT)


def _rotation_rows(zl: ExpandedLayout, E: Blocks, cars: list[Car], Sn: np.ndarray, Gn: np.ndarray):
    """Gradient and Gauss-Newton diagonal of the rotation parameters (per carriage, (n, 3) each) and the
    coupling blocks ``A = d(R c_rear)/d rot``, ``B = -d(R c_front)/d rot`` (n, 3, 3) in the order of ``zl.cars``."""
    nr = zl.nr
    H, gc = E.Hcar, E.gcar
    Htt, gt = H[:, nr:, nr:], gc[:, nr:]
    Rk = E.R[zl.cars]
    JL = E.Jl[zl.cars]
    cr = np.array([cars[k].c_rear for k in zl.cars])
    cf = np.array([cars[k].c_front for k in zl.cars])
    A = -skew(np.einsum("nij,nj->ni", Rk, cr)) @ JL
    B = skew(np.einsum("nij,nj->ni", Rk, cf)) @ JL
    F = np.where(zl.is_first[:, None, None], 0.0, B)
    Ft = np.swapaxes(F, 1, 2)
    Ho = H[:, :3, :3] + Ft @ H[:, 3:, :3] + H[:, :3, 3:] @ F + Ft @ Htt @ F
    go = gc[:, :3] + np.einsum("nji,nj->ni", F, gt)
    cc = F + A
    cct = np.swapaxes(cc, 1, 2)
    Ho = Ho + cct @ Sn @ cc
    go = go + np.einsum("nji,nj->ni", cc, Gn)
    return go, np.diagonal(Ho, axis1=1, axis2=2), (A, B)


def chain_gradient_and_diagonal(lay: ChainLayout, zl: ExpandedLayout, E: Blocks, cars: list[Car]):
    """Gradient (n,) and the diagonal (n,) of the Gauss-Newton matrix in the chain parameters ``x`` (exact, by
    suffix sums along each chain: a link or rotation moves every carriage behind it), the coupling blocks
    ``(A, B)`` (None with rotations held) and the link blocks (L, 3, 3) of the Gauss-Newton matrix, a sphere
    link's with the sphere's curvature added (padded as ``ChainLayout.GT_pad``)."""
    g = np.zeros(lay.n)
    d = np.zeros(lay.n)
    nr = zl.nr
    n = len(zl.cars)
    Htt, gt = E.Hcar[:, nr:, nr:], E.gcar[:, nr:]
    # suffix sums within each chain: S[i] = sum over the carriages from i to the end of its chain
    Sg = np.cumsum(Htt[::-1], axis=0)[::-1]
    Gg = np.cumsum(gt[::-1], axis=0)[::-1]
    Sg = np.concatenate([Sg, np.zeros((1, 3, 3))])
    Gg = np.concatenate([Gg, np.zeros((1, 3))])
    end = zl.chain_end  # per carriage: index (in zl.cars) one past its chain's last carriage
    S = Sg[:n] - Sg[end]
    G = Gg[:n] - Gg[end]
    nxt = np.minimum(np.arange(n) + 1, n)
    last = (np.arange(n) + 1) == end
    Sn = np.where(last[:, None, None], 0.0, Sg[nxt] - Sg[end])
    Gn = np.where(last[:, None], 0.0, Gg[nxt] - Gg[end])
    fi = zl.first_pos
    g[zl.tfirst_x] = G[fi].ravel()
    d[zl.tfirst_x] = np.diagonal(S[fi], axis1=1, axis2=2).ravel()
    AB = None
    if lay.rot_free:
        go, do, AB = _rotation_rows(zl, E, cars, Sn, Gn)
        g[zl.rot_x] = go.ravel()
        d[zl.rot_x] = do.ravel()
    Hl = E.Hl
    if zl.n_links:
        ib = zl.link_rear_pos
        GT = lay.GT_pad
        if lay.link_sph.any():
            # the sphere's curvature (the constraint's term of the Lagrangian's Hessian): along any direction e of
            # the chart, d2T = -(|GT e|^2 / s) u normal to the sphere, so the cost's second derivative gains
            # mu GT^T GT, mu = -(dcost/dT . u) / s >= 0 while the constraint binds
            gT = G[ib] + E.gTp
            T = E.T
            mu = -np.einsum("ni,ni->n", gT, T) / np.einsum("ni,ni->n", T, T)
            mu = np.where(lay.link_sph & (mu > 0.0), mu, 0.0)
            Hl = Hl + mu[:, None, None] * np.einsum("nji,njk->nik", GT, GT)
        m = zl.link_mask
        g[zl.link_x[m]] = (np.einsum("nji,nj->ni", GT, G[ib]) + E.gl)[m]
        d[zl.link_x[m]] = (np.einsum("nji,njk,nki->ni", GT, S[ib], GT) + np.diagonal(Hl, axis1=1, axis2=2))[m]
    nf = zl.nf
    if nf:
        g[lay.f_off:lay.f_off + nf] = E.gf
        d[lay.f_off:lay.f_off + nf] = np.diag(E.Hff)
    return g, d, AB, Hl


def kkt_values(lay: ChainLayout, zl: ExpandedLayout, E: Blocks, AB, Hl: np.ndarray):
    """The values of Hz and of the coupling matrix C on their fixed patterns (see :meth:`ExpandedLayout.kkt`),
    and the gradient gz (nz,). ``AB``, ``Hl``: from :func:`chain_gradient_and_diagonal`."""
    vals = [E.Hcar.ravel()]
    gz = np.zeros(zl.nz)
    z0 = np.array([zl.zc[k] for k in zl.cars], dtype=int)
    gz[(z0[:, None] + np.arange(zl.bs)).ravel()] = E.gcar.ravel()
    if zl.nf:
        Hcf = E.Hcf.ravel()
        vals += [Hcf, Hcf, E.Hff.ravel()]
        gz[zl.zf:] = E.gf
    if not zl.n_links:
        return np.concatenate(vals), np.zeros(0), gz
    vals.append(Hl[zl.link_mask2])
    gz[zl.link_z[zl.link_mask]] = E.gl[zl.link_mask]
    nl = zl.n_links
    blocks = [np.broadcast_to(_EYE3.ravel(), (nl, 9)), np.broadcast_to(-_EYE3.ravel(), (nl, 9)),
              -lay.GT_pad.reshape(nl, 9)]
    if lay.rot_free:
        A, B = AB
        ib = zl.link_rear_pos
        blocks += [-A[ib - 1].reshape(nl, 9), -B[ib].reshape(nl, 9)]
    return np.concatenate(vals), np.stack(blocks, axis=1)[zl.c_mask], gz


def solve_kkt(K: np.ndarray | sp.csc_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """Solve the KKT system ``K``: dense LU (LAPACK) for a small system, SuperLU for a large one. None when it is
    singular or the solution is not finite."""
    try:
        if isinstance(K, np.ndarray):
            sol = np.linalg.solve(K, rhs)
        else:
            sol = splu(K, permc_spec="MMD_AT_PLUS_A").solve(rhs)
    except (RuntimeError, np.linalg.LinAlgError):  # exactly singular
        return None
    return sol if np.all(np.isfinite(sol)) else None


@dataclass
class LMResult:
    x: np.ndarray
    nfev: int
    message: str
    ok: bool


def _focal_bounds(prob: Problem, lay: ChainLayout, nf: int, options: SolveOptions):
    """log(f / f_ref) bounds of each focal group: the sweep's field-of-view range (guards against a runaway
    along the depth / focal ambiguity)."""
    flo = np.zeros(nf)
    fhi = np.zeros(nf)
    for i, grp in enumerate(lay.focal_views):
        v = grp[0]
        half_w = 0.5 * prob.views[v].intrinsics.width
        lo_deg, hi_deg = options.hfov_range_deg
        flo[i] = math.log(half_w / math.tan(math.radians(hi_deg) / 2) / lay.f_ref[v])
        fhi[i] = math.log(half_w / math.tan(math.radians(lo_deg) / 2) / lay.f_ref[v])
    return flo, fhi


def levenberg_marquardt(prob: Problem, lay: ChainLayout, contact: Contact | None, options: SolveOptions) -> LMResult:
    """Minimise the step's cost from ``lay.x0``: Levenberg-Marquardt with Marquardt scaling (``d``, the exact
    diagonal of the Gauss-Newton matrix in ``x``) and Nielsen's damping update, a trust-region method in the
    sense of Moré (1978); each step solved through the KKT system of ``z``."""
    if lay.n == 0:
        return LMResult(lay.x0, 0, "nothing to optimise", True)
    zl = ExpandedLayout(lay)
    tol = options.tolerance
    max_ev = int(options.max_iterations)
    x = lay.x0.copy()
    flo, fhi = _focal_bounds(prob, lay, zl.nf, options)
    if zl.nf:
        x[lay.f_off:] = np.clip(x[lay.f_off:], flo, fhi)
    E = gauss_newton_blocks(prob, lay, zl, x, contact, options)
    nfev = 1
    lam, nu = 1e-3, 2.0
    nc = 3 * zl.n_links
    while True:
        g, d, AB, Hl = chain_gradient_and_diagonal(lay, zl, E, prob.cars)
        dmax = float(np.max(d)) if len(d) else 1.0
        d = np.maximum(d, 1e-12 * max(1.0, dmax))
        cost = E.cost
        if float(np.max(np.abs(g) / np.sqrt(d))) < tol * max(1.0, math.sqrt(2 * cost)):
            return LMResult(x, nfev, "gradient small", True)
        hv, cv, gz = kkt_values(lay, zl, E, AB, Hl)
        K0 = zl.kkt(hv, cv, np.zeros(zl.nz))
        dz = np.zeros(zl.nz)
        dz[zl.xz] = d
        rhs = np.concatenate([-gz, np.zeros(nc)])
        while True:
            sol = solve_kkt(zl.kkt(hv, cv, lam * dz), rhs)
            if sol is None:
                lam *= 10.0
                if lam > 1e16:
                    return LMResult(x, nfev, "trust region collapsed", False)
                continue
            z = sol[:zl.nz]
            dx = z[zl.xz]
            pred = -float(gz @ z) - 0.5 * float(z @ (K0 @ np.concatenate([z, np.zeros(nc)]))[:zl.nz])
            if 0.0 <= pred <= tol * cost:
                # no reduction worth taking is predicted (MINPACK's ftol test): a minimum to the tolerance, also
                # at the kink of the contact term, where rejected steps would shrink the region without end
                return LMResult(x, nfev, "converged (predicted reduction below tolerance)", True)
            xn = x + dx
            if zl.nf and not np.all((xn[lay.f_off:] >= flo) & (xn[lay.f_off:] <= fhi)):
                # the focal would leave the sweep's field-of-view range: a failed step (radius shrinks)
                lam *= nu
                nu *= 2.0
                if lam > 1e16:
                    return LMResult(x, nfev, "trust region collapsed", False)
                continue
            En = gauss_newton_blocks(prob, lay, zl, xn, contact, options)
            nfev += 1
            cn = En.cost
            rho = (cost - cn) / pred if pred > 0 else -1.0
            if TRACE is not None:
                TRACE.append((nfev, cost, cn, pred, lam, float(np.linalg.norm(dx)),
                              float(np.max(np.abs(g) / np.sqrt(d)))))
            if rho > 0 and np.isfinite(cn):
                small = abs(cost - cn) < tol * cost or float(np.linalg.norm(dx)) < tol * (
                    tol + float(np.linalg.norm(x)))
                x, E = xn, En
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                if small:
                    return LMResult(x, nfev, "converged (cost / step change below tolerance)", True)
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                return LMResult(x, nfev, "trust region collapsed", False)
            if nfev >= max_ev:
                return LMResult(x, nfev, "maximum evaluations reached", False)
        if nfev >= max_ev:
            return LMResult(x, nfev, "maximum evaluations reached", False)
