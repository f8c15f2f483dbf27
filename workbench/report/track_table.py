"""The report's "On the track" table: every carriage's chainage, lateral offset and yaw relative to the railway line
(``terrain.railways``; definitions in ``workbench/core/track.py`` and ``docs/gis.md``, "Railway lines")."""

from __future__ import annotations

import math

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
    rows = []
    for i, car in enumerate(project.settings.consist):
        tp = positions.get(car.number)
        row = {"number": car.number, "color": "#%02x%02x%02x" % car_color(index.get(car.number, i)),
               "chainage": "–", "ci_chainage": "–", "offset": "–", "ci_offset": "–", "yaw": "–", "ci_yaw": "–",
               "beyond_end": False}
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
    return {"line": line.label, "layer": project.relative(layer.path), "origin": origin, "n_lines": len(layer.lines),
            "rows": rows, "any_beyond_end": any(r["beyond_end"] for r in rows),
            "figures": {n: p.to_dict() for n, p in positions.items()}}
