"""The marked-point picker: a small local web page (standard-library HTTP server + an HTML canvas).

``serve(root)`` starts a server on 127.0.0.1 for one incident; a browser shows a photo beside the
carriage's faces (its livery, the model's textured sides and ends, with the marked points). The user picks a
marked point on a face, then its place in the photo; zoom (mouse wheel), pan (drag), undo (Ctrl+Z) and save
(Ctrl+S). The automatic points (``out/correspond/correspondences.json``) are shown for review: picking a
point again overrides it (a manual point replaces an automatic one in the ``correspond`` stage), and an
automatic point found wrong is rejected (key R; the stage then drops it).

Endpoints: ``GET /`` page; ``GET /picker.js``; ``GET /api/state``; ``GET /photo/<name>``;
``GET /reference/<car>/<face>.png``; ``POST /api/save`` with ``{"observations": [...], "rejected": [...]}``;
``GET /api/overlay?view=<photo>``: after a solve, the carriages' outlines and every pick's residual
(:mod:`.overlay`); ``POST /api/pose`` with one carriage's current picks: its pose on the spot and where its
other marked points should fall (:mod:`.live`; nothing is written). A pick may be made from two edges drawn
along a rounded or hidden corner (``construction`` in correspondences.json, :mod:`workbench.files.correspondences`).
Control points (:mod:`.control`, :mod:`.map`; docs/picker.md): ``GET /api/map`` (the map's georeference and
layers), ``GET /map.png``, ``GET /api/control_points``; ``POST /api/locate`` (a map click or typed coordinates:
project CRS, WGS84 and the DEM's height), ``POST /api/control_points`` (a save of control_points.json, checked
as the georef stage reads it, atomic, the previous file kept as ``.bak``), ``POST /api/georef`` (the georef stage
run in-process: residuals, camera placements and their uncertainty).

The picker holds forensic work, so it trusts no request (docs/formats.md, "correspondences.json"):

* It listens on 127.0.0.1 only. Every request must name it in ``Host`` (``127.0.0.1:PORT`` or
  ``localhost:PORT``: a DNS-rebinding page is refused) and, where it sends an ``Origin``, come from the page
  itself (same origin); a request another site's page makes (``Sec-Fetch-Site`` cross-site or same-site) is
  refused unless it is a navigation to the page.
* A random token, new at every start, is embedded in the page (``<meta name="picker-token">``); ``/api/state``
  and every write must send it in the ``X-Picker-Token`` header, and a write must be ``Content-Type:
  application/json`` with a ``Content-Length`` of at most 4 MiB. Otherwise: 403, 415, 411 or 413.
* A save is validated completely before anything is written: JSON (UTF-8, no NaN or Infinity, no duplicate
  keys, nested at most 8 deep), the keys ``observations`` and ``rejected`` (lists of objects, nothing else),
  then the stage's own reader and validator (``workbench.files.correspondences``: types, finite numbers, carriage,
  point and photo names, pixels inside the photo, duplicates). A bad save is a 400 whose JSON ``error`` names
  the key and the value (cut to a few dozen characters) and leaves the file as it was.
* A good save writes ``correspondences.json`` atomically (a temp file renamed over it) and first keeps the
  previous file, when it differs, as ``correspondences.json.bak`` beside it (one generation: the file as it was
  before the last save that changed it).
* Only files inside the incident folder are served: a photo whose resolved path (a symlink) leaves the folder
  is left out of the page and answered 404.
* A bad request is answered with a JSON ``{"error": ...}`` and logged as one line, never a traceback; an
  unexpected error is a 500 with a JSON message (nothing is written). A port already in use is a
  :class:`WorkbenchError` naming the port (choose another with ``--port``).
"""

from __future__ import annotations

import errno
import hmac
import io
import json
import logging
import re
import secrets
import socket
import sys
import threading
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, quote, unquote

import numpy as np

from ..core.io import atomic_write_bytes, atomic_write_text, to_json
from ..files import correspondences as mf
from ..correspond.references import FACES, face_reference
from ..errors import InputError, OutputError, WorkbenchError
from ..project import Project
from .control import ControlPointsApi
from .live import live_pose
from .overlay import solution_overlay, strict

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
REFERENCE_PX_PER_M = 40.0
HOST = "127.0.0.1"
TOKEN_HEADER = "X-Picker-Token"
TOKEN_MARK = "__PICKER_TOKEN__"  # in static/index.html, replaced by the run's token
MAX_BODY = 4 << 20  # bytes of a save (thousands of points fit in under 1 MiB)
MAX_DEPTH = 8  # JSON nesting of a save (a valid one is 4 deep)
BACKUP_SUFFIX = ".bak"
SAVE_KEYS = ("observations", "rejected")
CONTROL_ENDPOINTS = ("/api/locate", "/api/control_points", "/api/georef")
SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
                               "img-src 'self' data: blob:; connect-src 'self'; base-uri 'none'; "
                               "form-action 'none'; frame-ancestors 'none'",
}


class Refused(Exception):
    """A request the picker answers with ``status`` and a JSON ``{"error": message}``."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = int(status)
        self.message = message


class WriteFailed(Exception):
    """The incident's file could not be written (a read-only folder, a full disk): a 500, nothing changed."""


def _cut(value: object, n: int = 60, *, quote: bool = True) -> str:
    return mf.cut_for_message(value, n, quote=quote)


@dataclass
class PickerState:
    """What the page needs, gathered once per request (the files may change between saves)."""

    project: Project
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _warned: set = field(default_factory=set, repr=False)
    _control: ControlPointsApi | None = field(default=None, repr=False)

    @property
    def control(self) -> ControlPointsApi:
        """The control-point endpoints (the map is built on first use)."""
        if self._control is None:
            self._control = ControlPointsApi(self.project, self.image_sizes)
        return self._control

    @property
    def path(self) -> Path:
        return self.project.manual_picks_path

    @property
    def backup_path(self) -> Path:
        return self.path.with_name(mf.FILE_NAME + BACKUP_SUFFIX)

    def _inside(self, p: Path) -> bool:
        try:
            real = p.resolve(strict=True)
        except (OSError, RuntimeError):
            return False
        return real.is_relative_to(self.project.root) and real.is_file()

    def photos(self) -> list[Path]:
        """The incident's photos that lie inside its folder (a symlink that leaves it is left out, logged once)."""
        out = []
        for p in self.project.photo_paths():
            if self._inside(p):
                out.append(p)
            elif p.name not in self._warned:
                self._warned.add(p.name)
                log.warning("picker: photo %s is left out: it resolves outside the incident folder %s (or is not "
                            "a file)", p, self.project.root)
        return out

    def photo(self, name: str) -> Path | None:
        """The photo called ``name`` if it is one of the incident's and lies inside its folder."""
        hit = {p.name: p for p in self.photos()}.get(name)
        return hit if hit is not None and self._inside(hit) else None

    def image_sizes(self) -> dict[str, tuple[int, int]]:
        from PIL import Image

        out = {}
        for p in self.photos():
            try:
                with Image.open(p) as im:
                    out[p.name] = im.size
            except Exception as exc:  # PIL raises many kinds for a bad file
                raise InputError(f"{p}: not a readable photo ({type(exc).__name__}: {_cut(str(exc), 80)}); replace "
                                 f"or remove it") from None
        return out

    def _own(self) -> mf.CorrespondenceFile | None:
        """The incident's correspondences.json as it is (None: absent)."""
        if not self.path.is_file():
            return None
        return mf.parse(self.project.read_json(self.path), self.path)

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
        own = self._own()
        if own is not None:
            manual = [o.to_json() for o in own.observations]
            rejected = [r.model_dump(exclude_defaults=True) for r in own.rejected]
        auto = []
        ap = project.stage_dir("correspond") / mf.FILE_NAME
        if ap.is_file():
            auto = [o.to_json() for o in mf.parse(project.read_json(ap), ap).observations if o.source == "sift"]
        return {"incident": project.settings.incident.name, "root": str(project.root),
                "photos": [{"name": n, "width": w, "height": h, "url": f"/photo/{quote(n)}"}
                           for n, (w, h) in sizes.items()],
                "cars": cars, "manual": manual, "rejected": rejected, "automatic": auto}

    def check(self, payload: object) -> mf.CorrespondenceFile:
        """The file a save of ``payload`` would write, validated completely; :class:`InputError` naming the key
        and the value otherwise. Writes nothing."""
        shape = '{"observations": [...], "rejected": [...]}'
        if not isinstance(payload, dict):
            raise InputError(f"the save must be a JSON object {shape}; got {type(payload).__name__} {_cut(payload)}")
        unknown = [k for k in payload if k not in SAVE_KEYS]
        if unknown:
            raise InputError(f"unknown key {_cut(unknown[0])} in the save (its keys: observations, rejected)")
        for k in SAVE_KEYS:
            if k not in payload:
                raise InputError(f"{k}: missing from the save (send [] for none)")
            if not isinstance(payload[k], list):
                raise InputError(f"{k} = {_cut(payload[k])}: must be a list of objects")
            for i, item in enumerate(payload[k]):
                if not isinstance(item, dict):
                    raise InputError(f"{k}[{i}] = {_cut(item)}: must be an object")
        for i, o in enumerate(payload["observations"]):
            if o.get("source", "manual") != "manual":
                raise InputError(f"observations[{i}].source = {_cut(o.get('source'))}: the picker saves manual "
                                 f"points only ('manual')")
        doc: dict = {"observations": [dict(o, source="manual") for o in payload["observations"]],
                     "rejected": list(payload["rejected"])}
        try:
            old = self._own()
        except WorkbenchError:  # unreadable now: the save replaces it (and keeps it as the backup)
            old = None
        if old is not None:
            doc["needs_manual"] = [n.model_dump() for n in old.needs_manual]
            if old.note:
                doc["note"] = old.note
        types = self.project.carriage_types()
        return mf.validate(mf.parse(doc, self.path), self.path,
                           points={n: list(t.marked_points) for n, t in types.items()},
                           image_sizes=self.image_sizes())

    def save(self, payload: object) -> dict:
        """Validate a save (:meth:`check`), then write the incident's file atomically, keeping the previous one
        as ``correspondences.json.bak`` when it differs. Returns what was written."""
        with self._lock:
            cf = self.check(payload)
            text = to_json(cf.to_json())
            backup = None
            try:
                old = self.path.read_bytes() if self.path.is_file() else None
                if old is not None and old != text.encode("utf-8"):
                    backup = atomic_write_bytes(self.backup_path, old)
                atomic_write_text(self.path, text)
            except OutputError as exc:  # core.io's own message: the file, why, what to do
                raise WriteFailed(str(exc)) from None
            except OSError as exc:
                raise WriteFailed(f"could not write {self.path} ({exc.strerror or exc}); the file is unchanged: "
                                  f"check that the incident folder is writable and the disk has room") from None
        return {"saved": str(self.path), "backup": str(backup) if backup else None, "n": len(cf.observations),
                "n_rejected": len(cf.rejected)}


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


_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)
_BRACKET = re.compile(r"[\[\]{}]")


def _too_deep(text: str, limit: int = MAX_DEPTH) -> bool:
    """Whether JSON ``text`` nests arrays and objects more than ``limit`` deep (strings skipped)."""
    depth = 0
    for m in _BRACKET.finditer(_STRING.sub('""', text)):
        depth += 1 if m.group() in "[{" else -1
        if depth > limit:
            return True
    return False


def _no_duplicates(pairs: list) -> dict:
    seen: dict = {}
    for k, v in pairs:
        if k in seen:
            raise Refused(400, f"key {_cut(k)} appears twice in one object")
        seen[k] = v
    return seen


def _refuse_constant(name: str):
    raise Refused(400, f"{name} is not a number a save may hold (send finite numbers)")


def parse_body(data: bytes) -> object:
    """A save's JSON; :class:`Refused` (400) for anything but UTF-8 JSON without NaN/Infinity, duplicate keys or
    deep nesting."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise Refused(400, f"the body is not UTF-8 (byte {exc.start})") from None
    if not text.strip():
        raise Refused(400, 'the body is empty: send {"observations": [...], "rejected": [...]}')
    if _too_deep(text):
        raise Refused(400, f"the JSON is nested more than {MAX_DEPTH} deep")
    try:
        return json.loads(text, parse_constant=_refuse_constant, object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError; so is a 5000-digit number
        raise Refused(400, f"not JSON: {_cut(str(exc), 80)}") from None


class PickerHandler(BaseHTTPRequestHandler):
    """The picker's requests: every check of the module docstring, then the page, its files and the save.
    A server uses a subclass bound to its run's :class:`PickerState`, token and page (:func:`_handler`)."""

    state: PickerState
    token: str
    page_bytes: bytes
    server_version = "workbench-picker"
    sys_version = ""
    timeout = 10  # seconds a client may take to send its request (a short body does not hold a thread)
    _body_read = False

    # -- answers -------------------------------------------------------------------------------------
    def log_message(self, fmt, *args):  # http.server's access log: debug only, never stderr by itself
        log.debug("picker: " + fmt, *args)

    def _send(self, status: int, body: bytes, ctype: str, extra: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        for k, v in {**SECURITY_HEADERS, **(extra or {})}.items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, data: object, extra: dict | None = None) -> None:
        self._send(status, json.dumps(data).encode(), "application/json", extra)

    def _refuse(self, status: int, message: str, extra: dict | None = None) -> None:
        """One log line and a JSON answer; the connection is closed after it."""
        log.warning("picker: %d for %s %s: %s", status,
                    _cut(getattr(self, "command", None) or "-", 20, quote=False),
                    _cut(getattr(self, "path", None) or "-", 80, quote=False), message)
        self.close_connection = True
        if not self._body_read:
            self._discard_body()
        try:
            self._json(status, {"error": message}, extra)
        except OSError:  # the client has gone
            pass

    def send_error(self, code, message=None, explain=None):  # noqa: D401 - http.server's own refusals
        """http.server's refusals of a malformed request (request line, headers, HTTP version): JSON, one
        log line, and a 4xx (a malformed request is the client's fault: never a 5xx)."""
        code = int(code)
        if code >= 500:
            code = 400
        if not hasattr(self, "command") or self.command is None:
            self.command = ""
        self._refuse(code, message or HTTPStatus(code).phrase)

    def _discard_body(self) -> None:
        """Read and drop a refused request's body (if small enough), so the client reads the answer, not a
        connection reset."""
        n = (self.headers.get("Content-Length") or "").strip() if getattr(self, "headers", None) else ""
        if not re.fullmatch(r"[0-9]{1,8}", n) or int(n) > MAX_BODY:
            return
        try:
            self.connection.settimeout(2)
            self.rfile.read(int(n))
        except OSError:
            pass
        self._body_read = True

    # -- checks --------------------------------------------------------------------------------------
    def _origins(self) -> tuple[set[str], set[str]]:
        port = self.server.server_address[1]
        hosts = {f"127.0.0.1:{port}", f"localhost:{port}"}
        return hosts, {f"http://{h}" for h in hosts}

    def _gate(self, *, token_needed: bool, navigation_ok: bool) -> None:
        hosts, origins = self._origins()
        host = self.headers.get_all("Host") or []
        if len(host) != 1 or host[0].strip().lower() not in hosts:
            given = f"Host {_cut(host[0])}" if len(host) == 1 else f"{len(host)} Host headers"
            raise Refused(403, f"{given}: not this picker (use http://127.0.0.1:{self.server.server_address[1]}/)")
        origin = self.headers.get_all("Origin") or []
        if len(origin) > 1 or (origin and origin[0].strip().lower() not in origins):
            raise Refused(403, f"Origin {_cut(origin[0])} is not this picker's page")
        site = (self.headers.get("Sec-Fetch-Site") or "").strip().lower()
        mode = (self.headers.get("Sec-Fetch-Mode") or "").strip().lower()
        if site in ("cross-site", "same-site") and not (navigation_ok and mode == "navigate"):
            raise Refused(403, f"a request from another site ({site}) is refused")
        if token_needed:
            given = self.headers.get(TOKEN_HEADER) or ""
            if not hmac.compare_digest(given.encode("utf-8", "replace"), self.token.encode()):
                raise Refused(403, f"missing or wrong {TOKEN_HEADER} header: reload the picker's page "
                                   f"(the token changes at every start)")

    def _read_body(self) -> bytes:
        ctype = (self.headers.get("Content-Type") or "").split(";")
        params = {p.split("=", 1)[0].strip().lower(): p.split("=", 1)[-1].strip().strip('"').lower()
                  for p in ctype[1:] if p.strip()}
        if ctype[0].strip().lower() != "application/json" or params.get("charset", "utf-8") != "utf-8":
            raise Refused(415, f"Content-Type {_cut(self.headers.get('Content-Type'))}: a save must be "
                               f"application/json (UTF-8)")
        if self.headers.get("Transfer-Encoding"):
            raise Refused(411, "send the body with a Content-Length (no Transfer-Encoding)")
        lengths = self.headers.get_all("Content-Length") or []
        if len(lengths) != 1:
            raise Refused(411, "a save needs one Content-Length header")
        n = lengths[0].strip()
        if not re.fullmatch(r"[0-9]{1,15}", n):
            raise Refused(400, f"Content-Length {_cut(n)} is not a number of bytes")
        if int(n) > MAX_BODY:
            raise Refused(413, f"Content-Length {int(n)}: a save is at most {MAX_BODY} bytes")
        n = int(n)
        try:
            data = self.rfile.read(n)
        except (TimeoutError, socket.timeout):
            self._body_read = True
            raise Refused(408, f"the body did not arrive within {self.timeout} s (Content-Length {n})") from None
        self._body_read = True
        if len(data) != n:
            raise Refused(400, f"the body has {len(data)} bytes, Content-Length says {n}")
        return data

    # -- dispatch ------------------------------------------------------------------------------------
    def _run(self, work) -> None:
        self._body_read = False
        try:
            if not self.path.startswith("/"):
                raise Refused(400, f"request target {_cut(self.path)} is not a path")
            work(unquote(self.path.split("?", 1)[0].split("#", 1)[0]))
            if not self._body_read:  # a body nobody asked for (a GET with one): read it, or the close resets
                self._discard_body()
        except Refused as exc:
            self._refuse(exc.status, exc.message)
        except WorkbenchError as exc:  # the save or the incident's files: one line naming file, key, value
            self._refuse(400, str(exc))
        except WriteFailed as exc:
            self._refuse(500, str(exc))
        except (BrokenPipeError, ConnectionResetError):
            log.info("picker: %s %s: the client closed the connection", self.command, _cut(self.path, 80))
            self.close_connection = True
        except Exception as exc:  # a bug: one line (the traceback with -vv), a 500, nothing written
            log.error("picker: internal error on %s %s: %s: %s", self.command, _cut(self.path, 80),
                      type(exc).__name__, _cut(str(exc), 200))
            log.debug("picker: traceback", exc_info=True)
            self._refuse(500, f"internal error ({type(exc).__name__}); nothing was written")

    def _get(self, path: str) -> None:
        page_paths = ("/", "/index.html")
        self._gate(token_needed=path.startswith("/api/"), navigation_ok=path in page_paths)
        if path in page_paths:
            return self._send(200, self.page_bytes, "text/html; charset=utf-8")
        if path in ("/picker.js", "/map.js"):
            return self._send(200, (STATIC / path[1:]).read_bytes(), "text/javascript; charset=utf-8")
        if path == "/map.png":
            return self._send(200, self.state.control.map.png(), "image/png")
        if path == "/api/map":  # no map (no orthophoto or DEM, or an orthophoto without georeference): said why
            try:
                return self._json(200, strict(self.state.control.map.document()))
            except InputError as exc:
                return self._json(200, {"available": False, "reason": str(exc)})
        if path == "/api/control_points":
            return self._json(200, strict(self.state.control.document()))
        if path == "/api/state":
            return self._json(200, self.state.document())
        if path == "/api/overlay":
            view = (parse_qs(self.path.split("?", 1)[1] if "?" in self.path else "").get("view") or [None])[0]
            if view is not None and self.state.photo(view) is None:
                raise Refused(404, f"no photo {_cut(view)} in the incident")
            return self._json(200, strict(solution_overlay(self.state.project, view)))
        if path.startswith("/photo/"):
            name = path[len("/photo/"):]
            p = self.state.photo(name)
            if p is None:
                raise Refused(404, f"no photo {_cut(name)} in the incident")
            ctype = {".png": "image/png", ".tif": "image/tiff", ".tiff": "image/tiff"}.get(p.suffix.lower(),
                                                                                           "image/jpeg")
            return self._send(200, p.read_bytes(), ctype)
        m = re.fullmatch(r"/reference/([^/]+)/([a-z]+)\.png", path)
        if path.startswith("/reference/"):
            if not m or m.group(1) not in self.state.project.carriage_types() or m.group(2) not in FACES:
                raise Refused(404, f"no reference {_cut(path[len('/reference/'):])}")
            from PIL import Image

            buf = io.BytesIO()
            ref = _reference(self.state.project, m.group(1), m.group(2))
            Image.fromarray(np.ascontiguousarray(ref.image)).save(buf, "PNG")
            return self._send(200, buf.getvalue(), "image/png")
        raise Refused(404, f"no such page {_cut(path)}")

    def _post(self, path: str) -> None:
        if path not in ("/api/save", "/api/pose") + CONTROL_ENDPOINTS:
            self._gate(token_needed=False, navigation_ok=False)
            raise Refused(404, f"no such endpoint {_cut(path)}")
        self._gate(token_needed=True, navigation_ok=False)
        payload = parse_body(self._read_body())
        if path in CONTROL_ENDPOINTS:
            return self._control_post(path, payload)
        if path == "/api/pose":  # reads only: the same checks as a save, then nothing written
            try:
                return self._json(200, strict(live_pose(self.state.project, payload, self.state.image_sizes())))
            except InputError as exc:
                raise Refused(400, f"pose request refused: {exc}") from None
        try:
            result = self.state.save(payload)
        except InputError as exc:
            raise Refused(400, f"save refused, {mf.FILE_NAME} unchanged: {exc}") from None
        log.info("picker: saved %d points and %d rejections to %s", result["n"], result["n_rejected"],
                 result["saved"])
        self._json(200, result)

    def _control_post(self, path: str, payload: object) -> None:
        """The control-point writes and queries (:mod:`.control`): a bad request is a 400 naming the key and
        the value, and nothing is written."""
        api = self.state.control
        if path == "/api/locate":
            return self._json(200, strict(api.locate(payload)))
        if path == "/api/georef":
            if payload not in ({}, None):
                raise Refused(400, "georef takes an empty object {} (it runs on the saved control_points.json)")
            try:
                return self._json(200, strict(api.run_georef()))
            except WorkbenchError as exc:
                raise Refused(400, f"georef: {exc}") from None
        try:
            result = api.save(payload)
        except InputError as exc:
            raise Refused(400, f"save refused, control_points.json unchanged: {exc}") from None
        log.info("picker: saved %d control points (%d picks) to %s", result["n"], result["n_picks"], result["saved"])
        self._json(200, result)

    def do_GET(self) -> None:  # noqa: N802 - http.server API
        self._run(self._get)

    def do_POST(self) -> None:  # noqa: N802
        self._run(self._post)

    def _not_allowed(self) -> None:
        def work(path: str) -> None:
            raise Refused(405, f"method {_cut(self.command)} is not allowed (GET, POST)")

        self._run(work)

    def __getattr__(self, name: str):  # any other method (HEAD, PUT, OPTIONS, BREW, ...): 405, not 501
        if name.startswith("do_"):
            return self._not_allowed
        raise AttributeError(name)



def _handler(state: PickerState, token: str) -> type[PickerHandler]:
    """A handler class bound to one picker: its state, its token, and its page with the token embedded."""
    page = (STATIC / "index.html").read_text(encoding="utf-8")
    if TOKEN_MARK not in page:
        raise RuntimeError(f"{STATIC / 'index.html'} lacks the token mark {TOKEN_MARK}")
    page_bytes = page.replace(TOKEN_MARK, token).encode("utf-8")

    class Handler(PickerHandler):
        pass

    Handler.state, Handler.token, Handler.page_bytes = state, token, page_bytes
    return Handler


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address) -> None:  # not socketserver's traceback on stderr
        exc = sys.exc_info()[1]
        log.warning("picker: connection from %s ended: %s: %s", client_address[0], type(exc).__name__,
                    _cut(str(exc), 120))


class PickerServer:
    """A running picker (background thread). ``url`` to open; ``token`` the run's write token; ``close()`` to
    stop. Listens on 127.0.0.1 only; ``port`` 0 picks a free one."""

    def __init__(self, root: str | Path, host: str = HOST, port: int = 0) -> None:
        if host not in (HOST, "localhost"):
            raise WorkbenchError(f"the picker listens on {HOST} only (got host {host!r})")
        self.project = Project(root)
        self.project.settings  # validate early
        self.token = secrets.token_urlsafe(32)
        handler = _handler(PickerState(self.project), self.token)
        try:
            self.httpd = _Server((HOST, port), handler)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise WorkbenchError(f"port {port} on {HOST} is already in use (another picker or program); choose "
                                     f"another with --port, e.g. --port {port + 1 if port < 65535 else 8765}") from None
            if exc.errno == errno.EACCES:
                raise WorkbenchError(f"port {port} on {HOST}: permission denied; choose a port from 1024 to 65535 "
                                     f"with --port") from None
            raise WorkbenchError(f"cannot listen on {HOST}:{port} ({exc.strerror or exc}); choose another port "
                                 f"with --port") from None
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1}, name="picker",
                                       daemon=True)

    @property
    def port(self) -> int:
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

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


def serve(root: str | Path, *, host: str = HOST, port: int = 8765, open_browser: bool = True) -> None:
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
