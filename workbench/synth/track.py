"""The track the synthetic consist left, as a railway layer, and each carriage's true place relative to it.

The layer (``<layers>/<scenario>_railways.geojson``, read by ``workbench/files/railways.py``) is the train's track
centre line (top of rail, 1 m vertices, in the project CRS): the polyline the consist was laid along. The truth is
computed on the exact circular arc the synthetic track follows (:class:`~workbench.synth.terrain.CurveLayout`), not
on the polyline, so the workbench's own figures (``workbench/core/track.py``, on the layer as read) can be checked
against it; the definitions are those of ``docs/gis.md``, "Railway lines": chainage from the line's first vertex
along the direction of travel, lateral offset positive to the left of it, yaw = track bearing minus the carriage's
heading (positive: the front turned left), all from the carriage's body centre.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..core.frames import SceneFrame, hpr_from_rotation
from ..core.track import wrap_deg
from ..files.railways import write_railways_geojson

LINE_NAME = "track the train ran on"


def line_id(scenario_id: str) -> str:
    return f"{scenario_id}-track"


def write_track_layer(path: Path, st, frame: SceneFrame, scenario_id: str) -> Path:
    """Write the train's track (``st.track_enu``, ENU of ``frame``) as a GeoJSON railway layer in the project CRS."""
    crs_xyh = frame.crs_from_enu(np.asarray(st.track_enu, dtype=float))
    epsg = frame.crs.to_epsg()
    crs = f"EPSG:{epsg}" if epsg is not None else frame.crs.to_wkt()
    return write_railways_geojson(path, [{"id": line_id(scenario_id), "name": LINE_NAME, "coords": crs_xyh,
                                          "top_of_rail": True}], crs)


def carriage_track_truth(placed, st, scenario_id: str) -> list[dict]:
    """Per carriage (in order): its true chainage (m), lateral offset (m), yaw relative to the track (deg) and the
    track bearing there, from its body centre and heading, on the exact arc of the track."""
    lay = st.layout
    track = np.asarray(st.track_enu, dtype=float)
    _, phi0 = lay.offset_along(track[:1, 0], track[:1, 1])
    out = []
    for p in placed:
        centre = p.world_from_carriage.apply(np.asarray(p.ctype.bounding_box()).mean(axis=0))
        off, phi = lay.offset_along(centre[:1], centre[1:2])
        phi = float(phi[0])
        tangent = -math.sin(phi) * lay.ref + math.cos(phi) * lay.forward0  # d/dphi of the arc: the travel direction
        bearing = math.degrees(math.atan2(tangent[0], tangent[1])) % 360.0
        heading = hpr_from_rotation(p.world_from_carriage.rotation)[0]
        out.append({"line_id": line_id(scenario_id), "chainage_m": lay.radius * (phi - float(phi0[0])),
                    "offset_m": float(off[0]), "yaw_deg": wrap_deg(bearing - heading), "track_bearing_deg": bearing})
    return out
