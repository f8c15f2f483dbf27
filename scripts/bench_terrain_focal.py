#!/usr/bin/env python
"""Calibration of hand-pick solves with the terrain contact when the DEM has the error the solve states (issue 21).

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python scripts/bench_terrain_focal.py \\
        --route known,focal --dem-sigma 0.10 --n 300 --seed0 270000

``scripts/bench_calibration.py --terrain`` gives the solve the simulated plane itself: a DEM exact to the
carriages' own spread about it (the couplers' play, 0-3 cm, a random walk along the consist), whatever accuracy
the solve states. Here the solve gets the ground the carriages stand on (``--ground carriages``, the default: the
plane raised under each carriage by its wheels' height over it at the truth; ``--ground plane``: the plane, with
that walk) plus one height error per carriage drawn with ``--dem-sigma``
(``workbench.solve.simulate.dem_with_error``: independent per carriage, the contact term's model of a DEM's
error) and states ``terrain_sigma_m = --dem-sigma``: what a solve of a real incident does with a DEM of stated
accuracy (the solve stage states ``terrain.dem_vertical_accuracy_m``). ``--slack`` sets the couplings' play
(default 0.03 m, as ``bench_calibration``). The problems, the noise and the figures are ``bench_calibration``'s
routes ``known`` / ``focal`` (the same cases, seeds, records and table); the DEM's errors are drawn from the
problem's seed + 7 000 000. The table's line counts the carriages on their wheels' row (step 4's facts) and among
them those whose rotation from their own pixels could not confirm them level against the stated accuracy, kept
on it at step 4's solution; the rest have the lowest point's row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from bench_calibration import axis_stats, hand_consists, print_table  # noqa: E402
from workbench.solve import SolveOptions, solve_consist  # noqa: E402
from workbench.solve.simulate import dem_with_error  # noqa: E402

DEM_SEED_OFFSET = 7_000_000  # the DEM's errors from another stream than the problem's


def route_dem(n: int, seed0: int, estimate_focal: bool, dem_sigma_m: float, log=print,
              slack_m: float = 0.03, ground: str = "carriages") -> tuple[list[dict], dict]:
    """Solve fresh problems (``bench_calibration.HAND_CASES`` cycled, :func:`bench_calibration.hand_consists`) on a DEM with error ``dem_sigma_m`` per
    carriage, stated as such, until ``n`` carriages have intervals; ``slack_m``: the couplings' play
    (``simulate_consist``'s; the carriages' spread about the plane grows with it along the consist, a random walk
    the contact's per-carriage model does not describe, unless the DEM is of the carriages' ground: ``ground``,
    as :func:`~workbench.solve.simulate.dem_with_error`). Returns (records, info)."""
    info = {"seeds": [], "skipped_seeds": [], "not_converged": 0, "left_out": 0, "focal_z": [],
                      "dem_sigma_m": dem_sigma_m, "slack_m": slack_m, "ground": ground,
                      "contact_rows": 0, "wheel_rows": 0, "level_rows": 0}

    def solve(sim, seed: int, sigma: float):
        dem = dem_with_error(sim, dem_sigma_m, seed + DEM_SEED_OFFSET, ground)
        res = solve_consist(sim.carriages, sim.links, sim.views,
                            SolveOptions(pixel_sigma_px=sigma, estimate_focal=estimate_focal,
                                         compute_covariance=True, terrain_sigma_m=dem_sigma_m), terrain=dem)
        facts = next((st.facts for st in res.steps if st.name == "4_all"), {})
        info["contact_rows"] += len(res.carriages)
        info["wheel_rows"] += len(facts.get("contact_on_wheels", []))
        info["level_rows"] += len(facts.get("contact_level", {}))
        return res

    return hand_consists(n, seed0, estimate_focal, solve, info, log, slack_m=slack_m), info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="known,focal", help="comma-separated: known, focal")
    ap.add_argument("--n", type=int, default=300, help="carriages per route (at least)")
    ap.add_argument("--seed0", type=int, default=270000, help="first seed (fresh seeds)")
    ap.add_argument("--dem-sigma", type=float, default=0.10,
                    help="the DEM's height error per carriage (m), drawn and stated (default SolveOptions' 0.10)")
    ap.add_argument("--slack", type=float, default=0.03,
                    help="the couplings' play (m; default simulate_consist's and bench_calibration's 0.03)")
    ap.add_argument("--ground", choices=("carriages", "plane"), default="carriages",
                    help="the DEM's truth: the ground the carriages stand on (default) or the plane (their walk "
                         "about it, the couplers' play, counted as DEM error)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    routes = [r.strip() for r in a.route.split(",") if r.strip()]
    for r in routes:
        if r not in ("known", "focal"):
            ap.error(f"unknown route {r!r}; routes: known, focal")
    if not (a.dem_sigma > 0):
        ap.error(f"--dem-sigma {a.dem_sigma}: must be positive (metres)")
    if not (a.slack > 0):
        ap.error(f"--slack {a.slack}: must be positive (metres)")
    out = a.out or REPO / "bench_out" / f"terrain_dem_{'_'.join(routes)}_{a.dem_sigma:g}_{a.ground}.json"
    result = {"command": " ".join(sys.argv), "seed0": a.seed0, "dem_sigma_m": a.dem_sigma, "slack_m": a.slack,
              "ground": a.ground,
              "routes": {}}
    for r in routes:
        print(f"route {r} on a DEM with error {a.dem_sigma:g} m per carriage: solving until {a.n} carriages ...",
              flush=True)
        recs, info = route_dem(a.n, a.seed0, r == "focal", a.dem_sigma, log=lambda m: print(m, flush=True),
                               slack_m=a.slack, ground=a.ground)
        st = axis_stats(recs)
        extra = (f", {info['time_s']:.0f} s; left out {info['left_out']}; contact rows of {info['contact_rows']}: "
                 f"wheels {info['wheel_rows']} (unconfirmed at step 3, kept at step 4: {info['level_rows']})")
        if "focal_rms_z" in info:
            extra += (f"; focal: RMS z {info['focal_rms_z']:.3f}, mean z {info['focal_mean_z']:+.2f}, coverage "
                      f"{100 * info['focal_coverage']:.1f} %")
        print_table(r, st, extra)
        result["routes"][r] = {"stats": st, "info": info, "records": recs}
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(result, indent=1))
        tmp.replace(out)
    print(f"\nsaved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
