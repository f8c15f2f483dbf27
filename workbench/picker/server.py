"""The marked-point picker: a small local web page (standard-library HTTP server + an HTML canvas).

``serve(root)`` starts a server on 127.0.0.1 for one incident; a browser shows a photo beside the
carriage's faces (its livery, the model's textured sides and ends, with the marked points). The user picks a
marked point on a face, then its place in the photo; zoom (mouse wheel), pan (drag), undo (Ctrl+Z) and save
(Ctrl+S). The automatic points (``out/correspond/correspondences.json``) are shown for review: picking a
point again overrides it (a manual point replaces an automatic one in the ``correspond`` stage), and an
automatic point found wrong is rejected (key R; the stage then drops it).

Saving writes the incident's ``correspondences.json`` atomically, after the same validation as the stage
(unknown carriage or point names, out-of-image coordinates, duplicates are refused with the message).

Endpoints: ``GET /`` page; ``GET /api/state``; ``GET /photo/<name>``; ``GET /reference/<car>/<face>.png``;
``POST /api/save`` with ``{"observations": [...], "rejected": [...]}``. Only local connections; no external resources.
"""

from __future__ import annotations

import io
import json
import logging
import threading
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..correspond import manual as mf
from ..correspond.references import FACES, face_reference
from ..errors import InputError, WorkbenchError
from ..project import Project

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
REFERENCE_PX_PER_M = 40.0


@dataclass
class PickerState:
    """What the page needs, gathered once per request (the files may change between saves)."""

    project: Project

    def photos(self) -> list[Path]:
        return self.project.photo_paths()

    def image_sizes(self) -> dict[str, tuple[int, int]]:
        from PIL import Image

        out = {}
        for p in self.photos():
            with Image.open(p) as im:
                out[p.name] = im.size
        return out

    def document(self) -> dict:
        project = self.project
        types = project.carriage_types()
        sizes = self.image_sizes()
        cars = []
        for c in project.settings.consist:
            ct = types[c.number]
            faces = {}
            for f in FACES:
                ref = _reference(project, c.number, f)
                if not ref.points:  # the roof: no marked point lies on its plane
                    continue
                faces[f] = {"url": f"/reference/{c.number}/{f}.png", "width": int(ref.image.shape[1]),
                            "height": int(ref.image.shape[0]),
                            "points": {n: [round(float(v), 2) for v in p] for n, p in ref.points.items()}}
            cars.append({"number": c.number, "type": ct.id, "name": ct.name, "points": list(ct.marked_points),
                         "point_faces": {n: list(fs) for n, fs in ct.marked_point_faces.items()}, "faces": faces})
        manual, rejected = [], []
        mp = project.root / mf.FILE_NAME
        if mp.is_file():
            own = mf.parse(project.read_json(mp), mp)
            manual = [o.to_json() for o in own.observations]
            rejected = [r.model_dump(exclude_defaults=True) for r in own.rejected]
        auto = []
        ap = project.stage_dir("correspond") / mf.FILE_NAME
        if ap.is_file():
            auto = [o.to_json() for o in mf.parse(project.read_json(ap), ap).observations if o.source == "sift"]
        return {"incident": project.settings.incident.name, "root": str(project.root),
                "photos": [{"name": n, "width": w, "height": h, "url": f"/photo/{n}"} for n, (w, h) in sizes.items()],
                "cars": cars, "manual": manual, "rejected": rejected, "automatic": auto}

    def save(self, payload: object) -> Path:
        """Validate ``{"observations": [...], "rejected": [...]}`` (manual points, automatic points found
        wrong) and write the incident's file atomically."""
        project = self.project
        path = project.root / mf.FILE_NAME
        if not isinstance(payload, dict):
            raise InputError("the picker sent no JSON object")
        obs = [dict(o, source="manual") for o in payload.get("observations", []) if isinstance(o, dict)]
        doc = {"observations": obs, "rejected": [r for r in payload.get("rejected", []) if isinstance(r, dict)]}
        old = None
        if path.is_file():
            try:
                old = mf.parse(project.read_json(path), path)
            except WorkbenchError:
                old = None
        if old is not None:
            doc["needs_manual"] = [n.model_dump() for n in old.needs_manual]
            if old.note:
                doc["note"] = old.note
        types = project.carriage_types()
        cf = mf.validate(mf.parse(doc, path), path, points={n: list(t.marked_points) for n, t in types.items()},
                         image_sizes=self.image_sizes())
        return project.write_json(path, cf.to_json())


_ref_cache: dict[tuple[str, str, str], object] = {}
_ref_lock = threading.Lock()


def _reference(project: Project, number: str, face: str):
    key = (str(project.root), number, face)
    with _ref_lock:
        hit = _ref_cache.get(key)
    if hit is None:
        ct = project.carriage_types()[number]
        hit = face_reference(ct, number, face, REFERENCE_PX_PER_M)
        with _ref_lock:
            _ref_cache[key] = hit
    return hit


def _handler(state: PickerState):
    class Handler(BaseHTTPRequestHandler):
        server_version = "workbench-picker"

        def log_message(self, fmt, *args):  # route to logging, not stderr
            log.debug("picker: " + fmt, *args)

        def _send(self, status: int, body: bytes, ctype: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, status: int, data: object) -> None:
            self._send(status, json.dumps(data).encode(), "application/json")

        def do_GET(self) -> None:  # noqa: N802 - http.server API
            path = unquote(self.path.split("?")[0])
            try:
                if path in ("/", "/index.html"):
                    return self._send(200, (STATIC / "index.html").read_bytes(), "text/html; charset=utf-8")
                if path == "/picker.js":
                    return self._send(200, (STATIC / "picker.js").read_bytes(), "text/javascript; charset=utf-8")
                if path == "/api/state":
                    return self._json(200, state.document())
                if path.startswith("/photo/"):
                    name = path[len("/photo/"):]
                    photos = {p.name: p for p in state.photos()}
                    if name not in photos:
                        return self._json(404, {"error": f"no photo {name!r}"})
                    ctype = "image/png" if name.lower().endswith(".png") else "image/jpeg"
                    return self._send(200, photos[name].read_bytes(), ctype)
                if path.startswith("/reference/") and path.endswith(".png"):
                    number, face = path[len("/reference/"):-4].split("/", 1)
                    if number not in state.project.carriage_types() or face not in FACES:
                        return self._json(404, {"error": f"no reference {number}/{face}"})
                    from PIL import Image

                    buf = io.BytesIO()
                    Image.fromarray(np.ascontiguousarray(_reference(state.project, number, face).image)).save(buf, "PNG")
                    return self._send(200, buf.getvalue(), "image/png")
                return self._json(404, {"error": f"no such page {path!r}"})
            except WorkbenchError as exc:
                return self._json(400, {"error": str(exc)})

        def do_POST(self) -> None:  # noqa: N802
            if self.path != "/api/save":
                return self._json(404, {"error": f"no such endpoint {self.path!r}"})
            n = int(self.headers.get("Content-Length") or 0)
            try:
                payload = json.loads(self.rfile.read(n) or b"{}")
                written = state.save(payload)
            except json.JSONDecodeError as exc:
                return self._json(400, {"error": f"not JSON: {exc}"})
            except WorkbenchError as exc:
                return self._json(400, {"error": str(exc)})
            return self._json(200, {"saved": str(written), "n": len(payload.get("observations", [])),
                                    "n_rejected": len(payload.get("rejected", []))})

    return Handler


class PickerServer:
    """A running picker (background thread). ``url`` to open; ``close()`` to stop."""

    def __init__(self, root: str | Path, host: str = "127.0.0.1", port: int = 0) -> None:
        self.project = Project(root)
        self.project.settings  # validate early
        self.httpd = ThreadingHTTPServer((host, port), _handler(PickerState(self.project)))
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="picker", daemon=True)

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> "PickerServer":
        self.thread.start()
        log.info("picker for %s at %s", self.project.root, self.url)
        return self

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    def __enter__(self) -> "PickerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def serve(root: str | Path, *, host: str = "127.0.0.1", port: int = 8765, open_browser: bool = True) -> None:
    """Run the picker for incident ``root`` until interrupted (the ``workbench pick`` command)."""
    srv = PickerServer(root, host, port).start()
    if open_browser:
        import webbrowser

        webbrowser.open(srv.url)
    log.warning("picker running at %s (Ctrl+C to stop)", srv.url)
    try:
        srv.thread.join()
    except KeyboardInterrupt:
        pass
    finally:
        srv.close()
