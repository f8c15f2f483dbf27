#!/usr/bin/env python
"""Benchmark of the stitch stage (workbench.stitch) against cv2.Stitcher defaults and Hugin.

Part ``real`` (``--parts real``): the photo sets in ../shared/data/stitching, each method in its own
subprocess (wall time and peak resident memory of that process and its children, from getrusage):
  ours      workbench.stitch.stitch_photos, default options (register at 0.6 MP: SIFT on a half-size copy,
            matches refined by Lucas-Kanade at 0.6 MP; compose at full resolution)
  ours_full the same with sift_half=False (SIFT with its doubled first octave at 0.6 MP: slower)
  cv2       cv2.Stitcher_create(cv2.Stitcher_PANORAMA).stitch(...) (its defaults: ORB, 0.6 MP, full compose);
            both timed from the call (imread for cv2) to the written JPEG
  hugin     pto_gen, cpfind --multirow --celeste, cpclean, autooptimiser -a -m -l -s, pano_modify, nona, enblend
Reported: success, photos kept (weir_noise.jpg must be left out), time, peak memory, output size.
Set ``petra_24mp`` (not in the default list): the Petra photos enlarged to 24 MP, for peak memory at full size.

Part ``truth`` (``--parts truth``): pure-rotation sets with known focal and rotations:
  spuyten / frankford   the samples' panorama sets (1600x1200, k1 = -0.08, k2, p1, p2), EXIF focal in the photos
  nodist                a `workbench synth` panorama set without distortion (generated once under bench_out/)
  cut-grid / cut-row    views cut from a real photo (Petra) by known rotations, 640x480, k1 = 0 and -0.1
Per set: focal error (%) and rotation error (degrees, after the one global alignment) of every photo, for
ours (routes calibrated, exif where EXIF exists, unknown) and for cv2.Stitcher (focal and R from
``estimateTransform`` / ``cameras()``).

Prints tables and writes bench_out/stitch.json. Run it niced on a shared machine:
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python scripts/bench_stitch.py
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "stitching"
OUT = ROOT / "bench_out"
sys.path.insert(0, str(ROOT))

REAL_SETS = {
    "weir": ("opencv_weir", ["weir_1.jpg", "weir_2.jpg", "weir_3.jpg", "weir_noise.jpg"]),
    "budapest": ("opencv_budapest", [f"budapest{i}.jpg" for i in range(1, 7)]),
    "arches_9518": ("skimage_pano_arches", ["JDW_9518.jpg", "JDW_9519.jpg", "JDW_9520.jpg"]),
    "arches_0302": ("skimage_pano_arches", ["JDW_0302.jpg", "JDW_0303.jpg", "JDW_0304.jpg"]),
    "petra": ("skimage_pano_petra", ["DFM_4209.jpg", "DFM_4210.jpg", "DFM_4211.jpg"]),
}
EXPECTED_REJECTED = {"weir": ["weir_noise.jpg"]}
BIG = OUT / "stitch_big"  # petra_24mp: the Petra photos enlarged 2x (6000x3974, 24 MP), made on first use


def _set_paths(set_name: str) -> list[Path]:
    if set_name == "petra_24mp":
        import cv2

        BIG.mkdir(parents=True, exist_ok=True)
        out = []
        for n in REAL_SETS["petra"][1]:
            p = BIG / n
            if not p.is_file():
                img = cv2.imread(str(DATA / "skimage_pano_petra" / n))
                cv2.imwrite(str(p), cv2.resize(img, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC),
                            [cv2.IMWRITE_JPEG_QUALITY, 92])
            out.append(p)
        return out
    folder, names = REAL_SETS[set_name]
    return [DATA / folder / n for n in names]


# ----------------------------------------------------------------------------------------------------------
# workers (one subprocess per method and set)
# ----------------------------------------------------------------------------------------------------------
def _peak_mb() -> float:
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(self_kb, child_kb) / 1024.0


def worker_ours(paths: list[Path], out: Path, full_sift: bool = False) -> dict:
    import cv2

    from workbench.stitch import StitchOptions, stitch_photos

    t = time.perf_counter()
    r = stitch_photos(paths, options=StitchOptions(check_parallax=False, sift_half=not full_sift))
    cv2.imwrite(str(out), r.image, [cv2.IMWRITE_JPEG_QUALITY, 92])
    return {"ok": True, "kept": [s.name for s in r.model.sources], "rejected": r.rejected,
            "size": [r.model.width, r.model.height], "projection": r.model.projection,
            "time_s": time.perf_counter() - t,
            "parallax": {k: r.parallax[k] for k in ("verdict", "rms_work_px", "p90_work_px")},
            "focal_model": r.stats.get("focal_model"), "timings_s": r.stats["timings_s"]}


def worker_cv2(paths: list[Path], out: Path) -> dict:
    import cv2

    t = time.perf_counter()
    imgs = [cv2.imread(str(p)) for p in paths]
    st = cv2.Stitcher_create(cv2.Stitcher_PANORAMA)
    status, pano = st.stitch(imgs)
    if status != cv2.Stitcher_OK:
        return {"ok": False, "status": int(status), "time_s": time.perf_counter() - t}
    cv2.imwrite(str(out), pano, [cv2.IMWRITE_JPEG_QUALITY, 92])
    dt = time.perf_counter() - t  # timed like ours: from the call to the written panorama
    kept = [paths[i].name for i in np.asarray(st.component()).ravel()]
    return {"ok": True, "kept": kept, "rejected": [p.name for p in paths if p.name not in kept],
            "size": [pano.shape[1], pano.shape[0]], "time_s": dt}


def _run(cmd: list[str], cwd: Path) -> None:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{cmd[0]} failed ({r.returncode}): {r.stderr[-400:]}")


def worker_hugin(paths: list[Path], out: Path) -> dict:
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for p in paths:
            shutil.copy(p, d / p.name)
        names = [p.name for p in paths]
        _run(["pto_gen", "-o", "p.pto", *names], d)
        _run(["cpfind", "--multirow", "--celeste", "-o", "p.pto", "p.pto"], d)
        _run(["cpclean", "-o", "p.pto", "p.pto"], d)
        # photos with control points after cleaning (Hugin does not drop the others by itself)
        linked = set()
        for line in (d / "p.pto").read_text().splitlines():
            if line.startswith("c "):
                f = {t[0]: t[1:] for t in line.split()[1:]}
                linked |= {int(f["n"]), int(f["N"])}
        _run(["autooptimiser", "-a", "-m", "-l", "-s", "-o", "p.pto", "p.pto"], d)
        _run(["pano_modify", "--canvas=AUTO", "--crop=AUTO", "-o", "p.pto", "p.pto"], d)
        _run(["nona", "-m", "TIFF_m", "-o", "r", "p.pto"], d)
        parts = sorted(d.glob("r*.tif"))
        if not parts:
            return {"ok": False, "error": "nona wrote no image (no control points?)", "time_s": time.perf_counter() - t}
        _run(["enblend", "-o", "pano.tif", *[x.name for x in parts]], d)
        kept_idx = sorted(linked)
        import cv2

        pano = cv2.imread(str(d / "pano.tif"))
        cv2.imwrite(str(out), pano, [cv2.IMWRITE_JPEG_QUALITY, 92])
    kept = [names[i] for i in kept_idx]
    return {"ok": True, "kept": kept, "rejected": [n for n in names if n not in kept],
            "size": [pano.shape[1], pano.shape[0]], "time_s": time.perf_counter() - t}


def worker_main(method: str, set_name: str, out: Path) -> None:
    paths = _set_paths(set_name)
    try:
        res = {"ours": worker_ours, "ours_full": lambda p, o: worker_ours(p, o, full_sift=True), "cv2": worker_cv2,
               "hugin": worker_hugin}[method](paths, out)
    except Exception as exc:  # noqa: BLE001 - a failed method is a result of the benchmark
        res = {"ok": False, "error": f"{type(exc).__name__}: {str(exc)[:300]}"}
    res["peak_mb"] = _peak_mb()
    print("RESULT " + json.dumps(res))


def run_real(methods: list[str], sets: list[str]) -> list[dict]:
    rows = []
    (OUT / "stitch").mkdir(parents=True, exist_ok=True)
    for s in sets:
        for m in methods:
            out = OUT / "stitch" / f"{s}_{m}.jpg"
            t = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, "--worker", m, s, str(out)], capture_output=True, text=True,
                               env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
            wall = time.perf_counter() - t
            line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
            res = json.loads(line[-1][7:]) if line else {"ok": False, "error": p.stderr[-300:]}
            res.update({"set": s, "method": m, "process_wall_s": wall})
            if res.get("ok"):
                rej = sorted(x["name"] if isinstance(x, dict) else x for x in res.get("rejected", []))
                res["rejected_names"] = rej
                res["distractor_ok"] = rej == EXPECTED_REJECTED.get(s, [])
            rows.append(res)
            print(f"  {s:12s} {m:6s} ok={res.get('ok')} kept={len(res.get('kept', []))} "
                  f"t={res.get('time_s', float('nan')):.2f}s peak={res.get('peak_mb', 0):.0f}MB {res.get('error', '')}",
                  flush=True)
    return rows


# ----------------------------------------------------------------------------------------------------------
# ground truth
# ----------------------------------------------------------------------------------------------------------
def _truth_from_incident(root: Path) -> dict:
    from workbench.core.camera import CameraIntrinsics

    t = json.loads((root / "truth" / "ground_truth.json").read_text())
    ph = [p for p in t["photos"] if p["set"] == "panorama"]
    return {"paths": [root / p["photo"] for p in ph],
            "intrinsics": {Path(p["photo"]).name: CameraIntrinsics.from_dict(p["intrinsics"]) for p in ph},
            "rotations": {Path(p["photo"]).name: np.asarray(p["cam_from_world"])[:3, :3] for p in ph}, "exif": True}


def _nodist_set() -> dict:
    root = OUT / "stitch_truth" / "synth_nodist"
    if not (root / "truth" / "ground_truth.json").is_file():
        from workbench.synth.generate import SynthOptions, generate_incident

        print("  generating the undistorted synthetic panorama set (a few minutes)...", flush=True)
        generate_incident(root, SynthOptions(scenario="spuyten-duyvil", seed=3, n_cars=3, photo_width=1600,
                                             photo_height=1200, distortion=(0.0, 0.0, 0.0, 0.0, 0.0), n_panorama=5,
                                             n_multiview=0))
    return _truth_from_incident(root)


def _cut_set(kind: str, k1: float) -> dict:
    import cv2

    from workbench.core.camera import CameraIntrinsics
    from workbench.stitch.cutviews import cut_views, grid_rotations

    src = cv2.imread(str(DATA / "skimage_pano_petra" / "DFM_4210.jpg"))
    w, h = 640, 480
    f = w / 2 / np.tan(np.radians(15.0))
    intr = CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2 + 5.0, cy=(h - 1) / 2 - 4.0, k1=k1)
    rots = grid_rotations([-9.0, 9.0], [-6.0, 6.0], seed=1) if kind == "grid" else \
        grid_rotations([-12.0, 0.0, 12.0], [0.0], seed=2)
    views = cut_views(src, 2280.0, rots, intr)
    d = OUT / "stitch_truth" / f"cut_{kind}_k{k1:g}"
    d.mkdir(parents=True, exist_ok=True)
    for v in views:
        cv2.imwrite(str(d / v.name), v.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return {"paths": [d / v.name for v in views], "intrinsics": {v.name: intr for v in views},
            "rotations": {v.name: v.cam_from_src for v in views}, "exif": False}


def _errors(est_R: dict, est_f: dict, truth: dict) -> dict:
    from workbench.stitch.cutviews import rotation_errors_deg

    rot = rotation_errors_deg(est_R, truth["rotations"])
    foc = {n: 100.0 * (est_f[n] / truth["intrinsics"][n].fx - 1.0) for n in est_f}
    return {"focal_err_pct": foc, "rot_err_deg": rot, "max_abs_focal_err_pct": max(abs(x) for x in foc.values()),
            "max_rot_err_deg": max(rot.values()), "n_photos": len(rot)}


def truth_ours(truth: dict, route: str) -> dict:
    from workbench.render.exif import read_focal_px
    from workbench.stitch import StitchOptions, stitch_photos

    kw = {}
    if route == "calibrated":
        kw["calibrated"] = {p.name: truth["intrinsics"][p.name] for p in truth["paths"]}
    elif route == "exif":
        kw["focal_priors_px"] = {p.name: read_focal_px(p) for p in truth["paths"]}
    t = time.perf_counter()
    r = stitch_photos(truth["paths"], options=StitchOptions(compose=False, check_parallax=False), **kw)
    dt = time.perf_counter() - t
    row = _errors({s.name: s.cam_from_pano for s in r.model.sources},
                  {s.name: s.intrinsics.fx for s in r.model.sources}, truth)
    row.update({"time_s": dt, "intrinsics_source": r.intrinsics_source, "focal_model": r.stats.get("focal_model"),
                "k1": r.model.sources[0].intrinsics.k1, "rms_work_px": r.parallax["rms_work_px"]})
    return row


def truth_cv2(truth: dict) -> dict:
    import cv2

    imgs = [cv2.imread(str(p)) for p in truth["paths"]]
    st = cv2.Stitcher_create(cv2.Stitcher_PANORAMA)
    t = time.perf_counter()
    status = st.estimateTransform(imgs)
    dt = time.perf_counter() - t
    if status != cv2.Stitcher_OK:
        return {"ok": False, "status": int(status)}
    ws = st.workScale()
    comp = [int(i) for i in np.asarray(st.component()).ravel()]
    cams = st.cameras()
    names = [truth["paths"][i].name for i in comp]
    est_R = {n: np.asarray(c.R, float).T for n, c in zip(names, cams)}  # OpenCV's R is pano_from_cam
    est_f = {n: float(c.focal) / ws for n, c in zip(names, cams)}
    row = _errors(est_R, est_f, truth)
    row["time_s"] = dt
    return row


def run_truth(sets: list[str]) -> list[dict]:
    rows = []
    for s in sets:
        if s in ("spuyten", "frankford"):
            root = ROOT / "projects" / {"spuyten": "spuyten-duyvil", "frankford": "frankford-junction"}[s]
            if not (root / "truth" / "ground_truth.json").is_file():
                print(f"  {s}: sample not generated; skipped")
                continue
            truth = _truth_from_incident(root)
        elif s == "nodist":
            truth = _nodist_set()
        else:
            kind, k1 = s.split(":")  # cut-grid:-0.1
            truth = _cut_set(kind.removeprefix("cut-"), float(k1))
        routes = ["calibrated", "exif", "unknown"] if truth["exif"] else ["calibrated", "unknown"]
        for m in [*routes, "cv2"]:
            try:
                row = truth_cv2(truth) if m == "cv2" else truth_ours(truth, m)
            except Exception as exc:  # noqa: BLE001
                row = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            row.update({"set": s, "method": "cv2.Stitcher" if m == "cv2" else f"ours/{m}"})
            rows.append(row)
            if "max_rot_err_deg" in row:
                print(f"  {s:14s} {row['method']:16s} max|focal err| {row['max_abs_focal_err_pct']:7.3f} %  "
                      f"max rot err {row['max_rot_err_deg']:7.4f} deg  t={row['time_s']:.2f}s", flush=True)
            else:
                print(f"  {s:14s} {row['method']:16s} failed: {row.get('error', row.get('status'))}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default="real,truth")
    ap.add_argument("--methods", default="ours,ours_full,cv2,hugin")
    ap.add_argument("--sets", default=",".join(REAL_SETS), help="also: petra_24mp (24 MP photos)")
    ap.add_argument("--truth-sets", default="spuyten,frankford,nodist,cut-grid:0,cut-grid:-0.1,cut-row:0,cut-row:-0.1")
    ap.add_argument("--worker", nargs=3, metavar=("METHOD", "SET", "OUT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker_main(a.worker[0], a.worker[1], Path(a.worker[2]))
        return
    OUT.mkdir(exist_ok=True)
    result: dict = {"machine": {"cpus": os.cpu_count(), "load_avg_at_start": os.getloadavg()}}
    parts = a.parts.split(",")
    if "real" in parts:
        if not DATA.is_dir():
            sys.exit(f"{DATA} is not there")
        methods = [m for m in a.methods.split(",") if m != "hugin" or shutil.which("pto_gen")]
        print("real photo sets:")
        result["real"] = run_real(methods, a.sets.split(","))
        summary = {}
        for s in a.sets.split(","):
            by = {r["method"]: r for r in result["real"] if r["set"] == s}
            if "ours" in by and "cv2" in by and by["ours"].get("ok") and by["cv2"].get("ok"):
                summary[s] = {"time_ratio_ours_cv2": by["ours"]["time_s"] / by["cv2"]["time_s"],
                              "peak_ratio_ours_cv2": by["ours"]["peak_mb"] / by["cv2"]["peak_mb"]}
                if by.get("ours_full", {}).get("ok"):
                    summary[s]["time_ratio_ours_full_cv2"] = by["ours_full"]["time_s"] / by["cv2"]["time_s"]
                if by.get("hugin", {}).get("ok"):
                    summary[s]["time_ratio_hugin_cv2"] = by["hugin"]["time_s"] / by["cv2"]["time_s"]
        result["real_summary"] = summary
        print("\n| set | method | ok | kept | rejected | distractor ok | time s | peak MB | size |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in result["real"]:
            print(f"| {r['set']} | {r['method']} | {r.get('ok')} | {len(r.get('kept', []))} | "
                  f"{', '.join(r.get('rejected_names', [])) or '-'} | {r.get('distractor_ok', '-')} | "
                  f"{r.get('time_s', float('nan')):.2f} | {r.get('peak_mb', float('nan')):.0f} | "
                  f"{r.get('size', '-')} |")
        for s, v in summary.items():
            full = v.get("time_ratio_ours_full_cv2")
            print(f"  {s}: time ours/cv2 = {v['time_ratio_ours_cv2']:.2f}, "
                  f"peak ours/cv2 = {v['peak_ratio_ours_cv2']:.2f}"
                  + (f", ours_full/cv2 = {full:.2f}" if full is not None else "")
                  + (f", hugin/cv2 = {v['time_ratio_hugin_cv2']:.1f}" if "time_ratio_hugin_cv2" in v else ""))
    if "truth" in parts:
        print("ground truth:")
        result["truth"] = run_truth(a.truth_sets.split(","))
    from workbench.core.io import atomic_write_json

    atomic_write_json(OUT / "stitch.json", result)
    print(f"wrote {OUT / 'stitch.json'}")


if __name__ == "__main__":
    main()
