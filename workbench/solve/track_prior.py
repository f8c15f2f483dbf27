"""The railway line as a prior for carriages still on the rails (``on_track = true`` in the consist).

A carriage on the rails has both bogie pivots over the track's centre line. Each pivot (carriage frame
``(+-bogie_centres_m / 2, 0, 0)``) gives one soft row: its signed horizontal offset from the line, in pixel units
(``scale = pixel_sigma_px / track_sigma_m``). Two rows fix the carriage's lateral place and its yaw to the track
and leave its place along the track and its height to the photos (and the terrain contact). On a curve the body
centre then lies inside the line by the versine, as a real carriage does.

The rows share the terrain contact's interface (``cars``, ``rows``, ``residuals``), so the solver's blocks, the
covariance and the bias correction take them as they take the contact rows; :class:`SoftRows` stacks both terms.
The line is taken as known to ``track_sigma_m`` at each pivot independently (the map's error shared along the
line is not modelled; docs/solver.md, "On the rails").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..core.track import RailwayLine, bogie_pivots, reference_line

__all__ = ["TrackPrior", "SoftRows", "TrackPriorRecord", "track_prior"]


@dataclass(frozen=True)
class TrackPriorRecord:
    """What the prior did for one carriage marked on the rails: ``applied`` or why not (``reason``); the line; the
    pivots' offsets from it (m, left positive) at the start of the joint solve."""

    index: int  # in the consist
    number: str
    applied: bool
    reason: str  # why (not), in words for the warning and the report
    line: RailwayLine | None = None  # the nearest line, where there is one
    sigma_m: float | None = None  # the prior's 1-sigma per pivot, where applied
    start_offsets_m: tuple[float, float] | None = None  # front and rear pivot, at the start of step 4

    def to_dict(self) -> dict:
        line = self.line
        return {"number": self.number, "applied": self.applied, "reason": self.reason,
                "line_id": None if line is None else line.id, "line_name": None if line is None else line.name,
                "sigma_m": self.sigma_m,
                "start_offsets_m": None if self.start_offsets_m is None else [round(x, 4) for x in self.start_offsets_m]}


class TrackPrior:
    """Soft rows, two per carriage on the rails (its front pivot, then its rear one): ``scale * offset``.

    ``lines``: carriage index -> its line; ``pivots``: carriage index -> (2, 3) pivots in the carriage frame."""

    def __init__(self, lines: dict[int, RailwayLine], pivots: dict[int, np.ndarray], scale: float):
        self.scale = float(scale)
        ks = list(lines)
        self.cars = [k for k in ks for _ in range(2)]
        self._lines = [lines[k] for k in ks for _ in range(2)]
        self._S = np.vstack([np.asarray(pivots[k], dtype=float).reshape(2, 3) for k in ks]) if ks else np.zeros((0, 3))

    def offsets(self, R_r: np.ndarray, t_r: np.ndarray, rows: Sequence[int] | None = None):
        """Per row (poses ``R_r`` (n, 3, 3), ``t_r`` (n, 3) of the rows' carriages; ``rows``: which rows, None: all):
        the pivot's signed offset from its line (n,) (m, left of the line's direction positive), the line's left
        unit normal there (n, 2) and the pivot rotated, R s (n, 3)."""
        idx = np.arange(len(self.cars)) if rows is None else np.asarray(rows, dtype=int)
        q = np.einsum("nij,nj->ni", R_r, self._S[idx])
        X = q + t_r
        d = np.zeros(len(idx))
        nrm = np.zeros((len(idx), 2))
        for i, r in enumerate(idx):
            d[i], nrm[i] = self._lines[r].offset_and_normal(X[i, :2])
        return d, nrm, q

    def rows(self, R_r: np.ndarray, t_r: np.ndarray):
        """Residuals (n,), d residual / d X (n, 3), R s (n, 3) and a mask (every row counts), as Contact.rows."""
        d, nrm, q = self.offsets(R_r, t_r)
        a = np.column_stack([nrm, np.zeros(len(d))]) * self.scale
        return self.scale * d, a, q, np.ones(len(d), dtype=bool)

    def residuals(self, R_r: np.ndarray, t_r: np.ndarray, rows: Sequence[int]) -> np.ndarray:
        """The residuals of the rows ``rows`` (pixel units) at the poses given per row."""
        return self.scale * self.offsets(R_r, t_r, rows)[0]


class SoftRows:
    """The terrain contact and the track prior seen as one term of per-carriage rows (contact rows first)."""

    def __init__(self, contact: Any | None, track: TrackPrior | None):
        self.terrain_contact, self.track = contact, track
        self._parts = [p for p in (contact, track) if p is not None]
        self.cars = [k for p in self._parts for k in p.cars]
        self._edges = np.cumsum([0] + [len(p.cars) for p in self._parts])

    def rows(self, R_c: np.ndarray, t_c: np.ndarray):
        out = [p.rows(R_c[a:b], t_c[a:b]) for p, a, b in zip(self._parts, self._edges[:-1], self._edges[1:])]
        return tuple(np.concatenate([o[i] for o in out]) for i in range(4))

    def residuals(self, R_r: np.ndarray, t_r: np.ndarray, rows: Sequence[int]) -> np.ndarray:
        rows = np.asarray(rows, dtype=int)
        out = np.zeros(len(rows))
        for p, a, b in zip(self._parts, self._edges[:-1], self._edges[1:]):
            m = (rows >= a) & (rows < b)
            if m.any():
                out[m] = p.residuals(R_r[m], t_r[m], rows[m] - a)
        return out

    def clearance(self, R: np.ndarray, t: np.ndarray, k: int):
        return None if self.terrain_contact is None else self.terrain_contact.clearance(R, t, k)


def track_prior(cars: Sequence[Any], active: Sequence[int], R: np.ndarray, t: np.ndarray,
                lines: Sequence[RailwayLine], sigma_m: float, pixel_sigma_px: float, gate_m: float
                ) -> tuple[TrackPrior | None, list[TrackPriorRecord]]:
    """The prior for the carriages marked on the rails (``cars[k].on_track``) at the poses ``R``, ``t`` (the start
    of the joint solve). A carriage not solved, with no railway line, or whose pivots lie farther than ``gate_m``
    from the nearest line (the mark or the layer is wrong, or the carriage left the rails) gets no prior; each
    record says why."""
    recs: list[TrackPriorRecord] = []
    use_lines: dict[int, RailwayLine] = {}
    pivots: dict[int, np.ndarray] = {}
    active_set = set(active)
    for k, c in enumerate(cars):
        if not getattr(c, "on_track", False):
            continue
        if k not in active_set:
            recs.append(TrackPriorRecord(k, c.number, False, "the carriage is not solved"))
            continue
        if not lines:
            recs.append(TrackPriorRecord(k, c.number, False, "the incident has no railway line (terrain.railways)"))
            continue
        S = bogie_pivots(c.ctype)
        X = S @ R[k].T + t[k]
        line = reference_line(lines, X[:, :2])
        off = tuple(float(line.foot(x[:2]).offset_m) for x in X)
        if max(abs(o) for o in off) > gate_m:
            recs.append(TrackPriorRecord(
                k, c.number, False, f"its bogies lie {off[0]:+.1f} and {off[1]:+.1f} m from the nearest railway "
                f"line ({line.label}), beyond {gate_m:g} m: the on_track mark, the railway layer or the camera is "
                f"wrong, or the carriage left the rails; solved without the track", line, None, off))
            continue
        use_lines[k], pivots[k] = line, S
        recs.append(TrackPriorRecord(k, c.number, True, "both bogie pivots over the track centre", line,
                                     float(sigma_m), off))
    if not use_lines:
        return None, recs
    return TrackPrior(use_lines, pivots, pixel_sigma_px / sigma_m), recs
