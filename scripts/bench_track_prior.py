#!/usr/bin/env python3
"""Benchmark: the railway line as a prior for carriages still on the rails (issue 17, docs/solver.md "On the rails").

Simulated consists (``workbench.solve.simulate``: one photo, hand-picked points with Gaussian pixel noise, a
plane terrain). The last carriage stands on the rails: its line passes through its true bogie pivots, each moved
across the line by N(0, track_sigma) (the map's error the prior states). Each case is solved twice, without and
with the prior (``on_track`` and the line), and the carriage's figures relative to the line are compared with the
truth: the body centre's lateral offset, its place along the line, its yaw; and the camera-to-carriage distance.

Prints per figure the RMS error, the mean 1-sigma, RMS(error / sigma) and the coverage of the 95 % intervals, with
95 % confidence intervals (Wilson for coverage; chi-square for the RMS ratio), and saves JSON.

    .venv/bin/python scripts/bench_track_prior.py [--cases 60] [--redraws 4] [--out bench_out/track_prior.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workbench.core.track import RailwayLine, centre_heading_covariance, wrap_deg  # noqa: E402
from workbench.solve.model import SolveOptions  # noqa: E402
from workbench.solve.simulate import redraw, simulate_consist  # noqa: E402
from workbench.solve.solver import solve_consist  # noqa: E402
from workbench.core.track import bogie_pivots  # noqa: E402

FIGURES = ("lateral_m", "along_m", "yaw_deg")


def line_through(truth: np.ndarray, ctype, sigma_m: float, rng) -> tuple[RailwayLine, np.ndarray, np.ndarray]:
    """A straight line through the carriage's true bogie pivots, each moved across it by N(0, sigma_m); the line's
    direction (2,) and left normal (2,)."""
    X = bogie_pivots(ctype) @ truth[:3, :3].T + truth[:3, 3]
    d = X[0, :2] - X[1, :2]
    d /= np.linalg.norm(d)
    n = np.array([-d[1], d[0]])
    e = rng.normal(0.0, sigma_m, 2)
    a, b = X[0, :2] + e[0] * n, X[1, :2] + e[1] * n
    u = (a - b) / np.linalg.norm(a - b)
    s = np.arange(-150.0, 151.0, 10.0)
    P = np.column_stack([b + s[:, None] * u, np.full(len(s), float(X[:, 2].mean()))])
    return RailwayLine("bench-track", "bench", P), u, np.array([-u[1], u[0]])


def figures(cr, truth: np.ndarray, ctype, u: np.ndarray, n: np.ndarray) -> dict:
    """Errors and 1-sigmas of the body centre across and along the line and of the heading."""
    body_t = truth[:3, :3] @ np.array([0.0, 0.0, 0.5 * ctype.height_m]) + truth[:3, 3]
    head_t = math.degrees(math.atan2(truth[0, 0], truth[1, 0]))
    M = np.asarray(cr.world_from_carriage, dtype=float)
    C = centre_heading_covariance(M, cr.body_centre_m, cr.covariance_pose)
    e = np.asarray(cr.body_centre_m, dtype=float)[:2] - body_t[:2]
    head = math.degrees(math.atan2(M[0, 0], M[1, 0]))
    return {"lateral_m": (float(e @ n), math.sqrt(float(n @ C[:2, :2] @ n))),
            "along_m": (float(e @ u), math.sqrt(float(u @ C[:2, :2] @ u))),
            "yaw_deg": (wrap_deg(head - head_t), math.sqrt(float(C[2, 2])))}


def summary(rows: list[tuple[float, float]]) -> dict:
    e = np.array([r[0] for r in rows])
    s = np.array([r[1] for r in rows])
    z = e / s
    k = len(z)
    inside = int(np.sum(np.abs(z) <= 1.96))
    p = inside / k
    w = 1.96 * math.sqrt(p * (1 - p) / k + 0.25 * 1.96**2 / k**2) / (1 + 1.96**2 / k)
    c = (p + 0.5 * 1.96**2 / k) / (1 + 1.96**2 / k)
    rms_z = float(np.sqrt(np.mean(z**2)))
    lo, hi = (rms_z * math.sqrt(k / stats.chi2.ppf(q, k)) for q in (0.975, 0.025))
    return {"n": k, "rms_error": float(np.sqrt(np.mean(e**2))), "mean_sigma": float(np.mean(s)),
            "rms_z": rms_z, "rms_z_ci95": [lo, hi], "coverage": p, "coverage_ci95": [c - w, c + w]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=60, help="simulated geometries (default 60)")
    ap.add_argument("--redraws", type=int, default=4, help="noise draws per geometry (default 4)")
    ap.add_argument("--cars", type=int, default=3)
    ap.add_argument("--points", type=int, default=5, help="marked points per carriage (default 5)")
    ap.add_argument("--pixel-sigma", type=float, default=1.5)
    ap.add_argument("--distance-factor", type=float, default=1.6, help="camera distance in train lengths")
    ap.add_argument("--track-sigma", type=float, default=0.10, help="the line's error per pivot, m")
    ap.add_argument("--out", type=Path, default=Path("bench_out/track_prior.json"))
    a = ap.parse_args()
    rows: dict[str, dict[str, list]] = {"without": {f: [] for f in FIGURES}, "with": {f: [] for f in FIGURES}}
    t0 = time.perf_counter()
    skipped = 0
    failed = {"without": 0, "with": 0}
    for case in range(a.cases):
        try:
            base = simulate_consist(a.cars, seed=1000 + case, pixel_sigma_px=a.pixel_sigma, n_points=a.points,
                                    distance_factor=a.distance_factor)
        except RuntimeError:
            skipped += 1
            continue
        k = a.cars - 1
        for r in range(a.redraws):
            sim = redraw(base, seed=50_000 + 100 * case + r)
            rng = np.random.default_rng(90_000 + 100 * case + r)
            ctype = sim.carriages[k].carriage_type
            line, u, n = line_through(sim.truth[k], ctype, a.track_sigma, rng)
            cars = list(sim.carriages)
            for label in ("without", "with"):
                if label == "with":
                    cars[k] = replace(cars[k], on_track=True)
                opts = SolveOptions(pixel_sigma_px=a.pixel_sigma, track_sigma_m=a.track_sigma)
                res = solve_consist(cars, sim.links, sim.views, opts, sim.terrain,
                                    (line,) if label == "with" else ())
                cr = res.carriages[k]
                if not res.converged or cr.status != "solved" or cr.covariance_pose is None:
                    failed[label] += 1
                    continue
                for f, v in figures(cr, sim.truth[k], ctype, u, n).items():
                    rows[label][f].append(v)
    out = {"options": vars(a) | {"out": str(a.out)}, "skipped_geometries": skipped, "not_converged": failed,
           "time_s": time.perf_counter() - t0, "routes": {}}
    print(f"{a.cases - skipped} geometries x {a.redraws} draws, {a.cars} cars, {a.points} points, "
          f"{a.pixel_sigma} px, line error {a.track_sigma} m per pivot ({out['time_s']:.0f} s); not converged "
          f"(left out): {failed['without']} without the prior, {failed['with']} with it")
    print(f"{'':8s} {'figure':10s} {'n':>4s} {'RMS err':>8s} {'mean sd':>8s} {'RMS e/sd':>16s} {'coverage 95%':>22s}")
    for label in ("without", "with"):
        out["routes"][label] = {}
        for f in FIGURES:
            s = summary(rows[label][f])
            out["routes"][label][f] = s
            print(f"{label:8s} {f:10s} {s['n']:4d} {s['rms_error']:8.3f} {s['mean_sigma']:8.3f} "
                  f"{s['rms_z']:5.2f} [{s['rms_z_ci95'][0]:.2f}, {s['rms_z_ci95'][1]:.2f}] "
                  f"{100 * s['coverage']:6.1f} % [{100 * s['coverage_ci95'][0]:.1f}, "
                  f"{100 * s['coverage_ci95'][1]:.1f}]")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(a.out)
    print(f"saved {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
