"""The terrain in the solve: resting a carriage on it (step 2) and the soft contact term (step 4)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

_SAMPLE_CACHE: dict[tuple[str, int], np.ndarray] = {}


def surface_samples(ct: Any, n: int) -> np.ndarray:
    """``n`` samples (carriage frame, m) of a carriage type's surface, computed once per type and count."""
    key = (f"{ct.id}:{ct.source_path}", int(n))
    s = _SAMPLE_CACHE.get(key)
    if s is None:
        s = np.asarray(ct.sample_surface(n), dtype=float)
        _SAMPLE_CACHE[key] = s
    return s


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
    """Soft terrain contact per carriage: residual ``scale * min_s (z_s - h(xy_s))`` (scale = px_sigma / sigma_z).

    ``samples``: carriage index -> its surface samples (m, 3), carriage frame, metres; ``self.cars`` keeps their
    order, which is the order of the batched :meth:`clearances` and of the contact rows."""

    def __init__(self, terrain: Any, samples: dict[int, np.ndarray], scale: float, step: float = 0.05):
        self.terrain, self.samples, self.scale, self.step = terrain, samples, scale, step
        self.cars = list(samples)
        self._row = {k: i for i, k in enumerate(self.cars)}
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
        e = self.step
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        q = np.repeat(xy, 4, axis=0) + np.tile([[e, 0.0], [-e, 0.0], [0.0, e], [0.0, -e]], (len(xy), 1))
        h = np.asarray(self.terrain.height_at(q), dtype=float).reshape(-1, 4)
        g = np.column_stack([(h[:, 0] - h[:, 1]) / (2 * e), (h[:, 2] - h[:, 3]) / (2 * e)])
        return np.where(np.isfinite(g), g, 0.0)

    def residuals(self, R_r: np.ndarray, t_r: np.ndarray, rows: Sequence[int]) -> np.ndarray:
        """The residuals of the rows ``rows`` (pixel units, NaN off the terrain) at the poses given per row."""
        d, _, _ = self.clearances(R_r, t_r, [self.cars[i] for i in rows])
        return self.scale * d

    def rows(self, R_c: np.ndarray, t_c: np.ndarray):
        """Contact residuals and their derivatives for every carriage (poses as :meth:`clearances`): residual
        (n,) (0 off the terrain), ``a`` (n, 3) d residual / d X (0 off the terrain), R s (n, 3), on-terrain mask."""
        d, X, q = self.clearances(R_c, t_c)
        on = np.isfinite(d)
        gh = self.gradients(X[:, :2])
        a = np.column_stack([-gh, np.ones(len(d))]) * self.scale
        a[~on] = 0.0
        return np.where(on, self.scale * np.nan_to_num(d), 0.0), a, q, on
