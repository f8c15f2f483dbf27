"""The terrain in the solve: resting a carriage on it (step 2) and the soft contact term (step 4).

Each carriage's contact row is chosen by :func:`wheel_contact` from its pose and its rotation's uncertainty. A
carriage whose wheels are as level over the terrain as that uncertainty can tell gets the mean clearance of its
wheel treads' lowest points (the samples on the type's bottom plane, :func:`wheel_points`), each over the terrain
beneath it: linear in the pose on a plane, so a noisy rotation does not move it on average. Any other (derailed onto
one end or one side of its wheels, on its side or roof) gets the lowest of all samples. That row dips under a noisy
rotation whichever way the rotation errs when several samples touch at the truth (a carriage level on its wheels: by
about the wheelbase times the pitch error), so for a level carriage the fit lifted it (with the focal estimated the
consist slid up its rays: up too high, the focal too short), and, being concave in the tilt, it let the fit tilt a
level carriage to meet it (docs/calibration.md, "Hand picks, unknown focal"). Step 4 judges a carriage whose
rotation from its own pixels could not confirm it level against the terrain's stated accuracy again at its solution,
with its rotation's covariance there (the chain's and the contact's information added to its pixels').
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .loss import chi2_quantile

_SAMPLE_CACHE: dict[tuple[str, int], np.ndarray] = {}
WHEEL_PLANE_TOL_M = 0.01  # a sample within 1 cm of the type's lowest (carriage z) lies on its wheels' rail plane
WHEEL_SPREAD_SD = 4.0  # on_wheels' test: a wheel off the others' height by more sd than this is not on the ground


def surface_samples(ct: Any, n: int) -> np.ndarray:
    """``n`` samples (carriage frame, m) of a carriage type's surface, computed once per type and count."""
    key = (f"{ct.id}:{ct.source_path}", int(n))
    s = _SAMPLE_CACHE.get(key)
    if s is None:
        s = np.asarray(ct.sample_surface(n), dtype=float)
        _SAMPLE_CACHE[key] = s
    return s


def wheel_points(samples: np.ndarray) -> np.ndarray:
    """The samples (m, 3) on the type's bottom plane (carriage z within :data:`WHEEL_PLANE_TOL_M` of the lowest
    sample): the wheel treads where they meet the rail, for the library's types (z = 0 is top of rail,
    ``docs/conventions.md``); a mesh type's lowest hull vertices. Carriage frame, metres."""
    S = np.asarray(samples, dtype=float).reshape(-1, 3)
    if not len(S):
        return S
    return S[S[:, 2] <= S[:, 2].min() + WHEEL_PLANE_TOL_M]


def terrain_slopes(terrain: Any, xy: np.ndarray, step: float = 0.05) -> np.ndarray:
    """Terrain slopes (n, 2) (dh/dx, dh/dy; 0 where undefined) at ``xy`` (n, 2), central differences ``step`` m."""
    e = step
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    q = np.repeat(xy, 4, axis=0) + np.tile([[e, 0.0], [-e, 0.0], [0.0, e], [0.0, -e]], (len(xy), 1))
    h = np.asarray(terrain.height_at(q), dtype=float).reshape(-1, 4)
    g = np.column_stack([(h[:, 0] - h[:, 1]) / (2 * e), (h[:, 2] - h[:, 3]) / (2 * e)])
    return np.where(np.isfinite(g), g, 0.0)


def wheel_gradients(W: np.ndarray, R: np.ndarray, t: np.ndarray, terrain: Any) -> np.ndarray:
    """The derivatives (n, 3), m/rad, of each wheel point's clearance (``W`` (n, 3), carriage frame) less the
    wheels' mean clearance by the scene-frame rotation vector of the pose ``R`` (3, 3), ``t`` (3,): its lever arm
    crossed with the terrain's upward normal (unnormalised) beneath it."""
    Xw = np.asarray(W, dtype=float).reshape(-1, 3) @ R.T + t
    a = np.column_stack([-terrain_slopes(terrain, Xw[:, :2]), np.ones(len(Xw))])
    g = np.cross(Xw - t, a)  # d clearance / d rotation per wheel point
    return g - g.mean(axis=0)


def tilt_explained(dev: np.ndarray, g: np.ndarray, C: np.ndarray, xy: np.ndarray) -> bool:
    """Whether the wheels' clearances off their mean, ``dev`` (n,) m, show a tilt the rotation's uncertainty
    explains, taken together: the plane fitted to them over the wheel points' carriage-frame ``xy`` (n, 2) m (its
    slope along the carriage, a pitch against the ground, and across it, a roll) against that slope's covariance
    from the rotation's, ``C`` (3, 3) rad^2, through ``g`` (n, 3) (:func:`wheel_gradients`), plus
    :data:`WHEEL_PLANE_TOL_M` of height per wheel (the wheel points' own spread, the ground's shape under them); a
    chi-square with 2 degrees of freedom (1 for wheel points in a line), within the tail :data:`WHEEL_SPREAD_SD`
    standard deviations leave a normal (both sides). What the plane leaves (a twist, the ground's bumps) is the
    per-wheel test's."""
    A = np.column_stack([np.ones(len(dev)), np.asarray(xy, float) - np.mean(xy, axis=0)])
    B = np.linalg.pinv(A)[1:]  # (2, n): the plane's two slopes from the clearances
    b = B @ dev
    Sb = B @ (g @ C @ g.T + WHEEL_PLANE_TOL_M ** 2 * np.eye(len(dev))) @ B.T
    ev, V = np.linalg.eigh(0.5 * (Sb + Sb.T))
    keep = ev > 1e-12 * max(float(ev[-1]), 1e-300)  # wheel points in a line (a mesh type's): its one slope
    if not keep.any():
        return True
    y = V[:, keep].T @ b
    chi2 = float(np.sum(y * y / ev[keep]))
    return chi2 <= float(chi2_quantile(math.erf(WHEEL_SPREAD_SD / math.sqrt(2.0)), int(keep.sum())))


def wheel_contact(samples: np.ndarray, R: np.ndarray, t: np.ndarray, terrain: Any, cov_rot: np.ndarray,
                  sigma_z: float, tilt_test: bool = False) -> str:
    """Which contact row a carriage (pose ``R`` (3, 3), ``t`` (3,); its surface ``samples`` (m, 3), carriage
    frame) gets, from its pose and its rotation's uncertainty ``cov_rot`` (3, 3), rad^2, of the scene-frame
    rotation vector:

    * ``"wheels"``: seen to stand on all its wheels (:func:`on_wheels`): the wheels' mean clearance;
    * ``"level"``: its wheels as level as its rotation's uncertainty can tell (every one of its
      :func:`wheel_points` as high over the terrain as the others to within :data:`WHEEL_SPREAD_SD` standard
      deviations of what that uncertainty explains, plus :data:`WHEEL_PLANE_TOL_M`, and with ``tilt_test``
      their tilt taken together explained by it, :func:`tilt_explained`; its lowest sample over the
      plane of the terrain under its wheels a wheel point) but that tolerance over twice the terrain's stated
      accuracy ``sigma_z`` (m): not confirmed, since a carriage on one end tilted within the tolerance would pass,
      its wheels' mean half its wheels' spread off the ground. The solve gives it the wheels' row too and judges it
      again at step 4's solution (:func:`.steps.step_all`);
    * ``"lowest"``: any other (derailed onto one end or one side, on its side or roof; off the terrain;
      ``cov_rot`` not finite): the lowest sample's row."""
    S = np.asarray(samples, dtype=float).reshape(-1, 3)
    W = wheel_points(S)
    C = np.asarray(cov_rot, dtype=float).reshape(3, 3)
    if len(W) < 3 or not np.all(np.isfinite(C)):
        return "lowest"
    Xw = W @ R.T + t
    hw = np.asarray(terrain.height_at(Xw[:, :2]), dtype=float)
    if not np.all(np.isfinite(hw)):
        return "lowest"
    d = Xw[:, 2] - hw
    g = wheel_gradients(W, R, t, terrain)
    sd = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", g, C, g), 0.0))
    tol = WHEEL_SPREAD_SD * sd + WHEEL_PLANE_TOL_M
    if np.any(np.abs(d - d.mean()) > tol) or (tilt_test and not tilt_explained(d - d.mean(), g, C, W[:, :2])):
        return "lowest"
    A = np.column_stack([np.ones(len(Xw)), Xw[:, :2] - Xw[:, :2].mean(0)])
    coef, *_ = np.linalg.lstsq(A, hw, rcond=None)  # the ground's plane under the wheels (least squares)
    X = S @ R.T + t
    dp = X[:, 2] - (coef[0] + (X[:, :2] - Xw[:, :2].mean(0)) @ coef[1:])
    if not S[int(np.argmin(dp)), 2] <= S[:, 2].min() + WHEEL_PLANE_TOL_M:
        return "lowest"
    return "level" if np.any(tol > 2.0 * sigma_z) else "wheels"


def on_wheels(samples: np.ndarray, R: np.ndarray, t: np.ndarray, terrain: Any, cov_rot: np.ndarray,
              sigma_z: float) -> bool:
    """Whether a carriage is seen to stand on all its wheels (:func:`wheel_contact`'s ``"wheels"``): its wheels
    level over the terrain to within what its rotation's uncertainty explains, that tolerance no more than twice
    the terrain's stated accuracy ``sigma_z`` (m: else the rotation cannot tell a carriage on all its wheels from
    one on one end, whose wheels' mean clearance is half its wheels' spread off the ground), and its lowest sample
    a wheel point. A derailed carriage resting on one end or one side of its wheels, on its side or on its roof is
    not. Arguments as :func:`wheel_contact`."""
    return wheel_contact(samples, R, t, terrain, cov_rot, sigma_z) == "wheels"


def rest_on_terrain(world_from_carriage: np.ndarray, carriage_type: Any, terrain: Any,
                    n_samples: int = 400) -> tuple[np.ndarray, float]:
    """Step 2 for one carriage: move it along gravity (scene z only) until its lowest surface sample touches the
    terrain without penetrating it. Returns (new world_from_carriage (4, 4), dz applied in metres). A carriage
    outside the terrain (heights NaN) is returned unchanged with dz = NaN."""
    M = np.array(world_from_carriage, dtype=float)
    X = surface_samples(carriage_type, n_samples) @ M[:3, :3].T + M[:3, 3]
    d = X[:, 2] - np.asarray(terrain.height_at(X[:, :2]), dtype=float)
    if not np.any(np.isfinite(d)):
        return M, float("nan")
    dz = -float(np.nanmin(d))
    M[2, 3] += dz
    return M, dz


class Contact:
    """Soft terrain contact per carriage, ``scale`` = px_sigma / sigma_z. A carriage in ``wheels`` (carriage index ->
    its :func:`wheel_points`) has the residual ``scale * mean_w (z_w - h(xy_w))`` over its wheel points; any other
    the residual ``scale * min_s (z_s - h(xy_s))`` over its surface samples.

    ``samples``: carriage index -> its surface samples (m, 3), carriage frame, metres; ``self.cars`` keeps their
    order, which is the order of the batched :meth:`clearances` and of the contact rows. :meth:`clearance` is the
    lowest sample's height over the terrain (the reported clearance) whichever the row."""

    def __init__(self, terrain: Any, samples: dict[int, np.ndarray], scale: float, step: float = 0.05,
                 wheels: dict[int, np.ndarray] | None = None):
        self.terrain, self.samples, self.scale, self.step = terrain, samples, scale, step
        self.cars = list(samples)
        self._row = {k: i for i, k in enumerate(self.cars)}
        self.wheels = {k: np.asarray(w, dtype=float).reshape(-1, 3) for k, w in (wheels or {}).items()
                       if k in self._row and len(w)}
        mw = max((len(W) for W in self.wheels.values()), default=0)
        self._W = np.zeros((len(self.cars), mw, 3))  # padded; _wvalid marks the real wheel points
        self._wvalid = np.zeros((len(self.cars), mw), dtype=bool)
        self._on_wheels = np.zeros(len(self.cars), dtype=bool)
        for k, W in self.wheels.items():
            i = self._row[k]
            self._W[i, :len(W)], self._wvalid[i, :len(W)], self._on_wheels[i] = W, True, True
        m = max((len(S) for S in samples.values()), default=0)
        self._S = np.zeros((len(self.cars), m, 3))  # padded to the longest set; _valid marks the real samples
        self._valid = np.zeros((len(self.cars), m), dtype=bool)
        for i, k in enumerate(self.cars):
            S = np.asarray(samples[k], dtype=float).reshape(-1, 3)
            self._S[i, :len(S)] = S
            self._valid[i, :len(S)] = True

    def clearances(self, R_c: np.ndarray, t_c: np.ndarray, cars: Sequence[int] | None = None):
        """The clearance of several carriages at once: poses ``R_c`` (n, 3, 3), ``t_c`` (n, 3) of the carriages
        ``cars`` (consist indices; None: ``self.cars``). Returns the clearance (n,) (m; NaN for a carriage off
        the terrain), its lowest sample in the scene X (n, 3) and that sample rotated, R s (n, 3)."""
        rows = slice(None) if cars is None else np.array([self._row[k] for k in cars], dtype=int)
        S, valid = self._S[rows], self._valid[rows]
        X = S @ np.swapaxes(R_c, 1, 2) + t_c[:, None, :]  # (n, m, 3)
        if valid.all():
            h = np.asarray(self.terrain.height_at(X[:, :, :2].reshape(-1, 2)), dtype=float).reshape(valid.shape)
        else:
            h = np.full(valid.shape, np.nan)
            h[valid] = np.asarray(self.terrain.height_at(X[valid][:, :2]), dtype=float)
        dz = X[:, :, 2] - h
        dz = np.where(np.isfinite(dz), dz, np.inf)
        n = np.arange(len(S))
        i = np.argmin(dz, axis=1) if S.shape[1] else np.zeros(len(S), dtype=int)
        d = dz[n, i] if S.shape[1] else np.full(len(S), np.inf)
        d = np.where(np.isfinite(d), d, np.nan)
        return d, X[n, i], np.einsum("nij,nj->ni", R_c, S[n, i])

    def clearance(self, R: np.ndarray, t: np.ndarray, k: int):
        """Carriage ``k`` (scene poses ``R`` (N, 3, 3), ``t`` (N, 3)): (clearance m, lowest sample X (3,), R s
        (3,)), or None off the terrain."""
        d, X, q = self.clearances(R[[k]], t[[k]], [k])
        return None if not np.isfinite(d[0]) else (float(d[0]), X[0], q[0])

    def gradients(self, xy: np.ndarray) -> np.ndarray:
        """Terrain slopes (n, 2) (dh/dx, dh/dy; 0 where undefined) at ``xy`` (n, 2), central differences."""
        return terrain_slopes(self.terrain, xy, self.step)

    def _wheel_rows(self, R_c: np.ndarray, t_c: np.ndarray, rows: np.ndarray, grad: bool):
        """The wheel rows ``rows`` (indices into ``self.cars``; poses per row): mean clearance of the wheel points
        (n,) (m; NaN where any is off the terrain), with ``grad`` the mean terrain slope under them (n, 2), and
        R times their centroid (n, 3)."""
        W, valid = self._W[rows], self._wvalid[rows]
        X = W @ np.swapaxes(R_c, 1, 2) + t_c[:, None, :]
        h = np.full(valid.shape, np.nan)
        h[valid] = np.asarray(self.terrain.height_at(X[valid][:, :2]), dtype=float)
        cnt = valid.sum(axis=1)
        d = np.where(valid, X[:, :, 2] - h, 0.0).sum(axis=1) / cnt  # NaN where a wheel point is off the terrain
        q = np.einsum("nij,nj->ni", R_c, (W * valid[..., None]).sum(axis=1) / cnt[:, None])
        if not grad:
            return d, None, q
        g = np.zeros((len(rows), 2))
        g_all = self.gradients(X[valid][:, :2])
        owner = np.nonzero(valid)[0]
        np.add.at(g, owner, g_all)
        return d, g / cnt[:, None], q

    def residuals(self, R_r: np.ndarray, t_r: np.ndarray, rows: Sequence[int]) -> np.ndarray:
        """The residuals of the rows ``rows`` (pixel units, NaN off the terrain) at the poses given per row."""
        rows = np.asarray(rows, dtype=int)
        d, _, _ = self.clearances(R_r, t_r, [self.cars[i] for i in rows])
        w = self._on_wheels[rows]
        if w.any():
            d[w] = self._wheel_rows(R_r[w], t_r[w], rows[w], False)[0]
        return self.scale * d

    def rows(self, R_c: np.ndarray, t_c: np.ndarray):
        """Contact residuals and their derivatives for every carriage (poses as :meth:`clearances`): residual
        (n,) (0 off the terrain), ``a`` (n, 3) d residual / d X (0 off the terrain), R s (n, 3) (the lowest
        sample's, or the wheel points' centroid's: exact on a plane, the slope under the wheels averaged on a
        curved terrain), on-terrain mask."""
        d, X, q = self.clearances(R_c, t_c)
        gh = self.gradients(X[:, :2])
        w = self._on_wheels
        if w.any():
            d[w], gh[w], q[w] = self._wheel_rows(R_c[w], t_c[w], np.nonzero(w)[0], True)
        on = np.isfinite(d)
        a = np.column_stack([-gh, np.ones(len(d))]) * self.scale
        a[~on] = 0.0
        return np.where(on, self.scale * np.nan_to_num(d), 0.0), a, q, on
