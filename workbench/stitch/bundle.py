"""The rotation-only bundle adjustment (one camera centre): the matches stacked as observations, and the two
Levenberg-Marquardt passes over :class:`~workbench.stitch.bundle_problem.RotationBundleProblem` (docs/stitching.md,
step 6).

LM (MINPACK) walks the focal / distortion valley far better than trf. A robust first pass (soft L1, by rescaling
the residuals so that the loss is their sum of squares) on a subset of each pair's matches finds the inliers
and comes near the minimum; the final pass starts there with every inlier and converges in a few steps.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import logging
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from .bundle_problem import BundleOptions, Observations, RotationBundleProblem, min_work_scale
from .register import PairMatch, PhotoFeatures, median, unique_sorted

log = logging.getLogger(__name__)

__all__ = ["BAResult", "BundleOptions", "Observations", "bundle_adjust", "load_solver", "min_work_scale",
           "stack_observations"]


def stack_observations(pairs: list[PairMatch], feats: list[PhotoFeatures], kept: list[int], *,
                       max_per_pair: int = 300, seed: int = 0) -> Observations:
    """The inlier matches of the pairs of ``kept`` photos, at most ``max_per_pair`` of each (a random choice)."""
    rng = np.random.default_rng(seed)
    kset = set(kept)
    a, b, xa, xb, pid = [], [], [], [], []
    for k, p in enumerate(pairs):
        if p.i not in kset or p.j not in kset or p.n_inliers == 0:
            continue
        x_i = feats[p.i].keypoints[p.idx_i] if p.x_i is None else p.x_i
        x_j = feats[p.j].keypoints[p.idx_j] if p.x_j is None else p.x_j
        sel = np.arange(len(x_i))
        if len(sel) > max_per_pair:
            sel = np.sort(rng.choice(len(sel), max_per_pair, replace=False))
        a.append(np.full(len(sel), p.i))
        b.append(np.full(len(sel), p.j))
        xa.append(x_i[sel])
        xb.append(x_j[sel])
        pid.append(np.full(len(sel), k))
    return Observations(np.concatenate(a), np.concatenate(b), np.concatenate(xa), np.concatenate(xb),
                        np.concatenate(pid))


@dataclass
class BAResult:
    cam_from_pano: dict[int, np.ndarray]
    intrinsics: dict[int, CameraIntrinsics]  # per photo, full resolution, as on disk
    residuals_px: np.ndarray  # (M, 2, 2): per observation, a->b and b->a residual, full-resolution pixels
    used: np.ndarray  # (M,) bool: observations kept after outlier rejection
    cost: float
    n_iterations: int


def _compress_least_squares(r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (m,) and Jacobian (m, n) replaced by (n + 1,) and (n + 1, n) ones that Levenberg-Marquardt cannot
    tell apart: with R (n + 1, n + 1) upper triangular, R^T R = [J | r]^T [J | r] (so [J | r] = Q R, Q with
    orthonormal columns), r' = R[:, n] and J' = R[:, :n] give |J' p + r'| = |J p + r| for every step p, |r'| = |r|
    and J' has J's column norms (MINPACK's scaling): the same steps and tests up to rounding, but MINPACK factorises
    n + 1 rows instead of m = 4 per match (its own time was about 30 % of budapest's adjustment).
    R from the Cholesky factor of the column-equilibrated Gram matrix (QR when that is not positive definite)."""
    m, n = J.shape
    if m <= 2 * (n + 1):
        return r, J
    A = np.empty((m, n + 1))
    A[:, :n] = J
    A[:, n] = r
    G = A.T @ A
    c = np.sqrt(np.diag(G))
    c[c == 0] = 1.0
    try:
        L = np.linalg.cholesky(G / np.outer(c, c))
        R = L.T * c[None, :]
        if not np.all(np.isfinite(R)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        R = np.linalg.qr(A, mode="r")
    return np.ascontiguousarray(R[:, n]), np.ascontiguousarray(R[:, :n])


class _Objective:
    """``fun`` and ``jac`` for :func:`least_squares` (args: observation indices, robust), compressed.

    MINPACK asks for the Jacobian at almost every point whose residuals it has just asked for (each accepted step):
    both come from one evaluation, the Jacobian kept for that point (the same numbers as evaluating it again)."""

    def __init__(self, problem: RotationBundleProblem) -> None:
        self.problem = problem
        self.last: dict = {}

    def fun(self, x: np.ndarray, idx: np.ndarray, robust: bool) -> np.ndarray:
        r, J = self.problem.evaluate(x, idx, True)
        if robust:
            r, J = self.problem.soft_l1(r, J, 4 * len(idx))
        r, J = _compress_least_squares(r, J)
        self.last.update(x=x.copy(), idx=idx, J=J)
        return r

    def jac(self, x: np.ndarray, idx: np.ndarray, robust: bool) -> np.ndarray:
        if self.last.get("idx") is idx and np.array_equal(self.last["x"], x):
            return self.last["J"]
        r, J = self.problem.evaluate(x, idx, True)
        return _compress_least_squares(*(self.problem.soft_l1(r, J, 4 * len(idx)) if robust else (r, J)))[1]


def _minpack():
    """SciPy's MINPACK extension (``scipy.optimize._minpack``), loaded from its file without the package
    ``scipy.optimize`` (whose ``__init__`` imports every optimiser: 0.5-0.9 s of CPU, more than a small panorama's
    whole registration); None where that fails (then :func:`least_squares` imports SciPy's own)."""
    if "minpack" not in _MINPACK:
        _MINPACK["minpack"] = None
        try:
            name = "scipy.optimize._minpack"
            mod = sys.modules.get(name)
            if mod is None:
                spec = importlib.util.find_spec("scipy")
                folder = Path(next(iter(spec.submodule_search_locations))) / "optimize"
                path = next(iter(sorted(folder.glob("_minpack.*.so")) + sorted(folder.glob("_minpack.*.pyd"))))
                loader = importlib.machinery.ExtensionFileLoader(name, str(path))
                mod = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader))
                loader.exec_module(mod)
            _MINPACK["minpack"] = mod if callable(getattr(mod, "_lmder", None)) else None
        except (ImportError, OSError, StopIteration, TypeError, AttributeError) as exc:
            log.debug("stitch: MINPACK not loaded from its file (%s); scipy.optimize is imported", exc)
    return _MINPACK["minpack"]


_MINPACK: dict = {}


def load_solver() -> None:
    """Load what the adjustment will call now rather than at its first use: MINPACK's extension (:func:`_minpack`)
    and SciPy's package, which its first call imports (for ``LowLevelCallable``), and NumPy's random generators,
    which pick the matches it adjusts. Called while the photos' descriptions are still being computed on other
    threads, these imports leave the path to the panorama."""
    import numpy.random  # noqa: F401  (stack_observations, _robust_subset)
    import scipy  # noqa: F401

    _minpack()


@dataclass
class LMResult:
    """What :func:`least_squares` returns (the fields of SciPy's ``OptimizeResult`` that the adjustment reads)."""

    x: np.ndarray
    cost: float
    nfev: int
    info: int  # MINPACK's termination code (SciPy's own path: its status)
    message: str = ""


def least_squares(fun, x0: np.ndarray, jac, args: tuple = (), *, xtol: float, ftol: float,
                  max_nfev: int) -> LMResult:
    """``scipy.optimize.least_squares(fun, x0, jac, args=args, method="lm", xtol=xtol, ftol=ftol,
    max_nfev=max_nfev)``: MINPACK's ``lmder`` with SciPy's defaults for ``lm`` (gtol 1e-8, step bound factor 100,
    scaling by the Jacobian's columns), called as SciPy calls it (``_lsq.least_squares.call_minpack``), so the
    same steps and result; through SciPy itself where the extension could not be loaded on its own."""
    mp = _minpack()
    if mp is None:
        from scipy.optimize import least_squares as solve

        sol = solve(fun, x0, jac=jac, args=args, method="lm", xtol=xtol, ftol=ftol, max_nfev=max_nfev)
        return LMResult(sol.x, float(sol.cost), int(sol.nfev), int(sol.status), str(sol.message))
    x0 = np.atleast_1d(np.asarray(x0, dtype=float))

    def f(x):
        return np.atleast_1d(fun(x, *args))

    def J(x):
        return np.atleast_2d(jac(x, *args))

    x, info, status = mp._lmder(f, J, x0.copy(), (), True, False, ftol, xtol, 1e-8, max_nfev, 100.0, None)
    r = info["fvec"]
    return LMResult(x, float(0.5 * np.dot(r, r)), int(info["nfev"]), int(status), f"MINPACK info {status}")


def _solve(objective: _Objective, x: np.ndarray, idx: np.ndarray, robust: bool, tol: float, rnd: int,
           opts: BundleOptions) -> tuple[np.ndarray, float, int]:
    """One LM pass over the observations ``idx``: (parameters, cost, evaluations)."""
    sol = least_squares(objective.fun, x, jac=objective.jac, args=(idx, robust), xtol=tol, ftol=tol,
                        max_nfev=opts.max_nfev * 2)
    log.debug("BA round %d: %d evaluations, cost %.4g, %s", rnd, sol.nfev, float(sol.cost), sol.message)
    return sol.x, float(sol.cost), sol.nfev


def _robust_subset(obs: Observations, per_pair: int) -> np.ndarray:
    """(M,) bool: at most ``per_pair`` observations of each pair (a fixed random choice), for the robust pass."""
    rng = np.random.default_rng(0)
    sub = np.zeros(len(obs.a), dtype=bool)
    for pid in unique_sorted(obs.pair):
        rows = np.flatnonzero(obs.pair == pid)
        sub[rng.permutation(rows)[:per_pair]] = True
    return sub


def bundle_adjust(obs: Observations, kept: list[int], groups: dict[int, int], init: dict[int, CameraIntrinsics],
                  R0: dict[int, np.ndarray], work_scale: dict[int, float], options: BundleOptions | None = None, *,
                  focal_prior: dict[int, float] | None = None, used: np.ndarray | None = None,
                  start: dict[int, CameraIntrinsics] | None = None, **option_fields) -> BAResult:
    """Refine the rotations (the root, ``kept[0]``, keeps its ``R0``) and, unless ``fixed_intrinsics``, each camera
    group's focal, optionally its k1, k2 and principal point (:class:`BundleOptions`).

    ``groups``: photo -> camera group (photos of one group share focal and distortion); ``init``: starting
    intrinsics per photo, the priors' centres; ``focal_prior``: group -> focal px; ``work_scale``: work pixels per
    full-resolution pixel, per photo (residuals are in work pixels). ``option_fields``: :class:`BundleOptions`
    fields, over ``options``. ``used`` (M,) bool: the inliers when there is no robust pass (default every
    observation). ``start``: estimated intrinsics to start from (per photo; the priors stay ``init``'s), e.g. a
    previous adjustment's, with ``R0`` its rotations."""
    opts = BundleOptions(**option_fields) if options is None else replace(options, **option_fields)
    problem = RotationBundleProblem(obs, kept, groups, init, R0, work_scale, opts, focal_prior)
    objective = _Objective(problem)
    x = problem.start(start)
    used = np.ones(len(obs.a), dtype=bool) if used is None else used.copy()
    nfev, cost = 0, 0.0
    if len(x) and opts.robust_pass:
        # the robust pass only has to find the inliers and come near the minimum: a looser tolerance
        x, cost, n_ev = _solve(objective, x, np.flatnonzero(_robust_subset(obs, opts.robust_per_pair)), True,
                               opts.robust_tol, 0, opts)
        nfev += n_ev
        new_used = np.max(np.linalg.norm(problem.transfer_all(x), axis=2), axis=1) < opts.reject_work_px
        if new_used.sum() >= 0.5 * len(used):
            used = new_used  # else: the robust pass has not converged yet; LM goes on with every inlier
    if len(x) and opts.final_pass:
        idx = np.flatnonzero(used)
        robust = opts.final_loss_median > 0
        if robust:  # soft L1 at the scale of the inliers' median residual
            err = np.max(np.linalg.norm(problem.transfer_all(x), axis=2), axis=1)
            problem.c_loss = opts.final_loss_median * median(err[idx])
        x, cost, n_ev = _solve(objective, x, idx, robust, 1e-10, 1, opts)
        nfev += n_ev
    res = problem.transfer_all(x) / problem.s_obs[:, None, None]
    return BAResult(problem.rotations(x), problem.intrinsics(x), res, used, cost, nfev)
