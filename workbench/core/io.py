"""Atomic file writes and content hashing (used by the Project object and the runner)."""

from __future__ import annotations

import errno
import glob
import hashlib
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

from ..errors import InputError, OutputError

_UMASK: int | None = None


def _file_mode() -> int:
    """The mode a new file gets under the process's umask (``0o666 & ~umask``), read once.

    ``tempfile.mkstemp`` creates its file 0600 and a rename keeps that mode; atomic writes set this mode instead,
    so an incident folder shared with colleagues (or served by a web server) stays readable as the user's umask
    says.
    """
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0o022)
        os.umask(_UMASK)
    return 0o666 & ~_UMASK


def atomic_write(path: Path, write: Callable[[Path], None], suffix: str | None = None) -> Path:
    """Write ``path`` atomically: ``write(tmp)`` writes a temp file in the same folder, then it is renamed.

    A crash or an exception inside ``write`` leaves any earlier ``path`` untouched. The file gets the mode the
    user's umask gives a new file.
    ``suffix`` (default: the suffix of ``path``) is kept on the temp name so writers that
    infer the format from the extension (PIL, cv2, rasterio) still work.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix if suffix is not None else path.suffix,
                                        dir=path.parent)
    except OSError as exc:
        raise _output_error(path, exc) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno in _NO_SPACE_OR_ACCESS:
            raise _output_error(path, exc) from None
        raise
    return path


_NO_SPACE_OR_ACCESS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT}


def _output_error(path: Path, exc: OSError) -> Exception:

    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        todo = "free some space on that disk (or move the incident folder), then run the command again"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        todo = f"make {path.parent} writable (or copy the incident folder somewhere writable), then run it again"
    else:
        return exc
    return OutputError(f"{path}: cannot write ({exc.strerror}); {todo}; the files already there are unchanged")


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    return atomic_write(path, lambda p: p.write_bytes(data))


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def _json_default(obj: Any) -> Any:
    import numpy as np  # only values that JSON cannot write get here

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def to_json(data: Any) -> str:
    return json.dumps(data, indent=2, default=_json_default, allow_nan=False) + "\n"


def atomic_write_json(path: Path, data: Any) -> Path:
    """Write JSON atomically; numpy arrays and scalars are converted, NaN is refused."""
    return atomic_write_text(path, to_json(data))


def hash_file(path: Path, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def matrix_from_json(value, shape: tuple[int, ...], where: str):
    """A finite float array of ``shape`` from a JSON value; :class:`InputError` naming ``where`` otherwise."""
    import numpy as np

    dims = "x".join(str(n) for n in shape)
    try:
        M = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: not a {dims} array of numbers") from None
    if M.shape != tuple(shape) or not np.all(np.isfinite(M)):
        raise InputError(f"{where}: must be a finite {dims} array (got shape {M.shape})")
    return M


def _first_nonfinite(doc: Any, where: str = "") -> str | None:
    """The JSON path (``observations[3].uv[0]``) of the first NaN or infinity in a parsed document, or None."""
    if isinstance(doc, float) and not math.isfinite(doc):
        return where or "the document"
    if isinstance(doc, dict):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in doc.items())
    elif isinstance(doc, list):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(doc))
    else:
        return None
    for w, v in items:
        found = _first_nonfinite(v, w)
        if found is not None:
            return found
    return None


def read_json(path, *, missing: str = ""):
    """The JSON document at ``path``; :class:`InputError` naming the file when it is missing (with ``missing``
    appended: what to do), a folder, unreadable, not valid JSON, nested too deeply, or holding NaN or Infinity
    (which strict JSON does not have and no incident file needs)."""

    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        bad = _first_nonfinite(doc)
    except FileNotFoundError:
        raise InputError(f"{path}: " + (missing or "file not found")) from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a JSON file") from None
    except PermissionError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror}); make it readable") from None
    except (json.JSONDecodeError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not valid JSON ({str(exc)[:200]})") from None
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be an incident file") from None
    if bad is not None:
        raise InputError(f"{path}: {bad} is not finite (NaN or Infinity, which strict JSON does not have); write a "
                         f"finite number there, or leave the entry out")
    return doc


def resolve_dem_sources(value: str | Path, base: Path) -> list[Path]:
    """``terrain.dem`` -> the DEM file(s): one file, a folder (every .tif/.tiff in it) or a glob pattern.

    Relative values are relative to ``base`` (the incident folder). No match is an :class:`InputError`.
    """


    raw = str(value)
    p = Path(raw)
    p = p if p.is_absolute() else Path(base) / p
    if any(ch in raw for ch in "*?["):
        files = sorted(Path(x) for x in glob.glob(str(p), recursive=True) if Path(x).is_file())
        what = "pattern"
    elif p.is_dir():
        files = sorted(x for x in p.iterdir() if x.suffix.lower() in (".tif", ".tiff") and not x.name.startswith("."))
        what = "folder"
    else:
        if not p.is_file():
            raise InputError(f"terrain.dem = {raw!r} -> {p} does not exist; fix the path or put the DEM there")
        return [p]
    if not files:
        raise InputError(f"terrain.dem = {raw!r}: the {what} {p} matches no GeoTIFF; put the DEM tiles there or fix "
                         f"the key")
    return files
