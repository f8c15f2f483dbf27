"""Building footprints with heights as GeoJSON (format in ``docs/formats.md``, "Terrain layers"): the one reader
and writer.

A building is a dict ``{"id": str, "footprint_crs": (k, 2) polygon in the project CRS, "height_m": float,
"base_m": ground height (project vertical datum) or None, ...}``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS
from shapely.geometry import Polygon

from ..core.io import atomic_write_text, to_json
from ..errors import InputError

__all__ = ["write_buildings_geojson", "read_buildings_geojson"]


# ----------------------------------------------------------------------------------------------------------
# GeoJSON
# ----------------------------------------------------------------------------------------------------------
def _epsg_urn(crs: Any) -> str:
    c = CRS.from_user_input(crs)
    epsg = c.to_epsg()
    if epsg is None:
        raise ValueError(f"CRS {crs!r} has no EPSG code; the buildings GeoJSON needs one")
    return f"urn:ogc:def:crs:EPSG::{epsg}"


def write_buildings_geojson(path: str | Path, buildings: list[dict], crs: Any) -> Path:
    """GeoJSON FeatureCollection in the project CRS (a ``crs`` member with the EPSG URN), written atomically."""
    feats = []
    for b in buildings:
        ring = np.asarray(b["footprint_crs"], dtype=float)
        if not np.array_equal(ring[0], ring[-1]):
            ring = np.vstack([ring, ring[:1]])
        props = {"id": str(b["id"]), "height_m": float(b["height_m"]),
                 "base_m": None if b.get("base_m") is None else float(b["base_m"])}
        for k, v in b.items():
            if k not in ("id", "height_m", "base_m", "footprint_crs"):
                props[k] = v
        feats.append({"type": "Feature", "id": str(b["id"]), "properties": props,
                      "geometry": {"type": "Polygon", "coordinates": [np.round(ring, 4).tolist()]}})
    doc = {"type": "FeatureCollection", "name": "buildings",
           "crs": {"type": "name", "properties": {"name": _epsg_urn(crs)}}, "features": feats}
    return atomic_write_text(Path(path), to_json(doc))


def read_buildings_geojson(path: str | Path, *, expect_crs: Any = None) -> list[dict]:
    """Inverse of :func:`write_buildings_geojson`, validating every feature (InputError naming feature and file).

    ``expect_crs``: when given, the file's ``crs`` member must name the same EPSG code.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"buildings file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"buildings file {path} is not valid GeoJSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" or not isinstance(doc.get("features"), list):
        raise InputError(f"buildings file {path} is not a GeoJSON FeatureCollection")
    if expect_crs is not None:
        name = ((doc.get("crs") or {}).get("properties") or {}).get("name")
        if name is None:
            raise InputError(f"buildings file {path} has no 'crs' member; it must be in {expect_crs} "
                             f"(add \"crs\": {{\"type\": \"name\", \"properties\": {{\"name\": "
                             f"\"{_epsg_urn(expect_crs)}\"}}}})")
        try:
            same = CRS.from_user_input(name).to_epsg() == CRS.from_user_input(expect_crs).to_epsg()
        except Exception:  # noqa: BLE001
            same = False
        if not same:
            raise InputError(f"buildings file {path} is in {name}, but the project CRS is {expect_crs}; "
                             f"reproject it (e.g. ogr2ogr -t_srs {expect_crs})")
    out = []
    for i, feat in enumerate(doc["features"]):
        props = (feat or {}).get("properties") or {}
        fid = str(props.get("id", (feat or {}).get("id", f"#{i}")))
        geom = (feat or {}).get("geometry") or {}
        coords = geom.get("coordinates")
        if geom.get("type") == "MultiPolygon" and coords:
            coords = coords[0]
        if geom.get("type") not in ("Polygon", "MultiPolygon") or not coords:
            raise InputError(f"buildings file {path}: feature {fid} has no polygon geometry "
                             f"(type {geom.get('type')!r})")
        try:
            ring = np.asarray(coords[0], dtype=float)[:, :2]
        except (ValueError, IndexError, TypeError):
            raise InputError(f"buildings file {path}: feature {fid} has a malformed polygon") from None
        if len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]
        if len(ring) < 3 or not np.all(np.isfinite(ring)) or Polygon(ring).area <= 0:
            raise InputError(f"buildings file {path}: feature {fid} has a degenerate polygon ({len(ring)} points)")
        h = props.get("height_m")
        try:
            hv = float(h)
        except (TypeError, ValueError):
            hv = float("nan")
        if not (math.isfinite(hv) and hv > 0):
            raise InputError(f"buildings file {path}: feature {fid} has height_m={h!r}; it must be a number > 0")
        base = props.get("base_m")
        if base is not None:
            try:
                base = float(base)
            except (TypeError, ValueError):
                raise InputError(f"buildings file {path}: feature {fid} has base_m={base!r}; give a number "
                                 f"or leave it out") from None
        b = {"id": fid, "footprint_crs": ring, "height_m": hv, "base_m": base}
        for k, v in props.items():
            if k not in b:
                b[k] = v
        out.append(b)
    return out
