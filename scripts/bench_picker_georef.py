"""Control points through the picker (issue 17): repeated-noise statistics of georef from map picks, and the
real Berlin GCPs entered through the picker's typed-coordinate path.

    .venv/bin/python scripts/bench_picker_georef.py [--sample DIR] [--reps 40] [--out bench_out/picker_georef.json]
        [--sets synthetic,panorama,berlin] [--noise-m 0.5] [--noise-px 2] [--sweep 0.2,0.1,0.05]

*synthetic*: a small generated Spuyten Duyvil incident (``--sample``: an incident folder made by ``workbench
synth``, else one is generated under the work folder, about 40 s); one photo (the single-photo route), 6 ground
landmarks spread over it (the synthetic control points that lie on the DEM), each picked in the photo at the true
pixel plus ``--noise-px`` Gaussian noise per axis and on the map at the true easting/northing plus ``--noise-m``;
the height from the DEM (the picker's ``/api/locate``); saved and georeferenced through the picker's HTTP API
(``/api/control_points``, ``/api/georef``). Per repetition: the camera centre's and rotation's error against the
truth and whether the truth lies inside the stated 95 % ellipsoid (chi-squared, 3 degrees of freedom). Rows for a
sweep of the map noise too (``--sweep``).

*panorama*: the same incident with its panorama photos, stitched (the stitch stage), 6 ground landmarks spread in
azimuth around the camera, each picked in every panorama photo that shows it; the panorama route.

*berlin*: the OpenSfM Berlin photos (``../shared/data/multiview/opensfm_berlin``) as an incident with OpenSfM's
reconstruction as the SfM model; the two GCPs typed as latitude/longitude/altitude (``/api/locate``, typed) with
their OpenSfM pixels, saved, georeferenced (the multiview route); the figures beside those of the similarity fitted
directly to the same GCPs (tests/test_georef.py, docs/gis.md).

Prints the figures and saves them as JSON (``--out``).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import shutil
import sys
import time
import urllib.error
import urllib.request
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = REPO.parent / "shared" / "data"
BERLIN = DATA / "multiview" / "opensfm_berlin"
CHI2_3_95 = 7.815

CONSIST = ('[[consist]]\nnumber = "6100"\ntype = "shoreliner"\n')


# ----------------------------------------------------------------------------------------------------------------
# The picker's HTTP API, as the page calls it
# ----------------------------------------------------------------------------------------------------------------
class Client:
    """Calls a running picker as its page does (token from the page, same-origin headers)."""

    def __init__(self, url: str) -> None:
        self.url = url.rstrip("/")
        with urllib.request.urlopen(self.url + "/", timeout=30) as r:
            page = r.read().decode()
        self.token = re.search(r'<meta name="picker-token" content="([^"]+)">', page).group(1)

    def get(self, path: str):
        req = urllib.request.Request(self.url + path, headers={"X-Picker-Token": self.token})
        with urllib.request.urlopen(req, timeout=120) as r:
            return json.loads(r.read())

    def post(self, path: str, data) -> tuple[int, dict]:
        req = urllib.request.Request(self.url + path, data=json.dumps(data).encode(), method="POST",
                                     headers={"Content-Type": "application/json", "X-Picker-Token": self.token,
                                              "Origin": self.url})
        try:
            with urllib.request.urlopen(req, timeout=300) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())


# ----------------------------------------------------------------------------------------------------------------
# Synthetic: one photo, ground landmarks, map picks
# ----------------------------------------------------------------------------------------------------------------
def single_photo_incident(sample: Path, dst: Path, photo: str = "pano_01.jpg") -> Path:
    """A copy of a generated incident (``sample``, with its ``../../terrain`` layers) with one photo (the single
    route), no ``camera.position_enu`` (no prior from the truth) and no control points yet. Returns its root."""
    base = dst / "projects" / sample.name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(sample.parent.parent / "terrain", dst / "terrain")
    (base / "photos" / "single").mkdir(parents=True)
    for name in ("project.toml", "camera_profile.json"):
        shutil.copy2(sample / name, base / name)
    shutil.copytree(sample / "truth", base / "truth")
    shutil.copy2(next((sample / "photos").rglob(photo)), base / "photos" / "single" / photo)
    toml = (base / "project.toml").read_text()
    toml = re.sub(r"position_enu = \[[^\]]*\]\n?", "", toml)
    toml = re.sub(r'photos = "[^"]*"', 'photos = "photos/single"', toml)
    (base / "project.toml").write_text(toml)
    return base


def ground_landmarks(root: Path, sample: Path, photo: str, n: int = 6) -> list[dict]:
    """``n`` synthetic control points of ``sample`` that lie on the DEM (|h - DEM| < 0.05 m) and are seen in
    ``photo``, spread over it (farthest-point sampling in the image): name, true E/N/h and true pixel."""
    from workbench.core.camera import CameraIntrinsics
    from workbench.picker.map import MapService
    from workbench.project import Project

    project = Project(root)
    heights = MapService(project)
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    ph = next(p for p in truth["photos"] if Path(p["photo"]).name == photo)
    intr, M = CameraIntrinsics(**ph["intrinsics"]), np.asarray(ph["cam_from_world"], float)
    cps = json.loads((sample / "control_points.json").read_text())
    out = []
    for q in cps["points"]:
        E, N, h = q["coords"]
        if photo not in q["pixels"] or abs(h - heights.height_at(E, N)) > 0.05:
            continue
        enu = project.frame.enu_from_crs(np.array([E, N, h]))
        uv = intr.project((M[:3, :3] @ enu + M[:3, 3])[None])[0]
        out.append({"name": q["name"], "coords": [E, N, h], "uv": uv.tolist(),
                    "distance_m": float(np.linalg.norm(enu - np.asarray(ph["center_enu"], float)))})
    uv = np.array([o["uv"] for o in out])
    sel = [int(np.argmin(uv[:, 0]))]
    while len(sel) < min(n, len(out)):
        d = np.min(np.linalg.norm(uv[:, None] - uv[sel][None], axis=2), axis=1)
        sel.append(int(np.argmax(d)))
    return [out[i] for i in sel]


def noisy_picks(marks: list[dict], seed: int, noise_px: float, noise_m: float) -> list[dict]:
    """Each landmark as a person picks it: the pixel and the map position with Gaussian noise (fixed seed)."""
    rng = np.random.default_rng(seed)
    return [{"name": m["name"], "uv": (np.asarray(m["uv"]) + rng.normal(0, noise_px, 2)).tolist(),
             "en": (np.asarray(m["coords"][:2]) + rng.normal(0, noise_m, 2)).tolist()} for m in marks]


def truth_errors(root: Path, photo: str, cameras: dict) -> dict:
    """The georef result (``out/georef/cameras.json``) against the truth: centre error (m), rotation error (deg),
    squared Mahalanobis distance of the centre error under the stated covariance and whether it is inside 95 %."""
    from workbench.core.geometry import log_so3

    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    ph = next(p for p in truth["photos"] if Path(p["photo"]).name == photo)
    v = next(v for v in cameras["views"] if v["name"] == photo)
    Mt, M = np.asarray(ph["cam_from_world"], float), np.asarray(v["cam_from_world"], float)
    e = np.asarray(v["center_enu"]) - np.asarray(ph["center_enu"])
    rot = float(np.degrees(np.linalg.norm(log_so3(M[:3, :3] @ Mt[:3, :3].T))))
    C6 = np.asarray(cameras["georegistration"]["covariance_world_rotation_centre"], float)
    C = C6[3:, 3:]
    d2 = float(e @ np.linalg.solve(C, e))
    r = log_so3(M[:3, :3] @ Mt[:3, :3].T)  # rotation error, scene frame (left perturbation of cam_from_world^T)
    r_world = -Mt[:3, :3].T @ r  # world_from_cam error vector
    d2_rot = float(r_world @ np.linalg.solve(C6[:3, :3], r_world))
    return {"centre_error_m": float(np.linalg.norm(e)), "centre_error_enu_m": e.tolist(), "rotation_error_deg": rot,
            "mahalanobis2_centre": d2, "inside_95": d2 < CHI2_3_95, "mahalanobis2_rotation": d2_rot,
            "sigma_centre_enu_m": np.sqrt(np.diag(C)).tolist(),
            "sigma_rotation_deg": float(np.degrees(np.sqrt(np.linalg.eigvalsh(C6[:3, :3]).max())))}


def picks_through_api(client: Client, picks: list[dict], photo: str, sigma_m: float) -> dict:
    """The control points as the page builds them: each map position through ``/api/locate`` (from the map: the
    DEM's height), the photo pick, saved with ``/api/control_points``. Returns the saved document."""
    doc = {"crs": client.get("/api/control_points")["crs"], "points": []}
    for p in picks:
        st, loc = client.post("/api/locate", {"e": p["en"][0], "n": p["en"][1], "from": "map"})
        if st != 200:
            raise RuntimeError(f"locate {p['name']}: {loc}")
        doc["points"].append({"name": p["name"], "coords": [loc["e"], loc["n"], loc["dem_height_m"]],
                              "sigma_m": sigma_m, "pixels": {photo: [round(x, 2) for x in p["uv"]]}})
    st, res = client.post("/api/control_points", doc)
    if st != 200:
        raise RuntimeError(f"save: {res}")
    return doc


def _stats_row(errs: list[dict], reps: int, t0: float, **head) -> dict:
    """One row of figures over the repetitions ``errs`` (:func:`truth_errors` each, or ``{"error"}``)."""
    ok = [e for e in errs if "error" not in e]
    c = np.array([e["centre_error_m"] for e in ok])
    r = np.array([e["rotation_error_deg"] for e in ok])
    row = {**head, "reps": reps, "failed": len(errs) - len(ok),
           "centre_error_m": {"median": float(np.median(c)), "p90": float(np.quantile(c, 0.9)), "max": float(c.max())},
           "rotation_error_deg": {"median": float(np.median(r)), "p90": float(np.quantile(r, 0.9)),
                                  "max": float(r.max())},
           "within_1m": float(np.mean(c < 1.0)), "within_0.1deg": float(np.mean(r < 0.1)),
           "both_targets": float(np.mean((c < 1.0) & (r < 0.1))),
           "coverage_centre_95": float(np.mean([e["inside_95"] for e in ok])),
           "coverage_rotation_95": float(np.mean([e["mahalanobis2_rotation"] < CHI2_3_95 for e in ok])),
           "median_sigma_centre_enu_m": np.median([e["sigma_centre_enu_m"] for e in ok], axis=0).tolist(),
           "median_sigma_rotation_deg": float(np.median([e["sigma_rotation_deg"] for e in ok])),
           "seconds_per_rep": (time.perf_counter() - t0) / reps}
    print(json.dumps({k: v for k, v in row.items() if k not in ("landmarks", "distance_m")}))
    return row


def _repeat(client: Client, root: Path, photo: str, reps: int, make_picks) -> list[dict]:
    """``reps`` georefs through the picker's API, each from ``make_picks(seed)`` (saved by the caller's
    function); the truth errors of ``photo``'s camera."""
    errs = []
    for seed in range(reps):
        make_picks(seed)
        st, res = client.post("/api/georef", {})
        if st != 200:
            errs.append({"seed": seed, "error": res.get("error")})
            continue
        cams = json.loads((root / "out" / "georef" / "cameras.json").read_text())
        errs.append({"seed": seed, **truth_errors(root, photo, cams), "rms_px": res["rms_px"],
                     "n_flagged": sum(r["flagged"] for r in res["residuals"])})
    return errs


def state_pick_sigma(root: Path, noise_px: float) -> None:
    """The incident states its picks' pixel sigma (``georef.pick_sigma_px``), as a user who picks at that
    accuracy would."""
    toml = (root / "project.toml").read_text()
    if "[georef]" not in toml:
        (root / "project.toml").write_text(toml.rstrip() + f"\n\n[georef]\npick_sigma_px = {noise_px}\n")


def bench_synthetic(sample: Path, work: Path, reps: int, noise_px: float, noise_m: float, sweep: list[float],
                    photo: str = "pano_01.jpg") -> list[dict]:
    from workbench.picker import PickerServer

    root = single_photo_incident(sample, work / "synthetic", photo)
    state_pick_sigma(root, noise_px)
    marks = ground_landmarks(root, sample, photo)
    rows = []
    with PickerServer(root) as srv:
        client = Client(srv.url)
        for nm in [noise_m] + [x for x in sweep if x != noise_m]:
            t0 = time.perf_counter()
            errs = _repeat(client, root, photo, reps, lambda seed: picks_through_api(
                client, noisy_picks(marks, seed, noise_px, nm), photo, sigma_m=max(nm, 0.05)))
            rows.append(_stats_row(errs, reps, t0, set="synthetic", route="single", photo=photo,
                                   landmarks=[m["name"] for m in marks],
                                   distance_m=[round(m["distance_m"], 1) for m in marks], noise_px=noise_px,
                                   noise_m=nm, sigma_m_written=max(nm, 0.05)))
    return rows


def panorama_incident(sample: Path, dst: Path) -> Path:
    """A copy of a generated incident with its panorama photos (the panorama route), no ``camera.position_enu``
    and no control points, stitched (``workbench stitch``: the stitch stage's own panorama model)."""
    from workbench.pipeline import STAGES
    from workbench.project import Project
    from workbench.runner import Runner

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(sample.parent.parent / "terrain", dst / "terrain")
    base = dst / "projects" / sample.name
    shutil.copytree(sample, base, ignore=shutil.ignore_patterns("out", "control_points.json*", "multiview"))
    toml = (base / "project.toml").read_text()
    (base / "project.toml").write_text(re.sub(r"position_enu = \[[^\]]*\]\n?", "", toml))
    Runner(Project(base), STAGES).run(until="stitch")
    return base


def panorama_landmarks(root: Path, sample: Path, n: int = 6) -> list[dict]:
    """``n`` synthetic ground control points seen in the panorama photos, spread in azimuth around the camera:
    name, true E/N/h, true pixel in every panorama photo where the synthetic points say it is visible."""
    from workbench.core.camera import CameraIntrinsics
    from workbench.picker.map import MapService
    from workbench.project import Project

    project = Project(root)
    heights = MapService(project)
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    photos = {Path(p["photo"]).name: p for p in truth["photos"] if p["set"] == "panorama"}
    centre = np.asarray(next(iter(photos.values()))["center_enu"], float)
    out = []
    for q in json.loads((sample / "control_points.json").read_text())["points"]:
        E, N, h = q["coords"]
        seen = [k for k in q["pixels"] if k in photos]
        if not seen or abs(h - heights.height_at(E, N)) > 0.05:
            continue
        enu = project.frame.enu_from_crs(np.array([E, N, h]))
        pix = {}
        for k in seen:
            M = np.asarray(photos[k]["cam_from_world"], float)
            pix[k] = CameraIntrinsics(**photos[k]["intrinsics"]).project((M[:3, :3] @ enu + M[:3, 3])[None])[0].tolist()
        d = enu - centre
        out.append({"name": q["name"], "coords": [E, N, h], "pixels": pix, "distance_m": float(np.linalg.norm(d)),
                    "azimuth_deg": float(np.degrees(np.arctan2(d[0], d[1])) % 360.0)})
    az = np.array([o["azimuth_deg"] for o in out])
    sel = [int(np.argmin(az))]
    while len(sel) < min(n, len(out)):
        gap = np.min(np.abs((az[:, None] - az[sel][None] + 180.0) % 360.0 - 180.0), axis=1)
        sel.append(int(np.argmax(gap)))
    return [out[i] for i in sel]


def panorama_picks_through_api(client: Client, marks: list[dict], seed: int, noise_px: float, noise_m: float) -> None:
    """As :func:`picks_through_api`, each landmark picked in every panorama photo that shows it (own noise)."""
    rng = np.random.default_rng(seed)
    doc = {"crs": client.get("/api/control_points")["crs"], "points": []}
    for m in marks:
        en = np.asarray(m["coords"][:2]) + rng.normal(0, noise_m, 2)
        st, loc = client.post("/api/locate", {"e": float(en[0]), "n": float(en[1]), "from": "map"})
        if st != 200:
            raise RuntimeError(f"locate {m['name']}: {loc}")
        pix = {k: [round(float(x), 2) for x in np.asarray(uv) + rng.normal(0, noise_px, 2)]
               for k, uv in sorted(m["pixels"].items())}
        doc["points"].append({"name": m["name"], "coords": [loc["e"], loc["n"], loc["dem_height_m"]],
                              "sigma_m": max(noise_m, 0.05), "pixels": pix})
    st, res = client.post("/api/control_points", doc)
    if st != 200:
        raise RuntimeError(f"save: {res}")


def bench_panorama(sample: Path, work: Path, reps: int, noise_px: float, noise_m: float) -> list[dict]:
    """The panorama route: 6 landmarks spread in azimuth over the 4 stitched photos."""
    from workbench.picker import PickerServer

    root = panorama_incident(sample, work / "panorama")
    state_pick_sigma(root, noise_px)
    marks = panorama_landmarks(root, sample)
    photo = sorted({k for m in marks for k in m["pixels"]})[0]
    with PickerServer(root) as srv:
        client = Client(srv.url)
        t0 = time.perf_counter()
        errs = _repeat(client, root, photo, reps,
                       lambda seed: panorama_picks_through_api(client, marks, seed, noise_px, noise_m))
    return [_stats_row(errs, reps, t0, set="synthetic", route="panorama", photo=photo,
                       landmarks=[m["name"] for m in marks], distance_m=[round(m["distance_m"], 1) for m in marks],
                       azimuth_deg=[round(m["azimuth_deg"], 1) for m in marks],
                       n_picks=sum(len(m["pixels"]) for m in marks), noise_px=noise_px, noise_m=noise_m,
                       sigma_m_written=max(noise_m, 0.05))]


# ----------------------------------------------------------------------------------------------------------------
# Berlin: real photos, real GCPs typed in
# ----------------------------------------------------------------------------------------------------------------
def berlin_incident(dst: Path) -> tuple[Path, list[dict]]:
    """An incident of the 3 Berlin photos with OpenSfM's reconstruction as ``out/sfm/reconstruction.json``, and
    the GCPs as a person types them: (root, [{"name", "lat", "lon", "alt", "pixels"}])."""
    from scipy.spatial.transform import Rotation

    rec = json.loads((BERLIN / "reconstruction_example.json").read_text())[0]
    cam = next(iter(rec["cameras"].values()))
    w, h = cam["width"], cam["height"]
    size = max(w, h)
    ref = rec["reference_lla"]
    root = dst / "berlin"
    if root.exists():
        shutil.rmtree(root)
    (root / "photos" / "berlin").mkdir(parents=True)
    for p in sorted((BERLIN / "images").glob("*.jpg")):
        shutil.copy2(p, root / "photos" / "berlin" / p.name)
    (root / "project.toml").write_text(
        f'[incident]\nname = "OpenSfM Berlin (real photos, GCPs typed in the picker)"\ndate = 2024-01-01\n\n'
        f'[location]\nlat = {ref["latitude"]!r}\nlon = {ref["longitude"]!r}\nheight_m = {ref["altitude"]!r}\n'
        f'crs = "EPSG:25833"\n\n{CONSIST}\n[camera]\nsource = "sfm"\nphotos = "photos/berlin"\n')
    intr = {"width": w, "height": h, "fx": cam["focal"] * size, "fy": cam["focal"] * size, "cx": w / 2 - 0.5,
            "cy": h / 2 - 0.5, "skew": 0.0, "k1": cam["k1"], "k2": cam["k2"], "k3": 0.0, "p1": 0.0, "p2": 0.0}
    images = []
    for name, s in sorted(rec["shots"].items()):
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(s["rotation"]).as_matrix()
        M[:3, 3] = s["translation"]
        images.append({"name": name, "image": f"photos/berlin/{name}", "intrinsics": intr,
                       "cam_from_model": M.tolist()})
    (root / "out" / "sfm").mkdir(parents=True)
    (root / "out" / "sfm" / "reconstruction.json").write_text(json.dumps(
        {"images": images, "unregistered": [], "models": [], "intrinsics_source": "sfm",
         "note": "OpenSfM's reconstruction_example.json, converted (bench_picker_georef.py)"}))
    g = json.loads((BERLIN / "ground_control_points.json").read_text())
    gcps = [{"name": f"gcp_{p['id']}", "lat": p["position"]["latitude"], "lon": p["position"]["longitude"],
             "alt": p["position"]["altitude"],
             "pixels": {o["shot_id"]: [o["projection"][0] * size + w / 2 - 0.5,
                                       o["projection"][1] * size + h / 2 - 0.5] for o in p["observations"]}}
            for p in g["points"] if "position" in p]
    return root, gcps


def typed_gcps(client: Client, gcps: list[dict], sigma_m: float = 0.1) -> dict:
    """The GCPs typed as latitude/longitude (``/api/locate``, typed) with their own altitude, saved."""
    doc = {"crs": client.get("/api/control_points")["crs"], "points": []}
    for p in gcps:
        st, loc = client.post("/api/locate", {"lat": p["lat"], "lon": p["lon"], "from": "typed"})
        if st != 200:
            raise RuntimeError(f"locate {p['name']}: {loc}")
        doc["points"].append({"name": p["name"], "coords": [loc["e"], loc["n"], p["alt"]], "sigma_m": sigma_m,
                              "pixels": {k: [round(v[0], 3), round(v[1], 3)] for k, v in p["pixels"].items()}})
    st, res = client.post("/api/control_points", doc)
    if st != 200:
        raise RuntimeError(f"save: {res}")
    return doc


def bench_berlin(work: Path) -> dict:
    from workbench.files.control_points import load_control_points
    from workbench.files.reconstruction import read_reconstruction
    from workbench.georef.inputs import gps_enu, photos_by_name
    from workbench.georef.options import GeorefOptions
    from workbench.georef.similarity import solve_similarity
    from workbench.picker import PickerServer
    from workbench.project import Project

    root, gcps = berlin_incident(work)
    t0 = time.perf_counter()
    with PickerServer(root) as srv:
        client = Client(srv.url)
        typed_gcps(client, gcps)
        st, res = client.post("/api/georef", {})
    row: dict = {"set": "berlin", "georef_status": st, "seconds": time.perf_counter() - t0}
    if st == 200:
        row.update({"route": res["route"], "rms_px": res["rms_px"], "rms_m": res["rms_m"],
                    "residuals": [{k: r[k] for k in ("point", "view", "error_px", "error_m", "flagged")}
                                  for r in res["residuals"]], "warnings": res["warnings"]})
        g = json.loads((root / "out" / "georef" / "cameras.json").read_text())["georegistration"]
        row.update({k: g.get(k) for k in ("scale", "gps_rms_m", "n_points")})
    else:
        row["error"] = res.get("error")
    # today's figures: the similarity fitted directly to the picker's file (as tests/test_georef.py does)
    project = Project(root)
    cps = load_control_points(project.control_points_path, project.frame)
    views = list(read_reconstruction(project.reconstruction_path).main)
    photos = photos_by_name(project)
    gps = {v.name: gps_enu(project, photos[v.name]) for v in views}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        direct = solve_similarity(views, cps, gps_centres=gps, opts=GeorefOptions(), where="berlin")
    row["direct_similarity"] = {"scale": direct.stats["scale"], "rms_px": direct.stats["rms_px"],
                                "rms_m": direct.stats["rms_m"], "gps_rms_m": direct.stats["gps_rms_m"],
                                "residuals_px": [r["error_px"] for r in direct.residuals]}
    print(json.dumps(row))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sample", type=Path, default=None, help="a generated incident (workbench synth) to copy")
    ap.add_argument("--work", type=Path, default=REPO / "bench_out" / "picker_georef_work")
    ap.add_argument("--out", type=Path, default=REPO / "bench_out" / "picker_georef.json")
    ap.add_argument("--sets", default="synthetic,panorama,berlin")
    ap.add_argument("--reps", type=int, default=40)
    ap.add_argument("--noise-px", type=float, default=2.0)
    ap.add_argument("--noise-m", type=float, default=0.5)
    ap.add_argument("--sweep", default="", help="more map noises (m), comma-separated, e.g. 0.2,0.1,0.05")
    ap.add_argument("--photo", default="pano_01.jpg")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    warnings.simplefilter("ignore")
    a.work.mkdir(parents=True, exist_ok=True)
    out: dict = {"command": " ".join(sys.argv), "rows": []}
    sets = a.sets.split(",")
    if "synthetic" in sets:
        sample = a.sample
        if sample is None:
            sys.path.insert(0, str(REPO / "tests"))
            from conftest import SMALL_INCIDENT_OPTIONS

            from workbench.synth.control_points import write_control_points
            from workbench.synth.generate import SynthOptions, generate_incident

            sample = a.work / "sample" / "projects" / "spuyten-duyvil"
            if not (sample / "control_points.json").is_file():
                generate_incident(sample, SynthOptions(**SMALL_INCIDENT_OPTIONS))
                write_control_points(sample)
        sweep = [float(x) for x in a.sweep.split(",") if x.strip()]
        out["rows"] += bench_synthetic(sample.resolve(), a.work, a.reps, a.noise_px, a.noise_m, sweep, a.photo)
        if "panorama" in sets:
            out["rows"] += bench_panorama(sample.resolve(), a.work, a.reps, a.noise_px, a.noise_m)
    if "berlin" in sets and (BERLIN / "ground_control_points.json").is_file():
        out["rows"].append(bench_berlin(a.work))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1))
    print(f"saved {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
