"""Off-screen rendering: scenes of ENU meshes (``offscreen``), photos through real lenses (``lens``).

The renderer's names are loaded on first use, so importing the package does not import trimesh and Open3D.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .offscreen import OffscreenScene, RenderResult, SceneMesh

__all__ = ["OffscreenScene", "RenderResult", "SceneMesh"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import offscreen

        return getattr(offscreen, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
