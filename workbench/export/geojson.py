"""Carriage footprints and centres as GeoJSON (RFC 7946): WGS84 longitude, latitude, height; right-hand rule.

Per carriage two features: a ``Point`` at its body centre and a ``Polygon``, its footprint: the corners of its
body box (couplers excluded) projected vertically onto the ground, their convex hull, counter-clockwise. Every
vertex is converted on its own, ENU -> WGS84 through :class:`~workbench.core.frames.SceneFrame` (never an
offset added to the origin). Heights (third coordinate): the body centre's for the point, the exported terrain's
under each footprint vertex (the lowest body corner's where there is no terrain), in the DEM's vertical datum.

With a railway layer (``terrain.railways``) each carriage's features also carry its place on the track
(:func:`track_properties`; definitions in ``docs/gis.md``, "Railway lines").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
from scipy.spatial import ConvexHull

from ..files.scene import SceneCarriage
from .scene import ExportScene, ground_heights

if TYPE_CHECKING:  # pragma: no cover
    from ..core.track import TrackPosition

DECIMALS_DEG = 9  # ~0.1 mm
DECIMALS_M = 4


def footprint_enu(car: SceneCarriage, scene: ExportScene) -> np.ndarray:
    """(k, 3) ENU footprint ring of a carriage, counter-clockwise seen from above, not closed."""
    corners = car.body_corners_enu()
    hull = ConvexHull(corners[:, :2])
    ring_xy = corners[hull.vertices, :2]  # scipy gives 2-D hull vertices counter-clockwise
    z = ground_heights(scene.terrain, ring_xy)
    z = np.where(np.isfinite(z), z, corners[:, 2].min())
    return np.column_stack([ring_xy, z])


def _lonlath(p: np.ndarray) -> list[float]:
    return [round(float(p[0]), DECIMALS_DEG), round(float(p[1]), DECIMALS_DEG), round(float(p[2]), DECIMALS_M)]


def carriage_properties(car: SceneCarriage, frame: Any) -> dict[str, Any]:
    """The properties every export attaches to a carriage (JSON-ready). ``height_m``: the body centre's height
    in the DEM's vertical datum (metres); ``ci95_*``: 95% half widths of the body centre (scene east, north, up)
    and of the angles."""
    centre = frame.wgs84_from_enu(car.body_centre_enu[None])[0]
    ci = car.ci95_body_centre_m
    chpr = car.ci95_hpr_deg
    return {
        "number": car.number, "type": car.type_id, "type_name": car.type_name, "status": car.status,
        "heading_deg": round(car.heading_deg, 4), "pitch_deg": round(car.pitch_deg, 4),
        "roll_deg": round(car.roll_deg, 4),
        "ci95_east_m": None if ci is None else round(ci[0], 4),
        "ci95_north_m": None if ci is None else round(ci[1], 4),
        "ci95_up_m": None if ci is None else round(ci[2], 4),
        "ci95_heading_deg": None if chpr is None else round(chpr[0], 4),
        "ci95_pitch_deg": None if chpr is None else round(chpr[1], 4),
        "ci95_roll_deg": None if chpr is None else round(chpr[2], 4),
        "height_m": round(float(centre[2]), 4),
        "length_m": car.length_m, "width_m": car.width_m, "body_height_m": car.height_m,
        "doubtful": bool(car.doubt), "doubt": car.doubt or None,
    }


def track_properties(tp: "TrackPosition") -> dict[str, Any]:
    """A carriage's place on the railway line (JSON-ready): ``track_line`` (its id), ``chainage_m`` (along the line
    from its origin), ``lateral_offset_m`` (from the track centre, positive left of increasing chainage),
    ``yaw_to_track_deg`` (positive: the front turned left of increasing chainage), their ``ci95_*`` half widths
    (None without an uncertainty) and ``beyond_line_end``."""
    d = tp.to_dict(decimals=DECIMALS_M)
    return {"track_line": tp.line_id, "chainage_m": d["chainage_m"], "ci95_chainage_m": d["ci95_chainage_m"],
            "lateral_offset_m": d["offset_m"], "ci95_lateral_offset_m": d["ci95_offset_m"],
            "yaw_to_track_deg": d["yaw_deg"], "ci95_yaw_to_track_deg": d["ci95_yaw_deg"],
            "beyond_line_end": tp.beyond_end}


def carriages_geojson(scene: ExportScene, track: Mapping[str, "TrackPosition"] | None = None) -> dict:
    """The FeatureCollection (a JSON-ready dict); properties in :func:`carriage_properties`, and in
    :func:`track_properties` for the carriages in ``track`` ({car number: place on the railway line})."""
    f = scene.frame
    features = []
    for car in scene.carriages:
        props = carriage_properties(car, f)
        if track and car.number in track:
            props.update(track_properties(track[car.number]))
        centre = f.wgs84_from_enu(car.body_centre_enu[None])[0]
        features.append({"type": "Feature", "id": f"{car.number}-centre",
                         "properties": {**props, "feature": "body centre"},
                         "geometry": {"type": "Point", "coordinates": _lonlath(centre)}})
        ring = f.wgs84_from_enu(footprint_enu(car, scene))
        coords = [_lonlath(p) for p in ring]
        coords.append(coords[0])
        features.append({"type": "Feature", "id": f"{car.number}-footprint",
                         "properties": {**props, "feature": "footprint"},
                         "geometry": {"type": "Polygon", "coordinates": [coords]}})
    lon = [c for ft in features for c in _all_lon_lat(ft["geometry"])]
    bbox = [min(p[0] for p in lon), min(p[1] for p in lon), max(p[0] for p in lon), max(p[1] for p in lon)]
    return {"type": "FeatureCollection", "name": "carriages", "bbox": [round(x, DECIMALS_DEG) for x in bbox],
            "georeference": scene.georeference(), "features": features}


def _all_lon_lat(geometry: dict) -> list[list[float]]:
    if geometry["type"] == "Point":
        return [geometry["coordinates"]]
    return [p for ring in geometry["coordinates"] for p in ring]
