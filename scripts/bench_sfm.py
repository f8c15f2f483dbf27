#!/usr/bin/env python
"""Benchmark of multi-view SfM (workbench.intrinsics.sfm, pycolmap) on sets with and without ground truth.

Sets (``--sets``, comma separated):
  render    8 and 16 ray-cast photos (480x360) of a textured scene with exact cameras (workbench.intrinsics.synthetic)
  synth     a small `workbench synth` incident (2 cars, 8 multi-view photos of 480x360), generated here
  spuyten   projects/spuyten-duyvil/photos/multiview (12 photos, 1600x1200), truth in truth/ground_truth.json
            (generate the photos first: `workbench synth projects/spuyten-duyvil ...` as scripts/demo.sh does,
            or give a generated copy with --spuyten PATH)
  frankford the same for projects/frankford-junction (--frankford PATH)
  extra     every incident given with --extra PATH (e.g. a fresh seed: `workbench synth /tmp/x --seed 7`)
  lund      ../shared/data/multiview/opensfm_lund (29 photos, 1024x768, forward motion; GPS in EXIF)
  berlin    ../shared/data/multiview/opensfm_berlin (3 photos, 3264x2448; OpenSfM reference reconstruction)

Reports per run: photos registered, focal (px) and its error against the truth (%), k1/k2, camera-position RMS
after a similarity (Umeyama) alignment to the truth (metres; for Lund against GPS), rotation error, points,
mean reprojection error, time, the separate models. With --georef (incident sets), the georef stage is run on
the result from the incident's control_points.json three times: the main model only with every photo it has
(the stage before separate models were kept), every SfM model (photos that disagree with their control points
left out), and every model then each photo left placed on its own (resection): photos placed, camera-position and rotation errors against the truth
in the scene frame (no alignment). Prints a table and writes bench_out/sfm.json.

Run it niced on a shared machine:  OMP_NUM_THREADS=2 nice -n 10 .venv/bin/python scripts/bench_sfm.py
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT))

from workbench.core.camera import CameraIntrinsics  # noqa: E402
from workbench.core.io import atomic_write_json  # noqa: E402
from workbench.files.exif import exif_focal_prior  # noqa: E402
from workbench.intrinsics.sfm import SfmOptions, run_sfm, similarity_align  # noqa: E402
from workbench.intrinsics.synthetic import write_multiview_set  # noqa: E402

log = logging.getLogger("bench_sfm")


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))


def evaluate(result, truth_centres: dict | None, truth_R: dict | None, true_intr: CameraIntrinsics | None) -> dict:
    v0 = result.views[0].intrinsics
    row = {"n_images": result.stats["n_images"], "n_registered": len(result.views), "focal_px": v0.fx,
           "k1": v0.k1, "k2": v0.k2, "n_points": result.n_points_total,
           "reproj_px": result.stats["mean_reprojection_error_px"], "time_s": result.stats["time_s"],
           "timings_s": result.stats["timings_s"], "n_models": result.stats.get("n_models"),
           "retried_forward_motion": result.stats["retried_forward_motion"],
           "unregistered": result.unregistered, "warnings": result.stats["warnings"]}
    if true_intr is not None:
        row["focal_true_px"] = true_intr.fx
        row["focal_err_pct"] = 100.0 * (v0.fx / true_intr.fx - 1)
        r = np.hypot(true_intr.width / 2, true_intr.height / 2) / true_intr.fx  # radial distortion at the corner
        row["corner_distortion_err_pct"] = 100.0 * ((v0.k1 * r**2 + v0.k2 * r**4)
                                                    - (true_intr.k1 * r**2 + true_intr.k2 * r**4))
    if truth_centres:
        views = [v for v in result.views if v.name in truth_centres]
        if len(views) >= 3:
            src = np.array([v.center_model for v in views])
            dst = np.array([truth_centres[v.name] for v in views])
            s, R, t, res = similarity_align(src, dst)
            row["position_rms_m"] = float(np.sqrt(np.mean(res**2)))
            row["position_max_m"] = float(res.max())
            row["spread_m"] = float(np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1))))
            if truth_R:
                errs = [_rot_err_deg(v.cam_from_model[:3, :3] @ R.T, truth_R[v.name]) for v in views]
                row["rotation_err_deg_max"] = float(max(errs))
            # robust: the similarity of any 3 cameras that most others agree with (within 5 % of the spread),
            # refitted on those; views off by more are listed as outliers (wrong registrations)
            from itertools import combinations

            tol = 0.05 * row["spread_m"]
            best = np.ones(len(src), bool) if res.max() <= tol else None
            if best is None:
                n_best = 0
                for tri in combinations(range(len(src)), 3):
                    try:
                        s3, R3, t3, _ = similarity_align(src[list(tri)], dst[list(tri)])
                    except ValueError:
                        continue
                    inl = np.linalg.norm(src @ (s3 * R3).T + t3 - dst, axis=1) <= tol
                    if inl.sum() > n_best:
                        n_best, best = int(inl.sum()), inl
            if best is not None and best.sum() >= 3 and not best.all():
                s2, R2, t2, res2 = similarity_align(src[best], dst[best])
                row["outlier_views"] = [v.name for v, k in zip(views, best) if not k]
                row["position_rms_inliers_m"] = float(np.sqrt(np.mean(res2**2)))
                if truth_R:
                    row["rotation_err_deg_max_inliers"] = float(max(
                        _rot_err_deg(v.cam_from_model[:3, :3] @ R2.T, truth_R[v.name])
                        for v, k in zip(views, best) if k))
            row["per_view_position_err_m"] = {v.name: float(e) for v, e in zip(views, res)}
    return row


def bench_render(out: Path, n: int) -> list[dict]:
    folder = out / f"render_{n}"
    t0 = time.perf_counter()
    truth = write_multiview_set(folder, n, seed=0)
    t_render = time.perf_counter() - t0
    centres = {p["name"]: p["center"] for p in truth["photos"]}
    rots = {p["name"]: np.asarray(p["cam_from_world"])[:3, :3] for p in truth["photos"]}
    intr = CameraIntrinsics.from_dict(truth["intrinsics"])
    photos = sorted(folder.glob("*.jpg"))
    rows = []
    for label, prior in (("no prior", None), ("EXIF prior", _exif_prior(photos))):
        res = run_sfm(photos, options=SfmOptions(), prior=prior)
        rows.append({"set": f"render {n}x 480x360", "variant": label, "render_s": t_render,
                     **evaluate(res, centres, rots, intr)})
    return rows


def _exif_prior(photos: list[Path]) -> CameraIntrinsics | None:
    pr = exif_focal_prior(photos[0])
    if pr is None:
        return None
    return CameraIntrinsics(width=pr.width, height=pr.height, fx=pr.focal_px, fy=pr.focal_px,
                            cx=(pr.width - 1) / 2, cy=(pr.height - 1) / 2)


def _truth_of_incident(root: Path):
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    mv = [p for p in truth["photos"] if p["set"] == "multiview"]
    centres = {Path(p["photo"]).name: p["center_enu"] for p in mv}
    rots = {Path(p["photo"]).name: np.asarray(p["cam_from_world"])[:3, :3] for p in mv}
    return centres, rots, CameraIntrinsics.from_dict(mv[0]["intrinsics"])


def _label(root: Path) -> str:
    g = json.loads((root / "truth" / "ground_truth.json").read_text())["generator"]["options"]
    return f"{g['scenario']} seed {g['seed']}"


def georef_eval(root: Path, res, work: Path, centres: dict, rots: dict, rec: dict | None = None) -> dict:
    """The ``georef`` stage on an SfM result, in a scratch incident beside ``work`` (``camera.source = "sfm"``,
    the incident's control points): photos placed and their errors against the truth in the scene frame (no
    alignment), with every model (``after``) and with the main model only (``before``: the stage before the
    separate models were kept)."""
    import os
    import shutil
    import warnings

    from workbench.georef.stage import run_georef
    from workbench.project import Project

    from workbench.georef.options import GeorefOptions

    out = {}
    if rec is None:
        rec0 = None
    else:
        rec0 = json.loads(json.dumps(rec))
    for variant in ("before", "models", "resected", "after"):
        dst = work / f"georef_{root.name}_{variant}"
        if dst.exists():
            shutil.rmtree(dst)
        dst.mkdir(parents=True)
        for entry in root.iterdir():  # the incident by links; its settings edited in a copy
            if entry.name not in ("project.toml", "out"):
                os.symlink(entry.resolve(), dst / entry.name)
        toml = (root / "project.toml").read_text()
        toml = toml.replace('source = "calibrated"', 'source = "sfm"').replace('source = "exif"', 'source = "sfm"')
        toml = toml.replace('photos = "photos/panorama"', 'photos = "photos/multiview"')
        (dst / "project.toml").write_text(toml)
        project = Project(dst)
        rec = json.loads(json.dumps(rec0)) if rec0 is not None else res.to_json(project.relative)
        if variant == "before":
            rec["models"] = []
        atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                stage = run_georef(project, lambda f, m="": None,
                                   GeorefOptions(resect_unplaced=variant in ("resected", "after"),
                                                 reject_disagreeing_views=variant != "before",
                                                 adjust_camera=variant == "after"))
        except Exception as exc:  # noqa: BLE001 - a failed georegistration is a result
            out[variant] = {"n_placed": 0, "error": f"{type(exc).__name__}: {exc}"[:300]}
            continue
        doc = json.loads(stage.outputs["cameras"].read_text())
        errs = {v["name"]: float(np.linalg.norm(np.asarray(v["center_enu"]) - centres[v["name"]]))
                for v in doc["views"]}
        rerr = {v["name"]: _rot_err_deg(np.asarray(v["cam_from_world"])[:3, :3], rots[v["name"]])
                for v in doc["views"]}
        e = np.array(list(errs.values()))
        g = doc["georegistration"]
        # the stated uncertainty against the error: |error| / sigma (largest axis) and the squared Mahalanobis
        # distance (chi-square with 3 degrees of freedom: 95 % below 7.81) where a covariance is stated
        unc = g.get("view_uncertainty", {})
        ratio, mahal = {}, {}
        for v in doc["views"]:
            u = unc.get(v["name"], {})
            d = np.asarray(v["center_enu"]) - centres[v["name"]]
            if u.get("sigma_centre_m"):
                ratio[v["name"]] = float(np.linalg.norm(d) / u["sigma_centre_m"])
            if u.get("cov_centre_enu_m2") is not None:
                mahal[v["name"]] = float(d @ np.linalg.solve(np.asarray(u["cov_centre_enu_m2"]), d))
        out[variant] = {"n_placed": len(doc["views"]), "placed": sorted(errs),
                        "position_rms_m": float(np.sqrt(np.mean(e ** 2))), "position_max_m": float(e.max()),
                        "rotation_err_deg_max": float(max(rerr.values())), "georef_s": time.perf_counter() - t0,
                        "per_view_position_err_m": errs, "per_view_rotation_err_deg": rerr,
                        "per_view_err_over_sigma": ratio, "per_view_mahalanobis2": mahal,
                        "per_view_sigma_from": {n: u.get("from") for n, u in unc.items()},
                        "camera_adjustment": g.get("camera_adjustment"),
                        "models": [{k: m.get(k) for k in ("model", "status", "reason", "views", "placed",
                                                          "n_fitting_triangulated", "spread_m", "rms_px",
                                                          "sigma_centre_max_m", "overlap")}
                                   for m in g.get("models", [])],
                        "unregistered": g.get("unregistered", []),
                        "resected": [{k: r.get(k) for k in ("name", "n_points", "rms_px", "sigma_centre_max_m",
                                                            "intrinsics_from")} for r in g.get("resected", [])]}
    return out


def bench_incident(root: Path, label: str, variants, georef_work: Path | None = None,
                   reuse_sfm: bool = False) -> list[dict]:
    photos = sorted((root / "photos" / "multiview").glob("*.jpg"))
    if not photos or not (root / "truth" / "ground_truth.json").is_file():
        raise FileNotFoundError(f"{root}: no generated multi-view photos or truth; run `workbench synth` on it first")
    centres, rots, intr = _truth_of_incident(root)
    kept = None if georef_work is None else georef_work / f"georef_{root.name}_after" / "out" / "sfm" / "reconstruction.json"
    if reuse_sfm and kept is not None and kept.is_file():  # georef only, on the SfM result of an earlier run
        rec = json.loads(kept.read_text())
        row = {"set": label, "variant": "reused SfM result (" + str(kept) + ")", "n_images": len(photos),
               "n_registered": len(rec["images"])}
        row["georef"] = georef_eval(root, None, georef_work, centres, rots, rec=rec)
        return [row]
    rows = []
    for vlabel, opts, use_prior in variants:
        try:
            res = run_sfm(photos, options=opts, prior=_exif_prior(photos) if use_prior else None)
            row = {"set": label, "variant": vlabel, **evaluate(res, centres, rots, intr)}
            row["separate_models"] = [[v.name for v in m.views] for m in res.models]
            if georef_work is not None and (root / "control_points.json").is_file():
                row["georef"] = georef_eval(root, res, georef_work, centres, rots)
            rows.append(row)
        except Exception as exc:  # noqa: BLE001 - a failed run is a result
            rows.append({"set": label, "variant": vlabel, "n_images": len(photos), "n_registered": 0,
                         "error": str(exc)[:200]})
    return rows


BEFORE = SfmOptions(max_num_features=8192, sift_peak_threshold=0.02 / 3, sift_affine_shape=False,
                    sift_domain_size_pooling=False)  # the features before issue 4's fix (COLMAP's SIFT defaults)


def incident_variants() -> list:
    return [("EXIF prior (the stage's way)", SfmOptions(), True),
            ("EXIF prior, COLMAP SIFT defaults (before)", BEFORE, True)]


def bench_synth(out: Path) -> list[dict]:
    root = out / "synth_inc"
    if not (root / "truth" / "ground_truth.json").is_file():
        t0 = time.perf_counter()
        subprocess.run([str(ROOT / ".venv" / "bin" / "workbench"), "synth", str(root), "--cars", "2", "--width", "480",
                        "--height", "360", "--panorama", "2", "--multiview", "8"], check=True, capture_output=True)
        log.info("synth generated in %.1f s", time.perf_counter() - t0)
    return bench_incident(root, "workbench synth 8x 480x360", [("EXIF prior", SfmOptions(), True)])


def _gps_enu(photos: list[Path]) -> dict:
    """Camera positions from EXIF GPS, local east/north/up metres (tangent plane at the first photo)."""
    from PIL import Image

    def deg(v):
        return float(v[0]) + float(v[1]) / 60 + float(v[2]) / 3600

    out = {}
    for p in photos:
        with Image.open(p) as im:
            g = im.getexif().get_ifd(0x8825)
        if not g or 2 not in g or 4 not in g:
            continue
        lat = deg(g[2]) * (-1 if g.get(1) == "S" else 1)
        lon = deg(g[4]) * (-1 if g.get(3) == "W" else 1)
        alt = float(g.get(6, 0.0))
        out[p.name] = (lat, lon, alt)
    if not out:
        return {}
    lat0, lon0, _ = next(iter(out.values()))
    R = 6378137.0
    return {n: [math.radians(lon - lon0) * R * math.cos(math.radians(lat0)), math.radians(lat - lat0) * R, alt]
            for n, (lat, lon, alt) in out.items()}


def bench_lund() -> list[dict]:
    folder = DATA / "multiview" / "opensfm_lund" / "images"
    if not folder.is_dir():
        return []
    photos = sorted(folder.glob("*.jpg"))
    gps = _gps_enu(photos)
    gps_h = {n: [e, nn, 0.0] for n, (e, nn, _) in gps.items()}  # GPS heights of phones are poor: horizontal only
    rows = []
    for vlabel, opts in (("forward-motion options + EXIF prior", SfmOptions.forward_motion(matcher="exhaustive")),):
        res = run_sfm(photos, options=opts, prior=_exif_prior(photos))
        row = {"set": "lund 29x 1024x768", "variant": vlabel, **evaluate(res, gps_h, None, None)}
        row["exif_prior_px"] = _exif_prior(photos).fx
        row["note"] = "positions against phone GPS (horizontal), not ground truth"
        rows.append(row)
    return rows


def bench_berlin() -> list[dict]:
    folder = DATA / "multiview" / "opensfm_berlin" / "images"
    if not folder.is_dir():
        return []
    photos = sorted(folder.glob("*.jpg"))
    ref = json.loads((DATA / "multiview" / "opensfm_berlin" / "reconstruction_example.json").read_text())[0]
    cam = next(iter(ref["cameras"].values()))
    ref_f = cam["focal"] * max(cam["width"], cam["height"])
    res = run_sfm(photos, options=SfmOptions(max_image_size_px=1600), prior=_exif_prior(photos))
    row = {"set": "berlin 3x 3264x2448", "variant": "EXIF prior, features at 1600 px", **evaluate(res, None, None, None)}
    row["opensfm_reference_focal_px"] = ref_f
    row["focal_vs_opensfm_pct"] = 100.0 * (row["focal_px"] / ref_f - 1)
    return [row]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="render,synth,spuyten,frankford,lund,berlin")
    ap.add_argument("--out", default=str(ROOT / "bench_out" / "sfm.json"))
    ap.add_argument("--work", default=str(ROOT / "bench_out" / "sfm_work"))
    ap.add_argument("--spuyten", default=str(ROOT / "projects" / "spuyten-duyvil"), help="generated incident folder")
    ap.add_argument("--frankford", default=str(ROOT / "projects" / "frankford-junction"), help="generated incident folder")
    ap.add_argument("--extra", action="append", default=[], help="more generated incident folders (set 'extra')")
    ap.add_argument("--georef", action="store_true",
                    help="incident sets: also run the georef stage on the SfM result (every model, and the main model "
                         "only) from the incident's control points, and compare the cameras with the truth in the "
                         "scene frame")
    ap.add_argument("--reuse-sfm", action="store_true",
                    help="with --georef: when WORK/georef_<incident>_after/out/sfm/reconstruction.json exists (an "
                         "earlier run's SfM result), run only the georef variants on it")
    ap.add_argument("--variants", default="all", choices=("all", "stage"),
                    help="incident sets: 'stage' runs only the stage's options (not COLMAP's SIFT defaults too)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    out = Path(args.out)
    sets = args.sets.split(",")
    # keep the rows of sets not run this time (so sets can be run one by one)
    rows: list[dict] = []
    if out.is_file():
        rows = [r for r in json.loads(out.read_text()).get("rows", []) if r.get("group") not in sets]
    gw = work if args.georef else None

    def variants():
        v = incident_variants()
        return v[:1] if args.variants == "stage" else v

    runs = {
        "render": lambda: bench_render(work, 8) + bench_render(work, 16),
        "synth": lambda: bench_synth(work),
        "spuyten": lambda: bench_incident(Path(args.spuyten), "spuyten-duyvil seed 1", variants(), gw,
                                               args.reuse_sfm),
        "frankford": lambda: bench_incident(Path(args.frankford), "frankford-junction seed 1", variants(), gw,
                                                 args.reuse_sfm),
        "extra": lambda: [r for p in args.extra for r in bench_incident(Path(p), f"{_label(Path(p))}",
                                                                        variants(), gw)],
        "lund": bench_lund,
        "berlin": bench_berlin,
    }
    for name in sets:
        if name not in runs:
            sys.exit(f"--sets: unknown set {name!r}; known: {', '.join(runs)}")
        try:
            new_rows = runs[name]()
        except Exception as exc:  # noqa: BLE001 - report and go on with the next set
            log.exception("set %s failed", name)
            new_rows = [{"set": name, "variant": "-", "error": f"{type(exc).__name__}: {exc}"[:300]}]
        rows += [{"group": name, **r} for r in new_rows]
        atomic_write_json(out, {"rows": rows})
    cols = [("set", 26, "{}"), ("variant", 42, "{}"), ("n_registered", 4, "{}"), ("n_images", 4, "{}"),
            ("focal_px", 8, "{:.1f}"), ("focal_err_pct", 7, "{:+.2f}"), ("k1", 7, "{:+.3f}"), ("k2", 7, "{:+.3f}"),
            ("position_rms_m", 7, "{:.3f}"), ("position_max_m", 7, "{:.3f}"), ("position_rms_inliers_m", 7, "{:.3f}"), ("spread_m", 6, "{:.1f}"), ("rotation_err_deg_max", 6, "{:.2f}"),
            ("n_points", 6, "{}"), ("reproj_px", 5, "{:.2f}"), ("time_s", 6, "{:.1f}")]
    print(" | ".join(f"{c[:w]:>{w}}" for c, w, _ in cols))
    for r in rows:
        cells = []
        for c, w, fmt in cols:
            v = r.get(c)
            cells.append(f"{(fmt.format(v) if v is not None else '-'):>{w}}")
        print(" | ".join(cells))
    for r in rows:
        if r.get("error"):
            print(f"{r['set']} / {r['variant']}: {r['error']}")
        if r.get("per_view_position_err_m"):
            print(f"{r['set']} / {r['variant']}: registered, position error (m): "
                  + " ".join(f"{k}:{v:.2f}" for k, v in r["per_view_position_err_m"].items()))
        if r.get("outlier_views"):
            print(f"{r['set']} / {r['variant']}: outlier views (left out of the inlier RMS): {r['outlier_views']}")
        if r.get("warnings"):
            print(f"{r['set']} / {r['variant']}: warnings: {'; '.join(r['warnings'])}")
        if r.get("separate_models"):
            print(f"{r['set']} / {r['variant']}: separate SfM models: {r['separate_models']}")
        for gv, g in (r.get("georef") or {}).items():
            if g.get("error"):
                print(f"{r['set']} / {r['variant']}: georef {gv}: {g['error']}")
                continue
            what = {"before": "main model only, no check of single photos", "models": "every SfM model",
                    "resected": "every SfM model, then resection of the photos left",
                    "after": "the default: models, resection, shared camera adjusted"}[gv]
            print(f"{r['set']} / {r['variant']}: georef {gv} ({what})", end="")
            print(f": {g['n_placed']}/{r['n_images']} photos placed, position error RMS {g['position_rms_m']:.3f} / "
                  f"max {g['position_max_m']:.3f} m, rotation max {g['rotation_err_deg_max']:.3f} deg, "
                  f"{g['georef_s']:.1f} s")
            print("    per photo (m / deg): " + " ".join(
                f"{k}:{v:.3f}/{g['per_view_rotation_err_deg'][k]:.2f}"
                for k, v in g["per_view_position_err_m"].items()))
            if g.get("per_view_err_over_sigma"):
                mh = g.get("per_view_mahalanobis2", {})
                print("    error / stated 1-sigma (Mahalanobis^2): " + " ".join(
                    f"{k}:{v:.2f}" + (f"({mh[k]:.1f})" if k in mh else "")
                    for k, v in g["per_view_err_over_sigma"].items())
                    + (f"; {sum(x < 7.81 for x in mh.values())}/{len(mh)} inside the 95 % ellipsoid" if mh else ""))
            for a in g.get("camera_adjustment") or []:
                print(f"    camera adjustment over {len(a.get('photos', []))} photos, {a.get('n_observations')} "
                      f"picks: chosen {a.get('chosen')}, held-out RMS px {a.get('held_out_rms_px')}, intrinsics "
                      f"{a.get('free_intrinsics')} +- {a.get('sigma_intrinsics')}, condition "
                      f"{a.get('condition') or 0:.0f}, chi2_red {a.get('chi2_red') or 0:.3f}")
            for m in g["models"]:
                print(f"    {m['model']} {m['views']}: {m['status']}" + (f" ({m['reason']})" if m.get("reason") else
                      f", {m.get('n_fitting_triangulated')} points, spread {m.get('spread_m') or 0:.1f} m, "
                      f"sigma {m.get('sigma_centre_max_m') or 0:.3f} m, rms {m.get('rms_px') or 0:.2f} px"))
            for m in g.get("resected", []):
                print(f"    resected {m['name']}: {m['n_points']} points, rms {m['rms_px']:.2f} px, "
                      f"sigma {m['sigma_centre_max_m']:.3f} m, intrinsics: {m['intrinsics_from']}")
            for u in g.get("unregistered", []):
                print(f"    unplaced {u['name']}: {u['reason'][:300]}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
