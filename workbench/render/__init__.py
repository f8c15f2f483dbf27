"""Off-screen rendering: scenes of ENU meshes (``offscreen``), photos through real lenses (``lens``), EXIF JPEGs (``exif``)."""

from .offscreen import OffscreenScene, RenderResult, SceneMesh

__all__ = ["OffscreenScene", "RenderResult", "SceneMesh"]
