"""The rotation-only bundle adjustment's problem: its options, its parameters, and its residuals with their
analytic Jacobian (docs/stitching.md, step 6).

Parameters: a rotation vector per photo but the root (``cam_from_pano <- Exp(phi) cam_from_pano0``) and, unless
the intrinsics are fixed, per camera group ``log f`` [, ``k1``, ``k2``, ``dcx / f0``, ``dcy / f0``]. Residuals:
every match transferred a -> b and b -> a through the photos' lens models (4 per match), in work pixels, then
the priors. The Jacobian is analytic: rotations through SO(3)'s left Jacobian, the lens by implicit
differentiation of the undistortion, so each solver step costs one evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from ..core.camera import CameraIntrinsics, LensPrior
from ..core.geometry import exp_and_left_jacobian_so3
from ..core.options import Range, check_options

__all__ = ["BundleOptions", "Observations", "RotationBundleProblem", "min_work_scale", "undistort_radial"]


@dataclass(frozen=True, kw_only=True)
class BundleOptions:
    """What the adjustment estimates, its priors, its robust loss and its two passes (units in the names).

    ``fixed_intrinsics``: rotations only, each photo's ``init`` intrinsics used as they are (full distortion).
    Else one focal per camera group (fx = fy) and, with ``estimate_k1``, radial k1, k2 and the principal point,
    with the weak priors ``lens_prior`` (k1, k2: 0; principal point: ``init``'s; focal: ``focal_prior``, where
    given).
    ``robust_pass``: soft L1 (scale ``loss_scale_work_px``) on at most ``robust_per_pair`` matches per pair, to
    tolerance ``robust_tol``; matches within ``reject_work_px`` after it are the inliers. ``final_pass``: least
    squares on the inliers, or with ``final_loss_median`` > 0 soft L1 at that many times their median residual
    (the residuals' tail weighs less). Each pass stops after ``2 max_nfev`` evaluations."""

    fixed_intrinsics: bool
    estimate_k1: bool
    lens_prior: LensPrior = LensPrior(focal_rel=0.05, principal_point_rel=0.05, k1=0.25, k2=0.25)
    loss_scale_work_px: Annotated[float, Range(gt=0.0)] = 1.0
    reject_work_px: Annotated[float, Range(gt=0.0)] = 4.0
    max_nfev: Annotated[int, Range(ge=1)] = 60
    robust_per_pair: Annotated[int, Range(ge=1)] = 100
    robust_pass: bool = True
    final_pass: bool = True
    robust_tol: Annotated[float, Range(gt=0.0)] = 1e-6
    final_loss_median: Annotated[float, Range(ge=0.0)] = 0.0

    def __post_init__(self) -> None:
        check_options(self, "bundle adjustment options")


@dataclass
class Observations:
    """Inlier matches stacked: photo ``a`` (M,), ``b`` (M,), pixels as on disk ``xa``, ``xb`` (M, 2), pair id (M,)."""

    a: np.ndarray
    b: np.ndarray
    xa: np.ndarray
    xb: np.ndarray
    pair: np.ndarray


def min_work_scale(obs: Observations, work_scale: dict[int, float]) -> np.ndarray:
    """(M,) the smaller work scale of each observation's two photos (residuals in work pixels use it)."""
    ws = np.zeros(max(work_scale) + 1)
    ws[list(work_scale)] = list(work_scale.values())
    return np.minimum(ws[obs.a], ws[obs.b])


def undistort_radial(xd: np.ndarray, k1: np.ndarray, k2: np.ndarray, iterations: int = 6) -> np.ndarray:
    """Undistorted normalised (n, 2) of distorted ``xd`` (n, 2) under ``x (1 + k1 r^2 + k2 r^4)``, by Newton."""
    u, v = xd[:, 0], xd[:, 1]
    x, y = u.copy(), v.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(iterations):
            r2 = x * x + y * y
            s = 1.0 + r2 * (k1 + k2 * r2)
            ds = k1 + 2.0 * k2 * r2
            gx, gy = x * s - u, y * s - v
            # A = s I + 2 ds x x^T; A^-1 g by Sherman-Morrison
            c = 2.0 * ds * (x * gx + y * gy) / (s + 2.0 * ds * r2)
            sx, sy = (gx - x * c) / s, (gy - y * c) / s
            ok = np.isfinite(sx) & np.isfinite(sy)
            x = x - np.where(ok, sx, 0.0)
            y = y - np.where(ok, sy, 0.0)
    return np.column_stack([x, y])


class RotationBundleProblem:
    """The parameters, residuals and Jacobian of one adjustment (module docstring).

    ``kept``: the photos, the root (which keeps its rotation ``R0``; wave correction fixes the panorama's later)
    first; ``groups``: photo -> camera group; ``init``: starting intrinsics per photo (the priors' centres);
    ``work_scale``: work pixels per full-resolution pixel, per photo; ``focal_prior``: group -> focal px."""

    def __init__(self, obs: Observations, kept: list[int], groups: dict[int, int], init: dict[int, CameraIntrinsics],
                 R0: dict[int, np.ndarray], work_scale: dict[int, float], opts: BundleOptions,
                 focal_prior: dict[int, float] | None = None) -> None:
        self.obs, self.groups, self.init, self.opts, self.focal_prior = obs, groups, init, opts, focal_prior
        self.kept = kept = list(kept)
        self.pos = pos = {k: n for n, k in enumerate(kept)}
        self.free = free = [k for k in kept if k != kept[0]]
        self.gids = gids = sorted({groups[k] for k in kept})
        self.gpos = gpos = {g: n for n, g in enumerate(gids)}
        self.n_rot = n_rot = 3 * len(free)
        # log f [, k1, k2, dcx / f0, dcy / f0]
        self.n_gp = n_gp = 0 if opts.fixed_intrinsics else (5 if opts.estimate_k1 else 1)
        self.n_par = n_rot + n_gp * len(gids)
        self.f0 = f0 = {g: np.mean([init[k].fx for k in kept if groups[k] == g]) for g in gids}
        pos_of = np.zeros(max(kept) + 1, dtype=int)  # photo -> position, as an array (looked up per observation)
        pos_of[kept] = np.arange(len(kept))
        self.a_pos, self.b_pos = pos_of[obs.a], pos_of[obs.b]
        self.s_obs = min_work_scale(obs, work_scale)
        # parameter column of each photo position's rotation (-1: the root) and of its group's first parameter
        self.rot_col = np.full(len(kept), -1)
        for n_, k in enumerate(free):
            self.rot_col[pos[k]] = 3 * n_
        self.grp_of_pos = np.array([gpos[groups[k]] for k in kept])
        self.f0_of_pos = np.array([f0[groups[k]] for k in kept])
        self.gp_col = n_rot + n_gp * self.grp_of_pos
        self.cx0 = np.array([init[k].cx for k in kept])
        self.cy0 = np.array([init[k].cy for k in kept])
        self.ray_a = self.ray_b = None
        if opts.fixed_intrinsics:  # rays of the observations once, exactly
            self.ray_a, self.ray_b = np.zeros((len(obs.a), 3)), np.zeros((len(obs.a), 3))
            for k in kept:
                m = obs.a == k
                if m.any():
                    self.ray_a[m] = init[k].rays(obs.xa[m])
                m = obs.b == k
                if m.any():
                    self.ray_b[m] = init[k].rays(obs.xb[m])
        self.R0s = np.stack([R0[k] for k in kept])
        self.free_pos = np.array([pos[k] for k in free], dtype=int)
        self.single_group = len(gids) == 1
        self.c_loss = opts.loss_scale_work_px  # the soft-L1 scale (work px), set again for the final pass
        self._layouts: dict[int, tuple] = {}

    # -- parameters -----------------------------------------------------------------------------------------------
    def start(self, start: dict[int, CameraIntrinsics] | None) -> np.ndarray:
        """The parameter vector: rotations at ``R0``, intrinsics at ``init`` or at ``start``'s (per photo)."""
        x = np.zeros(self.n_par)
        n_rot, n_gp, f0 = self.n_rot, self.n_gp, self.f0
        if start is not None and n_gp:
            for g in self.gids:
                k = next(k for k in self.kept if self.groups[k] == g)
                c = start[k]
                x[n_rot + n_gp * self.gpos[g]] = np.log(c.fx / f0[g])
                if n_gp == 5:
                    x[n_rot + n_gp * self.gpos[g] + 1:n_rot + n_gp * (self.gpos[g] + 1)] = (
                        c.k1, c.k2, (c.cx - self.init[k].cx) / f0[g], (c.cy - self.init[k].cy) / f0[g])
        return x

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rotations (n, 3, 3) and their left Jacobians (zero for the root) per photo position, and the group
        parameters (groups, n_gp)."""
        Rs = self.R0s.copy()
        Jl = np.zeros((len(self.kept), 3, 3))
        if self.free:
            phi = x[:self.n_rot].reshape(-1, 3)
            dR, Jf = exp_and_left_jacobian_so3(phi)
            Rs[self.free_pos] = dR @ self.R0s[self.free_pos]
            Jl[self.free_pos] = Jf
        gp = x[self.n_rot:].reshape(len(self.gids), self.n_gp) if self.n_gp else np.zeros((len(self.gids), 0))
        return Rs, Jl, gp

    def rotations(self, x: np.ndarray) -> dict[int, np.ndarray]:
        """photo -> ``cam_from_pano`` (3, 3) at ``x``."""
        Rs, _, _ = self.unpack(x)
        return {k: Rs[self.pos[k]] for k in self.kept}

    def intrinsics(self, x: np.ndarray) -> dict[int, CameraIntrinsics]:
        """photo -> intrinsics at ``x`` (full resolution, as on disk; ``init``'s when fixed)."""
        _, _, gp = self.unpack(x)
        out_K = {}
        for k in self.kept:
            if self.opts.fixed_intrinsics:
                out_K[k] = self.init[k]
                continue
            g, f0 = self.gpos[self.groups[k]], self.f0[self.groups[k]]
            f = float(f0 * np.exp(gp[g, 0]))
            lens = gp[g, 1:5] if self.n_gp == 5 else np.zeros(4)
            out_K[k] = CameraIntrinsics(width=self.init[k].width, height=self.init[k].height, fx=f, fy=f,
                                        cx=self.init[k].cx + lens[2] * f0, cy=self.init[k].cy + lens[3] * f0,
                                        k1=float(lens[0]), k2=float(lens[1]))
        return out_K

    # -- the lens model ---------------------------------------------------------------------------------------------
    def _cam_params(self, gp: np.ndarray, ppos: np.ndarray):
        """Per row: f, k1, k2, cx, cy of the photo at each position (computed per position, then gathered)."""
        f = (self.f0_of_pos * np.exp(gp[self.grp_of_pos, 0]))[ppos]
        if self.n_gp == 5:
            g = gp[self.grp_of_pos]
            return (f, g[:, 1][ppos], g[:, 2][ppos], (self.cx0 + g[:, 3] * self.f0_of_pos)[ppos],
                    (self.cy0 + g[:, 4] * self.f0_of_pos)[ppos])
        z = np.zeros(len(ppos))
        return f, z, z, self.cx0[ppos], self.cy0[ppos]

    def _rays_est(self, x_px: np.ndarray, ppos: np.ndarray, gp: np.ndarray, jac: bool):
        """Rays (n, 3) (z = 1) of pixels ``x_px`` and, with ``jac``, d ray / d group parameters (n, 3, n_gp)."""
        n_gp = self.n_gp
        f, k1, k2, cx, cy = self._cam_params(gp, ppos)
        xd = np.column_stack([(x_px[:, 0] - cx) / f, (x_px[:, 1] - cy) / f])
        xu = undistort_radial(xd, k1, k2) if n_gp == 5 else xd
        r = np.column_stack([xu, np.ones(len(xu))])
        if not jac:
            return r, None
        n = len(xu)
        # d xd / d params: log f -> -xd; dcx/f0 -> (-f0/f, 0); dcy/f0 -> (0, -f0/f)
        dxd = np.zeros((n, 2, n_gp))
        dxd[:, :, 0] = -xd
        if n_gp == 5:
            q = self.f0_of_pos[ppos] / f
            dxd[:, 0, 3] = -q
            dxd[:, 1, 4] = -q
            r2 = np.sum(xu * xu, axis=1)
            s = 1.0 + r2 * (k1 + k2 * r2)
            ds = k1 + 2.0 * k2 * r2
            rhs = dxd.copy()
            rhs[:, :, 1] -= xu * r2[:, None]
            rhs[:, :, 2] -= xu * (r2 * r2)[:, None]
            # A^-1 rhs, A = s I + 2 ds xu xu^T (Sherman-Morrison)
            xr = xu[:, 0, None] * rhs[:, 0, :] + xu[:, 1, None] * rhs[:, 1, :]
            dxu = (rhs - xu[:, :, None] * (2.0 * ds / (s + 2.0 * ds * r2))[:, None, None] * xr[:, None, :]) \
                / s[:, None, None]
        else:
            dxu = dxd
        dr = np.zeros((n, 3, n_gp))
        dr[:, :2, :] = dxu
        return r, dr

    def _project_est(self, d: np.ndarray, ppos: np.ndarray, gp: np.ndarray, jac: bool):
        """Pixels (n, 2) of directions ``d`` (n, 3); with ``jac``: d p / d d (n, 2, 3), d p / d params (n, 2, n_gp)."""
        n_gp = self.n_gp
        f, k1, k2, cx, cy = self._cam_params(gp, ppos)
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / d[:, 2]
        y = d[:, :2] * iz[:, None]
        r2 = np.sum(y * y, axis=1)
        s = 1.0 + r2 * (k1 + k2 * r2) if n_gp == 5 else np.ones(len(y))
        yd = y * s[:, None]
        p = f[:, None] * yd + np.column_stack([cx, cy])
        if not jac:
            return p, None, None
        n = len(y)
        # d y / d d = iz [I | -y]; d yd / d y = s I + 2 ds y y^T,
        # so d yd / d d = iz [s I + 2 ds y y^T | -(s + 2 ds r2) y]
        fi = f * iz
        dp_dd = np.empty((n, 2, 3))
        if n_gp == 5:
            ds = k1 + 2.0 * k2 * r2
            c = (2.0 * fi * ds)[:, None, None] * y[:, :, None]
            dp_dd[:, :, :2] = c * y[:, None, :]
            dp_dd[:, 0, 0] += fi * s
            dp_dd[:, 1, 1] += fi * s
            dp_dd[:, :, 2] = -(fi * (s + 2.0 * ds * r2))[:, None] * y
        else:
            dp_dd[:, :, :2] = 0.0
            dp_dd[:, 0, 0] = dp_dd[:, 1, 1] = fi
            dp_dd[:, :, 2] = -fi[:, None] * y
        dp_dg = np.zeros((n, 2, n_gp))
        dp_dg[:, :, 0] = f[:, None] * yd
        if n_gp == 5:
            dp_dg[:, :, 1] = f[:, None] * y * r2[:, None]
            dp_dg[:, :, 2] = f[:, None] * y * (r2 * r2)[:, None]
            dp_dg[:, 0, 3] = self.f0_of_pos[ppos]
            dp_dg[:, 1, 4] = self.f0_of_pos[ppos]
        return p, dp_dd, dp_dg

    def _project_fixed(self, d: np.ndarray, ppos: np.ndarray, jac: bool):
        """Pixels (n, 2) of directions ``d`` (n, 3) through the fixed ``init`` lenses; with ``jac``, d p / d d."""
        out = np.zeros((len(d), 2))
        J = np.zeros((len(d), 2, 3)) if jac else None
        for k in self.kept:
            m = ppos == self.pos[k]
            if not m.any():
                continue
            lens = self.init[k]
            out[m] = lens.project(d[m])
            if jac:  # d p / d d by central differences (the full Brown-Conrady model; exact to ~1e-9 px)
                dm = d[m]
                h = 1e-6 * np.linalg.norm(dm, axis=1)
                for c in range(3):
                    e = np.zeros(3)
                    e[c] = 1.0
                    J[m, :, c] = (lens.project(dm + h[:, None] * e) - lens.project(dm - h[:, None] * e)) \
                        / (2.0 * h[:, None])
        return out, J

    # -- residuals and Jacobian -------------------------------------------------------------------------------------
    def _transfer(self, gp: np.ndarray, M: np.ndarray, src_pos: np.ndarray, dst_pos: np.ndarray, x_src: np.ndarray,
                  x_dst: np.ndarray, ray_src: np.ndarray | None, jac: bool):
        """Residuals (n, 2) (full-resolution px) of pixels ``x_src`` (n, 2) of photos ``src_pos`` transferred into
        photos ``dst_pos`` (``M`` (n, 3, 3): dst_from_src per observation; ``ray_src``: the rays of ``x_src`` when the
        intrinsics are fixed) and, with ``jac``: A (n, 2, 3) with d res / d rot(dst) = -A J_l(dst) and
        d res / d rot(src) = A M J_l(src); d res / d group(src) (n, 2, n_gp); d res / d group(dst).
        Both directions of every observation go through one call (elementwise: the same numbers as one call each)."""
        fixed = self.opts.fixed_intrinsics
        if fixed:
            r, dr = ray_src, None
        else:
            r, dr = self._rays_est(x_src, src_pos, gp, jac)
        d = M[:, :, 0] * r[:, 0, None] + M[:, :, 1] * r[:, 1, None] + M[:, :, 2] * r[:, 2, None]
        if fixed:
            p, dp_dd = self._project_fixed(d, dst_pos, jac)
            dp_dg = None
        else:
            p, dp_dd, dp_dg = self._project_est(d, dst_pos, gp, jac)
        res = p - x_dst
        bad = (d[:, 2] <= 0) | ~np.all(np.isfinite(res), axis=1)
        res[bad] = 1e3  # behind the other camera: a large, finite residual
        if not jac:
            return res, None
        # d d / d (dst rotation perturbation) = -[d]x, d d / d (src) = M [r]x = [d]x M; rows of dp_dd [d]x are
        # dp_dd[r] x d
        A = np.empty_like(dp_dd)  # np.cross(dp_dd, d[:, None, :]), the same products, without its overhead
        d0, d1, d2 = d[:, None, 0], d[:, None, 1], d[:, None, 2]
        A[:, :, 0] = dp_dd[:, :, 1] * d2 - dp_dd[:, :, 2] * d1
        A[:, :, 1] = dp_dd[:, :, 2] * d0 - dp_dd[:, :, 0] * d2
        A[:, :, 2] = dp_dd[:, :, 0] * d1 - dp_dd[:, :, 1] * d0
        J_gs = None
        if dr is not None:  # dp_dd M dr, with dr's z row zero
            DM = [dp_dd[:, :, 0, None] * M[:, 0, c, None, None] + dp_dd[:, :, 1, None] * M[:, 1, c, None, None]
                  + dp_dd[:, :, 2, None] * M[:, 2, c, None, None] for c in range(2)]  # 2 x (n, 2, 1)
            J_gs = DM[0] * dr[:, None, 0, :] + DM[1] * dr[:, None, 1, :]
        blocks = [A, J_gs, dp_dg]
        for B in blocks:
            if B is not None:
                B[bad] = 0.0
        return res, blocks

    def _layout(self, idx: np.ndarray) -> tuple:
        """What :meth:`evaluate` needs of the observations ``idx`` that does not depend on the parameters (once per
        set): the blocks of consecutive observations of one pair of photos (stacked pair by pair: one block per
        pair), and both directions' positions and pixels stacked, a -> b (rows :n) then b -> a (rows n:)."""
        hit = self._layouts.get(id(idx))
        if hit is not None and hit[0] is idx:
            return hit[1]
        ap, bp = self.a_pos[idx], self.b_pos[idx]
        cut = np.flatnonzero((np.diff(ap) != 0) | (np.diff(bp) != 0)) + 1
        starts = np.concatenate([[0], cut]).astype(int)
        ends = np.concatenate([cut, [len(idx)]]).astype(int)
        xa, xb = self.obs.xa[idx], self.obs.xb[idx]
        lay = (starts, ends, ap[starts], bp[starts], np.concatenate([ap, bp]), np.concatenate([bp, ap]),
               np.concatenate([xa, xb]), np.concatenate([xb, xa]),
               np.concatenate([self.ray_a[idx], self.ray_b[idx]]) if self.opts.fixed_intrinsics else None,
               self.s_obs[idx])
        self._layouts[id(idx)] = (idx, lay)  # (idx kept alive: its id is not reused while cached)
        return lay

    def _priors(self, gp: np.ndarray) -> tuple[list[float], list[tuple[int, float]]]:
        """The priors' residuals, and each one's (parameter column, derivative)."""
        o, n_rot, n_gp, gpos = self.opts, self.n_rot, self.n_gp, self.gpos
        extra, Jx = [], []
        if n_gp and self.focal_prior:
            for g in self.gids:
                if g in self.focal_prior:
                    f_g = self.f0[g] * np.exp(gp[gpos[g], 0])
                    sig = o.lens_prior.focal_rel * self.focal_prior[g]
                    extra.append((f_g - self.focal_prior[g]) / sig)
                    Jx.append((n_rot + n_gp * gpos[g], f_g / sig))
        if n_gp == 5:
            lp = o.lens_prior
            for q, sig in ((1, lp.k1), (2, lp.k2), (3, lp.principal_point_rel), (4, lp.principal_point_rel)):
                for g in self.gids:
                    extra.append(gp[gpos[g], q] / sig)
                    Jx.append((n_rot + n_gp * gpos[g] + q, 1.0 / sig))
        return extra, Jx

    def evaluate(self, x: np.ndarray, idx: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals (4 per observation in ``idx``, work px, then the priors) and, with ``jac``, their Jacobian."""
        Rs, Jl, gp = self.unpack(x)
        starts, ends, pa, pb, src2, dst2, xsrc2, xdst2, ray2, s = self._layout(idx)
        M_ba = Rs[pb] @ np.transpose(Rs[pa], (0, 2, 1))  # per pair: b_from_a
        M_ab = np.transpose(M_ba, (0, 2, 1))
        lens_ = ends - starts
        Mo_ba, Mo_ab = np.repeat(M_ba, lens_, axis=0), np.repeat(M_ab, lens_, axis=0)
        n = len(idx)
        res2, B2 = self._transfer(gp, np.concatenate([Mo_ba, Mo_ab]), src2, dst2, xsrc2, xdst2, ray2, jac)
        r = (np.stack([res2[:n], res2[n:]], axis=1) * s[:, None, None]).reshape(-1)
        extra, Jx = self._priors(gp)
        r = np.concatenate([r, np.asarray(extra, dtype=float)])
        if not jac:
            return r, None
        J = np.zeros((n + (len(extra) + 3) // 4, 2, 2, self.n_par))  # rows: observation, direction, x / y
        for w, (src, dst, Mp, rows) in enumerate(((pa, pb, M_ba, slice(None, n)), (pb, pa, M_ab, slice(n, None)))):
            B = [None if b_ is None else b_[rows] * s[:, None, None] for b_ in B2]
            self._fill_jacobian(J[:n, w], B, src, dst, Mp, Jl, starts, ends)
        J = J.reshape(-1, self.n_par)[:4 * n + len(extra)]
        for q, (c, v) in enumerate(Jx):
            J[4 * n + q, c] = v
        return r, J

    def _fill_jacobian(self, J: np.ndarray, B: list, src: np.ndarray, dst: np.ndarray, Mp: np.ndarray, Jl: np.ndarray,
                       starts: np.ndarray, ends: np.ndarray) -> None:
        """One direction's rows (n, 2, n_par) of the Jacobian, block of pairs by block: the source and destination
        photos' rotations and camera groups (``B``: :meth:`_transfer`'s blocks, scaled to work pixels)."""
        A, J_gs, J_gd = B
        n_gp, n_rot = self.n_gp, self.n_rot
        for q, (s0, e0) in enumerate(zip(starts, ends)):
            cs, cd = self.rot_col[src[q]], self.rot_col[dst[q]]
            if cs >= 0:
                J[s0:e0, :, cs:cs + 3] = A[s0:e0] @ (Mp[q] @ Jl[src[q]])
            if cd >= 0:
                J[s0:e0, :, cd:cd + 3] = -(A[s0:e0] @ Jl[dst[q]])
            if n_gp and not self.single_group:
                gs, gd = self.gp_col[src[q]], self.gp_col[dst[q]]
                if J_gs is not None:
                    J[s0:e0, :, gs:gs + n_gp] += J_gs[s0:e0]
                J[s0:e0, :, gd:gd + n_gp] += J_gd[s0:e0]
        if n_gp and self.single_group:
            J[:, :, n_rot:] = J_gd if J_gs is None else J_gs + J_gd

    def soft_l1(self, r: np.ndarray, J: np.ndarray | None, n_obs: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals and Jacobian rescaled so that their sum of squares is the soft-L1 loss of the observations'
        residuals (scale :attr:`c_loss`): rho(z) = 2 (sqrt(1 + z^2) - 1) = g(z)^2,
        g(z) = z sqrt(2 / (1 + sqrt(1 + z^2)))."""
        c_loss = self.c_loss
        z = r[:n_obs] / c_loss
        rho = np.sqrt(1.0 + z * z)
        sq = np.sqrt(2.0 / (1.0 + rho))
        r = r.copy()
        r[:n_obs] = c_loss * z * sq
        if J is not None:
            J = J.copy()
            J[:n_obs] *= (sq - z * z / (sq * rho * (1.0 + rho) ** 2))[:, None]
        return r, J

    def transfer_all(self, x: np.ndarray) -> np.ndarray:
        """(M, 2, 2) residuals (work pixels) of every observation, a -> b and b -> a."""
        m = len(self.obs.a)
        r, _ = self.evaluate(x, np.arange(m), False)
        return r[:4 * m].reshape(m, 2, 2)
