"""Robust losses of the residuals, with the formulas and scaling of scipy's ``least_squares``.

``rho(z)`` of the squared scaled residual ``z = (r / scale)^2``, scaled back so that ``rho ~ r^2`` for small
``r``: ``huber`` (quadratic to ``scale``, linear beyond), ``soft_l1`` (a smooth huber) and ``cauchy``.
"""

from __future__ import annotations

import functools

import numpy as np


@functools.lru_cache(maxsize=64)
def chi2_quantile(p: float, dof: float) -> float:
    """The chi-square distribution's ``p`` quantile with ``dof`` degrees of freedom, as scipy.stats computes it
    (``2 gammaincinv(dof / 2, p)``), without importing scipy.stats."""
    from scipy.special import gammaincinv

    return 2.0 * float(gammaincinv(dof / 2.0, p))


def _rho(z: np.ndarray, loss: str, derivatives: bool) -> np.ndarray:
    """(3, m): rho(z), rho'(z), rho''(z) (the last two only with ``derivatives``) of the unit-scale loss."""
    rho = np.empty((3, len(z)))
    if loss == "huber":
        mask = z <= 1
        rho[0, mask] = z[mask]
        rho[0, ~mask] = 2 * z[~mask]**0.5 - 1
        if derivatives:
            rho[1, mask] = 1
            rho[1, ~mask] = z[~mask]**-0.5
            rho[2, mask] = 0
            rho[2, ~mask] = -0.5 * z[~mask]**-1.5
    elif loss == "soft_l1":
        t = 1 + z
        rho[0] = 2 * (t**0.5 - 1)
        if derivatives:
            rho[1] = t**-0.5
            rho[2] = -0.5 * t**-1.5
    elif loss == "cauchy":
        rho[0] = np.log1p(z)
        if derivatives:
            t = 1 + z
            rho[1] = 1 / t
            rho[2] = -1 / t**2
    else:
        raise ValueError(f"unknown robust loss {loss!r}")
    return rho


def robust_rho(r: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """(3, m): the loss of each residual ``r`` and its first and second derivatives with respect to ``r^2``."""
    rho = _rho((r / scale) ** 2, loss, True)
    rho[0] *= scale ** 2
    rho[2] /= scale ** 2
    return rho


def robust_half_cost(r: np.ndarray, loss: str, scale: float) -> float:
    """Half the summed loss of the residuals ``r`` (what scipy's loss function returns with ``cost_only``)."""
    rho = _rho((r / scale) ** 2, loss, False)
    return 0.5 * scale ** 2 * np.sum(rho[0])
