"""Second-order bias of the chained least-squares estimate, and its correction (``SolveOptions.bias_correction``).

Why
    The least-squares (maximum-likelihood) estimate of a nonlinear model is biased at second order in the noise:
    for a far consist the depth of each carriage enters the pixels as ``1 / Z`` and a nearly side-on carriage's
    yaw at second order, and the benchmark shows the estimate pulled towards the camera by an amount that grows
    as sigma^2 (docs/solver.md). The bias is a property of the model at the solution, so it can be estimated
    there and subtracted.

The formula (Box 1971, "Bias in nonlinear estimation"; Cook, Tsai & Wei 1986)
    Rows ``rho_i(theta)`` whitened by their assumed noise (the weighted pixel rows over the pixel sigma, the
    couplers' offset prior ``T / sigma_T``, the terrain contact ``clearance / sigma_z``), Jacobian ``J``,
    ``H = J^T J``, true row covariance ``S`` (diagonal: ``w_noise^2`` for the pixel rows, 1 for the others), the
    estimator's covariance ``C = H^-1 J^T S J H^-1`` (the sandwich of :mod:`.uncertainty`; ``H^-1`` when
    ``S = I``) and ``H_i`` the Hessian of row ``i``. Expanding the normal equations to second order,

        E[theta_hat] - theta = -H^-1 ( 1/2 J^T d + sum_i H_i c_i ),   d_i = trace(C H_i),
        c_i = E[(M e)_i delta_1] = -H^-1 J^T S M[:, i],   M = I - J H^-1 J^T.

    With every row weighted by its inverse noise variance (``S = I``: the per-point weighting, or equal point
    counts) ``J^T S M = 0`` and this is Box's ``-1/2 H^-1 J^T d``; the second term is the per-carriage
    weighting's own (its cross term between the residual and the first-order error).

Second derivatives without an analytic Hessian
    Each row depends on few parameters (a pixel row on its carriage's rotation, origin and the focal of its
    photo; a coupler row on the two carriages of its link; a contact row on its carriage). With ``L`` a square
    root of the local block of ``C`` (``L L^T = C_loc``), ``d_i = sum_j L_j^T H_i L_j`` and
    ``L_j^T H_i L_j = rho_i(theta + L_j) + rho_i(theta - L_j) - 2 rho_i(theta)`` up to fourth-order terms: central
    differences with a one-sigma step (sigma points), exact for a quadratic row and averaging the curvature over
    the scale the estimate actually spreads. All rows are evaluated together per column ``j``: 2 x (6 or 7)
    evaluations of the pixel residuals, whatever the number of carriages. The second term's ``H_i c_i`` comes
    from the same differences by polarisation, ``a^T H b = (D(a + b) - D(a - b)) / 4`` with ``D(u) = u^T H u``.

Parametrisation
    The free-pose parameters of :mod:`.uncertainty` (per carriage a scene-frame rotation vector ``R <- Exp(w)
    R`` and the origin's translation, plus the focal in pixels): the bias is that of these parameters, so the
    corrected body centres (``R c_body + t``, a 2 m lever) are corrected to the same order, and every carriage's
    translation is its own (not the sum of its predecessors' rotations, as in the solver's chain
    parametrisation, where the correction would need every predecessor's second-order term).

Constraints
    The corrected poses are put back on the chain: each link's offset ``T`` is recomputed from them, clipped to
    the ball ``|T| <= slack`` when the correction would take it out (the followers then move with the clip, so
    that every other offset is kept), and the chain's translations are recomposed from its first carriage. The
    terrain contact term is one of the rows (its curvature counts); step 2's placement is not redone.

Limits
    Second order only (an expansion in sigma^2; where the estimate's spread is not small against the curvature,
    as a carriage barely determined along the line of sight, it is a first correction, not an unbiased
    estimate). The shared misfit of a face (``face_sigma_px``) enters ``C`` but not ``S`` (the cross term assumes
    independent rows). Not applied with a robust loss (the IRLS weights are not a fixed noise model) nor with an
    estimated focal (:func:`.chain._bias_skip_reason`: there the expansion fails, docs/solver.md); the code
    handles a focal parameter (and the tests check it against the expansion) for diagnostics.

Safeguard
    The expansion is valid only where the bias is small against the estimate's spread. A carriage whose predicted
    bias exceeds ``max_over_sd`` (``SolveOptions.bias_max_over_sd``, 1) standard deviations in any of its six
    pose components is left uncorrected (:func:`correct`; ``BiasCorrection.skipped`` and the step's note name
    it); when every carriage is, nothing is applied. On the benchmark at a known focal no carriage reached it
    in 150 trials per cell, but the far, noisy cell comes close (12 cars at 2 px: largest ratio 0.94 in 40
    trials; 0.32 at 6 cars, 2 px); it guards a real scene's poorly observed carriage.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from .projection import _distort_with_derivs, exp_so3
from .uncertainty import _contact_rows, _inv, _prior_rows, _rows

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
    """Pixels of the observation rows ``idx`` with a pose and a focal per row (as ``_Problem.project``: the
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
        _, xd, yd, *_ = _distort_with_derivs(x, y, intr)
        fr = f_rows[sel]
        uv[sel, 0] = fr * xd + intr.skew * yd + intr.cx
        uv[sel, 1] = fr * (intr.fy / intr.fx) * yd + intr.cy
    return uv


def _sqrt_psd(C: np.ndarray) -> np.ndarray:
    """Batched square roots ``L`` (..., m, m) with ``L L^T = C`` for symmetric positive semi-definite ``C``."""
    lam, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    return V * np.sqrt(np.maximum(lam, 0.0))[..., None, :]


class _Units:
    """Groups of whitened rows that share their parameters: ``S`` (n, m) global parameter indices per unit,
    ``rows`` (n, q) the rows of each unit in the stacked whitened row vector, ``evaluate(delta)`` (n, m) local
    perturbations -> (n, q) whitened row values."""

    def __init__(self, S: np.ndarray, rows: np.ndarray, evaluate):
        self.S, self.rows, self.evaluate = S, rows, evaluate

    def second(self, u: np.ndarray, r0: np.ndarray) -> np.ndarray:
        """``D(u) = rho(theta + u) + rho(theta - u) - 2 rho(theta)`` per unit and row."""
        return self.evaluate(u) + self.evaluate(-u) - 2.0 * r0


def estimate_bias(prob, cars, R, t, f, focal_views, chains, slacks, contact, model: dict,
                  sigma_cfg: float) -> tuple[np.ndarray, dict]:
    """Second-order bias (see the module doc) of the free-pose parameters at the solution ``R, t, f``: a vector in
    the order of ``model`` (per active carriage ``omega (3), origin (3)``, then each focal group's focal in px).
    ``model``: :func:`.uncertainty.covariance_model` at this solution (its ``cov`` and pixel ``sigma``). Also
    returns diagnostics (the two terms' sizes)."""
    act = prob.active
    col, P = model["col"], model["P"]
    sigma = float(model["sigma"])
    C = model["cov"]
    nA = len(act)
    units: list[_Units] = []
    Jblocks = []
    row0 = 0
    noise = []

    # -- pixel rows (measured points only, as in the covariance) ------------------------------------------------
    J, _, _, _ = _rows(prob, R, t, f, focal_views)
    meas = getattr(prob, "measured", None)
    idx = np.arange(len(prob.P)) if meas is None or len(meas) != len(prob.P) else np.nonzero(meas)[0]
    keep = np.stack([2 * idx, 2 * idx + 1], axis=1).reshape(-1)
    Jblocks.append(J[keep] / sigma)
    noise.append(np.repeat(prob.w_noise[idx] ** 2, 2))
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

    def eval_pix(delta, Rr0=Rr0, tr0=tr0, fr0=fr0, idx=idx):
        Rr = exp_so3(delta[:, :3]) @ Rr0
        fr = fr0 + delta[:, 6] if delta.shape[1] > 6 else fr0
        uv = _project_rows(prob, idx, Rr, tr0 + delta[:, 3:6], fr)
        return (uv - uv_obs) * w_idx[:, None] / sigma

    units.append(_Units(S, row0 + np.arange(2 * len(idx)).reshape(-1, 2), eval_pix))
    row0 += 2 * len(idx)

    # -- the couplers' offset prior -------------------------------------------------------------------------
    Jp = _prior_rows(cars, R, t, chains, slacks, col, P)
    links = [(ch[j], ch[j + 1], sl[j]) for ch, sl in zip(chains, slacks) for j in range(len(ch) - 1)]
    if links:
        Jblocks.append(Jp)
        noise.append(np.ones(len(Jp)))
        a_, b_ = np.array([L[0] for L in links]), np.array([L[1] for L in links])
        sT = np.array([L[2] for L in links]) / math.sqrt(5.0)
        S = np.concatenate([np.array([col[k] for k in a_])[:, None] + np.arange(6),
                            np.array([col[k] for k in b_])[:, None] + np.arange(6)], axis=1)
        cr = np.array([cars[k].c_rear for k in a_])
        cf = np.array([cars[k].c_front for k in b_])

        def eval_link(delta, a_=a_, b_=b_, sT=sT, cr=cr, cf=cf):
            Ra = exp_so3(delta[:, 0:3]) @ R[a_]
            Rb = exp_so3(delta[:, 6:9]) @ R[b_]
            T = (t[b_] + delta[:, 9:12] + np.einsum("nij,nj->ni", Rb, cf)) - \
                (t[a_] + delta[:, 3:6] + np.einsum("nij,nj->ni", Ra, cr))
            return T / sT[:, None]

        units.append(_Units(S, row0 + np.arange(3 * len(links)).reshape(-1, 3), eval_link))
        row0 += 3 * len(links)

    # -- terrain contact ---------------------------------------------------------------------------------------
    Jc, ck = _contact_rows(contact, R, t, col, P, sigma_cfg)
    if ck:
        Jblocks.append(Jc)
        noise.append(np.ones(len(Jc)))
        sz = sigma_cfg / contact.scale
        S = np.array([col[k] for k in ck])[:, None] + np.arange(6)

        def eval_contact(delta, ck=ck, sz=sz):
            d, _, _ = contact.clearances(exp_so3(delta[:, :3]) @ R[ck], t[ck] + delta[:, 3:6], ck)
            return (d / sz)[:, None]

        units.append(_Units(S, row0 + np.arange(len(ck))[:, None], eval_contact))
        row0 += len(ck)

    Jw = np.vstack(Jblocks)
    Sdiag = np.concatenate(noise)
    Hi = _inv(Jw.T @ Jw)

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

    # the weighting's cross term (zero when every row is weighted by its inverse noise variance)
    g2 = np.zeros(P)
    Sm = Sdiag - 1.0
    if np.abs(Sm).max() > 1e-12:
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
    bias = -Hi @ (g1 + g2)
    return bias, {"box_term_norm": float(np.linalg.norm(Hi @ g1)), "cross_term_norm": float(np.linalg.norm(Hi @ g2))}


def correct(prob, cars, R, t, f, focal_views, chains, slacks, contact, model: dict, sigma_cfg: float,
            views, max_over_sd: float = 1.0) -> BiasCorrection:
    """The bias-corrected poses (and focal) put back on the chain (see the module doc), with what moved.

    The safeguard: a second-order expansion is valid only where the bias is small against the estimate's spread.
    A carriage whose predicted bias exceeds ``max_over_sd`` standard deviations in any of its six pose components
    (rotation vector, origin) is left uncorrected (its bias set to zero; ``skipped`` names it); a focal whose
    bias exceeds it leaves the focal uncorrected. When every carriage is skipped nothing is applied."""
    bias, diag = estimate_bias(prob, cars, R, t, f, focal_views, chains, slacks, contact, model, sigma_cfg)
    if not np.all(np.isfinite(bias)):
        log.warning("bias correction: the estimated bias is not finite; not applied")
        return BiasCorrection(False, note="not applied: the estimated bias is not finite")
    col = model["col"]
    sd = np.sqrt(np.maximum(np.diag(model["cov"]), 1e-300))
    ratio = float(np.max(np.abs(bias) / sd)) if len(bias) else 0.0
    bias = bias.copy()
    skipped = []
    for k in prob.active:
        c = col[k]
        r_k = float(np.max(np.abs(bias[c:c + 6]) / sd[c:c + 6]))
        if not r_k < max_over_sd:
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
            focal_shift[views[v].name] = df
    # back onto the chain: offsets from the corrected poses, clipped to the ball, translations recomposed
    clipped = 0
    for ch, sl in zip(chains, slacks):
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
        ang = float(np.degrees(np.arccos(np.clip((np.trace(Rn[k] @ R[k].T) - 1.0) / 2.0, -1.0, 1.0))))
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
