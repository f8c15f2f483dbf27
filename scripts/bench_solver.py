#!/usr/bin/env python
"""Monte Carlo benchmark of the chained pose solver (workbench.solve) on simulated consists.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_solver.py [--quick] [--out bench_out/solver.json]

For consists of 3, 6, 12 carriages, pixel noise 0.5 / 1 / 2 px, known and unknown focal, couplings held
(slack 3 cm, true offsets uniform inside it): RMS carriage body-centre error (m) and rotation error (deg) of

* this solver (``solve_consist``, no terrain: the accuracy runs use the pixels and couplers only, the model the
  bound is computed for);
* per-carriage OpenCV PnP (SQPnP then ``cv2.solvePnPRefineLM``, raw pixels with K and distortion; with an
  unknown focal it is given the TRUE focal, an optimistic baseline);
* the Cramér-Rao bound of the chained problem at the truth, ``sqrt(mean over trials and carriages of
  trace(body-centre covariance))``, with held couplings modelled as the solver models them (offset prior
  N(0, (slack/sqrt 5)^2) per axis, see workbench/solve/uncertainty.py) and, for an unknown focal, the focal as
  a parameter;

plus the per-axis coverage of the solver's 95 % intervals (body centre), and, to tell a solver failure from the
estimator's own spread, the same cost minimised from the truth (``refine_from``): its RMS error against the CRB,
the trials where the solver ended at a higher cost, and the mean error along the optical axis (the ML estimate's
bias towards the camera grows as sigma^2). Timing: all four steps (with a
plane terrain, so step 2 and the contact term run) for 10 carriages, and how time grows up to 100 carriages,
for a camera at most 400 m away (a panorama of photos for long consists) and for one photo from 1.1 train
lengths away, each with the centre error against the truth and the CRB.
The solver (and the truth-started fit) run with ``SolveOptions.bias_correction`` as it ships (on: the
second-order bias removed, workbench/solve/bias.py; not applied with an unknown focal), and each cell prints the
same trials at the uncorrected truth-started minimum, paired; ``--no-bias-correction`` turns it off. The bound
is ``crb(weighting="per_point")`` (the ML information); with unequal point counts ``crb(weighting=<the
solver's>)`` is printed too.
Set OMP_NUM_THREADS=1 for one core (the script sets it when unset).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", os.environ["OMP_NUM_THREADS"])
os.environ.setdefault("MKL_NUM_THREADS", os.environ["OMP_NUM_THREADS"])

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402

from workbench.solve import SolveOptions, SolveWarning, crb, refine_from, solve_consist  # noqa: E402
from workbench.solve.simulate import redraw, simulate_consist  # noqa: E402

cv2.setNumThreads(1)


def rot_err_deg(Ra, Rb):
    return float(np.rad2deg(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))


def body_centre(ct, R, t):
    return R @ np.array([0.0, 0.0, ct.height_m / 2]) + t


def pnp_baseline(sim):
    view = sim.views[0]
    K, dist = view.intrinsics.K, view.intrinsics.dist_coeffs
    M = view.cam_from_world
    Rw, tw = M[:3, :3].T, -M[:3, :3].T @ M[:3, 3]
    out = []
    for car in sim.carriages:
        obs = car.observations["photo"]
        P = np.array([car.carriage_type.marked_points[n] for n in obs], dtype=np.float64)
        uv = np.array(list(obs.values()), dtype=np.float64).reshape(-1, 1, 2)
        ok, rvec, tvec = cv2.solvePnP(P, uv, K, dist, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(P, uv, K, dist, rvec, tvec)
        Rc = cv2.Rodrigues(rvec)[0]
        out.append((Rw @ Rc, Rw @ tvec.reshape(3) + tw))
    return out


def body_centres(sim, poses):
    return np.array([body_centre(c.carriage_type, M[:3, :3], M[:3, 3]) for c, M in zip(sim.carriages, poses)])


def split_bias(n, sigma, est_focal, trials, seed0, draws, weighting, points, bias_correction=False):
    """Bias / spread of the estimator itself: for each of the cell's geometries, ``draws`` new draws of the
    coupler offsets and the pixel noise (``simulate.redraw``), each minimised from the truth (``refine_from``,
    the solver's own minimum where it finds it). Per geometry the mean error is its bias; returns the cell's
    MSE, squared bias (less its own sampling variance, MSE / draws) and covariance, each over the mean CRB
    trace, and the mean error along the optical axis."""
    mse, bias2, crbt, depth = [], [], [], []
    opts = SolveOptions(pixel_sigma_px=sigma, estimate_focal=est_focal, weighting=weighting, check_image_bounds=False,
                        bias_correction=bias_correction)
    for k in range(trials):
        base = simulate_consist(n, seed=seed0 + k, pixel_sigma_px=sigma, n_points=points)
        cam_R = base.views[0].cam_from_world[:3, :3]
        E, tr = [], []
        for j in range(draws):
            sim = redraw(base, (seed0 + k) * 1000 + j)
            ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
            E.append(body_centres(sim, ml["world_from_carriage"]) - body_centres(sim, sim.truth))
            tr.append(np.mean([np.trace(C) for C in crb(sim.carriages, sim.links, sim.views, sim.truth, sigma,
                                                           est_focal, weighting="per_point")["body_centre_cov"]]))
        E = np.array(E)
        m = float(np.mean(np.sum(E**2, axis=2)))
        mse.append(m)
        bias2.append(float(np.mean(np.sum(E.mean(0) ** 2, axis=1))) - m / draws)
        crbt.append(float(np.mean(tr)))
        depth.append(float(np.mean((E @ cam_R.T)[..., 2])))
    c = float(np.mean(crbt))
    return {"draws": draws, "mse_over_crb": float(np.mean(mse)) / c, "bias2_over_crb": float(np.mean(bias2)) / c,
            "cov_over_crb": (float(np.mean(mse)) - float(np.mean(bias2))) / c,
            "ratio_if_unbiased": float(np.sqrt((np.mean(mse) - np.mean(bias2)) / c)),
            "mean_depth_error_m": float(np.mean(depth))}


def run_config(n, sigma, est_focal, trials, seed0, weighting="per_carriage", points=7, bias_correction=False):
    e_s, e_p, r_s, r_p, b2, cover, times, bad = [], [], [], [], [], [], [], 0
    ef2, fb2, e_ml, worse, depth, at_slack, b2w = [], [], [], 0, [], 0, []
    e_min, cover_min, depth_min, shift, skipped, box = [], [], [], [], [], []
    opts = SolveOptions(pixel_sigma_px=sigma, estimate_focal=est_focal, weighting=weighting,
                        bias_correction=bias_correction)
    for k in range(trials):
        sim = simulate_consist(n, seed=seed0 + k, pixel_sigma_px=sigma, n_points=points)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(sim.carriages, sim.links, sim.views, opts)
        times.append(time.perf_counter() - t0)
        bad += res.status != "converged"
        at_slack += sum(L["offset_norm_m"] >= L["slack_m"] * (1 - 1e-6) for L in res.links)
        # the same cost minimised from the truth: tells a solver failure (it ends higher) from the estimator's own
        # spread (it ends at the same point)
        ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
        # the solver's minimum against the truth-started one (with the bias correction the reported poses are
        # moved off the minimum: compare the costs at the minima)
        worse += res.cost_at_minimum > ml["cost"] * (1 + 1e-6) + 1e-6
        if bias_correction:
            shift.append(res.bias_correction.get("max_shift_m", 0.0))
            # the safeguard: carriages left uncorrected (predicted bias >= bias_max_over_sd sd), Box's measure
            skipped.append(len(res.bias_correction.get("skipped", [])))
            box.append(res.bias_correction.get("max_bias_over_sd", 0.0))
        # the bound: the ML information (every point 1 / sigma^2); the estimator's own covariance with its
        # weighting (crb(weighting=...)) is the same when every carriage shows the same number of points, and is
        # kept as "crb_weighted" otherwise
        bound = crb(sim.carriages, sim.links, sim.views, sim.truth, sigma, est_focal, weighting="per_point")
        if np.ndim(points) > 0:
            bw = crb(sim.carriages, sim.links, sim.views, sim.truth, sigma, est_focal, weighting=weighting)
            b2w += [np.trace(C) for C in bw["body_centre_cov"]]
        cam_R = sim.views[0].cam_from_world[:3, :3]
        pnp = pnp_baseline(sim)
        for i, (c, M) in enumerate(zip(res.carriages, sim.truth)):
            ct = sim.carriages[i].carriage_type
            bt = body_centre(ct, M[:3, :3], M[:3, 3])
            e = c.body_centre_m - bt
            e_s.append(e @ e)
            Mm = ml["world_from_carriage"][i]
            em = body_centre(ct, Mm[:3, :3], Mm[:3, 3]) - bt
            e_ml.append(em @ em)
            if bias_correction:
                # the truth-started minimum before the correction (= the solver's, where it reaches it): the same
                # trial without the correction, and the solver's intervals centred there
                M0 = ml.get("world_from_carriage_minimum", ml["world_from_carriage"])[i]  # not applied: the same
                e0 = body_centre(ct, M0[:3, :3], M0[:3, 3]) - bt
                e_min.append(e0 @ e0)
                cover_min.append(np.abs(e0) <= c.ci95_body_centre_m)
                depth_min.append(float((cam_R @ e0)[2]))
            depth.append(float((cam_R @ e)[2]))  # along the first photo's optical axis (+: farther)
            r_s.append(rot_err_deg(c.world_from_carriage[:3, :3], M[:3, :3]) ** 2)
            ep = body_centre(ct, *pnp[i]) - bt
            e_p.append(ep @ ep)
            r_p.append(rot_err_deg(pnp[i][0], M[:3, :3]) ** 2)
            b2.append(np.trace(bound["body_centre_cov"][i]))
            cover.append(np.abs(e) <= c.ci95_body_centre_m)
        if est_focal:
            ef2.append((res.focal_px["photo"] - sim.views[0].intrinsics.fx) ** 2)
            fb2.append(bound["focal_sigma"][0] ** 2)
    rms = float(np.sqrt(np.mean(e_s)))
    crb_rms = float(np.sqrt(np.mean(b2)))
    # bootstrap over trials (the carriages of one trial are correlated): 95 % interval of the ratio and of
    # PnP / solver
    es_t, b2_t, ep_t = (np.asarray(a).reshape(trials, n).sum(1) for a in (e_s, b2, e_p))
    rng = np.random.default_rng(1)
    bi = rng.integers(0, trials, (2000, trials))
    ratio_bs = np.sqrt(es_t[bi].sum(1) / b2_t[bi].sum(1))
    pnp_bs = np.sqrt(ep_t[bi].sum(1) / es_t[bi].sum(1))
    cov_n = np.sum(cover, axis=0)
    cov_ci = [wilson(int(k), len(cover)) for k in cov_n]
    row = {"n_cars": n, "sigma_px": sigma, "focal": "unknown" if est_focal else "known", "trials": trials,
           "solver_rms_m": rms, "solver_rot_rms_deg": float(np.sqrt(np.mean(r_s))),
           "pnp_rms_m": float(np.sqrt(np.mean(e_p))), "pnp_rot_rms_deg": float(np.sqrt(np.mean(r_p))),
           "crb_rms_m": crb_rms, "ratio_to_crb": rms / crb_rms, "pnp_over_solver": float(np.sqrt(np.mean(e_p))) / rms,
           "truth_start_rms_m": float(np.sqrt(np.mean(e_ml))),
           "truth_start_ratio_to_crb": float(np.sqrt(np.mean(e_ml))) / crb_rms,
           "trials_worse_than_truth_start": int(worse),
           "mean_depth_error_m": float(np.mean(depth)),
           "mean_depth_error_se_m": float(np.std(np.asarray(depth).reshape(trials, n).mean(1), ddof=1) / np.sqrt(trials)),
           "ratio_ci95": np.percentile(ratio_bs, [2.5, 97.5]).tolist(),
           "pnp_over_solver_ci95": np.percentile(pnp_bs, [2.5, 97.5]).tolist(),
           "coverage95_enu": np.mean(cover, axis=0).tolist(), "coverage95_enu_ci95": cov_ci,
           "not_converged": int(bad), "links_at_slack": int(at_slack),
           "weighting": weighting, "points": points if np.ndim(points) == 0 else list(points),
           "mean_time_s": float(np.mean(times))}
    if b2w:
        row["crb_weighted_rms_m"] = float(np.sqrt(np.mean(b2w)))
    row["bias_correction"] = bool(bias_correction)
    if bias_correction:
        # the same trials at the (truth-started) minimum, uncorrected: paired with the corrected figures
        em_t = np.asarray(e_min).reshape(trials, n).sum(1)
        eml_t = np.asarray(e_ml).reshape(trials, n).sum(1)
        row["uncorrected_min_rms_m"] = float(np.sqrt(np.mean(e_min)))
        row["uncorrected_min_ratio_to_crb"] = float(np.sqrt(np.mean(e_min))) / crb_rms
        r_bs = np.sqrt(em_t[bi].sum(1) / b2_t[bi].sum(1))
        row["uncorrected_min_ratio_ci95"] = np.percentile(r_bs, [2.5, 97.5]).tolist()
        dd = eml_t - em_t  # corrected minus uncorrected summed squared error per trial (truth start)
        row["paired_sq_err_diff_m2"] = float(dd.mean())
        row["paired_sq_err_diff_se_m2"] = float(dd.std(ddof=1) / np.sqrt(trials))
        row["uncorrected_coverage95_enu"] = np.mean(cover_min, axis=0).tolist()
        row["uncorrected_mean_depth_error_m"] = float(np.mean(depth_min))
        row["correction_max_shift_m_median"] = float(np.nanmedian(shift))
        row["correction_max_shift_m_max"] = float(np.nanmax(shift))
        row["correction_carriages_skipped"] = int(np.sum(skipped))
        row["correction_trials_with_a_skip"] = int(np.sum(np.asarray(skipped) > 0))
        row["correction_max_bias_over_sd_max"] = float(np.max(box)) if box else 0.0
    if est_focal:
        row["focal_rms_px"] = float(np.sqrt(np.mean(ef2)))
        row["focal_crb_px"] = float(np.sqrt(np.mean(fb2)))
        row["focal_max_abs_err_px"] = float(np.sqrt(np.max(ef2)))
    return row


def wilson(k, n, z=1.959963984540054):
    """Wilson 95 % interval of a binomial proportion k / n."""
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return [float(c - h), float(c + h)]


def timing(ns, repeats, max_distance_m=None, bias_correction=False):
    """Time of all four steps per consist size; also the median centre error against the truth and the CRB,
    so that a fast wrong answer shows. ``max_distance_m``: the camera stands at most that far and turns (a
    panorama of several photos) instead of one photo from 1.1 train lengths away."""
    out = []
    for n in ns:
        sim = simulate_consist(n, seed=7, pixel_sigma_px=1.0, max_distance_m=max_distance_m)
        opts = SolveOptions(pixel_sigma_px=1.0, bias_correction=bias_correction)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=sim.terrain)  # warm caches
            ts, cpu, steps = [], [], None
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=sim.terrain)
                ts.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                steps = {s.name: round(s.time_s, 4) for s in res.steps}
        errs = [float(np.linalg.norm(c.body_centre_m - body_centre(sim.carriages[i].carriage_type, M[:3, :3],
                                                                        M[:3, 3])))
                for i, (c, M) in enumerate(zip(res.carriages, sim.truth))]
        bound = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, False)
        b = np.sqrt([np.trace(c) for c in bound["body_centre_cov"]])
        cam = sim.views[0].camera_centre
        dist = [float(np.linalg.norm(M[:3, 3] - cam)) for M in sim.truth]
        out.append({"n_cars": n, "median_s": float(np.median(ts)), "min_s": float(np.min(ts)),
                    "median_cpu_s": float(np.median(cpu)), "status": res.status,
                    "steps_s": steps, "iterations": res.iterations, "n_views": len(sim.views),
                    "distance_m": [min(dist), max(dist)], "median_err_m": float(np.median(errs)),
                    "max_err_m": float(np.max(errs)), "median_crb_m": float(np.median(b))})
    return out


def print_timing(tim, title):
    print(f"\n{title}")
    for i, t in enumerate(tim):
        grow = ""
        if i > 0:
            p = np.log(t["median_s"] / tim[i - 1]["median_s"]) / np.log(t["n_cars"] / tim[i - 1]["n_cars"])
            grow = f"  (x{t['median_s'] / tim[i - 1]['median_s']:.2f} vs {tim[i - 1]['n_cars']} cars: ~N^{p:.2f})"
        print(f"  {t['n_cars']:>4} cars, {t['n_views']} photo(s) at {t['distance_m'][0]:.0f}-{t['distance_m'][1]:.0f} m: "
              f"{t['median_s']:.3f} s{grow} (CPU {t['median_cpu_s']:.3f} s)  ({t['status']}, {t['iterations']} "
              f"evaluations; centre error median "
              f"{t['median_err_m']:.2f} m, max {t['max_err_m']:.2f} m; CRB median {t['median_crb_m']:.2f} m; "
              f"steps {t['steps_s']})", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a ~30 s run (fewer trials)")
    ap.add_argument("--trials", type=int, default=None,
                    help="trials per configuration (default: 150; --quick: 6)")
    ap.add_argument("--out", default="bench_out/solver.json")
    ap.add_argument("--timing-only", action="store_true", help="only the timing part (no Monte Carlo)")
    ap.add_argument("--cells", default=None,
                    help="only these cells, comma-separated CARS:PX:FOCAL, e.g. 12:2:known,12:2:unknown")
    ap.add_argument("--weighting", default="per_carriage", choices=("per_carriage", "per_point"),
                    help="the solver's residual weighting (SolveOptions.weighting; identical when every carriage "
                         "shows the same number of points)")
    ap.add_argument("--points", default="7",
                    help="visible points per carriage, one count or a comma-separated cycle (e.g. 4,10,6,10,5,8: "
                         "unequal counts, where the weightings differ)")
    ap.add_argument("--split", type=int, default=0, metavar="DRAWS",
                    help="also split each cell's error into bias and spread: DRAWS new draws of offsets and noise "
                         "per geometry, minimised from the truth (slow: trials x DRAWS fits)")
    ap.add_argument("--no-timing", action="store_true", help="skip the timing part")
    ap.add_argument("--timing-sizes", default=None,
                    help="consist sizes of the timing part, comma-separated (default 3,5,10,20,50,100)")
    ap.add_argument("--bias-correction", action=argparse.BooleanOptionalAction,
                    default=SolveOptions().bias_correction,
                    help="SolveOptions.bias_correction (default: its default, on): the solver (and the truth-started "
                         "fit) report the second-order bias-corrected poses (not applied with an unknown focal); "
                         "each cell also prints the same trials at the uncorrected minimum (paired), and the "
                         "timing runs with it; --no-bias-correction turns it off")
    args = ap.parse_args(argv)
    points = [int(p) for p in args.points.split(",")]
    points = points[0] if len(points) == 1 else tuple(points)
    cells = None
    if args.cells:
        cells = set()
        for c in args.cells.split(","):
            a, b, fo = c.split(":")
            cells.add((int(a), float(b), fo == "unknown"))
    def n_trials(n):
        if args.trials:
            return args.trials
        return 6 if args.quick else 150

    t_all = time.perf_counter()
    rows = []
    print(f"{'cars':>4} {'px':>4} {'focal':>7} {'N':>4} | {'solver m':>9} {'PnP m':>9} {'CRB m':>9} {'ratio [95% CI]':>19} "
          f"{'PnP/sol [95% CI]':>19} | {'sol deg':>7} {'PnP deg':>7} | {'coverage95 E/N/U':>18} | {'t/solve':>7}")
    for est in (() if args.timing_only else (False, True)):
        for n in (3, 6, 12):
            for sigma in (0.5, 1.0, 2.0):
                if args.quick and sigma != 1.0 and n != 6:
                    continue
                if cells is not None and (n, sigma, est) not in cells:
                    continue
                seed0 = 10_000 * n + int(100 * sigma) + (5000 if est else 0)
                r = run_config(n, sigma, est, n_trials(n), seed0, args.weighting, points, args.bias_correction)
                rows.append(r)
                cv = "/".join(f"{c * 100:.0f}" for c in r["coverage95_enu"])
                lo, hi = r["ratio_ci95"]
                plo, phi = r["pnp_over_solver_ci95"]
                print(f"{n:>4} {sigma:>4} {r['focal']:>7} {r['trials']:>4} | {r['solver_rms_m']:9.4f} {r['pnp_rms_m']:9.4f} "
                      f"{r['crb_rms_m']:9.4f} {r['ratio_to_crb']:6.3f} [{lo:.2f},{hi:.2f}] "
                      f"{r['pnp_over_solver']:6.2f} [{plo:.2f},{phi:.2f}] | "
                      f"{r['solver_rot_rms_deg']:7.3f} {r['pnp_rot_rms_deg']:7.3f} | {cv:>18} | "
                      f"{r['mean_time_s']:7.3f}" + (f"  focal rms {r['focal_rms_px']:.1f} px (CRB "
                                                    f"{r['focal_crb_px']:.1f}, max |err| "
                                                    f"{r['focal_max_abs_err_px']:.0f})" if est else ""), flush=True)
                print("      coverage 95% CI (Wilson, per axis E/N/U): " + "  ".join(
                    f"[{a * 100:.1f},{b * 100:.1f}]" for a, b in r["coverage95_enu_ci95"])
                      + f"; started at the truth: ratio {r['truth_start_ratio_to_crb']:.3f}, solver worse in "
                        f"{r['trials_worse_than_truth_start']}/{r['trials']}; mean depth error "
                        f"{r['mean_depth_error_m']:+.3f} m (se {r['mean_depth_error_se_m']:.3f}); couplers at the "
                        f"slack {r['links_at_slack']}" + (f"; crb() (per-carriage weights) {r['crb_weighted_rms_m']:.4f} m"
                                                          if "crb_weighted_rms_m" in r else ""), flush=True)
                if args.bias_correction:
                    a_, b_ = r["uncorrected_min_ratio_ci95"]
                    print(f"      bias correction: uncorrected minimum (truth start) ratio "
                          f"{r['uncorrected_min_ratio_to_crb']:.3f} [{a_:.2f},{b_:.2f}] -> corrected (truth start) "
                          f"{r['truth_start_ratio_to_crb']:.3f}; paired summed sq. error corrected - uncorrected "
                          f"{r['paired_sq_err_diff_m2']:+.4f} m^2 (se {r['paired_sq_err_diff_se_m2']:.4f}); coverage "
                          f"uncorrected " + "/".join(f"{c * 100:.1f}" for c in r["uncorrected_coverage95_enu"])
                          + f"; mean depth error uncorrected {r['uncorrected_mean_depth_error_m']:+.3f} m; largest "
                            f"shift per solve median {r['correction_max_shift_m_median']:.3f} m, max "
                            f"{r['correction_max_shift_m_max']:.3f} m; carriages left uncorrected (bias >= "
                            f"{SolveOptions().bias_max_over_sd:g} sd) "
                            f"{r['correction_carriages_skipped']} in {r['correction_trials_with_a_skip']} trials, "
                            f"largest bias/sd {r['correction_max_bias_over_sd_max']:.2f}", flush=True)
                if args.split:
                    sp = split_bias(n, sigma, est, n_trials(n), seed0, args.split, args.weighting, points,
                                    args.bias_correction)
                    r["split"] = sp
                    print(f"      bias/spread ({sp['draws']} draws per geometry, from the truth): MSE/CRB "
                          f"{sp['mse_over_crb']:.3f} = bias^2 {sp['bias2_over_crb']:.3f} + covariance "
                          f"{sp['cov_over_crb']:.3f}; ratio without the bias {sp['ratio_if_unbiased']:.3f}; mean "
                          f"depth error {sp['mean_depth_error_m']:+.3f} m", flush=True)
    allcov = np.concatenate([[c for c in r["coverage95_enu"]] for r in rows]) if rows else np.array([np.nan])
    ns = (3, 10, 30) if args.quick else (3, 5, 10, 20, 50, 100)
    if args.timing_sizes:
        ns = tuple(int(v) for v in args.timing_sizes.split(","))
    reps = 2 if args.quick else 5
    tim, tim_far = [], []
    if not args.no_timing:
        tim = timing(ns, reps, max_distance_m=400.0, bias_correction=args.bias_correction)
        print_timing(tim, "time (all four steps, plane terrain + contact term, covariance included; median of "
                     "repeats);\ncamera at most 400 m away, turning (a panorama of photos) when the consist does not "
                     "fit one photo:")
        tim_far = timing(ns, reps, bias_correction=args.bias_correction)
        print_timing(tim_far, "the same with one photo from 1.1 train lengths away (a 100-car train is ~2.6 km long: "
                              "its cars are ~27 px long in a 4000 px photo):")
    summary = {
        "worst_ratio_known_focal": max((r["ratio_to_crb"] for r in rows if r["focal"] == "known"), default=None),
        "worst_ratio_unknown_focal": max((r["ratio_to_crb"] for r in rows if r["focal"] == "unknown"),
                                         default=None),
        "pnp_over_solver_6cars_1px_known": next((r["pnp_over_solver"] for r in rows if r["n_cars"] == 6
                                                 and r["sigma_px"] == 1.0 and r["focal"] == "known"), None),
        "coverage_min": float(allcov.min()), "coverage_max": float(allcov.max()),
        "time_10_cars_s": next((t["median_s"] for t in tim if t["n_cars"] == 10), None),
        "time_100_cars_s": next((t["median_s"] for t in tim if t["n_cars"] == 100), None),
        "status_100_cars": next((t["status"] for t in tim if t["n_cars"] == 100), None),
        "time_100_cars_one_far_photo_s": next((t["median_s"] for t in tim_far if t["n_cars"] == 100), None),
        "status_100_cars_one_far_photo": next((t["status"] for t in tim_far if t["n_cars"] == 100), None),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "bias_correction": bool(args.bias_correction),
        "total_time_s": time.perf_counter() - t_all,
    }
    print("\nsummary:", json.dumps(summary, indent=1))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"configs": rows, "timing": tim, "timing_one_far_photo": tim_far,
                                "summary": summary}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
