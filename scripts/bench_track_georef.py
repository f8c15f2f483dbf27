"""Track picks as a georeferencing feature (issue 17): the panorama camera of a synthetic incident placed from
points picked on the rails, against the truth.

For each incident (default: the two samples' truths, ``projects/spuyten-duyvil`` and ``projects/frankford-junction``:
their photos need not be generated, only ``truth/ground_truth.json`` and the layers) the true track picks are made
once (``synth.control_points.track_picks_document``: the left and right rails, 12 points each per panorama photo
where visible, ray-cast against terrain, buildings and carriages) and so are its landmarks
(``control_points_document``). Each seed then draws: the picks' noise (``--pick-sigma`` px, the setting's 2 px),
a GPS centre (east/north 1-sigma 5 m, up 15 m: a phone's fix, as ``bench_georef_gps.py``), and for the cases
with map points two landmarks at random among those seen, their coordinates moved by 0.5 m (as clicked on a map,
``sigma_m`` 0.5) and their picks by 2 px. The central solver (``georef.central.solve_central``, the pipeline's
panorama route) places the panorama's rig with the railway layer as written (exact: its line sigma 0.02 m).

Cases: ``track_gps`` (track picks and the GPS prior: no landmark), ``track_2pts_gps`` (plus 2 map points),
``gps_2pts`` (the 2 map points and GPS without the track, for comparison), ``track_only`` (no prior at all: the
solver refuses, and why is printed once), ``track_position_1m`` (track picks and a camera position known to 1 m per
axis, as ``camera.position_enu`` states it: drawn at 1 m).

Printed and saved (``--out``, JSON) per case and incident: placed, camera centre error (median, 90 %, max) and its
component along the track, rotation error, the carriages' chainage error from the camera's placement (carriages
moved rigidly with the camera: the solve's own error not included), and coverage of the stated 95 % intervals:
centre (squared Mahalanobis distance <= 7.81), rotation (the same on the rotation vector), chainage
(|error| <= 1.96 sigma).

    nice -n 19 .venv/bin/python scripts/bench_track_georef.py [--seeds 20] [--out bench_out/track_georef.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from workbench.core.io import atomic_write_json  # noqa: E402
from workbench.errors import InputError  # noqa: E402
from workbench.files.control_points import parse_control_points  # noqa: E402
from workbench.georef.central import solve_central  # noqa: E402
from workbench.georef.options import GeorefOptions  # noqa: E402
from workbench.synth.control_points import control_points_document, track_picks_document  # noqa: E402
from workbench.synth.track_georef import chainage_errors, noisy_track_term, panorama_truth, rotation_error  # noqa: E402

CHI2_3_95 = 7.8147
GPS_SIGMA = np.array([5.0, 5.0, 15.0])
MAP_SIGMA_M, MAP_PICK_PX = 0.5, 2.0
CASES = ("track_gps", "track_2pts_gps", "gps_2pts", "track_only", "track_position_1m")
KNOWN_SIGMA = np.array([1.0, 1.0, 1.0])  # camera.position_enu's stated 1-sigma (a camera position known to a metre)


def _two_points(doc: dict, views, rng, pt) -> list:
    names = {v.name for v in views}
    cands = [p for p in doc["points"] if any(k in names for k in p["pixels"])]
    pick = rng.choice(len(cands), 2, replace=False)
    out = []
    for k in pick:
        p = cands[int(k)]
        coords = (np.asarray(p["coords"], float) + rng.normal(0.0, MAP_SIGMA_M, 3)).tolist()
        pix = {n: (np.asarray(uv, float) + rng.normal(0.0, MAP_PICK_PX, 2)).tolist()
               for n, uv in p["pixels"].items() if n in names}
        out.append({"name": p["name"], "coords": coords, "sigma_m": MAP_SIGMA_M, "pixels": pix})
    return parse_control_points({"crs": doc["crs"], "points": out}, pt.frame)


def _run_case(case: str, pt, entries, doc, seed: int, opts: GeorefOptions, pick_sigma: float) -> dict:
    rng = np.random.default_rng(seed)
    track = noisy_track_term(pt, entries, rng, pick_sigma, line_sigma_m=0.02, height_sigma_m=0.02)
    z = rng.normal(0.0, 1.0, 3)
    gps = pt.centre_enu + z * GPS_SIGMA
    cps = _two_points(doc, pt.views, rng, pt)
    if case == "track_position_1m":
        gps, sig = pt.centre_enu + z * KNOWN_SIGMA, KNOWN_SIGMA
    else:
        sig = GPS_SIGMA
    kw = {"track_gps": dict(cps=[], prior=True, track=True), "track_2pts_gps": dict(cps=cps, prior=True, track=True),
          "gps_2pts": dict(cps=cps, prior=True, track=False), "track_only": dict(cps=[], prior=False, track=True),
          "track_position_1m": dict(cps=[], prior=True, track=True)}[case]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_central(pt.views, kw["cps"], prior_centre=gps if kw["prior"] else None,
                                prior_sigma_m=sig if kw["prior"] else None, opts=opts,
                                track=track if kw["track"] else None, where=f"{case} seed {seed}")
        except InputError as exc:
            return {"placed": False, "reason": str(exc)}
    dt = time.perf_counter() - t0
    dc = res.centre_enu - pt.centre_enu
    tangent = track.tangent_at(pt.centre_enu)
    rv, rdeg = rotation_error(res.rig_from_world, pt.rig_from_world)
    C = res.stats.get("covariance_world_rotation_centre")
    out = {"placed": True, "seconds": dt, "centre_error_m": float(np.linalg.norm(dc)),
           "along_track_error_m": float(dc[:2] @ tangent), "rotation_error_deg": rdeg,
           "sigma_centre_m": res.stats.get("sigma_centre_m"), "observability": res.stats.get("track", {}).get(
               "observability")}
    Cw = None if C is None else np.asarray(C, float)
    if Cw is not None:
        out["centre_d2"] = float(dc @ np.linalg.solve(Cw[3:, 3:], dc))
        out["rotation_d2"] = float(rv @ np.linalg.solve(Cw[:3, :3], rv))
    err, sig = chainage_errors(pt, res.rig_from_world, res.centre_enu, Cw)
    out["chainage_error_m"] = err.tolist()
    out["chainage_sigma_m"] = None if sig is None else sig.tolist()
    return out


def _summary(recs: list[dict]) -> dict:
    placed = [r for r in recs if r["placed"]]
    s: dict = {"runs": len(recs), "placed": len(placed)}
    if not placed:
        s["reason"] = recs[0].get("reason") if recs else None
        return s
    ce = np.array([r["centre_error_m"] for r in placed])
    at = np.abs([r["along_track_error_m"] for r in placed])
    ro = np.array([r["rotation_error_deg"] for r in placed])
    ch = np.abs(np.concatenate([r["chainage_error_m"] for r in placed]))
    s.update({"centre_error_m": {"median": float(np.median(ce)), "p90": float(np.percentile(ce, 90)),
                                 "max": float(ce.max())},
              "centre_within_2m": float(np.mean(ce <= 2.0)),
              "along_track_error_m": {"median": float(np.median(at)), "max": float(at.max())},
              "rotation_error_deg": {"median": float(np.median(ro)), "p90": float(np.percentile(ro, 90)),
                                     "max": float(ro.max())},
              "chainage_error_m": {"median": float(np.median(ch)), "p90": float(np.percentile(ch, 90)),
                                   "max": float(ch.max())},
              "chainage_within_1m": float(np.mean(ch <= 1.0)),
              "seconds_median": float(np.median([r["seconds"] for r in placed]))})
    d2c = [r["centre_d2"] for r in placed if "centre_d2" in r]
    d2r = [r["rotation_d2"] for r in placed if "rotation_d2" in r]
    z = [abs(e) / sg for r in placed if r["chainage_sigma_m"] for e, sg in zip(r["chainage_error_m"],
                                                                               r["chainage_sigma_m"])]
    s["coverage_95"] = {"centre": float(np.mean(np.array(d2c) <= CHI2_3_95)) if d2c else None,
                        "rotation": float(np.mean(np.array(d2r) <= CHI2_3_95)) if d2r else None,
                        "chainage": float(np.mean(np.array(z) <= 1.96)) if z else None}
    sc = [max(r["sigma_centre_m"]) for r in placed if r.get("sigma_centre_m")]
    s["stated_sigma_centre_max_m_median"] = float(np.median(sc)) if sc else None
    obs = [r["observability"] for r in placed if r.get("observability")]
    if obs:
        s["track_rank"] = sorted({o.get("rank") for o in obs})
        sa = [o.get("sigma_along_track_from_track_m") for o in obs]
        s["sigma_along_track_from_track_m_median"] = float(np.median([x if x is not None else np.inf for x in sa]))
    return s


def _printed(x):
    """The summary as printed: floats to 4 significant digits (the JSON keeps them whole; a last-bit change of the
    arithmetic must not change what a reader compares)."""
    if isinstance(x, float):
        return float(f"{x:.4g}")
    if isinstance(x, dict):
        return {k: _printed(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_printed(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--incident", action="append", help="synthetic incident folder (repeatable)")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--pick-sigma", type=float, default=2.0, help="track picks' noise, px (drawn and stated)")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--out", default=str(ROOT / "bench_out" / "track_georef.json"))
    a = ap.parse_args(argv)
    logging.getLogger("workbench").setLevel(logging.ERROR)  # the residual warnings of every run: in the JSON
    incidents = a.incident or [str(ROOT / "projects" / "spuyten-duyvil"), str(ROOT / "projects" / "frankford-junction")]
    cases = [c for c in a.cases.split(",") if c]
    opts = replace(GeorefOptions(), sigma_px=MAP_PICK_PX, track_sigma_px=a.pick_sigma)
    result: dict = {"args": vars(a), "incidents": {}}
    for inc in incidents:
        t0 = time.perf_counter()
        pt = panorama_truth(inc)
        entries = track_picks_document(inc, sigma_px=0.0)
        doc = control_points_document(inc, sigma_px=0.0)
        print(f"{Path(inc).name}: {len(pt.views)} panorama photos, {sum(len(e['pixels']) for e in entries)} track "
              f"picks ({len(entries)} rails x photos), {len(doc['points'])} landmarks; set up in "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
        per_case = {}
        for case in cases:
            recs = [_run_case(case, pt, entries, doc, s, opts, a.pick_sigma)
                    for s in range(a.first_seed, a.first_seed + a.seeds)]
            summ = _summary(recs)
            per_case[case] = {"summary": summ, "runs": recs}
            print(f"  {case}: {json.dumps(_printed(summ))}", flush=True)
        result["incidents"][Path(inc).name] = per_case
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, result)
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
