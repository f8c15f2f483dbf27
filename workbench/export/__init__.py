"""Georeferenced exports of the reconstructed scene: glTF (GLB), GeoJSON, KMZ (Google Earth), CityJSON 2.0 and
Cesium 3D Tiles. Formats, axes and the georeference: ``docs/exports.md``; the stage: :mod:`.stage`."""

from .scene import GLTF_FROM_ENU, ExportOptions, ExportScene, build_scene

__all__ = ["GLTF_FROM_ENU", "ExportOptions", "ExportScene", "build_scene"]
