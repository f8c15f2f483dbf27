"""The real-photo sample's targets (issue 16): one real telephoto photo, hand picks, focal unknown, no EXIF.

    .venv/bin/python scripts/bench_real_photo.py [--out bench_out/real_photo.json]

Runs ``projects/keikyu-n1000-photo`` (its photo copied from ``../shared/data``) twice in temporary copies:

* **chained**: as the incident says (the coupling held, 5 cm of slack): RMS reprojection residual, the solved
  focal and its field of view, each car's RMS;
* **unlinked**: the same picks with the coupling declared broken and no link (``slack_broken_m`` absent): each
  car placed by its own picks (car 2, one side only, through the focal car 1 pins). The two cars were coupled,
  so the truth is a zero coupler gap, and, on straight track only, zero relative heading, pitch and roll: the
  script prints the gap and the relative angles, and whether zero lies inside their 95 % regions (the two cars'
  ``covariance_pose`` taken as independent, to first order: the errors they share, the focal's and the
  levelling's, cancel in these differences, so the regions are, if anything, too wide); then the same regions
  with the types' dimensional doubt added (``DIMENSION_DOUBT``: each uncertain dimension moved by its 1 sigma in
  a copy of the type files, the pair solved again, the changes taken as a first-order covariance).
* **track check** (chained rows with straight edges in ``scripts/bench_real_photo_lines.json``): is the track
  straight in the photo at all? Each car's axis from the vanishing point of two straight edges along its side
  (``workbench.core.vanishing``; no carriage dimension), the turn from each car to the next and a chi-square for
  "all zero"; and the adjacent track's rails put on car 1's rail plane, with the curvature they show (their
  plan/profile split depends on that plane's pitch: printed at +-1 sigma of it). On the sample the cars turn
  car by car: the issue's "relative angles 0" holds on straight track only, which this photo is not.

``--screen``: no solve; the photos of ``scripts/bench_real_photo_screen.json`` screened for a straight-track row
before any pick (each car's side vanishing point against the next car's, ``workbench.core.vanishing.
screen_straight_track``; a focal-free chi-square, 2 dof), with why the library's types could or could not give each
6 picks a car, and the photos not screened with the reason. Writes ``<out>_screen.json``.

``--rows sample,045`` (both by default): the second row is another photo of coupled cars of the class,
``1024px-Keikyu_1000_series_EMU_(II)_045.JPG`` (Wikimedia Commons, CC BY-SA, ../shared/data/SOURCES.md; set 1425, a
later lot than the sample's, the cars' right side, no EXIF), with the sample's settings and consist and its own
picks, ``scripts/bench_real_photo_045.json`` (made in ``workbench pick``, 10 of 11 from two edges). Read it with
two caveats: car 1's ``front.corner_setback_m`` in the type was measured on these same picks (``workbench
type-fit``), so car 1's fit there is not a check; and car 2 has 4 picks (its right side's corners: the type's door
points are on its left side), under the issue's 6.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from workbench.core.geometry import skew  # noqa: E402
from workbench.pipeline import STAGES  # noqa: E402
from workbench.project import Project  # noqa: E402
from workbench.runner import Runner  # noqa: E402

SAMPLE = ROOT / "projects" / "keikyu-n1000-photo"
TRAINS = "../shared/data/trains/photos_wikimedia_japan_emu/keikyu-1000/"
# row -> (its picks, its photos relative to the repository); the settings and the consist are the sample's
ROWS = {
    "sample": (SAMPLE / "correspondences.json",
               [ln.strip() for ln in (SAMPLE / "photos.txt").read_text().splitlines()
                if ln.strip() and not ln.startswith("#")]),
    "045": (ROOT / "scripts" / "bench_real_photo_045.json", [TRAINS + "1024px-Keikyu_1000_series_EMU_(II)_045.JPG"]),
}
CHI2_3_95 = 7.814727903251178
LINES = ROOT / "scripts" / "bench_real_photo_lines.json"  # straight edges and rails per row: the track check


def _copy(tmp: Path, unlinked: bool, row: str = "sample") -> Project:
    picks, photos = ROWS[row]
    root = tmp / row / ("unlinked" if unlinked else "chained")
    (root / "photos").mkdir(parents=True)
    shutil.copy(picks, root / "correspondences.json")
    toml = (SAMPLE / "project.toml").read_text()
    if unlinked:
        toml = toml.replace('coupling_to_next = "held"', 'coupling_to_next = "broken"')
    (root / "project.toml").write_text(toml)
    for line in photos:
        src = ROOT / line
        if not src.is_file():
            sys.exit(f"error: {src} not found: this benchmark needs ../shared/data beside the repository")
        shutil.copy(src, root / "photos" / src.name)
    return Project(root)


def _run(project: Project) -> dict:
    t0 = time.perf_counter()
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    sol = project.solution("bench")
    d = sol.doc
    (view, f), = d["focal_px"].items()
    w = project.cameras()[view].intrinsics.width
    out = {"time_s": round(time.perf_counter() - t0, 2), "focal_px": f,
           "sigma_focal_px": (d.get("sigma_focal_px") or {}).get(view),
           "hfov_deg": math.degrees(2 * math.atan(0.5 * w / f)), "rms_px": d["residual_rms_px"]["measured"],
           "n_picks": d["residual_rms_px"]["n_measured"], "status": [c.status for c in sol.carriages],
           "cars": {c.number: {"status": c.status, "rms_px": c.record.get("rms_px"),
                               "hpr_deg": [c.record.get(k) for k in ("heading_deg", "pitch_deg", "roll_deg")],
                               "ci95_hpr_deg": c.record.get("ci95_hpr_deg"),
                               "body_centre_m": c.record.get("body_centre_enu"),
                               "ci95_body_centre_m": c.record.get("ci95_body_centre_m")} for c in sol.carriages}}
    if len(sol.posed) == 2:
        gap, Cg, rel, Cr = _pair_vectors(project, sol)
        out["pair"] = {
            "coupler_gap_m": float(np.linalg.norm(gap)),
            "gap_ci95_m_per_axis": (1.959964 * np.sqrt(np.diag(Cg))).tolist(),  # along car 1's x, y, z
            "gap_zero_inside_95": bool(gap @ np.linalg.solve(Cg, gap) < CHI2_3_95),
            "relative_roll_pitch_yaw_deg": np.degrees(rel).tolist(),  # about car 1's x (roll), y, z (heading)
            "relative_ci95_deg": np.degrees(1.959964 * np.sqrt(np.diag(Cr))).tolist(),
            "relative_zero_inside_95": bool(rel @ np.linalg.solve(Cr, rel) < CHI2_3_95),
            "gap_vector_m": gap.tolist(), "relative_rotvec_rad": rel.tolist(),
            "gap_covariance_m2": Cg.tolist(), "relative_covariance_rad2": Cr.tolist(),
        }
    return out


def _pair_vectors(project: Project, sol) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The two cars' coupler gap (car 1's rear coupler face less car 2's front one) and car 2's rotation in car
    1's frame (a rotation vector, rad), both in car 1's axes, with their (3, 3) covariances from the two cars'
    ``covariance_pose`` (taken as independent: see the module's docstring)."""
    types = project.carriage_types()
    a, b = sol.posed
    Ma, Mb = a.world_from_carriage, b.world_from_carriage
    Ca, Cb = np.asarray(a.record["covariance_pose"], float), np.asarray(b.record["covariance_pose"], float)
    pa = Ma[:3, :3] @ types[a.number].coupler_rear
    pb = Mb[:3, :3] @ types[b.number].coupler_front
    R1 = Ma[:3, :3]
    gap = R1.T @ ((pa + Ma[:3, 3]) - (pb + Mb[:3, 3]))
    Ja = np.hstack([-skew(pa), np.eye(3)])
    Jb = np.hstack([-skew(pb), np.eye(3)])
    Cg = R1.T @ (Ja @ Ca @ Ja.T + Jb @ Cb @ Jb.T) @ R1
    rel = Rotation.from_matrix(R1.T @ Mb[:3, :3]).as_rotvec()  # car 2 in car 1's frame
    Cr = R1.T @ (Ca[:3, :3] + Cb[:3, :3]) @ R1
    return gap, Cg, rel, Cr


TYPES = ROOT / "workbench" / "rolling_stock" / "types"
PAIR_TYPES = ("keikyu-n1000", "keikyu-n1000-m")  # the consist's two types (the sample's and row 045's)


def _bump(text: str, key: str, delta: float) -> str:
    """The type file's first ``key = number`` line (its [dimensions], [profile] or [front] value) moved by delta."""
    m = re.search(rf"^({re.escape(key)}\s*=\s*)([-0-9.]+)", text, flags=re.M)
    if m is None:
        raise KeyError(key)
    return text[:m.start(2)] + f"{float(m.group(2)) + delta:.4f}" + text[m.end(2):]


def _bump_xyz(text: str, axis: int, value: float, delta: float) -> str:
    """Every ``xyz = [x, y, z]`` marked point whose coordinate ``axis`` is ``value`` moved by delta along it."""
    def move(m: re.Match) -> str:
        v = [float(t) for t in m.group(1).split(",")]
        if abs(v[axis] - value) < 1e-9:
            v[axis] += delta
        return "xyz = [" + ", ".join(f"{t:.4f}" for t in v) + "]"
    return re.sub(r"xyz = \[([^\]]*)\]", move, text)


# The types' dimensional doubt, 1 sigma, m (the type files' headers give the figures behind each): (what, sigma,
# the edit of (car 1's, car 2's) type file for a change d). Quantities of the class move on both cars together.
DIMENSION_DOUBT = [
    ("width (both cars; published 2.798 body, 2.836 over fittings; type-fit 2.772 +- 0.029)", 0.03,
     lambda t1, t2, d: (_bump(t1, "width_m", d), _bump_xyz(_bump(t2, "width_m", d), 1, 1.40, d / 2))),
    ("eave above the body bottom (both cars; measured +-5 px: +-0.04)", 0.04,
     lambda t1, t2, d: (_bump(t1, "eave_height_m", d), _bump_xyz(_bump(t2, "eave_height_m", d), 2, 3.36, d))),
    ("body bottom above the rail, all measured heights with it (both cars; not measured)", 0.03,
     lambda t1, t2, d: (_bump(_bump(_bump(t1, "body_bottom_m", d), "eave_height_m", d), "nose_base_height_m", d),
                        _bump_xyz(_bump_xyz(_bump(_bump(t2, "body_bottom_m", d), "eave_height_m", d),
                                            2, 0.95, d), 2, 3.36, d))),
    ("body length (both cars; 'about 17,500 mm')", 0.05,
     lambda t1, t2, d: (_bump(t1, "body_length_m", d), _bump(t2, "body_length_m", d))),
    ("cab front's nose base (car 1; measured +-5 px: +-0.04)", 0.04,
     lambda t1, t2, d: (_bump(t1, "nose_base_height_m", d), t2)),
    ("cab front's corner setback (car 1; type-fit 0.444 +- 0.041)", 0.041,
     lambda t1, t2, d: (_bump(t1, "corner_setback_m", d), t2)),
    ("middle door's rear edge along the car (car 2; the door centred: an estimate)", 0.10,
     lambda t1, t2, d: (t1, _bump_xyz(t2, 0, -0.65, d))),
]


def _dimension_doubt(tmp: Path, row: str, base: dict) -> dict:
    """The unlinked pair's gap and relative rotation moved by each DIMENSION_DOUBT term at +1 sigma (a solve on
    a copy whose ``rolling_stock/`` holds the edited types), their first-order covariance, and the pair's
    regions with it added to the picks' (``base``: the unlinked run's ``pair``)."""
    texts = [(TYPES / f"{t}.toml").read_text() for t in PAIR_TYPES]
    g0, r0 = np.asarray(base["gap_vector_m"]), np.asarray(base["relative_rotvec_rad"])
    J, terms = [], []
    for i, (what, sigma, edit) in enumerate(DIMENSION_DOUBT):
        project = _copy(tmp / f"doubt{i}", True, row)
        (project.root / "rolling_stock").mkdir()
        for tid, text in zip(PAIR_TYPES, edit(*texts, sigma)):
            (project.root / "rolling_stock" / f"{tid}.toml").write_text(text)
        Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
        gap, _, rel, _ = _pair_vectors(project, project.solution("bench"))
        J.append(np.concatenate([gap - g0, rel - r0]))
        terms.append({"what": what, "sigma_m": sigma, "gap_change_m": (gap - g0).tolist(),
                      "yaw_change_deg": math.degrees(rel[2] - r0[2])})
    J = np.array(J).T  # (6, terms): each column one term's 1-sigma change
    Cg = np.asarray(base["gap_covariance_m2"]) + J[:3] @ J[:3].T
    Cr = np.asarray(base["relative_covariance_rad2"]) + J[3:] @ J[3:].T
    return {"terms": terms,
            "gap_ci95_m_per_axis": (1.959964 * np.sqrt(np.diag(Cg))).tolist(),
            "gap_chi2": float(g0 @ np.linalg.solve(Cg, g0)),
            "relative_ci95_deg": np.degrees(1.959964 * np.sqrt(np.diag(Cr))).tolist(),
            "relative_chi2": float(r0 @ np.linalg.solve(Cr, r0)),
            "relative_chi2_picks_only": float(r0 @ np.linalg.solve(np.asarray(base["relative_covariance_rad2"]), r0))}


def _plan_curvature(points_carriage: np.ndarray) -> tuple[float, float]:
    """Curvature (1/m, positive turning left going forward) of points (n, 3) in a car's frame, fitted as
    y = a + b x + k x^2 / 2 in its rail plane, and its 1-sigma (one independent point in CORRELATION_PX)."""
    from workbench.core.vanishing import CORRELATION_PX

    x, y = points_carriage[:, 0], points_carriage[:, 1]
    A = np.c_[0.5 * x ** 2, x, np.ones_like(x)]
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    var = np.var(y - A @ coef) * CORRELATION_PX
    return float(coef[0]), float(np.sqrt(np.linalg.inv(A.T @ A)[0, 0] * var))


def _track_check(project: Project, row: str) -> dict | None:
    """Is the track straight where the photo was taken? Two measurements that use no carriage dimension:

    * each car's axis from its side's straight edges (their vanishing point, ``workbench.core.vanishing``), and
      the turn about the vertical from each car to the next (straight track: zero, to the fit's sigma);
    * the adjacent track's rails, their image points put on the rail plane of car 1 (the chained solve's camera
      and car 1's pose) and fitted with a constant curvature (a turn over one car's 18 m = curvature x 18 m).
    """
    spec = json.loads(LINES.read_text()).get(row)
    if spec is None:
        return None
    from PIL import Image

    from workbench.core.vanishing import edge_points, fit_image_edge, relative_yaw_deg, vanishing_point

    sol = project.solution("bench")
    view = project.cameras()[spec["photo"]]
    intr = view.intrinsics.with_focal(sol.focal_px[spec["photo"]])
    cam_from_world = sol.cam_from_world(view.cam_from_world)
    gray = np.asarray(Image.open(project.root / "photos" / spec["photo"]).convert("RGB"), float)[..., 1]
    up_cam = cam_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    vps = {}
    for car, lines in spec["cars"].items():
        a, b = (fit_image_edge(gray, *lines[k]) for k in ("body_bottom", "band_bottom"))
        vps[car] = vanishing_point(a, b)
    cars = sorted(vps, key=int)
    turns = {f"{p}-{q}": relative_yaw_deg(intr.K, up_cam, *vps[p], *vps[q]) for p, q in zip(cars, cars[1:])}
    out = {"vanishing_points_uv": {c: vps[c][0].tolist() for c in cars},
           "turn_deg": {k: [y, s] for k, (y, s) in turns.items()},
           "chi2_straight": float(sum((y / s) ** 2 for y, s in turns.values())), "dof": len(turns)}
    car1 = sol.posed[0]
    carriage_from_cam = np.linalg.inv(car1.world_from_carriage) @ np.linalg.inv(cam_from_world)
    sigma_pitch = math.radians(car1.record["sigma_hpr_deg"][1])
    rails = {}
    for name, poly in spec["rails"].items():
        uv = np.vstack([edge_points(gray, p, q) for p, q in zip(poly, poly[1:])])
        rails[name] = {"n_points": len(uv)}
        for key, pitch in (("", 0.0), ("_pitch_minus_sigma", -sigma_pitch), ("_pitch_plus_sigma", sigma_pitch)):
            tilt = Rotation.from_rotvec([0.0, pitch, 0.0]).as_matrix()  # the rail plane turned about car 1's y
            rays = tilt @ carriage_from_cam[:3, :3] @ intr.rays(uv).T
            o = tilt @ carriage_from_cam[:3, 3]
            pts = o + ((0.0 - o[2]) / rays[2])[:, None] * rays.T  # on the rail plane, z = 0 in car 1's frame
            k, sk = _plan_curvature(pts)
            # the turn of a car 18 m behind from the one ahead (the sign of turn_deg above): -18 m x curvature
            rails[name][f"next_car_turn_deg{key}"] = -math.degrees(18.0 * k)
            if not key:
                rails[name].update({"curvature_per_km": 1e3 * k, "sigma_per_km": 1e3 * sk,
                                    "x_range_m": [float(pts[:, 0].min()), float(pts[:, 0].max())],
                                    "y_mean_m": float(pts[:, 1].mean())})
    out["rails"] = rails
    out["car1_sigma_pitch_deg"] = math.degrees(sigma_pitch)
    return out


SCREEN = ROOT / "scripts" / "bench_real_photo_screen.json"  # photos screened for a straight-track row
PHOTOS = ROOT.parent / "shared" / "data" / "trains" / "photos_wikimedia_japan_emu"


def screen(path: Path = SCREEN) -> dict:
    """Every photo in the screening file (SCREEN): ``workbench.core.vanishing.screen_straight_track`` and whether
    the library's types could give it 6 picks a car (the file's ``eligible``)."""
    from PIL import Image

    from workbench.core.vanishing import screen_straight_track

    spec = json.loads(path.read_text())
    res = {}
    for name, entry in spec["photos"].items():
        src = PHOTOS / entry["folder"] / name
        if not src.is_file():
            sys.exit(f"error: {src} not found: the screening needs ../shared/data beside the repository")
        rgb = np.asarray(Image.open(src).convert("RGB"), float)
        r = res[name] = {"eligible": entry["eligible"], **screen_straight_track(rgb, entry["cars"])}
        # the photo's own error scale: the cars' halves should agree (chi-square 2 on average); where they agree
        # worse, the edges are less straight than the noise model, and the car-to-car chi-squares are scaled down
        halves = [c["halves_chi2"] for c in r["cars"].values() if c["halves_chi2"] is not None]
        r["halves_scale"] = max(1.0, float(np.mean(halves)) / 2.0) if halves else None
        for pair in r["pairs"].values():
            pair["chi2_scaled"] = pair["chi2"] / r["halves_scale"] if halves else None
    return {"photos": res, "not_screened": spec.get("not_screened", {})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "real_photo.json")
    ap.add_argument("--rows", default="sample,045", help="comma-separated: " + ", ".join(ROWS))
    ap.add_argument("--screen", action="store_true",
                    help="only screen the photos of scripts/bench_real_photo_screen.json for straight track")
    a = ap.parse_args()
    if a.screen:
        res = screen()
        for name, r in res["photos"].items():
            print(f"{name}:")
            for car, c in r["cars"].items():
                print(f"    car {car}: vanishing point " + ", ".join(f"{x:.1f}" for x in c["vanishing_point_uv"])
                      + " px (sigma " + ", ".join(f"{x:.1f}" for x in c["sigma_uv"]) + "); edges "
                      + ", ".join(f"{n} {e['n_points']} points RMS {e['rms_px']:.2f} px"
                                  for n, e in c["edges"].items()))
            print("    each car's front half against its rear half (one rigid body): chi-square "
                  + ", ".join(f"car {c} " + ("-" if v["halves_chi2"] is None else f"{v['halves_chi2']:.1f}")
                              for c, v in r["cars"].items())
                  + f": the photo's error scale x{r['halves_scale'] or float('nan'):.1f} on the chi-squares below")
            for pair, p in r["pairs"].items():
                scaled = p["chi2_scaled"] if p["chi2_scaled"] is not None else p["chi2"]
                verdict = "NOT straight" if scaled > chi2.ppf(0.95, 2) else "consistent with straight"
                print(f"    cars {pair}: vanishing points apart by "
                      + ", ".join(f"{x:+.1f}" for x in p["vp_difference_uv"])
                      + f" px, chi-square {p['chi2']:.1f}, scaled {scaled:.1f} (2 dof, 95 %: {chi2.ppf(0.95, 2):.2f}): "
                      f"{verdict}; turn at "
                      "an assumed hfov 10 / 20 / 30 deg (level camera): "
                      + " / ".join(f"{y:+.2f} +- {s:.2f}" for y, s in p["turn_deg_at_hfov"].values()) + " deg")
            print(f"    types: {r['eligible']}")
        for name, why in res["not_screened"].items():
            print(f"{name}: not screened: {why}")
        out = a.out.with_name(a.out.stem + "_screen.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=1))
        print(f"saved {out}")
        return
    rows = [r for r in a.rows.split(",") if r]
    if not rows or set(rows) - set(ROWS):
        sys.exit(f"error: --rows {a.rows!r}: give some of {', '.join(ROWS)}")
    logging.disable(logging.WARNING)
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for row in rows:
            for unlinked in (False, True):
                project = _copy(Path(tmp), unlinked, row)
                res[f"{row} {'unlinked' if unlinked else 'chained'}"] = r = _run(project)
                if not unlinked:
                    r["track"] = _track_check(project, row)
                elif "pair" in r:
                    r["dimension_doubt"] = _dimension_doubt(Path(tmp) / row, row, r["pair"])
    for k, r in res.items():
        print(f"{k}: {r['n_picks']} picks, RMS {r['rms_px']:.2f} px, focal {r['focal_px']:.0f} px "
              f"(sigma {r['sigma_focal_px'] or float('nan'):.0f}, hfov {r['hfov_deg']:.2f} deg), cars {r['status']}, "
              f"{r['time_s']} s")
        for n, c in r["cars"].items():
            print(f"    car {n}: RMS {c['rms_px']:.2f} px, heading/pitch/roll "
                  + " / ".join(f"{x:.2f}" for x in c["hpr_deg"]) + " deg, 95 % "
                  + " / ".join(f"{x:.2f}" for x in c["ci95_hpr_deg"]))
        p = r.get("pair")
        if p:
            print(f"    coupler gap {p['coupler_gap_m']:.3f} m (95 % per axis "
                  + ", ".join(f"{x:.2f}" for x in p["gap_ci95_m_per_axis"])
                  + f" m; zero inside: {p['gap_zero_inside_95']}); car 2 relative to car 1: roll/pitch/yaw "
                  + " / ".join(f"{x:.2f}" for x in p["relative_roll_pitch_yaw_deg"]) + " deg (95 % "
                  + " / ".join(f"{x:.2f}" for x in p["relative_ci95_deg"])
                  + f"; zero inside: {p['relative_zero_inside_95']})")
        dd = r.get("dimension_doubt")
        if dd:
            print(f"    with the types' dimensional doubt ({len(dd['terms'])} terms, first order) added: gap 95 % per "
                  "axis " + ", ".join(f"{x:.2f}" for x in dd["gap_ci95_m_per_axis"])
                  + f" m (chi-square {dd['gap_chi2']:.2f}); relative roll/pitch/yaw 95 % "
                  + " / ".join(f"{x:.2f}" for x in dd["relative_ci95_deg"])
                  + f" deg, chi-square {dd['relative_chi2']:.1f} (picks alone {dd['relative_chi2_picks_only']:.1f}; "
                  f"95 %: {CHI2_3_95:.1f})")
            for term in dd["terms"]:
                print(f"      {term['what']}, +{term['sigma_m']} m: gap moves "
                      + ", ".join(f"{x:+.3f}" for x in term["gap_change_m"])
                      + f" m, yaw {term['yaw_change_deg']:+.3f} deg")
        t = r.get("track")
        if t:
            print("    track check (no carriage dimension used): each car's turn from the one ahead, from its side's "
                  "vanishing point: " + ", ".join(f"cars {k} {y:+.2f} +- {s:.2f} deg" for k, (y, s) in
                                                   t["turn_deg"].items())
                  + f"; straight track: chi-square {t['chi2_straight']:.1f} ({t['dof']} dof, 95 %: "
                  f"{chi2.ppf(0.95, t['dof']):.1f})"
                  + (": NOT straight, so zero relative angles are not this photo's truth"
                     if t["chi2_straight"] > chi2.ppf(0.95, t["dof"]) else ""))
            for n, rl in t["rails"].items():
                print(f"    {n}: plan curvature {rl['curvature_per_km']:+.3f} +- {rl['sigma_per_km']:.3f} per km "
                      f"on car 1's rail plane (x {rl['x_range_m'][0]:.0f} to {rl['x_range_m'][1]:.0f} m, y "
                      f"{rl['y_mean_m']:.2f} m, {rl['n_points']} points): a car 18 m behind turned "
                      f"{rl['next_car_turn_deg']:+.2f} deg; with that plane pitched -/+ car 1's pitch sigma "
                      f"({t['car1_sigma_pitch_deg']:.2f} deg): {rl['next_car_turn_deg_pitch_minus_sigma']:+.2f} / "
                      f"{rl['next_car_turn_deg_pitch_plus_sigma']:+.2f} deg (a grazing view: plan and profile mix)")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print(f"saved {a.out}")


if __name__ == "__main__":
    main()
