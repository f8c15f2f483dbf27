"""The pose predictions counted in the covariance, with the error of the face alignment they come from (issue 21).

The correspond stage places a car's points off its found face (couplers, an unseen face's corners) by projecting
them with the car's pose in that photo (``method = "pose"``; ``correspond.assign.observations_of``), a planar PnP
on the face's inlier matches. The solve fits them as predictions (at 2 px; step 4b keeps them on every car where
they agree with the measured points), and until now its covariance left them out, as if the estimator were the
measured points' alone: against the truth the predictions place the cars far better than the measured points alone
(docs/calibration.md, "which piece is too wide"), so the intervals described another, worse estimator.

A prediction is not independent evidence: to first order the PnP pose from the matches is a function of the face's
homography (the pose is a 6-parameter sub-model of the homography's 8, fitted to the same matches, so
``d pose = (D^T A^T A D)^-1 D^T A^T A d h``), and the face's marked points ``y`` (2 n) placed by that homography
determine it (n >= 4). So the pose is the generalised least squares fit to those points with their own covariance
``C = L L^T`` (``L`` their loadings, ``workbench.correspond.alignment``),

    d pose = T d y,    T = (G^T C^+ G)^-1 G^T C^+,    G = d y / d pose,

and a prediction ``x_p`` of the same car in that photo moves by ``J_p T d y``: its loading on each face alignment
``beta`` of the car in that photo is ``J_p T_beta L_beta`` (2, 8), the same ``xi`` as the face's points. With these
rows in the sandwich ``H^-1 G H^-1`` (their weights in ``H`` as the fit has them, their correlated error in ``G``) the
covariance is that of the estimator the solve runs. Predictions of a car with fewer than 4 aligned points in that
photo stay out (as before). A point carried from another photo of the panorama is its source seen again: it counts
with its source's alignment error (:func:`carried_rows`, since session 31; one carried from a prediction, with
the prediction's, since session 32).

A face aligned by ECC from a predicted pose, without matches of its own (a guided face: the pose search's and the
completion's), is the same: the correspond stage fits the car's pose to its aligned faces' points
(``correspond.complete.joint_pose``) and predicts the other points from it. Its loading is its misfit in six
affine modes (:func:`.alignment_covariance.guided_loadings`); until session 31 its predictions stayed out too, and
its misfit was counted on its own points alone (docs/calibration.md, "Session 31").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .alignment_covariance import views_per_face

MIN_POINTS = 4  # the face's points that fix its homography (and the pose)


@dataclass
class PoseRows:
    """The counted predictions: ``info`` (P, P) their information ``sum J_p^T rho_p J_p`` (weighted rows, per
    pixel^2 of the solve's sigma, as ``Hp_unit``), ``contrib`` block -> (P, 8) their share of that face alignment's
    gradient ``sum_p J_p^T rho_p w_p L_p`` (to add to the block's in :func:`.alignment_covariance.alignment_term`),
    ``n`` how many predictions were counted, and ``loadings`` each counted prediction's row -> block -> its loading
    ``L_p`` (2, 8) on that alignment (what a point carried from it inherits, :func:`carried_rows`)."""

    info: np.ndarray
    contrib: dict[int, np.ndarray]
    n: int
    loadings: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)


def _loading_scale(prob, meas: np.ndarray, block: np.ndarray, views_shared: bool) -> np.ndarray:
    """(M,) the factor on each point's alignment loading: the square root of the photos its face is aligned in
    (:func:`.alignment_covariance.views_per_face`, as the measured points' in the covariance), or 1."""
    nface = views_per_face(np.where(meas, block, -1), prob.group, prob.view) if views_shared else \
        np.where(block >= 0, 1.0, 0.0)
    return np.sqrt(np.maximum(nface, 0.0))


def pose_rows(prob, J: np.ndarray, rho: np.ndarray, col: dict[int, int], views_shared: bool = True,
              block: np.ndarray | None = None, loading: np.ndarray | None = None) -> PoseRows | None:
    """The predictions of ``prob`` (:class:`.problem.Problem`; rows ``~measured``) counted as the module doc says.
    ``J`` (2M, P): the weighted pixel rows of every row (:func:`.uncertainty.pixel_rows`); ``rho`` (2M,) the robust
    loss's weights per row; ``col`` each carriage's first column; ``views_shared``: scale each face alignment's
    loading by the photos it is aligned in (:func:`.alignment_covariance.views_per_face`), as the measured points'.
    ``block`` (M,), ``loading`` (M, 2, 8): the alignments to use (None: the problem's; with the guided faces'
    of :func:`.alignment_covariance.guided_loadings`). None when no prediction qualifies."""
    meas = getattr(prob, "measured", None)
    block = getattr(prob, "block", None) if block is None else block
    loading = getattr(prob, "loading", None) if loading is None else loading
    M = len(prob.P)
    if meas is None or block is None or loading is None or len(meas) != M or len(block) != M or meas.all() \
            or not (block >= 0).any():
        return None
    scale = _loading_scale(prob, meas, block, views_shared)
    w = prob.w
    P = J.shape[1]
    Jr = J.reshape(M, 2, P)
    rr = rho.reshape(M, 2)
    info = np.zeros((P, P))
    contrib: dict[int, np.ndarray] = {}
    loadings: dict[int, dict[int, np.ndarray]] = {}
    n = 0
    for k in prob.active:
        c = col[k]
        rows_k = prob.by_car[k]
        for v in np.unique(prob.view[rows_k]):
            rows = rows_k[prob.view[rows_k] == v]
            S = rows[meas[rows] & (block[rows] >= 0)]
            preds = rows[~meas[rows]]
            if len(S) < MIN_POINTS or len(preds) == 0 or np.any(w[S] <= 0):
                continue
            G = (Jr[S, :, c:c + 6] / w[S, None, None]).reshape(-1, 6)  # d y / d pose, unweighted
            Ls = loading[S] * scale[S, None, None]
            Lf = Ls.reshape(-1, 8)
            bl = block[S]
            C = np.zeros((2 * len(S), 2 * len(S)))
            for b in np.unique(bl):  # the face alignments are independent of one another
                i2 = np.repeat(bl == b, 2)
                C[np.ix_(i2, i2)] = Lf[i2] @ Lf[i2].T
            Ci = np.linalg.pinv(C, rcond=1e-10, hermitian=True)
            N = G.T @ Ci @ G
            if np.linalg.cond(N) > 1e12:
                continue
            T = np.linalg.solve(N, G.T @ Ci)  # (6, 2 n)
            for p in preds:
                if w[p] <= 0:
                    continue
                Jw = Jr[p] * rr[p][:, None]  # weighted row, as in the sandwich
                Ju = Jr[p, :, c:c + 6] / w[p]  # d x_p / d pose, unweighted
                info += Jw.T @ Jr[p]
                loadings[int(p)] = {}
                for b in np.unique(bl):
                    i2 = np.repeat(bl == b, 2)
                    Lp = Ju @ T[:, i2] @ Lf[i2]  # (2, 8) on block b's xi
                    contrib[int(b)] = contrib.get(int(b), np.zeros((P, 8))) + Jw.T @ (w[p] * Lp)
                    loadings[int(p)][int(b)] = Lp
                n += 1
    return PoseRows(info, contrib, n, loadings) if n else None


def carried_rows(prob, J: np.ndarray, r: np.ndarray, rho: np.ndarray, col: dict[int, int], block: np.ndarray,
                 loading: np.ndarray, views_shared: bool = True, max_px: float = 1.5,
                 predicted: dict[int, dict[int, np.ndarray]] | None = None) -> PoseRows | None:
    """The points carried from another photo of a panorama (``prob.carried``; correspond's ``method = "carried"``)
    counted as what they are: a point found in photo a placed in photo b by the photos' homography, the same ray,
    so its error is its source's mapped by that homography's derivative ``D = d x_b / d x_a`` (2, 2). The fit
    weighs it as a point of its own; here it enters ``H`` with that weight and ``G`` with its source's face
    alignment error: its loading ``D L_a`` on the source's alignment. The source is the carriage's point of the
    same name in another photo whose residual, mapped by ``D``, comes within ``max_px`` of the carried point's
    (the correspond stage keeps the most confident of several): a measured, aligned point (its loading), or else a
    counted prediction (``predicted``: :attr:`PoseRows.loadings` of :func:`pose_rows`, its loading on each of the
    alignments its car's pose rests on). ``D`` is taken from the two rows' derivatives with respect to the point
    (photos from one place see a point's direction alone). A carried point without such a source stays out.
    ``J``, ``rho``, ``col`` as :func:`pose_rows`, ``r`` (2M,) the weighted residuals; ``block``, ``loading`` the
    alignments (M,), (M, 2, 8). None when none qualifies."""
    carried = getattr(prob, "carried", None)
    meas = getattr(prob, "measured", None)
    M = len(prob.P)
    if carried is None or meas is None or len(carried) != M or not carried.any():
        return None
    scale = _loading_scale(prob, meas, block, views_shared)
    predicted = predicted or {}
    is_pred = np.zeros(M, bool)
    is_pred[list(predicted)] = True
    w, P = prob.w, J.shape[1]
    Jr, rr = J.reshape(M, 2, P), rho.reshape(M, 2)
    res = r.reshape(M, 2) / np.where(w > 0, w, 1.0)[:, None]  # the residuals in pixels
    info = np.zeros((P, P))
    contrib: dict[int, np.ndarray] = {}
    n = 0
    for i in np.nonzero(carried & (w > 0))[0]:
        k, c = int(prob.car[i]), col.get(int(prob.car[i]))
        if c is None:
            continue
        here = (prob.car == k) & (prob.view != prob.view[i]) & np.all(np.isclose(prob.P, prob.P[i]), axis=1)
        Jb = Jr[i, :, c + 3:c + 6] / w[i]  # d x_b / d X (the point's derivative: the pose's translation columns)
        best, best_d = None, max_px
        for sources in (np.nonzero(here & meas & (block >= 0))[0], np.nonzero(here & is_pred)[0]):
            for s in sources:
                Ja = Jr[s, :, c + 3:c + 6] / w[s]
                D = Jb @ np.linalg.pinv(Ja, rcond=1e-8)
                d = float(np.linalg.norm(res[i] - D @ res[s]))
                if d < best_d:
                    best, best_d = (s, D), d
            if best is not None:
                break  # a measured source first: a prediction only where none is
        if best is None:
            continue
        s, D = best
        Jw = Jr[i] * rr[i][:, None]
        info += Jw.T @ Jr[i]
        source = {int(block[s]): loading[s] * scale[s]} if meas[s] else predicted[int(s)]
        for b, Ls in source.items():  # (2, 8) on each alignment the source's error comes from
            contrib[b] = contrib.get(b, np.zeros((P, 8))) + Jw.T @ (w[i] * (D @ Ls))
        n += 1
    return PoseRows(info, contrib, n) if n else None


def merged_rows(a: PoseRows | None, b: PoseRows | None) -> PoseRows | None:
    """Two sets of counted predictions as one (their information added, their shares of each alignment summed)."""
    if a is None or b is None:
        return a if b is None else b
    contrib = dict(a.contrib)
    for k, v in b.contrib.items():
        contrib[k] = contrib[k] + v if k in contrib else v
    return PoseRows(a.info + b.info, contrib, a.n + b.n, {**a.loadings, **b.loadings})
