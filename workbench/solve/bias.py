"""Second-order bias of the chained least-squares estimate, and its correction (``SolveOptions.bias_correction``).

The least-squares estimate of a nonlinear model is biased at second order in the noise (a far carriage is pulled
towards the camera by an amount growing as sigma^2). Box's (1971) formula estimates the bias at the solution
from sigma-point differences of the whitened rows (no analytic Hessian), in the free-pose parameters of
:mod:`.uncertainty`; :func:`correct` subtracts it where it is small against the spread and puts the poses back
on the chain. Formula, derivation and limits: ``docs/solver.md``, "Second-order bias correction".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..core.geometry import exp_so3, rotation_angle_deg
from .problem import Chains, Poses
from ..core.camera import distort_with_derivs
from .camera_term import inverse_psd, pose_determined
from .uncertainty import CovarianceModel, contact_rows, pixel_rows, prior_rows

log = logging.getLogger(__name__)


@dataclass
class BiasCorrection:
    """What the correction did. ``shift_*``: per free parameter block, the amount subtracted."""

    applied: bool
    note: str = ""
    max_shift_m: float = 0.0  # largest body-centre shift of a carriage (m)
    max_rotation_deg: float = 0.0  # largest rotation of a carriage (deg)
    focal_shift_px: dict = field(default_factory=dict)
    links_clipped: int = 0
    # Box's measure of nonlinearity: the largest |bias| of a parameter over its standard deviation (all carriages,
    # those left uncorrected included)
    max_bias_over_sd: float = 0.0
    # carriages left uncorrected because their predicted bias was not small against their spread:
    # [{"number", "bias_over_sd"}]
    skipped: list = field(default_factory=list)
    # {"number", "moved_m", "dz_m", "rotated_deg", "corrected"} (body centre; a carriage not corrected itself may
    # still move with its neighbours' correction, over a coupler clipped to the slack)
    per_carriage: list = field(default_factory=list)
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    f: np.ndarray | None = None

    def summary(self) -> dict:
        return {"applied": self.applied, "note": self.note, "max_shift_m": self.max_shift_m,
                "max_rotation_deg": self.max_rotation_deg, "focal_shift_px": dict(self.focal_shift_px),
                "links_clipped": self.links_clipped, "max_bias_over_sd": self.max_bias_over_sd,
                "skipped": [dict(e) for e in self.skipped]}


def _project_rows(prob, idx: np.ndarray, R_rows: np.ndarray, t_rows: np.ndarray, f_rows: np.ndarray) -> np.ndarray:
    """Pixels of the observation rows ``idx`` with a pose and a focal per row (as ``Problem.project``: the
    view's intrinsics with fx = f, fy = f * fy/fx, skew, principal point and distortion kept)."""
    Xw = np.einsum("nij,nj->ni", R_rows, prob.P[idx]) + t_rows
    uv = np.empty((len(idx), 2))
    views = prob.view[idx]
    for v in np.unique(views):
        sel = np.nonzero(views == v)[0]
        intr = prob.views[v].intrinsics
        M = np.asarray(prob.views[v].cam_from_world, dtype=float)
        Pc = Xw[sel] @ M[:3, :3].T + M[:3, 3]
        x, y = Pc[:, 0] / Pc[:, 2], Pc[:, 1] / Pc[:, 2]
        _, xd, yd, *_ = distort_with_derivs(x, y, intr)
        fr = f_rows[sel]
        uv[sel, 0] = fr * xd + intr.skew * yd + intr.cx
        uv[sel, 1] = fr * (intr.fy / intr.fx) * yd + intr.cy
    return uv


def _sqrt_psd(C: np.ndarray) -> np.ndarray:
    """Batched square roots ``L`` (..., m, m) with ``L L^T = C`` for symmetric positive semi-definite ``C``."""
    lam, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    return V * np.sqrt(np.maximum(lam, 0.0))[..., None, :]


class _Units:
    """Groups of whitened rows that share their parameters: ``S`` (n, m) global parameter indices per unit, ``J``
    the rows' whitened Jacobian (n q, P), ``noise`` their true variance factors (n q,), ``evaluate(delta)`` (n, m)
    local perturbations -> (n, q) whitened row values; ``rows`` (n, q) their place in the stacked rows."""

    def __init__(self, S: np.ndarray, J: np.ndarray, noise: np.ndarray, q: int, evaluate):
        self.S, self.J, self.noise, self.q, self.evaluate = S, J, noise, q, evaluate
        self.rows = np.zeros((len(S), q), dtype=int)

    def second(self, u: np.ndarray, r0: np.ndarray) -> np.ndarray:
        """``D(u) = rho(theta + u) + rho(theta - u) - 2 rho(theta)`` per unit and row."""
        return self.evaluate(u) + self.evaluate(-u) - 2.0 * r0


def _pixel_units(prob, R, t, f, focal_views, col, sigma: float) -> _Units:
    """The pixel rows (measured points only, as in the covariance): one unit per point."""
    nA = len(prob.active)
    J, _, _, _ = pixel_rows(prob, R, t, f, focal_views)
    meas = getattr(prob, "measured", None)
    idx = np.arange(len(prob.P)) if meas is None or len(meas) != len(prob.P) else np.nonzero(meas)[0]
    keep = np.stack([2 * idx, 2 * idx + 1], axis=1).reshape(-1)
    gi_of_view = {v: i for i, grp in enumerate(focal_views) for v in grp}
    m_pix = 7 if focal_views else 6
    S = np.zeros((len(idx), m_pix), dtype=int)
    car = prob.car[idx]
    base = np.array([col[k] for k in car]) if len(idx) else np.zeros(0, int)
    S[:, :6] = base[:, None] + np.arange(6)
    if focal_views:
        S[:, 6] = [6 * nA + gi_of_view[v] for v in prob.view[idx]]
    Rr0, tr0, fr0, w_idx = R[car], t[car], f[prob.view[idx]], prob.w[idx]
    uv_obs = prob.uv[idx]

    def eval_pix(delta):
        Rr = exp_so3(delta[:, :3]) @ Rr0
        fr = fr0 + delta[:, 6] if delta.shape[1] > 6 else fr0
        uv = _project_rows(prob, idx, Rr, tr0 + delta[:, 3:6], fr)
        return (uv - uv_obs) * w_idx[:, None] / sigma

    return _Units(S, J[keep] / sigma, np.repeat(prob.w_noise[idx] ** 2, 2), 2, eval_pix)


def _link_units(cars, R, t, chains, slacks, col, P) -> _Units | None:
    """The couplers' offset prior: one unit per link (the two carriages' poses)."""
    Jp = prior_rows(cars, R, t, chains, slacks, col, P)
    links = [(ch[j], ch[j + 1], sl[j]) for ch, sl in zip(chains, slacks) for j in range(len(ch) - 1)]
    if not links:
        return None
    a_, b_ = np.array([L[0] for L in links]), np.array([L[1] for L in links])
    sT = np.array([L[2] for L in links]) / math.sqrt(5.0)
    S = np.concatenate([np.array([col[k] for k in a_])[:, None] + np.arange(6),
                        np.array([col[k] for k in b_])[:, None] + np.arange(6)], axis=1)
    cr = np.array([cars[k].c_rear for k in a_])
    cf = np.array([cars[k].c_front for k in b_])

    def eval_link(delta):
        Ra = exp_so3(delta[:, 0:3]) @ R[a_]
        Rb = exp_so3(delta[:, 6:9]) @ R[b_]
        T = (t[b_] + delta[:, 9:12] + np.einsum("nij,nj->ni", Rb, cf)) - \
            (t[a_] + delta[:, 3:6] + np.einsum("nij,nj->ni", Ra, cr))
        return T / sT[:, None]

    return _Units(S, Jp, np.ones(len(Jp)), 3, eval_link)


def _contact_units(contact, R, t, col, P, sigma_cfg: float) -> _Units | None:
    """The soft per-carriage rows (terrain contact, track prior): one unit per row."""
    Jc, ck, idx = contact_rows(contact, R, t, col, P, sigma_cfg)
    if not ck:
        return None
    S = np.array([col[k] for k in ck])[:, None] + np.arange(6)

    def eval_contact(delta):
        r = contact.residuals(exp_so3(delta[:, :3]) @ R[ck], t[ck] + delta[:, 3:6], idx)
        return (r / sigma_cfg)[:, None]

    return _Units(S, Jc, np.ones(len(Jc)), 1, eval_contact)


def _cross_term(units: list[_Units], r0s: list[np.ndarray], Jw: np.ndarray, Hi: np.ndarray, Sdiag: np.ndarray,
                C: np.ndarray, P: int) -> np.ndarray:
    """``sum_i H_i c_i``, the weighting's cross term (zero when every row is weighted by its inverse noise
    variance), by polarisation of the same sigma-point differences."""
    g2 = np.zeros(P)
    Sm = Sdiag - 1.0
    if not np.abs(Sm).max() > 1e-12:
        return g2
    A = Jw.T * Sm  # J^T (S - I); J^T M = 0, so J^T S M = J^T (S - I) M
    JTSM = A - (A @ Jw) @ Hi @ Jw.T
    Cc = -Hi @ JTSM  # column i: c_i
    for u, r0 in zip(units, r0s):
        m = u.S.shape[1]
        eps = np.sqrt(np.maximum(C[u.S, u.S], 1e-30))  # (n, m): one sd per local axis
        for q in range(u.rows.shape[1]):
            ci = Cc[u.S, u.rows[:, q][:, None]]  # (n, m): row q's direction, local
            for j in range(m):
                a = np.zeros_like(ci)
                a[:, j] = eps[:, j]
                Hc = (u.second(a + ci, r0)[:, q] - u.second(a - ci, r0)[:, q]) / (4.0 * eps[:, j])
                np.add.at(g2, u.S[:, j], np.nan_to_num(Hc))
    return g2


def estimate_bias(prob, cars, R, t, f, focal_views, chains, slacks, contact, model: CovarianceModel,
                  sigma_cfg: float, hold: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Second-order bias (see the module doc) of the free-pose parameters at the solution ``R, t, f``: a vector in
    the order of ``model`` (per active carriage ``omega (3), origin (3)``, then each focal group's focal in px).
    ``model``: :func:`.uncertainty.covariance_model` at this solution (its ``cov`` and pixel ``sigma``); ``hold``
    (P,) bool: parameters held where they are (their bias 0, the others' as if they were known). Also returns
    diagnostics (the two terms' sizes)."""
    col, P = model.col, model.P
    C = model.cov
    units = [u for u in (_pixel_units(prob, R, t, f, focal_views, col, float(model.sigma)),
                         _link_units(cars, R, t, chains, slacks, col, P),
                         _contact_units(contact, R, t, col, P, sigma_cfg)) if u is not None]
    row0 = 0
    for u in units:
        u.rows = row0 + np.arange(u.q * len(u.S)).reshape(-1, u.q)
        row0 += u.q * len(u.S)
    Jw = np.vstack([u.J for u in units])
    if hold is not None and hold.any():
        Jw = Jw * ~hold  # held parameters: no column (the pseudo-inverse gives them none)
        C = C * np.outer(~hold, ~hold)
    Sdiag = np.concatenate([u.noise for u in units])
    Hi = inverse_psd(Jw.T @ Jw)

    # d_i = trace(C H_i) by sigma-point differences along the columns of sqrt(C_loc)
    d = np.zeros(row0)
    r0s = []
    for u in units:
        m = u.S.shape[1]
        r0 = u.evaluate(np.zeros((len(u.S), m)))
        r0s.append(r0)
        L = _sqrt_psd(C[u.S[:, :, None], u.S[:, None, :]])
        D = np.zeros_like(r0)
        for j in range(m):
            D += u.second(L[:, :, j], r0)
        d[u.rows.reshape(-1)] = np.nan_to_num(D).reshape(-1)
    g1 = 0.5 * (Jw.T @ d)
    g2 = _cross_term(units, r0s, Jw, Hi, Sdiag, C, P)
    bias = -Hi @ (g1 + g2)
    return bias, {"box_term_norm": float(np.linalg.norm(Hi @ g1)), "cross_term_norm": float(np.linalg.norm(Hi @ g2))}


def correct(prob, cars, poses: Poses, focal_views, chains: Chains, contact, model: CovarianceModel,
            sigma_cfg: float, max_over_sd: float = 1.0) -> BiasCorrection:
    """The bias-corrected poses (and focal) put back on the chain (see the module doc), with what moved.

    The safeguard: a second-order expansion is valid only where the bias is small against the estimate's spread.
    A carriage whose predicted bias exceeds ``max_over_sd`` standard deviations in any of its six pose components
    (rotation vector, origin) is left uncorrected (its bias set to zero; ``skipped`` names it); a focal whose
    bias exceeds it leaves the focal uncorrected. When every carriage is skipped nothing is applied.
    A carriage whose measured points leave its pose undetermined (``model.undetermined``, or a covariance block that
    is not one, :func:`.camera_term.pose_determined`: predictions or its chain placed it, and its covariance is that
    of a numerically singular information; the solution gives it no interval) has no bias to correct: it is skipped, and
    held where it is in the estimate (its columns and covariance out), so that its numbers (of any size, as a
    singular matrix's inverse gives them) reach neither its chain neighbours' terms nor, through the chain, their
    poses (seed 241027's 6223 once moved its neighbours 645 m that way)."""
    R, t, f = poses.R, poses.t, poses.f
    und = model.undetermined
    loose = [k for k in prob.active if (und is not None and und[model.col[k]:model.col[k] + 6].any())
             or not pose_determined(model.cov[model.col[k]:model.col[k] + 6, model.col[k]:model.col[k] + 6])]
    hold = np.zeros(model.P, bool)
    for k in loose:
        hold[model.col[k]:model.col[k] + 6] = True
    if loose and und is not None:
        hold[6 * len(prob.active):] |= und[6 * len(prob.active):]
    bias, diag = estimate_bias(prob, cars, R, t, f, focal_views, chains.members, chains.slacks, contact, model,
                               sigma_cfg, hold)
    if not np.all(np.isfinite(bias)):
        log.warning("bias correction: the estimated bias is not finite; not applied")
        return BiasCorrection(False, note="not applied: the estimated bias is not finite")
    col = model.col
    sd = np.sqrt(np.maximum(np.diag(model.cov), 1e-300))
    bias = bias.copy()
    skipped = []
    for k in loose:
        bias[col[k]:col[k] + 6] = 0.0
    ratio = float(np.max(np.abs(bias) / sd)) if len(bias) else 0.0
    for k in prob.active:
        c = col[k]
        r_k = float(np.max(np.abs(bias[c:c + 6]) / sd[c:c + 6]))
        if k not in loose and not r_k < max_over_sd:
            skipped.append({"number": cars[k].number, "bias_over_sd": r_k})
            bias[c:c + 6] = 0.0
    nA_ = len(prob.active)
    for i in range(len(focal_views)):
        if not abs(bias[6 * nA_ + i]) / sd[6 * nA_ + i] < max_over_sd:
            bias[6 * nA_ + i] = 0.0
    why = ""
    if skipped:
        names = ", ".join(f"{e['number']} ({e['bias_over_sd']:.2f} sd)" for e in skipped)
        why = (f"not applied to car(s) {names}: the second-order expansion does not hold where the bias is not "
               f"small against the spread (limit {max_over_sd:g} sd)")
    if loose:
        why = "; ".join(x for x in (why, f"not applied to car(s) {', '.join(cars[k].number for k in loose)}: its "
                                         "measured points do not determine its pose") if x)
        skipped += [{"number": cars[k].number, "bias_over_sd": None, "undetermined": True} for k in loose]
    if prob.active and len(skipped) == len(prob.active):
        return BiasCorrection(False, note=why, max_bias_over_sd=ratio, skipped=skipped)
    Rn, tn, fn = R.copy(), t.copy(), f.copy()
    for k in prob.active:
        c = col[k]
        Rn[k] = exp_so3(-bias[c:c + 3]) @ R[k]
        tn[k] = t[k] - bias[c + 3:c + 6]
    nA = len(prob.active)
    focal_shift = {}
    for i, grp in enumerate(focal_views):
        df = -float(bias[6 * nA + i])
        for v in grp:
            fn[v] = f[v] + df
            focal_shift[prob.views[v].name] = df
    # back onto the chain: offsets from the corrected poses, clipped to the ball, translations recomposed
    clipped = 0
    for ch, sl in zip(chains.members, chains.slacks):
        for j in range(len(ch) - 1):
            a, b = ch[j], ch[j + 1]
            T = tn[b] + Rn[b] @ cars[b].c_front - tn[a] - Rn[a] @ cars[a].c_rear
            nT = float(np.linalg.norm(T))
            if nT > sl[j]:
                T = T * (sl[j] / nT)
                clipped += 1
            tn[b] = tn[a] + Rn[a] @ cars[a].c_rear + T - Rn[b] @ cars[b].c_front
    per, mx, mr = [], 0.0, 0.0
    for k in prob.active:
        e = (Rn[k] @ cars[k].c_body + tn[k]) - (R[k] @ cars[k].c_body + t[k])
        ang = rotation_angle_deg(Rn[k], R[k])
        per.append({"number": cars[k].number, "moved_m": float(np.linalg.norm(e)), "dz_m": float(e[2]),
                    "rotated_deg": ang, "corrected": not any(x["number"] == cars[k].number for x in skipped)})
        mx, mr = max(mx, float(np.linalg.norm(e))), max(mr, ang)
    note = (f"second-order bias removed (Box 1971): largest body-centre shift {mx:.3f} m, largest rotation "
            f"{mr:.2f} deg" + (", focal " + ", ".join(f"{n} {v:+.1f} px" for n, v in focal_shift.items())
                               if focal_shift else "") +
            (f"; {clipped} coupler offset(s) clipped to the slack" if clipped else "") + ("; " + why if why else ""))
    log.debug("bias correction: %s (%s)", note, diag)
    return BiasCorrection(True, note=note, max_shift_m=mx, max_rotation_deg=mr, focal_shift_px=focal_shift,
                          links_clipped=clipped, max_bias_over_sd=ratio, per_carriage=per, R=Rn, t=tn, f=fn,
                          skipped=skipped)
