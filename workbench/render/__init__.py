"""Off-screen rendering: scenes of ENU meshes (``offscreen``), photos through real lenses (``lens``), EXIF JPEGs (``exif``)."""

from .offscreen import MAX_INSTANCE_ID, OffscreenScene, RenderResult, SceneMesh

__all__ = ["MAX_INSTANCE_ID", "OffscreenScene", "RenderResult", "SceneMesh"]
