#!/usr/bin/env python
"""The automatic points' error model, taken apart (issue 21): the kept auto-route incidents solved again with
variants of the covariance's pieces, scored against their truth.

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python scripts/bench_auto_error_model.py \
        --work bench_out/calibration_auto_survey --out bench_out/auto_error_model.json \
        '{}' '{"prior_dof": 0}' '{"face_sigma": 0.0}' '{"contact": 0}' '{"count_predictions": 1}' \
        '{"prior_dof": 0, "face_sigma": 0.15, "modes": [1, 1, 0, 0, 0, 0]}'

An experiment, not a product path: each variant (a JSON object) replaces one piece of the solve's covariance by
patching the solve's functions in this process; ``{}`` is the code as shipped. The incidents are those
``scripts/bench_calibration.py --route auto --survey-noise --work DIR`` generated and kept (their stitch, georef
and correspond outputs as they are); only the solve stage runs (about 1 s an incident). Keys:

``prior_dof``
    the degrees of freedom the configured pixel sigma (``solver.pixel_sigma_px``, a hand pick's 1 px) counts
    for when pooled with the residuals' (0: the residuals' alone);
``face_sigma``
    the face misfit (px) of the covariance (``solver.face_sigma_px``);
``modes``
    weights of the face misfit's modes, in order: shift u, shift v, the four affine terms, and two projective
    terms (a homography's remaining two: ``-(x, y) q`` for ``q`` = x and y, the points' centred coordinates over
    their RMS spread); the shipped model is ``[1, 1, 1, 1, 1, 1, 0, 0]``;
``per_view``
    1: each view's misfit independent (the shipped model shares a face's across its views);
``contact``
    0: the solve without the terrain contact (``SolveOptions.use_terrain_contact``);
``alignments``
    0: the points' face alignments (``alignment`` in correspondences.json, written by the correspond stage since
    issue 21) left out of the covariance (``uncertainty.covariance_model(use_alignments=False)``): the pooled pixel
    sigma and the fixed face misfit, the model before them;
``views_shared``
    1 (the default): a face's alignment error counted as shared by the photos it is aligned in
    (``alignment_covariance.views_per_face``), 0: each photo's independent;
``count_pose``
    0: the pose predictions left out of the covariance (``uncertainty.covariance_model(count_pose=False)``, the model
    before ``workbench.solve.pose_covariance``); 1 (the default): counted with their face alignment's error;
``photo_share``
    rho in [0, 1]: a face's error shared by the ``n`` photos it is aligned in with correlation rho, each photo's
    block counting ``1 + (n - 1) rho`` times its stated variance (the variance of the mean of ``n`` equicorrelated
    errors, the design effect; rho = 1 is the shipped ``views_per_face``, rho = 0 ``views_shared`` 0);
``release_all``
    1: step 4b's fit with every car's predictions released (their sigmas x ``solver.prediction_release``) kept for
    every car, so that the estimator is the one the covariance describes (measured points only; the shipped solve
    keeps the predictions at full weight on the cars where they agree with the measured points);
``count_predictions``
    1: the covariance counts the predicted points (projected from correspond's face poses, carried between
    photos) as measured, which the shipped model does not (they are functions of the measured ones).

Per variant it prints, per axis (east, north, up, heading, pitch, roll), the coverage of the 95 % intervals,
RMS z and robust z (median |error / sigma| / 0.6745) over every placed carriage with an interval, again without
``--exclude`` (default the gross failure of seed 230233, docs/calibration.md), and the fit's own intervals
(the truth moved by the camera's actual error), and the incidents with a carriage beyond 6 sigma; then the first
variant's intervals scaled by each of ``--scales``. Saves every record as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import bench_calibration as bc  # noqa: E402
import workbench.solve.stage as solve_stage  # noqa: E402
from workbench.project import Project  # noqa: E402
from workbench.solve import solver as solve_solver  # noqa: E402
from workbench.solve import uncertainty  # noqa: E402

AXES = ("east", "north", "up", "heading", "pitch", "roll")
SHIPPED = {"covariance_model": uncertainty.covariance_model, "shared_misfit": uncertainty._shared_misfit,
           "options": solve_stage.SolveOptions, "views_per_face": uncertainty.views_per_face,
           "step_predictions": solve_solver.step_predictions}


def misfit_modes(d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(2 n, 8) displacement modes of ``n`` points with centred pixels ``d`` (n, 2) and RMS spreads ``s`` (2,):
    shift u, shift v, u by x, u by y, v by x, v by y, then the homography's two projective terms, each of unit RMS
    size (the affine and projective ones only with 3 and 4 points or more)."""
    n = len(d)
    B = np.zeros((2 * n, 8))
    B[0::2, 0], B[1::2, 1] = 1.0, 1.0
    if n >= 3:
        xy = [d[:, j] / s[j] if s[j] > 1e-6 else np.zeros(n) for j in range(2)]
        for j, q in enumerate(xy):
            B[0::2, 2 + j], B[1::2, 4 + j] = q, q
        if n >= 4:
            for j, q in enumerate(xy):
                du, dv = -q * xy[0], -q * xy[1]
                norm = float(np.sqrt(np.mean(du**2 + dv**2))) or 1.0
                B[0::2, 6 + j], B[1::2, 6 + j] = du / norm, dv / norm
    return B


def patch(variant: dict) -> None:
    """Put the variant's pieces in place of the shipped ones (all restored first)."""
    uncertainty.covariance_model = SHIPPED["covariance_model"]
    uncertainty._shared_misfit = SHIPPED["shared_misfit"]
    solve_stage.SolveOptions = SHIPPED["options"]
    uncertainty.views_per_face = SHIPPED["views_per_face"]
    solve_solver.step_predictions = SHIPPED["step_predictions"]
    shipped_model = SHIPPED["covariance_model"]

    def covariance_model(*a, **k):
        if "prior_dof" in variant:
            a = list(a)
            if len(a) > 11:
                a[11] = variant["prior_dof"]
            else:
                k["prior_dof"] = variant["prior_dof"]
        if "face_sigma" in variant:
            k["face_sigma"] = variant["face_sigma"]
        if "alignments" in variant:
            k["use_alignments"] = bool(variant["alignments"])
        if "views_shared" in variant:
            k["views_shared"] = bool(variant["views_shared"])
        if "count_pose" in variant:
            k["count_pose"] = bool(variant["count_pose"])
        if variant.get("count_predictions"):
            prob = a[0]
            saved = getattr(prob, "measured", None)
            try:
                prob.measured = None
                return shipped_model(*a, **k)
            finally:
                prob.measured = saved
        return shipped_model(*a, **k)

    uncertainty.covariance_model = covariance_model
    if "photo_share" in variant:  # each photo's block counts 1 + (n - 1) rho times its variance (rho = 1: n)
        rho = float(variant["photo_share"])

        def views_per_face(*a, **k):
            n = SHIPPED["views_per_face"](*a, **k)
            return np.where(n > 0, 1.0 + (n - 1.0) * rho, 0.0)

        uncertainty.views_per_face = views_per_face
    if "modes" in variant or variant.get("per_view"):
        weights = np.zeros(8)
        given = variant.get("modes", [1, 1, 1, 1, 1, 1])
        weights[:len(given)] = given

        def shared_misfit(J, groups, views, uv, w, scale=None):
            P = J.shape[1]
            out = np.zeros((P, P))
            for i, g in enumerate(np.unique(groups[groups >= 0])):
                f = 1.0 if scale is None else float(scale[i])
                A = np.zeros((P, 8))
                for v in np.unique(views[groups == g]):
                    idx = np.nonzero((groups == g) & (views == v))[0]
                    d = uv[idx] - uv[idx].mean(0)
                    B = misfit_modes(d, np.sqrt(np.mean(d**2, axis=0))) * weights[None, :]
                    rows = np.stack([2 * idx, 2 * idx + 1], axis=1).reshape(-1)
                    Av = J[rows].T @ (B * np.repeat(w[idx], 2)[:, None])
                    if variant.get("per_view"):
                        out += f * (Av @ Av.T)
                    else:
                        A += Av
                out += f * (A @ A.T)
            return out

        uncertainty._shared_misfit = shared_misfit
    if variant.get("release_all"):  # step 4b's fit with every car's predictions released, kept for all

        def step_predictions(s, fit):
            released = s.prob.with_predictions_scaled(s.options.prediction_release)
            if not (~released.measured).any() or s.options.prediction_release <= 1.0:
                return SHIPPED["step_predictions"](s, fit)
            rel = s.chained(released, s.contact).solve(fit.poses)
            s.nfev += rel.nfev
            return rel, released

        solve_solver.step_predictions = step_predictions
    if "contact" in variant:
        shipped_options = SHIPPED["options"]

        def options(*a, **k):
            return shipped_options(*a, **{**k, "use_terrain_contact": bool(variant["contact"])})

        solve_stage.SolveOptions = options


def solve_all(work: Path, log=print) -> tuple[list[dict], list[dict]]:
    """The solve stage again on every kept incident under ``work``; (records, fit records)."""
    recs, fit = [], []
    for root in sorted(work.glob("inc_*")):
        if not (root / "out/correspond/correspondences.json").is_file():
            continue
        seed = int(root.name.split("_")[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                solve_stage.run_solve(Project(root), lambda *a, **k: None)
            except Exception as e:  # noqa: BLE001 - a failed incident is named, not fatal
                log(f"  seed {seed}: failed ({type(e).__name__}: {str(e)[:120]})")
                continue
        sol = json.loads((root / "out/solve/solution.json").read_text())
        truth = json.loads((root / "truth/ground_truth.json").read_text())
        cams = json.loads((root / "out/georef/cameras.json").read_text())
        cam = bc.camera_error(cams, truth)
        r, f, _, _ = bc.incident_records(f"seed{seed}", sol, truth, None if cam is None else cam[0])
        recs += r
        fit += f
    return recs, fit


def table_row(recs: list[dict]) -> dict:
    e = np.array([r["error"] for r in recs])
    s = np.array([r["sigma"] for r in recs])
    c = np.array([r["ci95"] for r in recs])
    z = e / s
    return {"n": len(recs), "coverage_pct": ((np.abs(e) <= c).mean(0) * 100).tolist(),
            "rms_z": np.sqrt((z**2).mean(0)).tolist(), "robust_z": (np.median(np.abs(z), 0) / 0.6745).tolist(),
            "beyond_6_sigma": sorted({r["problem"] for r, zz in zip(recs, z) if np.max(np.abs(zz)) > 6})}


def carriage_kinds(work: Path) -> dict[tuple[str, str], dict]:
    """Per (problem, car number) of the kept incidents: its number of ECC-guided homography points (no loading)
    and the most photos one of its faces is aligned in (from correspondences.json)."""
    out: dict[tuple[str, str], dict] = {}
    for root in sorted(work.glob("inc_*")):
        path = root / "out/correspond/correspondences.json"
        if not path.is_file():
            continue
        faces: dict[tuple[str, str], set] = {}
        for o in json.loads(path.read_text())["observations"]:
            if o.get("method") != "homography":
                continue
            k = (f"seed{root.name.split('_')[1]}", o["carriage"])
            c = out.setdefault(k, {"ecc": 0, "photos": 0})
            c["ecc"] += "alignment" not in o
            faces.setdefault((k[1], o.get("face")), set()).add(o["view"])
            c["photos"] = max(c["photos"], len(faces[(k[1], o.get("face"))]))
    return out


SPLITS = {"no ECC-guided point": lambda c: c["ecc"] == 0, "some ECC-guided points": lambda c: c["ecc"] > 0,
          "a face in <= 2 photos": lambda c: c["photos"] <= 2, "a face in 3+ photos": lambda c: c["photos"] >= 3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("variants", nargs="+", help="JSON objects (module doc); '{}': as shipped")
    ap.add_argument("--work", type=Path, default=ROOT / "bench_out" / "calibration_auto_survey")
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "auto_error_model.json")
    ap.add_argument("--exclude", nargs="*", default=["seed230233"], help="problems left out of the second rows")
    ap.add_argument("--scales", type=float, nargs="*", default=[0.85, 0.75, 0.7, 0.65],
                    help="the first variant's intervals scaled by each factor (a diagnosis: is the misfit one of "
                         "scale, the same on every axis, or of shape?)")
    ap.add_argument("--ci", action="store_true", help="also print scripts/bench_calibration.py's table (coverage, "
                    "RMS z, width / spread, robust z, each with its cluster-bootstrap 95 %% interval) per variant")
    ap.add_argument("--split", action="store_true", help="also print the rows (without the excluded) split by the "
                    "carriages' kind: with or without ECC-guided points, a face aligned in at most 2 or in 3+ photos")
    a = ap.parse_args()
    kinds = carriage_kinds(a.work) if a.split else {}
    results = []
    for text in a.variants:
        variant = json.loads(text)
        patch(variant)
        t0 = time.perf_counter()
        recs, fit = solve_all(a.work)
        kept = [r for r in recs if r["problem"] not in a.exclude]
        rows = {"all": table_row(recs), "without_excluded": table_row(kept),
                "fit_without_excluded": table_row([r for r in fit if r["problem"] not in a.exclude])}
        print(f"{json.dumps(variant)} ({time.perf_counter() - t0:.0f} s)")
        for name, row in rows.items():
            print(f"  {name:22s} n={row['n']:3d} coverage " + " ".join(f"{x:5.1f}" for x in row["coverage_pct"])
                  + " | RMS z " + " ".join(f"{x:5.2f}" for x in row["rms_z"])
                  + " | robust z " + " ".join(f"{x:5.2f}" for x in row["robust_z"])
                  + f" | beyond 6 sigma: {', '.join(row['beyond_6_sigma']) or '-'}")
        for label, sel in (SPLITS.items() if a.split else ()):
            for kind, rr in (("", kept), ("fit ", rows_fit := [r for r in fit if r["problem"] not in a.exclude])):
                sub = [r for r in rr if (r["problem"], r["number"]) in kinds
                       and sel(kinds[(r["problem"], r["number"])])]
                if sub:
                    row = table_row(sub)
                    print(f"    {kind}{label:24s} n={row['n']:3d} RMS z " + " ".join(f"{x:5.2f}" for x in row["rms_z"])
                          + " | robust z " + " ".join(f"{x:5.2f}" for x in row["robust_z"]))
            del rows_fit
        if a.ci:  # the calibration benchmark's table: every figure with its cluster-bootstrap 95 % interval
            for name, rr in (("all", recs), ("without the excluded", kept)):
                st = bc.axis_stats(rr)
                bc.print_table(f"auto {json.dumps(variant)}, {name}", st)
                rows["ci_" + name.replace(" ", "_")] = st
        results.append({"variant": variant, "rows": rows, "records": recs, "fit_records": fit})
    kept = [r for r in results[0]["records"] if r["problem"] not in a.exclude]
    for k in a.scales:
        row = table_row([{**r, "sigma": [k * x for x in r["sigma"]], "ci95": [k * x for x in r["ci95"]]} for r in kept])
        print(f"{json.dumps(results[0]['variant'])}, intervals x {k:g}, without the excluded: coverage "
              + " ".join(f"{x:5.1f}" for x in row["coverage_pct"]) + " | RMS z "
              + " ".join(f"{x:5.2f}" for x in row["rms_z"]))
    patch({})
    print("axes: " + ", ".join(AXES))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"work": str(a.work), "exclude": a.exclude, "results": results}))
    print(f"saved {a.out}")


if __name__ == "__main__":
    main()
