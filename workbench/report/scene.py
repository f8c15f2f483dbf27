"""The reconstructed scene, read from an incident's files: terrain, buildings, posed carriages, cameras.

Everything here is in the scene frame (ENU metres, ``docs/conventions.md``). The render stage, the report
and the desktop viewer all build their pictures from one :class:`IncidentScene`, which is read only from
files the stages wrote (``out/solve/solution.json``, ``out/georef/cameras.json`` or the incident's own
``cameras.json``, ``out/terrain/*.ply``) and from the incident's layers (DEM, orthophoto).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import trimesh

from ..core.camera import CameraIntrinsics
from ..core.track import RailwayLine
from ..errors import WorkbenchWarning
from ..files.scene import SceneCarriage, scene_carriages
from ..project import Project

log = logging.getLogger(__name__)

# Colours (sRGB 0..255) used for the layers everywhere (renders, map, viewer).
TERRAIN_RGB = (150, 158, 132)
BUILDING_RGB = (196, 188, 176)
CAMERA_RGB = (230, 40, 40)
MAX_TERRAIN_CELLS = 160_000  # terrain nodes for pictures (the terrain stage keeps 400 000): 1.2 m over 500 m
MAX_TEXTURE_PX = 2048  # the orthophoto is downsampled to at most this many pixels a side for rendering
# one distinct colour per carriage (tab10 without grey), for outlines, map and plots
CAR_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
              (227, 119, 194), (188, 189, 34), (23, 190, 207)]


def car_color(index: int) -> tuple[int, int, int]:
    return CAR_COLORS[index % len(CAR_COLORS)]


@dataclass
class SceneCamera:
    """One view of ``cameras.json``."""

    name: str
    image: Path | None
    intrinsics: CameraIntrinsics
    cam_from_world: np.ndarray  # (4, 4)

    @property
    def center_enu(self) -> np.ndarray:
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        return -R.T @ t


@dataclass
class IncidentScene:
    terrain: trimesh.Trimesh | None
    buildings: trimesh.Trimesh | None
    carriages: list[SceneCarriage]
    cameras: list[SceneCamera]
    solution: dict
    cameras_json: dict
    files: dict[str, Path] = field(default_factory=dict)  # what was read
    textured: bool = True  # the carriages drawn with their liveries
    track: trimesh.Trimesh | None = None  # the railway layer's lines as two rails (track_mesh)

    def carriage_mesh(self, c: SceneCarriage) -> trimesh.Trimesh:
        """Carriage ``c``'s model placed in the scene (with its livery when the scene is textured)."""
        return c.mesh(textured=self.textured, in_scene=True)

    def focus(self) -> tuple[np.ndarray, float]:
        """(centre (3,), radius m) of the carriages (or the cameras, when no carriage has a pose)."""
        pts = [c.corners_enu() for c in self.carriages]
        if not pts:
            pts = [np.array([c.center_enu for c in self.cameras])] if self.cameras else [np.zeros((1, 3))]
        P = np.vstack(pts)
        lo, hi = P.min(axis=0), P.max(axis=0)
        centre = 0.5 * (lo + hi)
        return centre, float(max(np.linalg.norm(hi - lo) / 2.0, 5.0))


# ----------------------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------------------

def load_cameras(project: Project) -> tuple[dict, list[SceneCamera]]:
    """(``cameras.json`` document, its views) of the incident; ({}, []) before georef."""
    cameras = project.cameras()
    if cameras is None:
        return {}, []
    cams = [SceneCamera(v.name, project.path(v.image) if v.image else None, v.intrinsics, v.cam_from_world)
            for v in cameras.views]
    return cameras.doc, cams


def with_solved_focal(cams: list[SceneCamera], focal_px: dict[str, float]) -> list[SceneCamera]:
    """The cameras with the focal the solve estimated (``solution.json`` ``focal_px``, per view), so renders,
    overlays and the viewer draw what the solve saw; a view the solution does not name keeps its own."""
    return [c if focal_px.get(c.name) is None else
            SceneCamera(c.name, c.image, c.intrinsics.with_focal(focal_px[c.name]), c.cam_from_world) for c in cams]


def _terrain_mesh(project: Project, *, textured: bool) -> trimesh.Trimesh | None:
    """The terrain with the orthophoto draped on it (the DEM read as the terrain stage reads it), else the
    terrain stage's mesh in a plain colour."""
    s = project.settings.terrain
    ortho = project.orthophoto_path() if textured else None
    if ortho is not None and s.dem:
        from PIL import Image

        tm = project.terrain_model(max_cells=MAX_TERRAIN_CELLS)
        with Image.open(ortho) as im:
            tex = im.convert("RGB")
            if max(tex.size) > MAX_TEXTURE_PX:  # the renderers linearise every texel: keep it affordable
                f = MAX_TEXTURE_PX / max(tex.size)
                tex = tex.resize((max(1, round(tex.size[0] * f)), max(1, round(tex.size[1] * f))),
                                 Image.Resampling.BILINEAR, reducing_gap=2.0)
            tex.load()
        return tm.mesh(texture=tex)
    ply = project.stage_dir("terrain") / "terrain.ply"
    if not ply.is_file():
        return None
    m = trimesh.load(ply, process=False, force="mesh")
    m.visual = trimesh.visual.ColorVisuals(m, face_colors=np.tile([*TERRAIN_RGB, 255], (len(m.faces), 1)))
    return m


def _buildings_mesh(project: Project) -> trimesh.Trimesh | None:
    ply = project.stage_dir("terrain") / "buildings.ply"
    if not ply.is_file():
        return None
    m = trimesh.load(ply, process=False, force="mesh")
    if getattr(m.visual, "kind", None) is None:
        m.visual = trimesh.visual.ColorVisuals(m, face_colors=np.tile([*BUILDING_RGB, 255], (len(m.faces), 1)))
    return m


RAIL_RGB = (62, 60, 64)  # steel
RAIL_HEAD_M = 0.07  # a rail head's width; drawn at twice that, so that it shows from afar
RAIL_ABOVE_GROUND_M = 0.2  # top of rail over the ground a DEM gives (rail, sleeper, ballast)


def _ribbon(line: RailwayLine, offset_m: float, width_m: float, z_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a flat band ``width_m`` wide along ``line`` at ``offset_m`` to its left, ``z_m`` above
    its heights, faces up."""
    a = line.rail_polyline(offset_m + width_m / 2, step_m=1e9)
    b = line.rail_polyline(offset_m - width_m / 2, step_m=1e9)
    n = len(a)
    V = np.vstack([a, b]) + [0.0, 0.0, z_m]
    i = np.arange(n - 1)
    # left edge a_i, right edge b_i = i + n; counter-clockwise seen from above (normal up)
    F = np.vstack([np.column_stack([i, i + n, i + 1]), np.column_stack([i + 1, i + n, i + 1 + n])])
    return V, F


def track_mesh(lines: Sequence[RailwayLine], top_of_rail: bool, gauge_m: float = 1.435) -> trimesh.Trimesh | None:
    """The railway lines as their two rails (flat bands at ``gauge_m`` plus a head's width apart, centre to centre):
    drawn over the terrain and its imagery, they show where the layer puts the track against where the photos and
    the orthophoto show it. ``top_of_rail``: the lines' heights are the rails' tops (a layer's own heights, as the
    synthetic generator writes them); else the ground's (draped on the DEM), the rails :data:`RAIL_ABOVE_GROUND_M`
    above it."""
    base = 0
    V_all, F_all, C_all = [], [], []
    rail_top = 0.0 if top_of_rail else RAIL_ABOVE_GROUND_M
    half = (gauge_m + RAIL_HEAD_M) / 2
    for line in lines:
        for off, w, z, rgb in [(s * half, 2 * RAIL_HEAD_M, rail_top, RAIL_RGB) for s in (1.0, -1.0)]:
            V, F = _ribbon(line, off, w, z)
            V_all.append(V)
            F_all.append(F + base)
            C_all.append(np.tile([*rgb, 255], (len(F), 1)))
            base += len(V)
    if not V_all:
        return None
    m = trimesh.Trimesh(np.vstack(V_all), np.vstack(F_all), process=False)
    m.visual = trimesh.visual.ColorVisuals(m, face_colors=np.vstack(C_all))
    return m


def _track(project: Project) -> trimesh.Trimesh | None:
    """The incident's railway layer as a track mesh (None without one): its own heights when it has them (top of
    rail), else draped on the DEM."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WorkbenchWarning)  # a layer with no line: the render stage reports it
        layer = project.railways(heights=False)
        if layer is not None and layer.heights != "file":
            layer = project.railways(heights=True)
    if layer is None:
        return None
    return track_mesh(layer.lines, top_of_rail=layer.heights == "file")


LAYERS = ("terrain", "buildings", "track")


def scene_layers(project: Project, *, textured: bool = True,
                 skip: Sequence[str] = ()) -> Iterator[tuple[str, trimesh.Trimesh | None]]:
    """The scene's layers that do not depend on the solution (:data:`LAYERS` but those in ``skip``), one by one:
    (name, mesh), None where the incident has none (read from the DEM, the orthophoto, the terrain stage's meshes
    and the railway layer)."""
    read = {"terrain": lambda: _terrain_mesh(project, textured=textured), "buildings": lambda: _buildings_mesh(project),
            "track": lambda: _track(project)}
    for name in LAYERS:
        if name not in skip:
            yield name, read[name]()


def load_scene(project: Project, *, textured: bool = True, with_terrain: bool = True,
               layers: dict[str, trimesh.Trimesh | None] | None = None) -> IncidentScene:
    """Read the reconstructed scene of ``project``. :class:`InputError` naming the 'solve' stage if it has not run.
    ``layers``: those of the :func:`scene_layers` read before (with the same ``textured``); the others are read here."""
    sol = project.solution("scene")
    cars, _ = scene_carriages(sol, project.carriage_types())
    cam_data, cams = load_cameras(project)
    cams = [SceneCamera(c.name, c.image, c.intrinsics, sol.cam_from_world(c.cam_from_world)) for c in cams]
    cams = with_solved_focal(cams, sol.focal_px)
    with_terrain = with_terrain and not sol.relative  # a relative scene is not in the DEM's frame
    if with_terrain:
        layers = dict(layers or {})
        layers.update(scene_layers(project, textured=textured, skip=tuple(layers)))
    terrain = layers["terrain"] if with_terrain else None
    buildings = layers["buildings"] if with_terrain else None
    files = {"solution": sol.path}
    if project.cameras_path():
        files["cameras"] = project.cameras_path()
    track = layers["track"] if with_terrain else None
    return IncidentScene(terrain, buildings, cars, cams, sol.doc, cam_data, files, textured, track)


# ----------------------------------------------------------------------------------------------------------
# Glyphs
# ----------------------------------------------------------------------------------------------------------
def camera_glyph(cam: SceneCamera, size_m: float = 3.0, rgb=CAMERA_RGB) -> trimesh.Trimesh:
    """A solid pyramid (apex at the camera centre, base towards the view) of depth ``size_m``, scene frame."""
    intr = cam.intrinsics
    hw = 0.5 * intr.width / intr.fx
    hh = 0.5 * intr.height / intr.fy
    V_cam = np.array([[0, 0, 0], [-hw, -hh, 1], [hw, -hh, 1], [hw, hh, 1], [-hw, hh, 1]], float) * size_m
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1], [1, 3, 2], [1, 4, 3]])
    R, t = cam.cam_from_world[:3, :3], cam.cam_from_world[:3, 3]
    V = (V_cam - t) @ R  # world = R^T (cam - t)
    m = trimesh.Trimesh(V, F, process=False)
    m.visual = trimesh.visual.ColorVisuals(m, face_colors=np.tile([*rgb, 255], (len(F), 1)))
    return m
