"""The ``report`` stage: the incident report as HTML and PDF, built only from files the stages wrote.

Reads ``out/solve/solution.json``, ``out/render/renders.json`` and the renders, every ``out/<stage>/stats.json``,
``out/state.json`` (provenance: input hashes, settings hashes, run times), ``cameras.json`` and the photos.
Writes ``out/report/report.html`` (next to its figures in ``out/report/figures/``; it links the renders in
``out/render/`` by relative paths, so keep ``out/`` together), ``out/report/report.pdf`` (A4, WeasyPrint) and
``out/report/report.json`` (the figures the report states, for checking and re-use).

The PDF engine is WeasyPrint: it lays out the same HTML and CSS as the on-screen report (CSS paged media:
running header with the incident name and date, "page N of M" footers, a "synthetic incident" banner,
tables that repeat their header rows across pages), needs only Pango from the system (no browser), and is
deterministic.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata as _md
import json
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..core.io import atomic_write, read_json
from ..core.stage_api import Progress, StageResult
from ..errors import InputError, StageError
from ..files.solution import doubts_of
from ..project import Project
from .beside import load_pdf_engine, run_beside
from .scene import car_color
from .calibration_notes import interval_scope, number_text as _f
from .track_table import track_table

log = logging.getLogger(__name__)

TEMPLATES = Path(__file__).parent / "templates"
SOFTWARE = ("train-wreck-workbench", "numpy", "scipy", "open3d", "pycolmap", "opencv-python-headless", "pyproj",
            "rasterio", "trimesh", "matplotlib", "weasyprint", "pydantic")
RESIDUAL_ARROW_SCALE = 20.0  # residual arrows are drawn this many times their length


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version(), "platform": platform.platform(terse=True)}
    for name in SOFTWARE:
        try:
            out[name] = _md.version(name)
        except _md.PackageNotFoundError:
            out[name] = "not installed"
    return out


# ----------------------------------------------------------------------------------------------------------
# Figures
# ----------------------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.family": "DejaVu Sans", "font.size": 8, "axes.titlesize": 9})
    return plt


def _save(fig, path: Path, dpi: int = 150) -> Path:
    kw = {"pil_kwargs": {"quality": 90}} if path.suffix.lower() in (".jpg", ".jpeg") else {}
    atomic_write(path, lambda p: fig.savefig(p, dpi=dpi, bbox_inches="tight", pad_inches=0.04, **kw))
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _view_points(cars: list[dict], view: str) -> list[tuple[dict, np.ndarray, np.ndarray]]:
    """[(carriage record, picked pixels (n, 2), residuals (n, 2))] of one view of the solution."""
    out = []
    for c in cars:
        obs = (c.get("observations") or {}).get(view) or {}
        res = (c.get("residuals_px") or {}).get(view) or {}
        if obs:
            out.append((c, np.array([obs[k] for k in obs], float).reshape(-1, 2),
                        np.array([res.get(k, [0.0, 0.0]) for k in obs], float).reshape(-1, 2)))
    return out


def points_figure(path: Path, img: np.ndarray, title: str, items: list[tuple[dict, np.ndarray, np.ndarray]],
                  max_width_px: int = 1400, min_width_frac: float = 0.45) -> dict:
    """``img`` (h, w, 3) with each marked point drawn where it was picked (circle, the carriage's colour) and its
    reprojection residual as an arrow (``RESIDUAL_ARROW_SCALE`` x its length), cropped around the points.
    ``items``: [(carriage record, pixels (n, 2), residuals (n, 2))]. Returns the count and RMS."""
    from PIL import Image

    plt = _plt()
    H, W = img.shape[:2]
    pts = np.vstack([uv for _c, uv, _r in items]) if items else np.zeros((0, 2))
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = 0.06 * W
        x0, x1 = lo[0] - pad, hi[0] + pad
        y0, y1 = lo[1] - pad, hi[1] + pad
        min_w = min_width_frac * W
        if x1 - x0 < min_w:
            x0, x1 = 0.5 * (x0 + x1) - min_w / 2, 0.5 * (x0 + x1) + min_w / 2
        min_h = 0.4 * (x1 - x0)
        if y1 - y0 < min_h:
            y0, y1 = 0.5 * (y0 + y1) - min_h / 2, 0.5 * (y0 + y1) + min_h / 2
        x0, x1 = max(x0, -0.5), min(x1, W - 0.5)
        y0, y1 = max(y0, -0.5), min(y1, H - 0.5)
    else:
        x0, x1, y0, y1 = -0.5, W - 0.5, -0.5, H - 0.5
    ci = (slice(int(max(y0, 0)), int(np.ceil(y1)) + 1), slice(int(max(x0, 0)), int(np.ceil(x1)) + 1))
    sub = img[ci]
    if sub.shape[1] > max_width_px:
        sub = np.asarray(Image.fromarray(sub).resize((max_width_px, round(sub.shape[0] * max_width_px / sub.shape[1])),
                                                     Image.Resampling.LANCZOS))
    fig, ax = plt.subplots(figsize=(7.2, min(7.2 * (y1 - y0) / (x1 - x0), 6.0)), dpi=150)
    ax.imshow(sub, extent=(ci[1].start - 0.5, ci[1].stop - 0.5, ci[0].stop - 0.5, ci[0].start - 0.5))
    n, sq = 0, 0.0
    for c, uv, r in items:
        ok = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(r), axis=1)
        uv, r = uv[ok], r[ok]
        if not len(uv):
            continue
        col = np.array(car_color(int(c.get("index", 0)))) / 255.0
        n += len(uv)
        sq += float(np.sum(r ** 2))
        ax.scatter(uv[:, 0], uv[:, 1], s=26, facecolors="none", edgecolors=[col], linewidths=1.2, zorder=3)
        ax.quiver(uv[:, 0], uv[:, 1], r[:, 0], r[:, 1], angles="xy", scale_units="xy",
                  scale=1.0 / RESIDUAL_ARROW_SCALE, color=[col], width=0.004, zorder=4)
        ax.annotate(str(c.get("number")), uv.mean(axis=0), xytext=(0, -16), textcoords="offset points", ha="center",
                    fontsize=7, fontweight="bold", color=col,
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=col, lw=0.8, alpha=0.9))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_axis_off()
    cropped = (x1 - x0) < W - 1 or (y1 - y0) < H - 1
    ax.set_title(f"{title}{' (detail)' if cropped else ''}: {n} marked points (circles); reprojection residuals "
                 f"drawn {RESIDUAL_ARROW_SCALE:g}x", fontsize=8)
    _save(fig, path)
    return {"n_points": n, "rms_px": math.sqrt(sq / n) if n else None}


def _rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def observations_figure(path: Path, photo_path: Path, view: str, cars: list[dict]) -> dict:
    """One photo with its marked points and residuals (see :func:`points_figure`)."""
    return {"view": view, **points_figure(path, _rgb(photo_path), view, _view_points(cars, view))}


def panorama_figure(path: Path, pano_path: Path, model_path: Path, cars: list[dict]) -> dict | None:
    """The stitched panorama with every photo's marked points and residuals carried into it through the panorama
    model (``workbench.core.panorama``); None when the model does not know the views."""
    from ..core.panorama import PanoramaModel

    try:
        model = PanoramaModel.from_dict(json.loads(model_path.read_text(encoding="utf-8")))
    except (ValueError, KeyError, TypeError, OSError) as exc:
        log.warning("report: %s cannot be read as a panorama model (%s); the panorama is shown without points",
                    model_path, exc)
        return None
    views = sorted({v for c in cars for v in (c.get("observations") or {})})
    per_car: dict[str, tuple[dict, list, list]] = {}
    for v in views:
        items = _view_points(cars, v)
        if v == "panorama":
            mapped = [(c, uv, r) for c, uv, r in items]
        else:
            try:
                k = model.source_index(v)
            except KeyError:
                continue
            mapped = []
            for c, uv, r in items:
                a = model.from_source(k, uv)
                b = model.from_source(k, uv + r)  # the residual's end, carried into the panorama
                mapped.append((c, a, b - a))
        for c, uv, r in mapped:
            entry = per_car.setdefault(str(c.get("number")), (c, [], []))
            entry[1].append(uv)
            entry[2].append(r)
    if not per_car:
        return None
    items = [(c, np.vstack(u), np.vstack(r)) for c, u, r in per_car.values()]
    return {"view": "panorama", **points_figure(path, _rgb(pano_path), "stitched panorama", items,
                                                 max_width_px=1800, min_width_frac=0.6)}


def residual_figure(path: Path, cars: list[dict], sigma_px: float | None) -> dict:
    """Two panels: every residual (du, dv) coloured by carriage with the 95% circle of the pixel noise, and the
    RMS residual of each carriage."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(7.2, 3.1), dpi=150, gridspec_kw={"width_ratios": [1, 1.35]})
    allr = []
    names, rms, cols = [], [], []
    for c in cars:
        r = np.array([v for d in (c.get("residuals_px") or {}).values() for v in d.values()], float).reshape(-1, 2)
        col = np.array(car_color(int(c.get("index", 0)))) / 255.0
        if len(r):
            a1.scatter(r[:, 0], r[:, 1], s=9, color=col, label=str(c.get("number")), alpha=0.85)
            allr.append(r)
        names.append(str(c.get("number")))
        rms.append(float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else 0.0)
        cols.append(col)
    R = np.vstack(allr) if allr else np.zeros((0, 2))
    lim = max(float(np.max(np.abs(R))) * 1.15 if len(R) else 1.0, 2.5 * (sigma_px or 1.0))
    if sigma_px:
        t = np.linspace(0, 2 * np.pi, 200)
        k = math.sqrt(-2.0 * math.log(0.05))  # 95% radius of a 2-D isotropic normal
        a1.plot(k * sigma_px * np.cos(t), k * sigma_px * np.sin(t), "k--", lw=0.8, label=f"95% ({sigma_px:g} px σ)")
    a1.axhline(0, color="0.6", lw=0.5)
    a1.axvline(0, color="0.6", lw=0.5)
    a1.set_xlim(-lim, lim)
    a1.set_ylim(lim, -lim)
    a1.set_aspect("equal")
    a1.set_xlabel("residual u (px)")
    a1.set_ylabel("residual v (px)")
    a1.set_title("Reprojection residuals")
    a1.legend(fontsize=6, loc="upper right", ncol=2, framealpha=0.8)
    y = np.arange(len(names))
    a2.barh(y, rms, color=cols)
    a2.set_yticks(y, names)
    a2.invert_yaxis()
    if sigma_px:
        a2.axvline(sigma_px * math.sqrt(2), color="k", ls="--", lw=0.8, label="expected RMS (√2 σ)")
        a2.legend(fontsize=6, loc="lower right")
    a2.set_xlabel("RMS residual (px)")
    a2.set_title("RMS residual per carriage")
    fig.tight_layout()
    _save(fig, path)
    return {"n_residuals": int(len(R)),
            "rms_px": float(np.sqrt(np.mean(np.sum(R ** 2, axis=1)))) if len(R) else None,
            "max_px": float(np.max(np.linalg.norm(R, axis=1))) if len(R) else None}


# ----------------------------------------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------------------------------------
def carriage_rows(project: Project, solution: dict) -> list[dict]:
    """One row per carriage of the consist with every number the report shows (strings, formatted)."""
    frame = project.frame
    by_number = {str(c.get("number")): c for c in solution.get("carriages", [])}
    types = project.carriage_types()
    doubts = doubts_of(solution)
    rows = []
    for i, car in enumerate(project.settings.consist):
        c = by_number.get(car.number, {})
        ct = types[car.number]
        row = {"index": i, "number": car.number, "type": ct.id, "type_name": ct.name,
               "status": c.get("status", "not in solution"),
               "color": "#%02x%02x%02x" % car_color(int(c.get("index", i))),
               "n_points": c.get("n_points", 0), "rms_px": _f(c.get("rms_px"), 2),
               "doubt": doubts.get(car.number, "").removeprefix(f"car {car.number}: ")
               if c.get("world_from_carriage") else ""}
        enu = c.get("body_centre_enu")
        crs = c.get("body_centre_crs")
        wgs = c.get("body_centre_wgs84")
        if (solution.get("frame") or {}).get("kind") == "relative":  # metres from the camera; nowhere on Earth
            crs, wgs = enu, None
        else:
            if enu is not None and crs is None:
                crs = frame.crs_from_enu(np.asarray(enu, float)).tolist()
            if enu is not None and wgs is None:
                wgs = frame.wgs84_from_enu(np.asarray(enu, float)).tolist()
        ci = c.get("ci95_body_centre_m") or [None] * 3
        hci = c.get("ci95_hpr_deg") or [None] * 3
        row.update({
            "e": _f(crs[0], 2) if crs else "–", "n": _f(crs[1], 2) if crs else "–", "h": _f(crs[2], 2) if crs else "–",
            "lat": _f(wgs[1], 7) if wgs else "–", "lon": _f(wgs[0], 7) if wgs else "–",
            "ci_e": _f(ci[0], 2), "ci_n": _f(ci[1], 2), "ci_u": _f(ci[2], 2),
            "heading": _f(c.get("heading_deg"), 1), "pitch": _f(c.get("pitch_deg"), 1),
            "roll": _f(c.get("roll_deg"), 1),
            "ci_heading": _f(hci[0], 2), "ci_pitch": _f(hci[1], 2), "ci_roll": _f(hci[2], 2),
            "coupling": (car.coupling_to_next.value if car.coupling_to_next else "–"),
            "gap": _f(c.get("coupler_gap_to_next_m"), 2) if car.coupling_to_next else "–",
            "clearance": _f(c.get("clearance_m"), 2),
        })
        rows.append(row)
    return rows


def findings(project: Project, solution: dict) -> list[str]:
    """Plain sentences for the first page: the wreck's extent, carriages on their side or tilted, broken couplings,
    carriages placed with less certainty, the largest uncertainty."""
    cars = [c for c in solution.get("carriages", []) if c.get("status") in ("solved", "carried")]
    out = []
    if len(cars) >= 2:
        P = np.array([c["body_centre_enu"] for c in cars], float)
        span = float(np.max(np.linalg.norm(P[:, None, :2] - P[None, :, :2], axis=2)))
        out.append(f"The {len(cars)} placed carriages lie within {span:.0f} m of one another (body centres).")
    side = [c for c in cars if abs(float(c.get("roll_deg", 0.0))) >= 60.0]
    tilt = [c for c in cars if 15.0 <= abs(float(c.get("roll_deg", 0.0))) < 60.0]
    if side:
        out.append("On its side: " + ", ".join(f"car {c['number']} (roll {_f(c['roll_deg'], 0)}°)" for c in side) + ".")
    if tilt:
        out.append("Tilted: " + ", ".join(f"car {c['number']} (roll {_f(c['roll_deg'], 0)}°)" for c in tilt) + ".")
    broken = [c for c in cars if c.get("coupling_to_next") == "broken"]
    if broken:
        out.append("Couplings broken behind " + ", ".join(
            f"car {c['number']}" + (f" (gap {_f(c.get('coupler_gap_to_next_m'), 1)} m)"
                                    if c.get("coupler_gap_to_next_m") is not None else "") for c in broken) + ".")
    doubts = doubts_of(solution)
    doubtful = [c["number"] for c in cars if str(c["number"]) in doubts]
    if doubtful:
        its = 'its' if len(doubtful) == 1 else 'their'
        out.append(f"Doubtful: car {', '.join(map(str, doubtful))}: {its} marked points do not settle {its} pose "
                   f"(the solution does not fit them, they disagree with the pose of the face they were matched on, "
                   f"or another pose fits them about as well, or far better but with the body inside a neighbour's, "
                   f"or the body shares space with another placed carriage's: a wrong pose branch, telescoped bodies "
                   f"or points matched on the wrong carriage), so the pose "
                   f"and its interval may be far off; "
                   f"check the points before acting on it (marked ‡ in section 2).")
    carried = [c["number"] for c in cars if c.get("status") == "carried"]
    if carried:
        out.append(f"Placed from their neighbours (too few marked points of their own): car {', '.join(carried)}.")
    left = [c.get("number") for c in solution.get("carriages", []) if c.get("status") == "left_out"]
    if left:
        out.append(f"Not placed: car {', '.join(map(str, left))} (see the warnings).")
    ci = [(max(c.get("ci95_body_centre_m") or [0.0]), c["number"]) for c in cars if c.get("ci95_body_centre_m")]
    if ci:
        worst = max(ci)
        out.append(f"Largest 95% position uncertainty: ±{worst[0]:.2f} m (car {worst[1]}); see section 2.")
    return out


def provenance(project: Project, state: dict) -> dict:
    stages = []
    for name, rec in state.items():
        if not isinstance(rec, dict) or name == "report":
            continue
        stages.append({
            "name": name, "status": rec.get("status", "?"), "started": rec.get("started_utc", "–"),
            "duration": _f(rec.get("duration_s"), 2), "settings": (rec.get("settings") or "")[:16],
            "inputs": [{"key": k, "sha": v[:16]} for k, v in sorted((rec.get("inputs") or {}).items())],
            "outputs": [{"key": k, "path": o.get("path", ""), "sha": o.get("sha256", "")[:16]}
                        for k, o in sorted((rec.get("outputs") or {}).items())],
            "error": rec.get("error"),
        })
    stages.sort(key=lambda st: st["started"])  # the order they ran in (ISO times sort as text)
    return {"stages": stages, "software": _versions(),
            "settings_toml": project.settings_path.read_text(encoding="utf-8")}


# ----------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------
def _stats(project: Project) -> dict[str, dict]:
    out = {}
    for p in sorted(project.out_dir.glob("*/stats.json")):
        try:
            out[p.parent.name] = project.read_json(p)
        except InputError as exc:
            log.warning("report: %s", exc)
    return out


def _jpeg_copy(src: Path, dst: Path, quality: int = 90) -> Path:
    """A JPEG copy of a render for the report (the PDF embeds JPEG as it is, but re-compresses PNG: slow, large)."""
    from PIL import Image

    with Image.open(src) as im:
        rgb = im.convert("RGB")
    return atomic_write(dst, lambda p: rgb.save(p, format="JPEG", quality=quality, optimize=True))


def _rel(from_dir: Path, path: Path) -> str:
    return Path(os.path.relpath(path, from_dir)).as_posix()


def _figure_jobs(project: Project, cams: dict, cars: list[dict], figs: Path, sigma: float | None):
    """([(figure function, args)] for each observed view's photo, the panorama (when stitched) and the residuals,
    the panorama's path, whether its figure is among them)."""
    jobs: list[tuple] = []
    views = {v.get("name"): v for v in cams.get("views", [])}
    pano = cams.get("panorama") or {}
    observed = []
    for c in cars:
        for v in (c.get("observations") or {}):
            if v not in observed:
                observed.append(v)
    for v in observed:
        img = None
        if v in views and views[v].get("image"):
            img = project.path(views[v]["image"])
        elif v == "panorama" and pano.get("image"):
            img = project.path(pano["image"])
        if img is None or not img.is_file():
            log.warning("report: no image for view %s; its points are not drawn", v)
            continue
        jobs.append((observations_figure, (figs / f"observations_{Path(v).stem}.jpg", img, v, cars)))
    pj = project.stage_dir("stitch") / "panorama.jpg"
    pm = project.stage_dir("stitch") / "panorama.json"
    with_pano = pj.is_file() and pm.is_file()
    if with_pano:
        jobs.append((panorama_figure, (figs / "observations_panorama.jpg", pj, pm, cars)))
    jobs.append((residual_figure, (figs / "residuals.png", cars, sigma)))
    return jobs, pj, with_pano


def build_context(project: Project, progress: Progress) -> tuple[dict, dict]:
    """(template context, report.json figures) from the incident's files."""
    s = project.settings
    out = project.stage_dir("report")
    figs = out / "figures"
    sol = project.solution("report")
    solution = sol.doc
    renders = read_json(project.stage_dir("render") / "renders.json",
                        missing=f"not found; the report needs the 'render' stage's output. Run `workbench run "
                                f"{project.root}` (or `--only render`)")
    state = project.read_state()
    stats = _stats(project)
    cameras = project.cameras()
    cams = cameras.doc if cameras is not None else {}
    cars = solution.get("carriages", [])

    progress(0.1, "figures")
    # the figures of the solution (points, residuals) are drawn in two processes beside this one, which meanwhile copies
    # the renders and loads the PDF engine; the same figures, drawn by the same code
    sigma = solution.get("sigma_px")
    jobs, pj, with_pano = _figure_jobs(project, cams, cars, figs, sigma)
    # two processes where matplotlib is loaded here already (the stage's work ahead): each would import it otherwise
    drawn = run_beside(jobs, processes=2 if "matplotlib.pyplot" in sys.modules else 1)

    try:
        by_kind: dict[str, list] = {}
        progress(0.4, "renders")
        for r in renders.get("renders", []):
            r = dict(r)
            src = project.path(r["sheet"] if r["kind"] == "orbit" and r.get("sheet") else r["path"])
            if not src.is_file():
                raise InputError(f"{src}: listed in {project.stage_dir('render') / 'renders.json'} but missing; run "
                                 f"the 'render' stage again (`workbench run {project.root} --only render --force`)")
            if r["kind"] == "map":  # line art: keep it lossless
                r["src"] = _rel(out, src)
            else:
                r["src"] = _rel(out, _jpeg_copy(src, figs / f"{src.stem}.jpg"))
            by_kind.setdefault(r["kind"], []).append(r)
        rows = carriage_rows(project, solution)
        for r in by_kind.get("closeup", []):
            r["row"] = next((x for x in rows if x["number"] == r.get("carriage")), None)
        load_pdf_engine()
    except BaseException:
        try:  # the figures' process ends before the error is raised: no file of it left half-written
            drawn()
        except Exception:  # noqa: BLE001 - the first error is the one raised
            pass
        raise
    progress(0.45, "figures")
    results = drawn()
    res_info = results.pop()
    panorama_img, panorama_fig = None, None
    if with_pano:
        info = results.pop()
        if info is not None:
            panorama_fig = {**info, "src": _rel(out, figs / "observations_panorama.jpg")}
    if pj.is_file() and panorama_fig is None:
        panorama_img = _rel(out, _jpeg_copy(pj, figs / "panorama.jpg"))
    obs_figs = [{**info, "src": _rel(out, p)} for info, (_fn, (p, *_rest)) in zip(results, jobs)]

    loc = s.location
    ns = "N" if loc.lat >= 0 else "S"
    ew = "E" if loc.lon >= 0 else "W"
    summary = {
        "n_cars": len(s.consist), "n_solved": sum(1 for c in cars if c.get("status") == "solved"),
        "n_carried": sum(1 for c in cars if c.get("status") == "carried"),
        "n_left_out": sum(1 for c in cars if c.get("status") == "left_out") + (len(s.consist) - len(cars)),
        "status": solution.get("status", "?"), "message": solution.get("message", ""),
        "route": solution.get("route") or cams.get("route", "?"),
        "intrinsics_source": solution.get("intrinsics_source") or cams.get("intrinsics_source", "?"),
        "n_views": len(solution.get("views", [])) or len(cams.get("views", [])), "n_obs": res_info["n_residuals"],
        "rms_px": _f(res_info["rms_px"], 2), "sigma_px": _f(sigma, 2),
        "rms_measured": _f((solution.get("residual_rms_px") or {}).get("measured"), 2),
        "rms_predicted": _f((solution.get("residual_rms_px") or {}).get("predicted"), 2),
        "n_predicted": (solution.get("residual_rms_px") or {}).get("n_predicted") or 0,
        "sigma_est": _f(solution.get("sigma_px_estimated"), 2), "dof": solution.get("dof", "–"),
        "ci95_factor": _f(solution.get("ci95_factor"), 2),
        "georef": ("none: relative scene, levelled from the carriages" if sol.relative else
                   "the photo's GPS and compass (levelled from the carriages)"
                   if (solution.get("frame") or {}).get("kind") == "gps" else
                   (cams.get("georegistration") or {}).get("method", "–")),
        "interval_scope": interval_scope(solution, s.solver, s.terrain.dem_vertical_accuracy_m),
    }
    ctx = {
        "incident": {"name": s.incident.name, "date": s.incident.date.isoformat(),
                     "description": s.incident.description, "synthetic": s.incident.synthetic},
        "location": {"lat": f"{abs(loc.lat):.6f}° {ns}", "lon": f"{abs(loc.lon):.6f}° {ew}", "crs": loc.crs,
                     "crs_name": project.frame.crs.name, "height": _f(loc.height_m, 2),
                     "convergence": _f(project.frame.grid_convergence_deg(), 2)},
        "generated": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "summary": summary, "rows": rows, "warnings": [_warning_text(w) for w in solution.get("warnings", [])],
        "findings": findings(project, solution), "track": None if sol.relative else track_table(project, sol),
        "relative": relative_context(sol), "placement": placement_context(sol),
        "priors": priors_text(cams.get("georegistration") or {}),
        "overview": (by_kind.get("overview") or [None])[0], "map": (by_kind.get("map") or [None])[0],
        "photos": by_kind.get("photo", []), "closeups": by_kind.get("closeup", []),
        "orbit": (by_kind.get("orbit") or [None])[0], "observations": obs_figs, "panorama": panorama_img,
        "panorama_fig": panorama_fig,
        "residuals": {**res_info, "src": _rel(out, figs / "residuals.png"), "scale": RESIDUAL_ARROW_SCALE},
        "provenance": provenance(project, state), "render_engine": renders.get("engine", "?"),
        "stage_times": [{"name": k, "duration": _f(v.get("duration_s"), 2)} for k, v in stats.items()],
    }
    facts = {"summary": summary, "findings": ctx["findings"], "carriages": rows, "track": ctx["track"],
             "residuals": res_info,
             "observations": obs_figs,
             "panorama": panorama_fig}
    return ctx, facts


def relative_context(sol: Any) -> dict | None:
    """What the report says of a relative scene (no survey), or None for a georeferenced one."""
    if not sol.relative:
        return None
    lev = (sol.doc.get("frame") or {}).get("levelling") or {}
    tilt = lev.get("sigma_tilt_deg") or [float("nan")] * 2
    used = lev.get("cars_used") or []
    how = (f"levelled from {len(used)} carriage(s) standing on their wheels ({', '.join(used)})" if used else
           "levelled as if the photo had been held level (no carriage stands on its wheels)")
    return {"levelling": how, "tilt": f"{max(tilt):.2f}", "left_out": ", ".join(lev.get("cars_left_out") or []),
            "method": lev.get("method", "?")}


def priors_text(georegistration: dict) -> str | None:
    """One line on the priors the georegistration used (EXIF GPS, compass, ``camera.position_enu``), or None."""
    pri = georegistration.get("priors") or {}
    parts = []
    c = pri.get("centre") or {}
    if "centre" in (pri.get("used") or []) and c:
        s = [x for x in (c.get("sigma_enu_m") or [])[:2] if x is not None]
        src = {"exif_gps": "the photos' EXIF GPS", "camera.position_enu": "camera.position_enu"}.get(
            c.get("source"), str(c.get("source")))
        parts.append(f"camera centre from {src}" + (f" (±{max(s):.1f} m, 1σ)" if s else ""))
    for h in pri.get("heading") or []:
        parts.append(f"{h.get('photo')}'s compass {float(h.get('azimuth_deg', float('nan'))):.0f}° "
                     f"(±{float(h.get('sigma_deg', float('nan'))):.0f}°)")
    notes = [str(n) for n in pri.get("notes") or []]
    if not parts and not notes:
        return None
    return ("Priors used by the georegistration: " + ("; ".join(parts) if parts else "none")
            + (". Not used: " + " ".join(notes) if notes else "."))


def placement_context(sol: Any) -> dict | None:
    """What the report says of a scene placed by a photo's GPS and compass (``frame.kind = "gps"``), or None."""
    fr = sol.doc.get("frame") or {}
    if fr.get("kind") != "gps":
        return None
    p = fr.get("placement") or {}
    s = [x for x in (p.get("sigma_enu_m") or [])[:2] if x is not None]
    return {"sigma_h": f"{max(s):.1f}" if s else "?", "sigma_az": _f(p.get("sigma_azimuth_deg"), 0),
            "height_from": p.get("height_from", "?"), "source": p.get("source", "?")}


def render_html(ctx: dict) -> str:
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), undefined=jinja2.StrictUndefined,
                             autoescape=jinja2.select_autoescape(["html", "j2"]))
    css = (TEMPLATES / "report.css").read_text(encoding="utf-8")
    return env.get_template("report.html.j2").render(css=css, **ctx)


def write_pdf(html: str, base_dir: Path, path: Path) -> int:
    """Lay out ``html`` (relative links resolved against ``base_dir``) as a PDF; returns the number of pages."""
    try:
        import weasyprint
    except (ImportError, OSError) as exc:
        raise StageError(f"the PDF engine WeasyPrint cannot be loaded ({exc}); install it with `uv sync` and its "
                         f"system libraries with `apt-get install -y libpango-1.0-0 libpangoft2-1.0-0`") from None
    doc = weasyprint.HTML(string=html, base_url=str(base_dir)).render()
    atomic_write(path, lambda p: doc.write_pdf(p))
    return len(doc.pages)


def ahead(project: Project) -> Iterator[None]:
    """``StageSpec.ahead``: the stage's imports, one step each, done in its process from the solve stage on, on the
    cores the stages then leave idle (``runner``): the PDF engine (WeasyPrint, about a second) and matplotlib, which
    the figures' processes (forked from this one) then have loaded."""
    load_pdf_engine()
    yield
    _plt()
    yield


def run_report(project: Project, progress: Progress) -> StageResult:
    t0 = time.perf_counter()
    started = time.time()
    out = project.stage_dir("report")
    ctx, facts = build_context(project, progress)
    for old in (out / "figures").glob("*"):  # figures of views or carriages that are gone
        if old.is_file() and old.stat().st_mtime < started - 1.0:
            old.unlink()
    progress(0.5, "HTML")
    html = render_html(ctx)
    html_path = project.write_text(out / "report.html", html)
    progress(0.6, "PDF")
    t_pdf = time.perf_counter()
    pages = write_pdf(html, out, out / "report.pdf")
    t_pdf = time.perf_counter() - t_pdf
    facts["pages"] = pages
    json_path = project.write_json(out / "report.json", facts)
    progress(1.0, f"{pages} pages")
    return StageResult(outputs={"html": html_path, "pdf": out / "report.pdf", "facts": json_path},
                       stats={"pages": pages, "pdf_bytes": (out / "report.pdf").stat().st_size,
                              "n_figures": len([f for f in (out / "figures").iterdir() if not f.name.startswith(".")]),
                              "pdf_time_s": round(t_pdf, 3),
                              "figures_time_s": round(time.perf_counter() - t0 - t_pdf, 3)})


def _warning_text(w: object) -> str:
    """A solver warning as a reader sees it: its message (the solution lists {car, kind, message} records)."""
    if isinstance(w, dict):
        return str(w.get("message") or "; ".join(f"{k}: {v}" for k, v in w.items()))
    return str(w)
