"""The report's "On the track" table: every carriage's chainage, lateral offset and yaw relative to the railway line
(``terrain.railways``; definitions in ``workbench/core/track.py`` and ``docs/gis.md``, "Railway lines")."""

from __future__ import annotations

import math

import numpy as np

from ..core.track import bogie_pivots, rails_check
from ..files.railways import carriage_track_positions
from ..files.solution import Solution
from ..project import Project
from .scene import car_color


def _f(x: float | None, nd: int, sign: bool = False) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    return (f"{x:+.{nd}f}" if sign else f"{x:.{nd}f}").replace("-", "\u2212")


def track_table(project: Project, solution: Solution) -> dict | None:
    """The table's rows (formatted, consist order) and its line; None without a railway layer or a posed
    carriage. ``figures``: the unformatted figures per car number (for ``report.json``)."""
    layer = project.railways(heights=False)
    positions = carriage_track_positions(solution, layer)
    if not positions:
        return None
    index = {c.number: c.index for c in solution.carriages}
    checks = _rails_checks(project, solution, layer, positions)
    prior = {r.get("number"): r for r in solution.doc.get("track_prior") or [] if isinstance(r, dict)}
    rows = []
    for i, car in enumerate(project.settings.consist):
        tp = positions.get(car.number)
        row = {"number": car.number, "color": "#%02x%02x%02x" % car_color(index.get(car.number, i)),
               "chainage": "–", "ci_chainage": "–", "offset": "–", "ci_offset": "–", "yaw": "–", "ci_yaw": "–",
               "beyond_end": False, "held": bool(prior.get(car.number, {}).get("applied")), "rails": "–",
               "rails_offsets": "–"}
        chk = checks.get(car.number)
        if row["held"]:
            row["rails"] = "held †"
        elif chk is not None:
            row["rails"] = chk.verdict if chk.verdict != "cannot tell" else \
                f"cannot tell (± {_f(1.96 * max(chk.sigma_m), 2)} m)"
            row["rails_offsets"] = " / ".join(_f(x, 2, sign=True) for x in chk.offsets_m)
        if tp is not None:
            row.update({"chainage": _f(tp.chainage_m, 2), "ci_chainage": _f(tp.ci95("chainage_m"), 2),
                        "offset": _f(tp.offset_m, 2, sign=True), "ci_offset": _f(tp.ci95("offset_m"), 2),
                        "yaw": _f(tp.yaw_deg, 1, sign=True), "ci_yaw": _f(tp.ci95("yaw_deg"), 2),
                        "beyond_end": tp.beyond_end})
        rows.append(row)
    tp = next(iter(positions.values()))
    line = next(ln for ln in layer.lines if ln.id == tp.line_id)
    posts = line.properties.get("chainage_source")
    if posts:
        origin = (f"the {len(posts['posts'])} kilometre post(s) beside the line (OpenStreetMap railway:position; "
                  f"they agree with the line's length to {posts['spread_m']:g} m)")
    elif line.chainage_origin_m:
        origin = f"chainage {line.chainage_origin_m:g} m at its first vertex (the layer's chainage_origin)"
    else:
        origin = "its first vertex"
    held = [r for r in prior.values() if r.get("applied")]
    return {"line": line.label, "layer": project.relative(layer.path), "origin": origin, "n_lines": len(layer.lines),
            "rows": rows, "any_beyond_end": any(r["beyond_end"] for r in rows),
            "held_sigma_m": held[0].get("sigma_m") if held else None,
            "not_held": [f"{r.get('number')}: {r.get('reason')}" for r in prior.values() if not r.get("applied")],
            "figures": {n: p.to_dict() for n, p in positions.items()},
            "rails_checks": {n: c.to_dict() for n, c in checks.items()},
            "line_sigma_m": float(project.settings.solver.track_sigma_m)}


def _rails_checks(project: Project, solution: Solution, layer, positions: dict) -> dict:
    """Per posed carriage with a covariance: may it stand on the rails of its reference line (core.track.rails_check,
    the line accurate to ``solver.track_sigma_m``, the camera's share of the interval as an error common to the car)?"""
    types = project.carriage_types()
    lines = {ln.id: ln for ln in layer.lines} if layer is not None else {}
    out = {}
    for c in solution.posed:
        tp, cov = positions.get(c.number), c.record.get("covariance_pose")
        if tp is None or cov is None or c.number not in types or tp.line_id not in lines:
            continue
        total, fit = c.floats("sigma_body_centre_m"), c.floats("sigma_body_centre_fit_m")
        common = None
        if total is not None and fit is not None:
            common = np.diag([max(total[i] ** 2 - fit[i] ** 2, 0.0) for i in range(2)])
        out[c.number] = rails_check(lines[tp.line_id], c.world_from_carriage, bogie_pivots(types[c.number]),
                                    np.asarray(cov, dtype=float), float(project.settings.solver.track_sigma_m),
                                    common_cov_en=common)
    return out
