"""Shading data computed ahead of a render: the ray tracer's per-corner normals and texture of a large layer (the
terrain), computed while other work runs (the render stage's ``ahead``), and taken by the scene it is added to
(``OffscreenScene.add``) instead of computing it again."""

from __future__ import annotations

_SHADED: dict[int, tuple] = {}  # id(mesh) -> (mesh, its shading data); kept for the process's life


def remember(mesh, data) -> None:
    """Keep ``data``, the shading data of ``mesh`` (``offscreen.shading_data`` of it), for a scene given this very
    mesh object later."""
    _SHADED[id(mesh)] = (mesh, data)


def shaded_ahead(mesh):
    """The shading data kept for this very mesh object (:func:`remember`), else None."""
    hit = _SHADED.get(id(mesh))
    return hit[1] if hit is not None and hit[0] is mesh else None
