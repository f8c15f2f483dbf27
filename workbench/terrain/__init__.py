"""Terrain: DEM reading, the ENU terrain mesh and exact surface queries (:class:`TerrainModel`)."""

from .dem import DemHolesFilled, TerrainModel

__all__ = ["TerrainModel", "DemHolesFilled"]
