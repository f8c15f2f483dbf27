"""Atomic file writes and content hashing (used by the Project object and the runner)."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np


def atomic_write(path: Path, write: Callable[[Path], None], suffix: str | None = None) -> Path:
    """Write ``path`` atomically: ``write(tmp)`` writes a temp file in the same folder, then it is renamed.

    A crash or an exception inside ``write`` leaves any earlier ``path`` untouched.
    ``suffix`` (default: the suffix of ``path``) is kept on the temp name so writers that
    infer the format from the extension (PIL, cv2, rasterio) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix if suffix is not None else path.suffix,
                                    dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    return atomic_write(path, lambda p: p.write_bytes(data))


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def _json_default(obj: Any) -> Any:
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


def hash_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def matrix_from_json(value, shape: tuple[int, ...], where: str):
    """A finite float array of ``shape`` from a JSON value; :class:`InputError` naming ``where`` otherwise."""
    import numpy as np

    from ..errors import InputError

    dims = "x".join(str(n) for n in shape)
    try:
        M = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: not a {dims} array of numbers") from None
    if M.shape != tuple(shape) or not np.all(np.isfinite(M)):
        raise InputError(f"{where}: must be a finite {dims} array (got shape {M.shape})")
    return M


def read_json(path, *, missing: str = ""):
    """The JSON document at ``path``; :class:`InputError` naming the file when it is missing (with ``missing``
    appended: what to do) or not valid JSON."""
    import json
    from pathlib import Path

    from ..errors import InputError

    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: " + (missing or "file not found")) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
