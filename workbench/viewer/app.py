"""Desktop viewer of a reconstructed incident: ``workbench view projects/NAME``.

An Open3D GUI window (Filament; Vulkan or OpenGL, on the CPU through Mesa where there is no GPU):

* the scene in the scene frame (ENU metres): terrain (with the orthophoto where there is one), buildings,
  the carriages in their solved poses with their liveries, the cameras as red frustums;
* drag to orbit, wheel to zoom, right-drag (or shift-drag) to pan (Open3D's standard controls);
* the panel on the right: a check box per layer, the list of carriages, and the selected carriage's
  numbers (position in the project CRS and WGS84, heading/pitch/roll, 95% half widths, coupling);
* pick a carriage by clicking it with Ctrl held (or in the list); it is outlined in yellow.

``view(root, screenshot=PATH)`` draws one frame, writes the window to ``PATH`` (PNG) and returns: that is
how the viewer is tested under ``xvfb-run``. Everything shown is read from files (see
:mod:`workbench.report.scene`); nothing is computed here that the report does not also show.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..core.io import atomic_write
from ..errors import RenderError
from ..project import Project

log = logging.getLogger(__name__)

LAYERS = ("terrain", "buildings", "carriages", "cameras")
PANEL_WIDTH_EM = 21


def _open3d():
    try:
        import open3d as o3d
        import open3d.visualization.gui as gui
        import open3d.visualization.rendering as rendering
    except (ImportError, OSError) as exc:
        from ..report.render_stage import DEBIAN_PACKAGES

        raise RenderError(f"the viewer needs Open3D's GUI ({exc}); on Debian/Ubuntu: "
                          f"`apt-get install -y {DEBIAN_PACKAGES}`") from None
    return o3d, gui, rendering


RELATIVE = "relative frame (not georeferenced)"


def carriage_text(row: dict, crs: str) -> str:
    """The numbers of one carriage (a row of :func:`workbench.report.report_stage.carriage_rows`), as text."""
    lines = [f"Car {row['number']}  ({row['type']})",
             f"status {row['status']}, {row['n_points']} points, RMS {row['rms_px']} px"]
    if row.get("doubt"):  # the report's '‡ doubtful': these numbers and their ± may be far off
        lines += [f"DOUBTFUL: {row['doubt']}"]
    lines += ["", f"Body centre, {crs} (95% half width):"]
    if crs == RELATIVE:  # no place on the Earth: metres from the camera
        lines += [f"  x  {row['e']} m  ± {row['ci_e']}  (right of the camera)",
                  f"  y  {row['n']} m  ± {row['ci_n']}  (ahead of the camera)",
                  f"  z  {row['h']} m  ± {row['ci_u']}  (above the camera)"]
    else:
        lines += [f"  E  {row['e']} m  ± {row['ci_e']}",
                  f"  N  {row['n']} m  ± {row['ci_n']}",
                  f"  h  {row['h']} m  ± {row['ci_u']}",
                  f"  lat {row['lat']}°  lon {row['lon']}°"]
    lines += ["",
              f"Heading {row['heading']}° ± {row['ci_heading']}" + ("  (from the camera's direction)"
                                                                     if crs == RELATIVE else ""),
              f"Pitch   {row['pitch']}° ± {row['ci_pitch']}",
              f"Roll    {row['roll']}° ± {row['ci_roll']}",
              "",
              f"Coupling to next: {row['coupling']}, gap {row['gap']} m",
              f"Terrain clearance {row['clearance']} m"]
    return "\n".join(lines).replace("\u2212", "-")  # the GUI font has no minus sign


class IncidentViewer:
    """The viewer window of one incident (create it after ``gui.Application.instance.initialize()``)."""

    def __init__(self, project: Project, *, width: int = 1280, height: int = 800) -> None:
        from ..report.render_stage import (SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG, fit_distance, view_direction,
                                           viewer_azimuth)
        from ..report.report_stage import carriage_rows
        from ..report.scene import camera_glyph, load_scene

        o3d, gui, rendering = _open3d()
        self.o3d, self.gui, self.rendering = o3d, gui, rendering
        self.project = project
        self.sc = load_scene(project)
        self.rows = {r["number"]: r for r in carriage_rows(project, self.sc.solution)}
        relative = (self.sc.solution.get("frame") or {}).get("kind") == "relative"
        self.crs = RELATIVE if relative else project.settings.location.crs
        self.selected: str | None = None
        app = gui.Application.instance
        self.window = app.create_window(f"{project.settings.incident.name} - workbench viewer", width, height)
        w = self.window
        em = w.theme.font_size

        self.widget = gui.SceneWidget()
        self.widget.scene = rendering.Open3DScene(w.renderer)
        self.widget.scene.set_background([0.70, 0.80, 0.91, 1.0])
        az, el = math.radians(SUN_AZIMUTH_DEG), math.radians(SUN_ELEVATION_DEG)
        sun = -np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)], np.float32)
        self.widget.scene.set_lighting(rendering.Open3DScene.LightingProfile.NO_SHADOWS, sun)
        self.widget.set_on_mouse(self._on_mouse)

        from ..render.offscreen import SceneMesh, to_open3d  # the renderer's trimesh -> Open3D conversion

        self._names: dict[str, list[str]] = {k: [] for k in LAYERS}

        def add(layer: str, name: str, mesh) -> None:
            m, mat = to_open3d(SceneMesh(name, mesh))
            self.widget.scene.add_geometry(name, m, mat)
            self._names[layer].append(name)

        if self.sc.terrain is not None:
            add("terrain", "terrain", self.sc.terrain)
        if self.sc.buildings is not None:
            add("buildings", "buildings", self.sc.buildings)
        for c in self.sc.carriages:
            add("carriages", f"car_{c.number}", self.sc.carriage_mesh(c))
        self.centre, self.radius = self.sc.focus()
        size = float(np.clip(0.05 * self.radius, 1.5, 8.0))
        for i, cam in enumerate(self.sc.cameras):
            add("cameras", f"camera_{i}", camera_glyph(cam, size))

        # ray casting of the carriages, for picking
        self._rays = o3d.t.geometry.RaycastingScene()
        self._gid: dict[int, str] = {}
        for c in self.sc.carriages:
            m = self.sc.carriage_mesh(c)
            gid = self._rays.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                                           o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
            self._gid[int(gid)] = c.number

        # camera: the report's overview
        bbox = o3d.geometry.AxisAlignedBoundingBox(self.centre - self.radius, self.centre + self.radius)
        self.widget.setup_camera(50.0, bbox, self.centre.astype(np.float32))
        self.home_eye = self.centre + view_direction(viewer_azimuth(self.sc, self.centre) + 25.0, 32.0) * \
            fit_distance(self.radius, width, height, 50.0, margin=0.9)
        self.reset_view()

        # panel
        panel = gui.Vert(0.4 * em, gui.Margins(0.6 * em, 0.6 * em, 0.6 * em, 0.6 * em))
        title = gui.Label(project.settings.incident.name)
        panel.add_child(title)
        panel.add_child(gui.Label(f"{project.settings.incident.date}  ·  {self.crs}"))
        panel.add_fixed(0.5 * em)
        panel.add_child(gui.Label("Layers"))
        self.checks = {}
        for layer in LAYERS:
            cb = gui.Checkbox(f"{layer} ({len(self._names[layer])})")
            cb.checked = True
            cb.set_on_checked(lambda on, layer=layer: self.show_layer(layer, on))
            panel.add_child(cb)
            self.checks[layer] = cb
        panel.add_fixed(0.5 * em)
        panel.add_child(gui.Label("Carriages (Ctrl+click one in the view)"))
        self.list = gui.ListView()
        self.numbers = [c.number for c in self.sc.carriages]
        self.list.set_items([f"{n}  {self.rows[n]['status'] if n in self.rows else ''}"
                             + ("  (doubtful)" if self.rows.get(n, {}).get("doubt") else "") for n in self.numbers])
        self.list.set_max_visible_items(8)
        self.list.set_on_selection_changed(lambda text, dbl: self.select(text.split()[0]))
        panel.add_child(self.list)
        panel.add_fixed(0.5 * em)
        self.details = gui.Label("Pick a carriage to see its position,\nattitude and 95% uncertainty.")
        panel.add_child(self.details)
        panel.add_stretch()
        home = gui.Button("Reset view")
        home.set_on_clicked(self.reset_view)
        panel.add_child(home)
        self.panel = panel
        w.add_child(self.widget)
        w.add_child(panel)
        w.set_on_layout(self._layout)

    # -- layout and camera ----------------------------------------------------------------------------
    def _layout(self, ctx) -> None:
        r = self.window.content_rect
        pw = PANEL_WIDTH_EM * self.window.theme.font_size
        self.widget.frame = self.gui.Rect(r.x, r.y, r.width - pw, r.height)
        self.panel.frame = self.gui.Rect(r.get_right() - pw, r.y, pw, r.height)

    def reset_view(self) -> None:
        self.widget.look_at(self.centre.astype(np.float32), self.home_eye.astype(np.float32),
                            np.array([0.0, 0.0, 1.0], np.float32))

    def show_layer(self, layer: str, on: bool) -> None:
        if layer not in self._names:
            raise ValueError(f"unknown layer {layer!r}; the layers are {', '.join(LAYERS)}")
        for n in self._names[layer]:
            self.widget.scene.show_geometry(n, bool(on))
        if layer == "carriages" and self.selected and self.widget.scene.has_geometry("selection"):
            self.widget.scene.show_geometry("selection", bool(on))
        self.checks[layer].checked = bool(on)

    # -- picking -------------------------------------------------------------------------------------
    def _camera_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        cam = self.widget.scene.camera
        return np.asarray(cam.get_view_matrix(), float), np.asarray(cam.get_projection_matrix(), float)

    def widget_pixel(self, point_enu: np.ndarray) -> tuple[float, float] | None:
        """Where a scene point appears in the 3-D view: (x, y) pixels from the view's top-left, None if behind."""
        V, P = self._camera_matrices()
        clip = P @ V @ np.append(np.asarray(point_enu, float), 1.0)
        if clip[3] <= 0:
            return None
        ndc = clip[:3] / clip[3]
        f = self.widget.frame
        return (ndc[0] + 1.0) * 0.5 * f.width, (1.0 - ndc[1]) * 0.5 * f.height

    def carriage_at(self, x: float, y: float) -> str | None:
        """The carriage seen at pixel (x, y) of the 3-D view (from its top-left), or None."""
        V, P = self._camera_matrices()
        f = self.widget.frame
        eye = np.linalg.inv(V)[:3, 3]
        inv = np.linalg.inv(P @ V)
        d = None
        for z in (0.0, 0.5, -0.5, 0.9):  # any point on the pixel's ray (Filament's depth range varies)
            q = inv @ np.array([2.0 * x / f.width - 1.0, 1.0 - 2.0 * y / f.height, z, 1.0])
            if abs(q[3]) > 1e-12 and np.all(np.isfinite(q)):
                q = q[:3] / q[3] - eye
                if np.linalg.norm(q) > 1e-9:
                    d = q / np.linalg.norm(q)
                    break
        if d is None:
            return None
        ray = np.concatenate([eye, d]).astype(np.float32)[None]
        ans = self._rays.cast_rays(self.o3d.core.Tensor(ray))
        if not np.isfinite(ans["t_hit"].numpy()[0]):
            return None
        return self._gid.get(int(ans["geometry_ids"].numpy()[0]))

    def _on_mouse(self, event) -> int:
        gui = self.gui
        if (event.type == gui.MouseEvent.Type.BUTTON_DOWN and event.is_button_down(gui.MouseButton.LEFT)
                and event.is_modifier_down(gui.KeyModifier.CTRL)):
            f = self.widget.frame
            number = self.carriage_at(event.x - f.x, event.y - f.y)
            if number is not None:
                self.select(number)
            return gui.Widget.EventCallbackResult.HANDLED
        return gui.Widget.EventCallbackResult.IGNORED

    def select(self, number: str) -> None:
        """Show carriage ``number``'s numbers in the panel and outline it in the view."""
        car = next((c for c in self.sc.carriages if c.number == number), None)
        if car is None:
            raise ValueError(f"no carriage {number!r} with a pose; the carriages are {', '.join(self.numbers)}")
        self.selected = number
        self.details.text = carriage_text(self.rows[number], self.crs)
        o3d = self.o3d
        lines = o3d.geometry.LineSet.create_from_oriented_bounding_box(
            o3d.geometry.OrientedBoundingBox.create_from_points(o3d.utility.Vector3dVector(car.corners_enu())))
        lines.paint_uniform_color([1.0, 0.85, 0.0])
        mat = self.rendering.MaterialRecord()
        mat.shader = "unlitLine"
        mat.line_width = 3.0
        if self.widget.scene.has_geometry("selection"):
            self.widget.scene.remove_geometry("selection")
        self.widget.scene.add_geometry("selection", lines, mat)
        idx = self.numbers.index(number)
        if self.list.selected_index != idx:
            self.list.selected_index = idx
        self.window.post_redraw()

    # -- screenshots ---------------------------------------------------------------------------------
    def screenshot(self, path: Path, *, timeout_s: float = 60.0) -> Path:
        """Draw frames until the window shows on the display, then write the window (panel included, grabbed from
        the X display) to ``path``; without a display to grab from, the 3-D view alone."""
        app = self.gui.Application.instance
        path = Path(path)
        img = None
        t0 = time.perf_counter()
        grab_ok = True
        for _ in range(4):
            self.window.post_redraw()
            app.run_one_tick()
        while grab_ok and time.perf_counter() - t0 < timeout_s:
            self.window.post_redraw()
            app.run_one_tick()
            try:
                from PIL import ImageGrab

                fr = self.window.os_frame
                shot = ImageGrab.grab().crop((fr.x, fr.y, fr.x + fr.width, fr.y + fr.height))
            except Exception as exc:  # noqa: BLE001 - no X display, no XCB in Pillow, ...
                log.warning("viewer: cannot grab the window from the display (%s); writing the 3-D view only", exc)
                grab_ok = False
                break
            a = np.asarray(shot)
            # drawn: the panel (right) and the 3-D view (left) both show something
            pw = int(PANEL_WIDTH_EM * self.window.theme.font_size)
            if a[:, -pw:].std() > 2.0 and a[:, :-pw].std() > 2.0:
                img = shot
                for _ in range(2):  # one more frame, so the view is complete
                    self.window.post_redraw()
                    app.run_one_tick()
                fr = self.window.os_frame
                img = ImageGrab.grab().crop((fr.x, fr.y, fr.x + fr.width, fr.y + fr.height))
                break
            time.sleep(0.1)
        log.info("viewer: frame ready after %.1f s", time.perf_counter() - t0)

        if img is None:
            f = self.widget.frame
            from PIL import Image

            img = Image.fromarray(np.asarray(app.render_to_image(self.widget.scene, f.width, f.height)))
        atomic_write(path, lambda p: img.save(p, format="PNG"))
        return path


def view(root: str | Path, *, screenshot: str | Path | None = None, select: str | None = None,
         width: int = 1280, height: int = 800) -> Path | None:
    """Open the viewer on an incident (blocks until the window closes).

    ``screenshot``: draw one frame, write it (PNG) and return its path instead of waiting.
    ``select``: a car number to select at start.
    """
    project = Project(root)
    project.settings  # validate first

    project.require_solution("viewer")
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # Open3D aborts the process (no exception) when it cannot open a window
        raise RenderError("the viewer needs a display (DISPLAY is not set); on a machine without one run it "
                          f"under a virtual one: `xvfb-run -a workbench view {root}` (Debian: apt-get install -y "
                          f"xvfb xauth)")
    _o3d, gui, _rendering = _open3d()
    app = gui.Application.instance
    try:
        app.initialize()
    except Exception as exc:  # noqa: BLE001 - Open3D raises RuntimeError with varying text
        raise RenderError(f"the viewer cannot open a window ({exc}); it needs a display (run it under `xvfb-run` "
                          f"without one)") from None
    viewer = IncidentViewer(project, width=width, height=height)
    if select:
        viewer.select(select)
    if screenshot is not None:
        p = viewer.screenshot(Path(screenshot))
        viewer.window.close()
        app.run_one_tick()
        return p
    app.run()
    return None
