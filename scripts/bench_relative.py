"""Relative incidents (no survey): how often the 95 % intervals hold the truth after the levelling.

Simulated consists (``workbench.solve.simulate``, 3 cars on a level track, one photo from 12 m up) written as
incidents with hand picks and no control points, run through the stages ``inputs``, ``georef`` (route
``relative``), ``correspond`` (finder off) and ``solve``; the truth is moved into the levelled frame (origin at the
camera, z up, y along the ray through the photo's centre pixel) and every carriage's position and heading, pitch,
roll are compared with their 95 % half widths. Known focal (a camera profile) and estimated focal (no EXIF).

    .venv/bin/python scripts/bench_relative.py [--seeds 40] [--out bench_out/relative.json]

Prints per component the coverage (share of |error| <= half width) and the RMS of error / sigma; saves JSON.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_relative import _incident, _sim, _truth_levelled  # noqa: E402  (the test's incident builder)

from workbench.core.frames import hpr_from_rotation  # noqa: E402
from workbench.pipeline import STAGES  # noqa: E402
from workbench.runner import Runner  # noqa: E402

COMPONENTS = ("x", "y", "z", "heading", "pitch", "roll")


def run(seeds: int) -> dict:
    out: dict = {}
    for focal_known in (True, False):
        zs, failed, t0 = [], [], time.perf_counter()
        for seed in range(seeds):
            try:
                sim = _sim(seed)
            except RuntimeError:  # a car outside the photo: not this seed
                continue
            with tempfile.TemporaryDirectory() as tmp:
                project = _incident(Path(tmp) / "inc", sim, focal_known=focal_known)
                try:
                    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
                except Exception as exc:  # noqa: BLE001 - counted and reported
                    failed.append({"seed": seed, "error": str(exc)[:200]})
                    continue
                sol = project.solution("bench")
                L = _truth_levelled(sim)
                for car, M in zip(sol.carriages, sim.truth):
                    if car.world_from_carriage is None:
                        failed.append({"seed": seed, "car": car.number, "error": "no pose"})
                        continue
                    T = L @ M
                    e = np.asarray(car.world_from_carriage)[:3, 3] - T[:3, 3]
                    d = np.subtract(hpr_from_rotation(np.asarray(car.world_from_carriage)[:3, :3]),
                                    hpr_from_rotation(T[:3, :3]))
                    d[0] = (d[0] + 180.0) % 360.0 - 180.0
                    half = np.concatenate([car.record["ci95_position_m"], car.record["ci95_hpr_deg"]])
                    zs.append(np.concatenate([e, d]) / (half / 1.959964))
        Z = np.asarray(zs)
        key = "known_focal" if focal_known else "estimated_focal"
        out[key] = {"n_carriages": len(Z), "failed": failed, "time_s": round(time.perf_counter() - t0, 1),
                    "coverage95": dict(zip(COMPONENTS, np.mean(np.abs(Z) <= 1.959964, axis=0).round(3).tolist())),
                    "rms_z": dict(zip(COMPONENTS, np.sqrt(np.mean(Z ** 2, axis=0)).round(2).tolist()))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "relative.json")
    a = ap.parse_args()
    logging.disable(logging.WARNING)
    res = run(a.seeds)
    for k, v in res.items():
        print(f"{k}: {v['n_carriages']} carriages, {len(v['failed'])} failed, {v['time_s']} s")
        print("  coverage95 " + "  ".join(f"{c} {x:.3f}" for c, x in v["coverage95"].items()))
        print("  rms z      " + "  ".join(f"{c} {x:.2f}" for c, x in v["rms_z"].items()))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"seeds": a.seeds, **res}, indent=1))
    print(f"saved {a.out}")


if __name__ == "__main__":
    main()
