#!/usr/bin/env python
"""Calibration of the solve's 95 % intervals, route by route (issue 21): are they honest and sharp?

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python scripts/bench_calibration.py --route known --n 200
    ... --route focal --n 200
    ... --route auto --n 30          # ~40-60 s per generated incident on a loaded 2-core machine
    ... --route known,focal          # several routes, one table

Each route solves fresh problems (seeds from ``--seed0``) until it has ``--n`` solved carriages, and compares
every carriage's pose with the truth on six axes: body centre east, north, up (m) and heading, pitch, roll (deg).
Per route and axis it prints

* **coverage**: the share of carriages whose truth lies inside the 95 % interval (``ci95_*``: the solve's
  half widths, Student's t times sigma); target 90-98 %;
* **RMS z**: the root mean square of error / sigma (1 when the sigmas are the errors' true spread); target
  0.85-1.15;
* **width / spread**: the RMS of the sigmas over the RMS of the errors (1 when the intervals are as wide as the
  errors, above 1 when wider), and the mean 95 % half width beside the RMS error;
* **robust z**: median |error / sigma| / 0.6745 (1 when calibrated), which a few gross failures (a carriage on a
  wrong branch, 100 sigmas off) barely move where they dominate the RMS.

Each figure has a 95 % confidence interval from a cluster bootstrap over the solved problems (one incident's
carriages share its camera, focal and noise draw, so they are not independent; resampling whole problems keeps
that). The coverage's Wilson interval (carriages taken as independent) is saved too.

Routes:

``known``
    hand picks (true pixels plus Gaussian noise) on one photo, known camera: ``simulate_consist`` +
    ``solve_consist(compute_covariance=True)``, cycling 4 and 7 cars at 0.7 and 1.5 px (the cases of issue 21),
    the solver's defaults (per-carriage weighting, bias correction, no terrain);
``focal``
    the same problems with the focal unknown (``SolveOptions(estimate_focal=True)``);
``relative``, ``relative_focal``
    relative incidents (no survey; docs/gis.md, "Relative incidents"): 3 cars, hand picks at 0.5 px (stated),
    one photo, the track tilted N(0, 0.5 deg) per axis; known focal (a camera profile) or estimated (and the
    principal point: drawn as the solve states it); the pipeline up to ``solve``;
``auto``
    generated incidents (``workbench synth``: 800x600 photos, a 4-photo panorama, 4-7 cars, the seed varying),
    control points from the truth, then the pipeline up to ``solve`` (stitch, georef, correspond with automatic
    points, solve): the demo's route. Its intervals include the georeferenced camera's uncertainty.
``multiview``
    generated incidents (800x600, 8 multi-view photos, 4-5 cars), each solved ``--draws`` times with fresh noise:
    control points (0.5 px, their stated 5 cm survey error), an exact SfM model in a random frame (or disturbed:
    ``--sfm-noise DEG M``), hand picks (0.5 or 1 px), then the georef (multi-view route) and solve stages. Scored
    with the camera term and, as "before", with the fit's own intervals (``sigma_*_fit_*``).

Results are saved as JSON (``--out``, default ``bench_out/calibration_<routes>.json``: one record per carriage
and the table), so runs can be merged (``--merge a.json b.json``) to reach 200 carriages in several sittings.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # one core per run (set before numpy loads); not when imported (tests)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", os.environ["OMP_NUM_THREADS"])
    os.environ.setdefault("MKL_NUM_THREADS", os.environ["OMP_NUM_THREADS"])

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from workbench.core.frames import hpr_from_rotation  # noqa: E402
from workbench.core.geometry import skew  # noqa: E402
from workbench.solve import SolveOptions, SolveWarning, solve_consist  # noqa: E402
from workbench.solve.simulate import simulate_consist  # noqa: E402

AXES = ("east", "north", "up", "heading", "pitch", "roll")
UNITS = ("m", "m", "m", "deg", "deg", "deg")
Z95 = 1.959963984540054


# ----------------------------------------------------------------------------------------------------------
# statistics (shared by every route)
# ----------------------------------------------------------------------------------------------------------
def wilson(k: float, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a proportion k / n."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (c - h, c + h)


def _wrap_deg(a):
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


def cluster_bootstrap(records: list[dict], n_boot: int, seed: int):
    """The clusters of ``records`` (``record["problem"]``: one incident's carriages share its camera and noise draw)
    and their bootstrap: ``(cl (n,) each record's cluster, C, n_c (C,) records per cluster, W (1 + n_boot, C) cluster
    counts, row 0 the sample itself, sums: (n, k) -> (C, k) per-cluster sums)``."""
    keys = [r["problem"] for r in records]
    ids = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    cl = np.array([ids[k] for k in keys])
    C = len(ids)
    n_c = np.bincount(cl, minlength=C).astype(float)

    def sums(x):
        out = np.zeros((C, x.shape[1]))
        np.add.at(out, cl, x)
        return out

    W = np.random.default_rng(seed).multinomial(C, np.full(C, 1.0 / C), size=n_boot).astype(float)
    return cl, C, n_c, np.vstack([np.ones(C), W]), sums


def axis_stats(records: list[dict], n_boot: int = 2000, seed: int = 0) -> dict:
    """Per axis: coverage, RMS z, width / spread, mean half width and RMS error, each with a 95 % cluster
    bootstrap interval (clusters: ``record["problem"]``); the coverage's Wilson interval too."""
    ok = [r for r in records if all(x is not None and math.isfinite(x) and x > 0 for x in r["sigma"])]
    dropped = len(records) - len(ok)  # intervals not given (or, from older runs, not finite)
    records = ok
    err = np.array([r["error"] for r in records], float)  # (n, 6)
    sig = np.array([r["sigma"] for r in records], float)
    half = np.array([r["ci95"] for r in records], float)
    cl, C, n_c, W, per_cluster = cluster_bootstrap(records, n_boot, seed)
    inside = per_cluster((np.abs(err) <= half).astype(float))
    z2 = per_cluster((err / sig) ** 2)
    e2 = per_cluster(err ** 2)
    s2 = per_cluster(sig ** 2)
    hw = per_cluster(half)

    def figures(w):
        n = w @ n_c
        return {"coverage": (w @ inside) / n[:, None], "rms_z": np.sqrt((w @ z2) / n[:, None]),
                "width_over_spread": np.sqrt((w @ s2) / np.maximum(w @ e2, 1e-300)),
                "mean_half_width": (w @ hw) / n[:, None], "rms_error": np.sqrt((w @ e2) / n[:, None])}

    f = figures(W)
    # robust scale of z: median |z| / 0.6745 (1 when calibrated; a few gross failures barely move it), its
    # bootstrap over the same cluster resamples
    absz = np.abs(err / sig)
    members = [np.nonzero(cl == c)[0] for c in range(C)]
    rob = np.empty((len(W), 6))
    for b, w in enumerate(W):
        idx = np.concatenate([np.repeat(members[c], int(k)) for c, k in enumerate(w) if k > 0])
        rob[b] = np.median(absz[idx], axis=0) / 0.6744897501960817
    f["robust_z"] = rob
    out = {"n_carriages": int(len(records)), "n_problems": C, "n_without_interval": dropped, "axes": {}}
    for j, ax in enumerate(AXES):
        a = {"unit": UNITS[j]}
        for name, v in f.items():
            a[name] = float(v[0, j])
            lo, hi = np.percentile(v[1:, j], [2.5, 97.5])
            a[name + "_ci95"] = [float(lo), float(hi)]
        k = int(round(a["coverage"] * len(records)))
        a["coverage_wilson_ci95"] = list(wilson(k, len(records)))
        a["within_target"] = bool(0.90 <= a["coverage"] <= 0.98 and 0.85 <= a["rms_z"] <= 1.15)
        out["axes"][ax] = a
    return out


def print_table(route: str, st: dict, extra: str = "") -> None:
    print(f"\nroute {route}: {st['n_carriages']} carriages in {st['n_problems']} problems"
          + (f" ({st['n_without_interval']} more placed without an interval)" if st["n_without_interval"] else "")
          + extra)
    print(f"{'axis':>8} | {'coverage % [95% CI]':>22} | {'RMS z [95% CI]':>21} | {'width/spread [95% CI]':>22} | "
          f"{'mean 95% half width':>19} | {'RMS error':>10} | {'robust z [95% CI]':>21} | target")
    for ax, a in st["axes"].items():
        c, (cl, ch) = a["coverage"], a["coverage_ci95"]
        z, (zl, zh) = a["rms_z"], a["rms_z_ci95"]
        w, (wl, wh) = a["width_over_spread"], a["width_over_spread_ci95"]
        print(f"{ax:>8} | {100 * c:6.1f} [{100 * cl:5.1f}, {100 * ch:5.1f}] | {z:5.3f} [{zl:5.3f}, {zh:5.3f}] | "
              f"{w:5.3f} [{wl:5.3f}, {wh:5.3f}]  | {a['mean_half_width']:12.4f} {a['unit']:<4} | "
              f"{a['rms_error']:10.4f} | {a['robust_z']:5.3f} [{a['robust_z_ci95'][0]:5.3f}, {a['robust_z_ci95'][1]:5.3f}] | "
              f"{'ok' if a['within_target'] else 'MISS'}")


# ----------------------------------------------------------------------------------------------------------
# one carriage against its truth
# ----------------------------------------------------------------------------------------------------------
def record(problem: str, number: str, M_est: np.ndarray, body_est, M_true: np.ndarray, body_true,
           sigma_body, ci_body, sigma_hpr, ci_hpr, **extra) -> dict:
    """A carriage's six errors (body centre ENU, heading / pitch / roll), sigmas and 95 % half widths."""
    h_est = np.array(hpr_from_rotation(np.asarray(M_est, float)[:3, :3]))
    h_true = np.array(hpr_from_rotation(np.asarray(M_true, float)[:3, :3]))
    e = np.concatenate([np.subtract(body_est, body_true), _wrap_deg(h_est - h_true)])
    return {"problem": problem, "number": number, "error": e.tolist(),
            "sigma": np.concatenate([sigma_body, sigma_hpr]).tolist(),
            "ci95": np.concatenate([ci_body, ci_hpr]).tolist(), **extra}


# ----------------------------------------------------------------------------------------------------------
# the body centre's error along the line of sight (a panorama's depth) and across it
# ----------------------------------------------------------------------------------------------------------
SIGHT = ("sight", "across", "up_tilted")  # along the line of sight, horizontal across it, their cross product


def sight_frame(origin, target) -> np.ndarray:
    """(3, 3) rows, ENU: the line of sight from ``origin`` to ``target`` (unit), the horizontal unit vector across
    it (to the left, seen from ``origin``) and their cross product (up, tilted by the sight's dip)."""
    u = np.subtract(target, origin).astype(float)
    u /= np.linalg.norm(u)
    v = np.array([-u[1], u[0], 0.0])
    v /= np.linalg.norm(v)
    return np.vstack([u, v, np.cross(u, v)])


def sight_z(car: dict, body_true, origin) -> list[float] | None:
    """A solved carriage's body-centre error over its sigma in :func:`sight_frame` (seen from ``origin``, the
    camera's centre), from its (6, 6) ``covariance_pose`` (the scene rotation vector, then the origin, as the solve
    writes it: the same sigmas as ``sigma_body_centre_m``, rotated); None without one. A mean of these z away from
    0 over many carriages is a bias (e.g. along the sight: carriages placed too far or too near), which the
    per-axis east / north figures only show as a little too narrow."""
    cov = car.get("covariance_pose")
    if cov is None or car.get("world_from_carriage") is None or car.get("body_centre_enu") is None:
        return None
    C = np.asarray(cov, float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return None
    M = np.asarray(car["world_from_carriage"], float)
    body = np.asarray(car["body_centre_enu"], float)
    J = np.hstack([-skew(body - M[:3, 3]), np.eye(3)])  # d(body centre) / d(omega, t): R' = exp(omega) R, t' = t + dt
    F = sight_frame(origin, body_true)
    s = np.sqrt(np.diag(F @ J @ C @ J.T @ F.T))
    return (F @ (body - np.asarray(body_true, float)) / s).tolist()


def sight_stats(records: list[dict], n_boot: int = 2000, seed: int = 0) -> dict | None:
    """Mean z (the bias), RMS z and coverage of ``sight_z`` per direction, each with a 95 % cluster bootstrap
    interval (clusters: ``record["problem"]``); None when no record has them."""
    recs = [r for r in records if r.get("sight_z") is not None]
    if not recs:
        return None
    Z = np.array([r["sight_z"] for r in recs], float)
    q = np.array([float(r.get("t_factor") or Z95) for r in recs])
    _, C, n_c, W, sums = cluster_bootstrap(recs, n_boot, seed)
    s1, s2, inside = sums(Z), sums(Z ** 2), sums((np.abs(Z) <= q[:, None]).astype(float))
    n = (W @ n_c)[:, None]
    figs = {"mean_z": (W @ s1) / n, "rms_z": np.sqrt((W @ s2) / n), "coverage": (W @ inside) / n}
    out = {"n_carriages": len(recs), "n_problems": C, "axes": {}}
    for j, ax in enumerate(SIGHT):
        a = {}
        for name, v in figs.items():
            a[name] = float(v[0, j])
            a[name + "_ci95"] = [float(x) for x in np.percentile(v[1:, j], [2.5, 97.5])]
        out["axes"][ax] = a
    return out


def print_sight(route: str, st: dict | None) -> None:
    if st is None:
        return
    print(f"\nroute {route}: the body centre seen from the camera ({st['n_carriages']} carriages in "
          f"{st['n_problems']} problems)")
    print(f"{'direction':>10} | {'mean z [95% CI]':>22} | {'RMS z [95% CI]':>21} | {'coverage % [95% CI]':>22}")
    for ax, a in st["axes"].items():
        m, z, c = a["mean_z"], a["rms_z"], a["coverage"]
        print(f"{ax:>10} | {m:+6.3f} [{a['mean_z_ci95'][0]:+6.3f}, {a['mean_z_ci95'][1]:+6.3f}] | "
              f"{z:5.3f} [{a['rms_z_ci95'][0]:5.3f}, {a['rms_z_ci95'][1]:5.3f}] | "
              f"{100 * c:6.1f} [{100 * a['coverage_ci95'][0]:5.1f}, {100 * a['coverage_ci95'][1]:5.1f}]")


GROSS_Z = 5.0  # an error beyond this many sigmas on some axis: a gross failure, not the tail of the noise model


def print_doubts(route: str, recs: list[dict]) -> None:
    """The carriages the solution marks doubtful (``files.solution.doubts_of``: the report, the viewer and the
    exports show the mark beside the pose), the table again without them (what a reader who heeds the mark
    relies on), and the gross failures (|z| > ``GROSS_Z`` on some axis) caught and missed by the mark."""
    flagged = [x for x in recs if x.get("doubtful")]
    if not flagged:
        return

    def zmax(x: dict) -> float:
        return float(np.max(np.abs(np.divide(x["error"], x["sigma"]))))

    gross = [x for x in recs if zmax(x) > GROSS_Z]
    missed = [x for x in gross if not x.get("doubtful")]
    print(f"{route}: {len(flagged)} of {len(recs)} carriages marked doubtful (max |z| "
          + " ".join(f"{zmax(x):.1f}" for x in sorted(flagged, key=zmax, reverse=True))
          + f"); gross failures (|z| > {GROSS_Z:g}): {len(gross)}, {len(gross) - len(missed)} marked"
          + (", unmarked: " + ", ".join(f"{x['problem']}:{x['number']} ({zmax(x):.1f})" for x in missed)
             if missed else ""))
    print_table(route + " without the carriages marked doubtful", axis_stats([x for x in recs
                                                                               if not x.get("doubtful")]))


# ----------------------------------------------------------------------------------------------------------
# routes 1 and 2: hand picks on simulated consists, focal known or estimated
# ----------------------------------------------------------------------------------------------------------
HAND_CASES = ((4, 0.7), (7, 1.5), (4, 1.5), (7, 0.7))  # (cars, pixel sigma): issue 21's cases


def route_hand(n: int, seed0: int, estimate_focal: bool, log=print, terrain: bool = False,
               terrain_sigma_m: float | None = None) -> tuple[list[dict], dict]:
    """``terrain``: solve with the simulated plane as the terrain (step 2 and the contact term, as the solve stage
    runs with a DEM), its stated accuracy ``terrain_sigma_m`` (None: ``SolveOptions``' default). The simulated
    carriages rest on the plane to within 2 cm (1 sd: the couplers' play), so the plane is that accurate."""
    info = {"seeds": [], "skipped_seeds": [], "not_converged": 0, "left_out": 0, "time_s": 0.0, "focal_z": []}
    tsig = {} if terrain_sigma_m is None else {"terrain_sigma_m": float(terrain_sigma_m)}

    def solve(sim, seed: int, sigma: float):
        return solve_consist(sim.carriages, sim.links, sim.views,
                             SolveOptions(pixel_sigma_px=sigma, estimate_focal=estimate_focal,
                                          compute_covariance=True, **tsig), terrain=sim.terrain if terrain else None)

    return hand_consists(n, seed0, estimate_focal, solve, info, log), info


def hand_consists(n: int, seed0: int, estimate_focal: bool, solve, info: dict, log=print, **sim_kw) -> list[dict]:
    """The hand routes' loop (here and in ``bench_terrain_focal``): fresh problems, :data:`HAND_CASES` cycled from
    ``seed0``, simulated (``simulate_consist`` with ``sim_kw``; a seed it cannot place is listed as skipped), each
    solved by ``solve(sim, seed, sigma)`` (its solver warnings silenced) and scored (:func:`score_consist`) until
    ``n`` carriages have records; ``info`` filled as it goes, with the time and :func:`focal_summary`. Returns the
    records."""
    recs: list[dict] = []
    s, t0 = seed0, time.perf_counter()
    while len(recs) < n:
        n_cars, sigma = HAND_CASES[(s - seed0) % len(HAND_CASES)]
        seed, s = s, s + 1
        try:
            sim = simulate_consist(n_cars, seed=seed, pixel_sigma_px=sigma, **sim_kw)
        except RuntimeError:
            info["skipped_seeds"].append(seed)
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve(sim, seed, sigma)
        score_consist(res, sim, seed, n_cars, sigma, estimate_focal, recs, info)
        if len(info["seeds"]) % 10 == 0:
            log(f"  {len(info['seeds'])} problems, {len(recs)} carriages, {time.perf_counter() - t0:.0f} s")
    info["time_s"] = time.perf_counter() - t0
    focal_summary(info)
    return recs


def score_consist(res, sim, seed: int, n_cars: int, sigma: float, estimate_focal: bool, recs: list[dict],
                  info: dict) -> None:
    """One solved simulated consist scored against its truth: its carriages' records appended to ``recs``, the
    problem's seed, convergence, left-out carriages and focal z in ``info`` (shared with bench_terrain_focal)."""
    info["seeds"].append(seed)
    info["not_converged"] += res.status != "converged"
    if estimate_focal and res.sigma_focal_px:
        name = sim.views[0].name
        info["focal_z"].append((res.focal_px[name] - sim.views[0].intrinsics.fx) / res.sigma_focal_px[name])
    for c, M, ci in zip(res.carriages, sim.truth, sim.carriages):
        if c.covariance_pose is None:
            info["left_out"] += 1
            continue
        bt = M[:3, :3] @ [0, 0, ci.carriage_type.height_m / 2] + M[:3, 3]
        recs.append(record(f"seed{seed}", c.number, c.world_from_carriage, c.body_centre_m, M, bt,
                           c.sigma_body_centre_m, c.ci95_body_centre_m, c.sigma_hpr_deg, c.ci95_hpr_deg,
                           n_cars=n_cars, sigma_px=sigma, converged=res.status == "converged",
                           t_factor=res.ci95_factor, dof=res.dof))


def focal_summary(info: dict) -> None:
    """The focal's RMS z, mean z and coverage over ``info["focal_z"]`` (when any), into ``info``."""
    if info["focal_z"]:
        fz = np.array(info["focal_z"])
        info.update(focal_rms_z=float(np.sqrt(np.mean(fz ** 2))), focal_mean_z=float(fz.mean()),
                    focal_coverage=float(np.mean(np.abs(fz) <= Z95)))


def route_known(n, seed0, log=print, terrain=False, terrain_sigma_m=None):
    return route_hand(n, seed0, False, log, terrain, terrain_sigma_m)


def route_focal(n, seed0, log=print, terrain=False, terrain_sigma_m=None):
    return route_hand(n, seed0, True, log, terrain, terrain_sigma_m)


# ----------------------------------------------------------------------------------------------------------
# route 3: generated incidents through the pipeline, automatic points
# ----------------------------------------------------------------------------------------------------------
AUTO_CARS = (4, 5, 6, 7)


SURVEY_NOISE_MARK = "coordinates perturbed by their sigma_m (bench_calibration --survey-noise)"


def perturb_control_points(path: Path, seed: int) -> None:
    """Give the synthetic control points the survey error they state: each coordinate + N(0, sigma_m^2) (the
    generator writes exact coordinates with sigma_m = 0.05 m, so the georegistration's covariance, which
    believes sigma_m, is wider than its errors). Once per file (marked in its description)."""
    doc = json.loads(path.read_text())
    if SURVEY_NOISE_MARK in doc.get("description", ""):
        return
    rng = np.random.default_rng(seed)
    for p in doc["points"]:
        sd = float(p.get("sigma_m") or 0.0)
        p["coords"] = [round(float(x) + rng.normal(0.0, sd), 4) for x in p["coords"]]
    doc["description"] = doc.get("description", "") + "; " + SURVEY_NOISE_MARK
    path.write_text(json.dumps(doc, indent=1))


DEM_NOISE_TAG = "bench_calibration_dem_error_m"  # the GeoTIFF tag that marks a DEM given its error (--dem-noise)


def perturb_dem(root: Path, seed: int) -> None:
    """Give the synthetic incident's DEM the vertical error it states (``terrain.dem_vertical_accuracy_m``):
    :func:`workbench.synth.terrain.dem_error` added to the exact terrain the generator writes (under which a
    terrain contact that believes the stated 0.25 m is far better held than it thinks). Once per file (a tag in
    the GeoTIFF); written to a temporary file and renamed."""
    import tomllib

    import rasterio

    from workbench.core.io import atomic_write
    from workbench.synth.terrain import dem_error

    terrain = tomllib.loads((root / "project.toml").read_text())["terrain"]
    path, sd = root / terrain["dem"], float(terrain["dem_vertical_accuracy_m"])
    with rasterio.open(path) as src:
        if DEM_NOISE_TAG in src.tags():
            return
        z, profile, tags, res = src.read(1), src.profile, src.tags(), abs(src.res[0])
    valid = z != profile.get("nodata")
    z = np.where(valid, z + dem_error(np.random.default_rng([seed, 2]), z.shape, res, sd), z).astype(z.dtype)

    def write(tmp: Path) -> None:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(z, 1)
            dst.update_tags(**tags, **{DEM_NOISE_TAG: str(sd)})

    atomic_write(path, write, suffix=".tif")


def solve_incident(root: Path, seed: int, n_cars: int, width: int = 800, height: int = 600,
                   n_panorama: int | None = None, n_multiview: int = 0, resolve: bool = False,
                   survey_noise: bool = False, dem_noise: bool = False) -> dict:
    """Generate one incident (``workbench synth``; kept when already generated), write its control points, run
    the pipeline up to ``solve`` (``resolve``: the solve stage again, the rest as it is); returns the solution and
    the truth (both as JSON documents). ``survey_noise``: :func:`perturb_control_points`; ``dem_noise``:
    :func:`perturb_dem` (before the pipeline: every stage sees the DEM with its error)."""
    from workbench import pipeline
    from workbench.project import Project
    from workbench.runner import Runner
    from workbench.synth.control_points import write_control_points
    from workbench.synth.generate import SynthOptions, generate_incident

    generate_incident(root, SynthOptions(seed=seed, n_cars=n_cars, photo_width=width, photo_height=height,
                                         n_panorama=n_panorama, n_multiview=n_multiview))
    write_control_points(root)
    if survey_noise:
        perturb_control_points(root / "control_points.json", seed)
    if dem_noise:
        perturb_dem(root, seed)
    project = Project(root)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        runner = Runner(project, list(pipeline.STAGES))
        runner.run(until="solve")
        if resolve:
            runner.run(only=["solve"], force=True)
    sol = json.loads((root / "out/solve/solution.json").read_text())
    truth = json.loads((root / "truth/ground_truth.json").read_text())
    cams = root / "out/georef/cameras.json"
    return {"solution": sol, "truth": truth, "cameras": json.loads(cams.read_text()) if cams.is_file() else None}


def camera_error(cameras: dict, truth: dict) -> tuple[np.ndarray, dict] | None:
    """The georegistration's error as the rigid motion ``T`` (4, 4) of the scene that takes the true camera onto
    the estimated one (``world_from_cam_est @ cam_from_world_true``: a carriage solved perfectly relative to the
    camera lands at ``T @ truth``), and its rotation (rad) and centre (m) errors over their stated sigmas."""
    if not cameras or not cameras.get("views"):
        return None
    v = cameras["views"][0]
    ph = next((p for p in truth.get("photos", []) if Path(p.get("photo", "")).name == v["name"]), None)
    if ph is None:
        return None
    Me, Mt = np.asarray(v["cam_from_world"], float), np.asarray(ph["cam_from_world"], float)
    T = np.linalg.inv(Me) @ Mt
    from scipy.spatial.transform import Rotation

    w = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    c_e, c_t = -Me[:3, :3].T @ Me[:3, 3], -Mt[:3, :3].T @ Mt[:3, 3]
    C = (cameras.get("georegistration") or {}).get("covariance_world_rotation_centre")
    z = None
    if C is not None:
        sd = np.sqrt(np.diag(np.asarray(C, float)))
        z = (np.concatenate([w, c_e - c_t]) / sd).tolist()
    return T, {"rotation_err_deg": np.degrees(w).tolist(), "centre_err_m": (c_e - c_t).tolist(), "z": z}


def incident_records(problem: str, sol: dict, truth: dict, T_cam: np.ndarray | None = None,
                     **extra) -> tuple[list[dict], list[dict], int, int]:
    """The placed carriages' records of one solved incident; the same against the fit's own intervals and the
    truth carried by the camera's error ``T_cam`` (:func:`camera_error`: what the fit alone got wrong); the number
    left out and the number placed without an interval (a pose its measured points do not determine)."""
    from workbench.files.solution import doubts_of

    by_number = {c["number"]: c for c in truth["carriages"]}
    doubts = doubts_of(sol)
    recs, fit, left, no_interval = [], [], 0, 0
    for c in sol["carriages"]:
        if c.get("world_from_carriage") is None:
            left += 1
            continue
        if c.get("sigma_body_centre_m") is None or None in c["sigma_body_centre_m"]:
            no_interval += 1
            continue
        t = by_number[c["number"]]
        recs.append(record(problem, c["number"], c["world_from_carriage"], c["body_centre_enu"],
                           t["world_from_carriage"], t["body_centre_enu"], c["sigma_body_centre_m"],
                           c["ci95_body_centre_m"], c["sigma_hpr_deg"], c["ci95_hpr_deg"], status=c["status"],
                           n_points=c["n_points"], t_factor=sol.get("ci95_factor"), dof=sol.get("dof"),
                           sigma_px=sol.get("sigma_px"), sigma_px_estimated=sol.get("sigma_px_estimated"),
                           camera_uncertainty=bool((sol.get("camera_uncertainty") or {}).get("included")),
                           doubtful=c["number"] in doubts, **extra))
        if sol.get("route") == "panorama" and truth.get("panorama_center_enu") is not None:  # one camera centre
            recs[-1]["sight_z"] = sight_z(c, t["body_centre_enu"], truth["panorama_center_enu"])
        if T_cam is not None and c.get("sigma_body_centre_fit_m") is not None:
            q = float(sol.get("ci95_factor") or Z95)
            sb, sh = np.asarray(c["sigma_body_centre_fit_m"], float), np.asarray(c["sigma_hpr_fit_deg"], float)
            fit.append(record(problem, c["number"], c["world_from_carriage"], c["body_centre_enu"],
                              T_cam @ np.asarray(t["world_from_carriage"], float),
                              T_cam[:3, :3] @ np.asarray(t["body_centre_enu"], float) + T_cam[:3, 3],
                              sb, q * sb, sh, q * sh, **extra))
    return recs, fit, left, no_interval


def pose_searched(root: Path) -> set[str]:
    """The carriages the correspond stage's chain/terrain pose search found in some photo of incident ``root``
    (``cars_by_pose_search`` of ``out/correspond/stats.json``; none where the file is absent)."""
    path = root / "out" / "correspond" / "stats.json"
    if not path.is_file():
        return set()
    photos = json.loads(path.read_text()).get("photos") or {}
    return {str(c) for v in photos.values() for c in (v.get("cars_by_pose_search") or [])}


def finder_split(recs: list[dict]) -> dict[str, list[dict]]:
    """The automatic route's unmarked carriages (not ``doubtful``) by how the finder placed them (``found_by``:
    ``matched``, a face matched in every photo it was found in; ``pose_search``, found by the pose search in some
    photo). Their intervals come from different terms (docs/calibration.md, "Session 25"), so each is told apart."""
    out: dict[str, list[dict]] = {}
    for r in recs:
        if not r.get("doubtful") and r.get("found_by"):
            out.setdefault(r["found_by"], []).append(r)
    return dict(sorted(out.items()))


def route_auto(n: int, seed0: int, log=print, work: Path | None = None, keep: bool = True,
               resolve: bool = False, survey_noise: bool = False, dem_noise: bool = False
               ) -> tuple[list[dict], dict]:
    """Incidents ``work/inc_<seed>`` (kept, so that ``resolve`` can solve them again after a change to the solve,
    without the 40-60 s of the earlier stages)."""
    work = work or REPO / "bench_out" / "calibration_auto"
    recs, info = [], {"seeds": [], "failed": [], "left_out": 0, "no_interval": 0, "time_s": 0.0, "work": str(work),
                      "fit_records": [], "camera": []}
    s = seed0
    t0 = time.perf_counter()
    while len(recs) < n:
        seed, n_cars = s, AUTO_CARS[(s - seed0) % len(AUTO_CARS)]
        s += 1
        root = work / f"inc_{seed}"
        t1 = time.perf_counter()
        try:
            out = solve_incident(root, seed, n_cars, resolve=resolve, survey_noise=survey_noise,
                                 dem_noise=dem_noise)
        except Exception as e:  # noqa: BLE001 - a failed incident is counted and named, not fatal
            info["failed"].append({"seed": seed, "error": f"{type(e).__name__}: {str(e)[:300]}"})
            log(f"  seed {seed}: failed ({type(e).__name__}: {str(e)[:120]})")
            if len(info["failed"]) >= 3 and len({f["error"] for f in info["failed"][-3:]}) == 1 \
                    and all(f["seed"] >= seed - 2 for f in info["failed"][-3:]):
                log("  three incidents in a row failed the same way: stopping (a broken checkout, not a finding)")
                break
            continue
        cam = camera_error(out["cameras"], out["truth"])
        r, fit, left, no_int = incident_records(f"seed{seed}", out["solution"], out["truth"],
                                                None if cam is None else cam[0], n_cars=n_cars)
        searched = pose_searched(root)
        for x in r + fit:
            x["found_by"] = "pose_search" if x["number"] in searched else "matched"
        recs += r
        info["fit_records"] += fit
        if cam is not None:
            info["camera"].append({"seed": seed, **cam[1]})
        info["seeds"].append(seed)
        info["left_out"] += left
        info["no_interval"] += no_int
        zs = [np.max(np.abs(np.divide(x["error"], x["sigma"]))) for x in r]
        log(f"  seed {seed}: {n_cars} cars, {len(r)} placed, sigma_px {out['solution'].get('sigma_px'):.3f} "
            f"(estimated {out['solution'].get('sigma_px_estimated') or float('nan'):.3f}), max |z| per car "
            f"{' '.join(f'{z:.1f}' for z in zs)}; {time.perf_counter() - t1:.0f} s; {len(recs)} carriages so far")
        if not keep:
            shutil.rmtree(root, ignore_errors=True)
    info["time_s"] = time.perf_counter() - t0
    return recs, info


# ----------------------------------------------------------------------------------------------------------
# routes 4 and 5: relative incidents (no survey), through the pipeline, the track tilted against gravity
# ----------------------------------------------------------------------------------------------------------
TRACK_TILT_DEG = 0.5  # the simulated track's grade and cant, per horizontal axis, and what the incidents state
RELATIVE_PICK_SIGMA_PX = 0.5  # the picks' noise, and the pixel sigma the incidents state


def route_relative_any(n: int, seed0: int, estimate_focal: bool, log=print,
                       pp_uniform: bool = False) -> tuple[list[dict], dict]:
    """Simulated consists (3 cars, 0.5 px picks, one photo from 12 m up) as incidents with no control points
    (``workbench.synth.relative``), the scene tilted by N(0, 0.5 deg) per horizontal axis against gravity (the
    track's grade and cant; stated as ``solver.level_sigma_common_deg = 0.5``, ``level_sigma_car_deg = 0``: no
    car tilted on its own), the pick noise stated (``solver.pixel_sigma_px = 0.5``, as the hand routes give the
    true sigma), run through inputs, georef (relative), correspond (finder off) and solve; the truth moved into
    the levelled frame. Focal estimated: the principal point (the solve takes it at the centre) drawn N(0, the
    sigma the solve states) per axis, or ``simulate_consist``'s uniform +-10 px (``pp_uniform``)."""
    import tempfile

    from workbench.pipeline import STAGES
    from workbench.project import Project
    from workbench.runner import Runner
    from workbench.solve.principal_point import guessed_principal_point_sigma_px
    from workbench.synth import relative as rel

    pp_sigma = guessed_principal_point_sigma_px(rel.WIDTH, rel.HEIGHT) if estimate_focal and not pp_uniform else None
    recs, info = [], {"seeds": [], "skipped_seeds": [], "failed": [], "left_out": 0, "time_s": 0.0, "track_tilt_deg":
                      TRACK_TILT_DEG, "principal_point_sigma_px": pp_sigma, "pick_sigma_px": RELATIVE_PICK_SIGMA_PX}
    solver = (f"level_sigma_common_deg = {TRACK_TILT_DEG}\nlevel_sigma_car_deg = 0.0\n"
              f"pixel_sigma_px = {RELATIVE_PICK_SIGMA_PX}\n")
    seed, t0 = seed0 - 1, time.perf_counter()
    while len(recs) < n:
        seed += 1
        try:
            sim = rel.relative_sim(seed, pixel_sigma_px=RELATIVE_PICK_SIGMA_PX, principal_point_sigma_px=pp_sigma)
        except RuntimeError:
            info["skipped_seeds"].append(seed)
            continue
        # the tilt from a stream of its own: default_rng(seed)'s first draws are the simulation's (its track's
        # azimuth comes from the same 64 bits as the first normal: |tilt| and azimuth correlated 0.1)
        truth, cam = rel.tilt_world(sim, np.random.default_rng([seed, 2]), TRACK_TILT_DEG)
        L = rel.levelled_truth(sim, cam)
        with tempfile.TemporaryDirectory() as tmp:
            project = Project(rel.write_relative_incident(Path(tmp) / "inc", sim, focal_known=not estimate_focal,
                                                      solver=solver))
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
            except Exception as exc:  # noqa: BLE001 - counted
                info["failed"].append({"seed": seed, "error": str(exc)[:200]})
                continue
            sol = project.solution("bench")
        info["seeds"].append(seed)
        for c, M, ci in zip(sol.carriages, truth, sim.carriages):
            r = c.record
            if c.world_from_carriage is None or r.get("sigma_body_centre_m") is None:
                info["left_out"] += 1
                continue
            T = L @ M
            bt = T[:3, :3] @ [0, 0, ci.carriage_type.height_m / 2] + T[:3, 3]
            recs.append(record(f"seed{seed}", c.number, c.world_from_carriage, r["body_centre_enu"], T, bt,
                               r["sigma_body_centre_m"], r["ci95_body_centre_m"], r["sigma_hpr_deg"],
                               r["ci95_hpr_deg"], focal_estimated=estimate_focal))
        if len(info["seeds"]) % 10 == 0:
            log(f"  {len(info['seeds'])} problems, {len(recs)} carriages, {time.perf_counter() - t0:.0f} s")
    info["time_s"] = time.perf_counter() - t0
    return recs, info


def route_relative(n, seed0, log=print, pp_uniform=False):
    return route_relative_any(n, seed0, False, log, pp_uniform)


def route_relative_focal(n, seed0, log=print, pp_uniform=False):
    return route_relative_any(n, seed0, True, log, pp_uniform)


# ----------------------------------------------------------------------------------------------------------
# route 6: multi-view incidents (SfM model placed by a similarity from control points), hand picks
# ----------------------------------------------------------------------------------------------------------
MV_CASES = ((5, 0.5), (4, 1.0))  # (cars, pixel sigma of the hand picks) of each base incident, cycled
MV_DRAWS = 10  # noise draws per generated incident (its geometry rendered once, ~15 s)
REAL_SFM_MAX_SEEDS = 12  # --real-sfm: incidents tried at most (SfM places too few photos of some)


def _mv_base(work: Path, seed: int, n_cars: int, size: tuple[int, int] = (800, 600)) -> Path:
    """A generated incident (``workbench synth``: ``size`` photos, 8 multi-view photos, 2 panorama photos) set up
    for the multi-view route (camera source sfm, the multi-view photos), with its control points' true pixels
    and coordinates cached (``cp_exact.json``). Photos other than 800x600 go to ``mv<W>_<seed>``."""
    from workbench.synth.control_points import control_points_document
    from workbench.synth.generate import SynthOptions, generate_incident

    root = work / (f"mv_{seed}" if size == (800, 600) else f"mv{size[0]}_{seed}") / "projects" / "inc"
    if not (root / "cp_exact.json").is_file():
        generate_incident(root, SynthOptions(seed=seed, n_cars=n_cars, photo_width=size[0], photo_height=size[1],
                                             n_panorama=2, n_multiview=8, supersample=1,
                                             layers_dir="../../terrain"))
        t = (root / "project.toml").read_text()
        (root / "project.toml").write_text(t.replace('source = "calibrated"', 'source = "sfm"')
                                           .replace('photos = "photos/panorama"', 'photos = "photos/multiview"'))
        (root / "cp_exact.json").write_text(json.dumps(control_points_document(root, sigma_px=0.0)))
    return root


def _sfm_noisy(rec: dict, scale: float, rng, sigma_deg: float, sigma_m: float) -> dict:
    """The reconstruction with each photo's SfM pose disturbed: its rotation by N(0, ``sigma_deg``) per axis, its
    centre by N(0, ``sigma_m``) per axis (scene metres; ``scale`` = the model's scene metres per unit): an SfM
    model that is not exact relative to itself."""
    from workbench.core.geometry import exp_so3

    for im in rec["images"]:
        C = np.asarray(im["cam_from_model"], float)
        centre = -C[:3, :3].T @ C[:3, 3] + rng.normal(0.0, sigma_m, 3) / scale
        R = C[:3, :3] @ exp_so3(np.radians(rng.normal(0.0, sigma_deg, 3)))
        C[:3, :3], C[:3, 3] = R, -R @ centre
        im["cam_from_model"] = C.tolist()
    return rec


def _real_sfm(root: Path, own_covariance: bool = True) -> dict:
    """The sfm stage itself (pycolmap, as ``workbench run`` runs it) on the base incident's multi-view photos, run
    once per incident (its reconstruction cached as ``sfm_real.json``: the run is deterministic, and the noise
    draws change only the picks and the control points). ``own_covariance`` False: the views' SfM pose
    covariance (``covariance_rotation_centre``) dropped, the route as it was before the sfm stage stated it."""
    cache = root / "sfm_real.json"
    if not cache.is_file():
        from workbench.intrinsics.stage import run_sfm_stage
        from workbench.project import Project

        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run_sfm_stage(Project(root), lambda *a: None)
        doc = json.loads((root / "out" / "sfm" / "reconstruction.json").read_text())
        doc.setdefault("stats", {})["bench_sfm_wall_s"] = round(time.perf_counter() - t0, 1)
        cache.write_text(json.dumps(doc))
    doc = json.loads(cache.read_text())
    if not own_covariance:
        for images in [doc.get("images", [])] + [m.get("images", []) for m in doc.get("models", [])]:
            for im in images:
                im.pop("pose_factor", None)
                im.pop("covariance_rotation_centre", None)
        doc.pop("pose_covariance", None)
    return doc


def sfm_view_errors(cameras: dict, truth: dict, cameras_path: Path) -> list[dict]:
    """Every placed photo's scene pose error against the truth (rotation vector of ``world_from_cam`` (rad, scene
    frame, on the left) and centre (m, ENU): the order of ``pose_uncertainty``) and its stated covariance
    (:meth:`~workbench.files.cameras.PoseUncertainty.view_covariance`): per view the error, the stated sigmas and
    the Mahalanobis distance squared (6 dof)."""
    from scipy.spatial.transform import Rotation

    from workbench.files.cameras import parse_pose_uncertainty

    pu = parse_pose_uncertainty(cameras, cameras_path)
    true_of = {Path(p.get("photo", "")).name: np.asarray(p["cam_from_world"], float) for p in truth.get("photos", [])}
    out = []
    for v in cameras.get("views", []):
        Mt = true_of.get(v["name"])
        if Mt is None:
            continue
        Me = np.asarray(v["cam_from_world"], float)
        w = Rotation.from_matrix(Me[:3, :3].T @ Mt[:3, :3]).as_rotvec()  # world_from_cam_est = Exp(w) world_from_cam_true
        e = np.concatenate([w, (-Me[:3, :3].T @ Me[:3, 3]) - (-Mt[:3, :3].T @ Mt[:3, 3])])
        C = None if pu is None else pu.view_covariance(v["name"])
        src = (((cameras.get("georegistration") or {}).get("pose_uncertainty") or {}).get("views") or {}) \
            .get(v["name"], {}).get("source")
        rec = {"view": v["name"], "source": src, "err": e.tolist(), "rot_err_deg": float(np.degrees(np.linalg.norm(w))),
               "centre_err_m": float(np.linalg.norm(e[3:])), "sigma": None, "maha2": None}
        if C is not None:
            rec["sigma"] = np.sqrt(np.maximum(np.diag(C), 0.0)).tolist()
            rec["maha2"] = float(e @ np.linalg.pinv(C, rcond=1e-12, hermitian=True) @ e)
        out.append(rec)
    return out


def print_placed_split(recs: list[dict], info: dict) -> None:
    """--real-sfm: the carriages of draws where an SfM model's similarity placed some photo (a view of source
    ``similarity``; records before the source was kept: some stated pose covariance) apart from those of draws
    where every photo was placed on its own (resected), with the camera term and with the fit's own intervals."""
    placed = {e["draw"] for e in info["view_errors"]
              if (e.get("source") == "similarity" if "source" in e else e["sigma"] is not None)}
    for label, rr in (("", recs), (" before (the fit's own)", info.get("fit_records", []))):
        for what, keep in (("SfM model placed", True), ("photos resected", False)):
            sub = [r for r in rr if (int(r["problem"][2:]) in placed) == keep]
            if sub:
                print_table(f"multiview{label}, draws with {what} (incidents "
                            f"{sorted({int(r['problem'][2:]) // 1000 for r in sub})})", axis_stats(sub))
    st = [e for e in info["view_errors"] if e["sigma"] is not None
          and (e.get("source") == "similarity" if "source" in e else e["draw"] in placed)]
    if st:
        print("SfM-placed " + view_error_summary(st))


def view_error_summary(errs: list[dict]) -> str:
    """One line on the placed photos' pose errors against their stated covariance (:func:`sfm_view_errors`)."""
    if not errs:
        return ""
    E = np.array([e["err"] for e in errs])
    line = (f"photo poses ({len(errs)} over the draws): RMS rotation error {np.degrees(np.sqrt(np.mean(np.sum(E[:, :3] ** 2, 1)))):.3f} deg, "
            f"RMS centre error {np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, 1))):.3f} m")
    st = [e for e in errs if e["sigma"] is not None]
    if st:
        Z = np.array([e["err"] for e in st]) / np.maximum(np.array([e["sigma"] for e in st]), 1e-300)
        rz = np.sqrt(np.mean(Z ** 2, axis=0))
        m2 = np.array([e["maha2"] for e in st])
        line += (f"; stated for {len(st)}: RMS z rotation {' '.join(f'{x:.2f}' for x in rz[:3])}, centre "
                 f"{' '.join(f'{x:.2f}' for x in rz[3:])}; mean Mahalanobis^2 / 6 {np.mean(m2) / 6:.2f} "
                 f"(median {np.median(m2) / 6:.2f})")
    return line


def mv_draw(root: Path, draw_seed: int, sigma_px: float, cp_sigma_px: float = 0.5,
            sfm_noise: tuple[float, float] = (0.0, 0.0), real_sfm: str | None = None) -> dict:
    """One noise draw on a multi-view base incident: the control points' pixels + N(0, ``cp_sigma_px``) and
    their coordinates + N(0, sigma_m) (the survey error they state), an exact SfM model in a random frame (a
    random similarity; ``sfm_noise`` (deg, m): each SfM pose disturbed, :func:`_sfm_noisy`), hand picks (true
    pixels + N(0, ``sigma_px``)), then the georef and solve stages.
    Returns the solution, the truth and the cameras (JSON documents)."""
    import tomllib

    import tomli_w

    from workbench.core.io import atomic_write_json
    from workbench.georef.stage import run_georef
    from workbench.project import Project
    from workbench.solve.stage import run_solve
    from workbench.synth.control_points import similarity, true_reconstruction
    from workbench.synth.handpicks import write_true_correspondences

    rng = np.random.default_rng(draw_seed)
    truth = json.loads((root / "truth/ground_truth.json").read_text())
    cp = json.loads((root / "cp_exact.json").read_text())
    for p in cp["points"]:
        p["coords"] = [float(x) + rng.normal(0.0, float(p.get("sigma_m") or 0.0)) for x in p["coords"]]
        p["pixels"] = {k: (np.asarray(uv, float) + rng.normal(0.0, cp_sigma_px, 2)).tolist()
                       for k, uv in p["pixels"].items()}
    atomic_write_json(root / "control_points.json", cp)
    scale = float(np.exp(rng.uniform(-1.5, 1.5)))
    S = similarity(scale, rng.uniform(-180, 180, 3) * [1, 0.5, 1], rng.normal(0.0, 50.0, 3))
    if real_sfm is not None:  # pycolmap's model of the photos (its own frame), with or without its covariance
        rec = _real_sfm(root, own_covariance=real_sfm == "covariance")
    else:
        rec = true_reconstruction(root, S)
    if any(sfm_noise):
        rec = _sfm_noisy(rec, scale, rng, *sfm_noise)
    atomic_write_json(root / "out" / "sfm" / "reconstruction.json", rec)
    write_true_correspondences(root, "multiview", sigma_px=sigma_px, seed=draw_seed)
    settings = tomllib.loads((root / "project.toml").read_text())  # the generator's [solver] keys kept
    settings.setdefault("solver", {})["pixel_sigma_px"] = sigma_px
    (root / "project.toml").write_text(tomli_w.dumps(settings))
    project = Project(root)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_georef(project, lambda *a: None)
        if real_sfm is not None:  # picks only in the photos placed (SfM or the georef left some out), as a user would
            placed = {v["name"] for v in json.loads((root / "out/georef/cameras.json").read_text())["views"]}
            corr = json.loads((root / "correspondences.json").read_text())
            corr["observations"] = [o for o in corr["observations"] if o["view"] in placed]
            atomic_write_json(root / "correspondences.json", corr)
        run_solve(project, lambda *a: None)
    cameras = json.loads((root / "out/georef/cameras.json").read_text())
    return {"solution": json.loads((root / "out/solve/solution.json").read_text()), "truth": truth,
            "cameras": cameras, "view_errors": sfm_view_errors(cameras, truth, root / "out/georef/cameras.json")}


def route_multiview(n: int, seed0: int, log=print, work: Path | None = None, draws: int = MV_DRAWS,
                    sfm_noise: tuple[float, float] = (0.0, 0.0), real_sfm: str | None = None,
                    max_incidents: int = REAL_SFM_MAX_SEEDS) -> tuple[list[dict], dict]:
    """Generated incidents (seeds from ``seed0``), each solved ``draws`` times with fresh noise (:func:`mv_draw`);
    the records with the camera term (``camera_uncertainty``) and, in ``info["fit_records"]``, the same carriages
    against the fit's own intervals (``sigma_*_fit_*``: the intervals before the camera term)."""
    work = work or REPO / "bench_out" / "calibration_multiview"
    recs, info = [], {"seeds": [], "failed": [], "left_out": 0, "no_interval": 0, "time_s": 0.0, "work": str(work),
                      "fit_records": [], "draws": draws, "sfm_noise_deg_m": list(sfm_noise),
                      "real_sfm": real_sfm, "view_errors": []}
    t0, k = time.perf_counter(), 0
    dead: set[int] = set()  # real SfM: incidents whose first draw failed (the same SfM model in every draw)
    while len(recs) < n:
        seed = seed0 + k // draws
        if real_sfm is not None and (seed - seed0 >= max_incidents or seed in dead):
            if seed - seed0 >= max_incidents:
                log(f"  {max_incidents} incidents tried: stopping")
                break
            k += 1
            continue
        n_cars, sigma = MV_CASES[(k // draws) % len(MV_CASES)]
        draw_seed = 1000 * seed + k % draws
        k += 1
        t1 = time.perf_counter()
        try:
            # pycolmap registers 2 of 8 photos of an 800x600 incident (seed 951); at 1600x1200 (bench_sfm's size) more
            base = _mv_base(work, seed, n_cars, (1600, 1200) if real_sfm else (800, 600))
            out = mv_draw(base, draw_seed, sigma, sfm_noise=sfm_noise, real_sfm=real_sfm)
        except Exception as e:  # noqa: BLE001 - a failed draw is counted and named, not fatal
            info["failed"].append({"seed": seed, "draw": draw_seed, "error": f"{type(e).__name__}: {str(e)[:300]}"})
            log(f"  seed {seed} draw {draw_seed}: failed ({type(e).__name__}: {str(e)[:160]})")
            if real_sfm is not None:
                if (k - 1) % draws == 0:  # its first draw: the SfM model or its placement failed, skip the rest
                    dead.add(seed)
                continue
            if len(info["failed"]) >= 5 and len(info["failed"]) > len(info["seeds"]):
                log("  most draws fail: stopping (a broken checkout, not a finding)")
                break
            continue
        sol = out["solution"]
        # the fit's own intervals against the truth itself: the intervals as they were before the camera term
        r, fit, left, no_int = incident_records(f"mv{draw_seed}", sol, out["truth"], np.eye(4), n_cars=n_cars,
                                                sigma_px_picks=sigma)
        recs += r
        info["fit_records"] += fit
        info["seeds"].append(draw_seed)
        info["view_errors"] += [{"draw": draw_seed, **e} for e in out.get("view_errors", [])]
        info["left_out"] += left
        info["no_interval"] += no_int
        cu = sol.get("camera_uncertainty") or {}
        info.setdefault("views_own_covariance", 0)
        info.setdefault("views_not_modelled", 0)
        info["views_own_covariance"] += len(cu.get("views_own_covariance") or [])  # re-posed by the adjustment
        info["views_not_modelled"] += len(cu.get("views_not_modelled") or [])
        if len(info["seeds"]) % 5 == 0:
            log(f"  {len(info['seeds'])} draws, {len(recs)} carriages, last {time.perf_counter() - t1:.1f} s, "
                f"{time.perf_counter() - t0:.0f} s in all; camera term included: "
                f"{(sol.get('camera_uncertainty') or {}).get('included')}")
    info["time_s"] = time.perf_counter() - t0
    return recs, info


ROUTES = {"known": route_known, "focal": route_focal, "auto": route_auto, "relative": route_relative,
          "relative_focal": route_relative_focal, "multiview": route_multiview}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="known,focal", help="comma-separated: " + ", ".join(ROUTES))
    ap.add_argument("--n", type=int, default=200, help="carriages per route (at least)")
    ap.add_argument("--seed0", type=int, default=210000, help="first seed (fresh seeds: not the tests' or "
                                                               "bench_solver's)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=None, help="routes auto, multiview: the incidents' folder "
                                                            "(default bench_out/calibration_<route>)")
    ap.add_argument("--terrain", action="store_true", help="routes known, focal: solve on the simulated terrain "
                                                           "(resting and the contact term, as the stage with a DEM)")
    ap.add_argument("--terrain-sigma", type=float, default=None,
                    help="with --terrain: the terrain's stated accuracy (m; default SolveOptions' 0.10)")
    ap.add_argument("--survey-noise", action="store_true",
                    help="route auto: perturb the control points' coordinates by the sigma_m they state")
    ap.add_argument("--dem-noise", action="store_true",
                    help="route auto: give the DEM the vertical error it states (a smooth field, perturb_dem)")
    ap.add_argument("--no-keep", action="store_true", help="route auto: delete each incident once solved")
    ap.add_argument("--resolve", action="store_true", help="route auto: run the solve stage again on incidents "
                                                           "already there (after a change to the solve)")
    ap.add_argument("--draws", type=int, default=MV_DRAWS, help="route multiview: noise draws per generated "
                                                                 "incident (each incident ~15 s to generate)")
    ap.add_argument("--sfm-noise", type=float, nargs=2, default=(0.0, 0.0), metavar=("DEG", "M"),
                    help="route multiview: disturb each SfM pose by N(0, DEG) per rotation axis and N(0, M) per "
                         "centre axis (default exact SfM models)")
    ap.add_argument("--real-sfm", choices=("covariance", "no-covariance"), default=None,
                    help="route multiview: run the sfm stage (pycolmap) on the generated photos instead of the exact "
                         "model; 'no-covariance' drops the views' SfM pose covariance it states (the route before)")
    ap.add_argument("--real-sfm-incidents", type=int, default=REAL_SFM_MAX_SEEDS, metavar="N",
                    help=f"with --real-sfm: incidents tried at most (default {REAL_SFM_MAX_SEEDS}; SfM places too "
                         f"few photos of some)")
    ap.add_argument("--pp-uniform", action="store_true", help="route relative_focal: the principal point "
                    "uniform +-10 px off the centre (simulate_consist's), not drawn with the sigma the solve states")
    ap.add_argument("--merge", type=Path, nargs="*", default=None,
                    help="merge saved runs (their carriage records, route by route) and print the table")
    ap.add_argument("--exclude", nargs="*", default=[], metavar="PROBLEM_PREFIX:NUMBER",
                    help="with --merge: leave out these carriages (e.g. mv708:6231, a gross failure named apart)")
    a = ap.parse_args(argv)
    if a.merge:
        def kept(x: dict) -> bool:  # --exclude PROBLEM_PREFIX:NUMBER (a named gross failure, reported apart)
            return not any(x["problem"].startswith(e.split(":")[0]) and x["number"] == e.split(":")[1]
                           for e in a.exclude)

        by_route: dict[str, list] = {}
        for p in a.merge:
            d = json.loads(p.read_text())
            for rt, v in d["routes"].items():
                by_route.setdefault(rt, []).extend(x for x in v["records"] if kept(x))
                if rt == "multiview":  # the same carriages with the fit's own intervals: before the camera term
                    by_route.setdefault(rt + " before", []).extend(
                        x for x in v["info"].get("fit_records", []) if kept(x))
        for rt, recs in by_route.items():
            print_table(rt, axis_stats(recs))
            print_doubts(rt, recs)
            for how, sub in finder_split(recs).items() if rt == "auto" else ():
                print_table(f"auto, unmarked, found by {how.replace('_', ' ')}", axis_stats(sub))
            print_sight(f"{rt}, unmarked", sight_stats([x for x in recs if not x.get("doubtful")]))
        return 0
    routes = [r.strip() for r in a.route.split(",") if r.strip()]
    for r in routes:
        if r not in ROUTES:
            ap.error(f"unknown route {r!r}; routes: {', '.join(ROUTES)}")
    out = a.out or REPO / "bench_out" / f"calibration_{'_'.join(routes)}.json"
    result = {"command": " ".join(sys.argv), "seed0": a.seed0, "terrain": a.terrain,
              "terrain_sigma_m": a.terrain_sigma, "routes": {}}
    for r in routes:
        print(f"route {r}: solving until {a.n} carriages ...", flush=True)
        kw = {"work": a.work, "keep": not a.no_keep, "resolve": a.resolve, "survey_noise": a.survey_noise,
              "dem_noise": a.dem_noise} \
            if r == "auto" else {"pp_uniform": a.pp_uniform} if r.startswith("relative") else \
            {"work": a.work, "draws": a.draws, "sfm_noise": tuple(a.sfm_noise), "real_sfm": a.real_sfm,
             "max_incidents": a.real_sfm_incidents} \
            if r == "multiview" else \
            {"terrain": a.terrain, "terrain_sigma_m": a.terrain_sigma}
        recs, info = ROUTES[r](a.n, a.seed0, log=lambda m: print(m, flush=True), **kw)
        if not recs:
            print(f"route {r}: no carriage solved ({len(info.get('failed', []))} failures)")
            result["routes"][r] = {"info": info, "records": []}
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(result, indent=1))
            continue
        st = axis_stats(recs)
        extra = f", {info['time_s']:.0f} s; left out {info.get('left_out', 0)}"
        if "focal_rms_z" in info:
            extra += f"; focal: RMS z {info['focal_rms_z']:.3f}, coverage {100 * info['focal_coverage']:.1f} %"
        print_table(r, st, extra)
        print_doubts(r, recs)
        if info.get("view_errors"):
            print(view_error_summary(info["view_errors"]))
        if info.get("real_sfm"):
            print_placed_split(recs, info)
        result["routes"][r] = {"stats": st, "info": info, "records": recs}
        if r == "auto":  # the unmarked carriages by how the finder placed them
            result["routes"][r]["stats_by_finder"] = {}
            for how, sub in finder_split(recs).items():
                result["routes"][r]["stats_by_finder"][how] = st_how = axis_stats(sub)
                print_table(f"auto, unmarked, found by {how.replace('_', ' ')}", st_how)
            result["routes"][r]["stats_sight"] = st_sight = sight_stats([x for x in recs if not x.get("doubtful")])
            print_sight("auto, unmarked", st_sight)
        if info.get("fit_records"):  # the fit's own intervals against the truth moved by the camera's error
            st_fit = axis_stats(info["fit_records"])
            zc = np.array([c["z"] for c in info.get("camera", []) if c.get("z") is not None])
            extra_c = "" if not len(zc) else (
                "; camera (georegistration) error / sigma, RMS over incidents: rotation "
                + " ".join(f"{x:.2f}" for x in np.sqrt(np.mean(zc[:, :3] ** 2, axis=0))) + ", centre "
                + " ".join(f"{x:.2f}" for x in np.sqrt(np.mean(zc[:, 3:] ** 2, axis=0))))
            print_table(r + (" before: the fit's own intervals (no camera term), against the truth"
                             if r == "multiview" else
                             " (the fit alone: its own intervals, the truth moved by the camera's error)"), st_fit,
                        extra_c)
            result["routes"][r]["stats_fit"] = st_fit
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1))
    print(f"\nsaved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
