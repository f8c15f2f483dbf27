"""The carriages for Google Earth: ``scene.kmz`` = ``doc.kml`` + one textured COLLADA model per carriage.

Placement (docs/exports.md has the derivation). KML places a ``<Model>`` at ``<Location>`` (longitude, latitude,
altitude; ``altitudeMode`` absolute) in a local frame there: model +X east, +Y north, +Z up, metres (COLLADA
``Z_UP``). ``<Orientation>`` ``heading`` is a rotation about that up axis, 0 = north, positive clockwise seen
from above, i.e. a compass bearing: ``local_from_model = Rz(-heading)``, exactly our heading. KML's reference
defines ``tilt`` and ``roll`` only as "clockwise about x / y" (no viewing direction, no order), so they are left
at 0 and each carriage's pitch and roll are built into its own model instead:

    model vertices = Rz(90°) · Ry(-pitch) · Rx(roll) · p_carriage      (carriage -> model axes; front = +Y)
    local_from_carriage = Rz(-heading) · model vertices = Rz(90° - heading) · Ry(-pitch) · Rx(roll)

which is ``world_from_carriage`` of docs/conventions.md. Heading, pitch and roll here are taken in the local ENU
frame *at the carriage* (not at the scene origin; they differ by ~0.001° per 100 m), so the placement is exact.
The model origin is the carriage origin (top of rail, midway between the couplers).
"""

from __future__ import annotations

import io
import logging
import zipfile
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from ..core.frames import SceneFrame, hpr_from_rotation
from ..core.geometry import orthonormal, rot_z
from .geojson import carriage_properties, footprint_enu
from ..files.scene import SceneCarriage
from .scene import ExportOptions, ExportScene

log = logging.getLogger(__name__)

KML_NS = "http://www.opengis.net/kml/2.2"


def local_attitude(car: SceneCarriage, frame: SceneFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin [lon, lat, h] of the carriage frame, ``local_from_carriage`` rotation (3, 3) in the ENU frame at
    that point, (heading, pitch, roll) degrees in that frame)."""
    p0 = car.world_from_carriage.translation
    geo0 = frame.wgs84_from_enu(p0[None])[0]
    local = SceneFrame(frame.crs, float(geo0[1]), float(geo0[0]), float(geo0[2]))
    pts = np.vstack([p0, p0 + np.eye(3)])
    q = local.enu_from_wgs84(frame.wgs84_from_enu(pts))
    A = (q[1:] - q[0]).T  # columns: the scene's E, N, U axes in the local frame
    local_from_scene = orthonormal(A)
    R = local_from_scene @ car.world_from_carriage.rotation
    return geo0, R, np.array(hpr_from_rotation(R))


def model_vertices(car: SceneCarriage, local_from_carriage: np.ndarray,
                   heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """((n, 3) the carriage's textured mesh vertices in KML model axes, ``model_from_carriage`` (3, 3)) for an
    ``<Orientation>`` of (heading_deg, tilt 0, roll 0): ``model_from_carriage = Rz(heading) @ local_from_carriage``."""
    M = rot_z(np.deg2rad(heading_deg)) @ local_from_carriage
    return np.asarray(car.mesh(textured=True).vertices, dtype=float) @ M.T, M


def collada_bytes(car: SceneCarriage, vertices: np.ndarray, normals: np.ndarray, texture_name: str) -> bytes:
    """A COLLADA 1.4 document (Z_UP, metres) of one carriage: triangles, normals, UVs, its livery texture."""
    import collada
    from collada import asset, geometry, material, scene, source

    doc = collada.Collada()
    doc.assetInfo.upaxis = asset.UP_AXIS.Z_UP
    doc.assetInfo.unitmeter = 1.0
    doc.assetInfo.unitname = "meter"
    image = material.CImage("livery-image", texture_name)
    surface = material.Surface("livery-surface", image)
    sampler = material.Sampler2D("livery-sampler", surface)
    effect = material.Effect("livery-effect", [surface, sampler], "lambert",
                             diffuse=material.Map(sampler, "UVSET0"), double_sided=True)
    mat = material.Material("livery-material", f"livery {car.number}", effect)
    doc.images.append(image)
    doc.effects.append(effect)
    doc.materials.append(mat)
    uv = np.asarray(car.mesh(textured=True).visual.uv, dtype=float)  # origin bottom-left, as COLLADA
    srcs = [source.FloatSource("verts-array", np.asarray(vertices, dtype=float).ravel(), ("X", "Y", "Z")),
            source.FloatSource("normals-array", np.asarray(normals, dtype=float).ravel(), ("X", "Y", "Z")),
            source.FloatSource("uv-array", uv.ravel(), ("S", "T"))]
    geom = geometry.Geometry(doc, "carriage-geometry", f"{car.type_id} {car.number}", srcs)
    inputs = source.InputList()
    inputs.addInput(0, "VERTEX", "#verts-array")
    inputs.addInput(1, "NORMAL", "#normals-array")
    inputs.addInput(2, "TEXCOORD", "#uv-array", set="0")
    idx = np.repeat(np.arange(len(vertices), dtype=np.int64), 3)  # one vertex per corner: same index thrice
    geom.primitives.append(geom.createTriangleSet(idx, inputs, "livery-ref"))
    doc.geometries.append(geom)
    node = scene.Node(f"car-{car.number}", children=[scene.GeometryNode(
        geom, [scene.MaterialNode("livery-ref", mat, inputs=[("UVSET0", "TEXCOORD", "0")])])])
    sc = scene.Scene("scene", [node])
    doc.scenes.append(sc)
    doc.scene = sc
    buf = io.BytesIO()
    doc.write(buf)
    return buf.getvalue()


def _sub(parent: ET.Element, tag: str, text: Any = None, **attrib: str) -> ET.Element:
    e = ET.SubElement(parent, tag, attrib)
    if text is not None:
        e.text = str(text)
    return e


def _extended(parent: ET.Element, props: dict) -> None:
    ext = _sub(parent, "ExtendedData")
    for k, v in props.items():
        if v is None:
            continue
        _sub(_sub(ext, "Data", name=k), "value", v)


def _fmt(x: float, nd: int) -> str:
    return f"{float(x):.{nd}f}"


def kmz_bytes(scene: ExportScene, options: ExportOptions) -> tuple[bytes, dict]:
    """The KMZ file's bytes (a zip: ``doc.kml``, ``models/car_<number>.dae`` and ``.jpg``) and statistics."""
    f = scene.frame
    kml = ET.Element("kml", xmlns=KML_NS)
    doc = _sub(kml, "Document")
    _sub(doc, "name", scene.title or "scene")
    _sub(doc, "description", "Carriages reconstructed by the train-wreck workbench; heights are the DEM's "
                             "(altitudeMode absolute). See docs/exports.md.")
    style = _sub(doc, "Style", id="footprint")
    ls = _sub(style, "LineStyle")
    _sub(ls, "color", "ff0000ff")
    _sub(ls, "width", 2)
    _sub(_sub(style, "PolyStyle"), "color", "400000ff")
    models = _sub(doc, "Folder")
    _sub(models, "name", "Carriage models")
    labels = _sub(doc, "Folder")
    _sub(labels, "name", "Car numbers")
    prints = _sub(doc, "Folder")
    _sub(prints, "name", "Footprints")
    files: dict[str, bytes] = {}
    placed = []
    for car in scene.carriages:
        props = carriage_properties(car, f)
        geo0, R_local, hpr = local_attitude(car, f)
        V, M = model_vertices(car, R_local, float(hpr[0]))
        normals = np.repeat(car.mesh(textured=True).face_normals, 3, axis=0) @ M.T
        stem = f"car_{car.number}"
        files[f"models/{stem}.jpg"] = scene.jpeg(car.mesh(textured=True).visual.material.image, options.livery_max_px,
                                                 options.jpeg_quality)
        files[f"models/{stem}.dae"] = collada_bytes(car, V, normals, f"{stem}.jpg")
        pm = _sub(models, "Placemark", id=f"model-{car.number}")
        _sub(pm, "name", f"{car.number} ({car.type_name})")
        _extended(pm, {**props, "kml_heading_deg": round(float(hpr[0]), 6),
                       "model_pitch_deg": round(float(hpr[1]), 6), "model_roll_deg": round(float(hpr[2]), 6)})
        model = _sub(pm, "Model", id=f"car-{car.number}")
        _sub(model, "altitudeMode", "absolute")
        loc = _sub(model, "Location")
        _sub(loc, "longitude", _fmt(geo0[0], 10))
        _sub(loc, "latitude", _fmt(geo0[1], 10))
        _sub(loc, "altitude", _fmt(geo0[2], 4))
        ori = _sub(model, "Orientation")
        _sub(ori, "heading", _fmt(hpr[0], 6))
        _sub(ori, "tilt", "0")
        _sub(ori, "roll", "0")
        sc = _sub(model, "Scale")
        for a in ("x", "y", "z"):
            _sub(sc, a, "1")
        _sub(_sub(model, "Link"), "href", f"models/{stem}.dae")
        # the number, floating above the roof
        top = f.wgs84_from_enu(car.world_from_carriage.apply(
            np.array([car.body_centre_carriage[0], car.body_centre_carriage[1], car.height_m + 1.0]))[None])[0]
        lab = _sub(labels, "Placemark", id=f"label-{car.number}")
        _sub(lab, "name", car.number)
        _extended(lab, props)
        pt = _sub(lab, "Point")
        _sub(pt, "altitudeMode", "absolute")
        _sub(pt, "coordinates", f"{_fmt(top[0], 10)},{_fmt(top[1], 10)},{_fmt(top[2], 3)}")
        fp = _sub(prints, "Placemark", id=f"footprint-{car.number}")
        _sub(fp, "name", f"{car.number} footprint")
        _sub(fp, "styleUrl", "#footprint")
        _extended(fp, props)
        poly = _sub(fp, "Polygon")
        _sub(poly, "altitudeMode", "clampToGround")
        ring = f.wgs84_from_enu(footprint_enu(car, scene))
        ring = np.vstack([ring, ring[:1]])
        coords = " ".join(f"{_fmt(p[0], 10)},{_fmt(p[1], 10)},{_fmt(p[2], 3)}" for p in ring)
        _sub(_sub(_sub(poly, "outerBoundaryIs"), "LinearRing"), "coordinates", coords)
        placed.append({"number": car.number, "location_wgs84": [float(x) for x in geo0],
                       "heading_deg": float(hpr[0]), "pitch_deg": float(hpr[1]), "roll_deg": float(hpr[2])})
    ET.indent(kml)
    kml_bytes = b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(kml, encoding="utf-8")
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("doc.kml", kml_bytes)  # first entry: Google Earth opens the first .kml in the archive
        for name, data in files.items():
            z.writestr(name, data)
    data = out.getvalue()
    return data, {"models": placed, "bytes": len(data)}
