"""On-disk cache of what the correspond stage computes from its inputs alone: each car's face references
(livery painted, SIFT over the tilts) and each photo's SIFT features (undistorted, upsampled).

A rerun of the stage (new manual picks, a changed camera, ``--force``) finds them in
``out/correspond/cache/`` instead of computing them again (SIFT on an upsampled photo: about 4 s of CPU each).
An entry's file name is the SHA-256 of everything its content depends on: the photo's bytes and intrinsics,
or the carriage type's specification and the car number; the matcher's options that shape it; the source of
the code that makes it (``CODE_FILES``) and the versions of OpenCV, NumPy and Pillow. A changed input gives
another name, so a stale entry is never read; the stage deletes the entries it did not use. A file that
cannot be read (cut short, corrupt) is computed again.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from .references import FaceReference

log = logging.getLogger(__name__)

VERSION = 1
_PKG = Path(__file__).resolve().parents[1]  # workbench/
# the code the cached content depends on
CODE_FILES = ("correspond/cache.py", "correspond/match.py", "correspond/references.py", "core/camera.py",
              "rolling_stock/*.py")
_code_digest: str | None = None


def code_digest() -> str:
    """SHA-256 of the cached content's code and libraries (computed once per process)."""
    global _code_digest
    if _code_digest is None:
        import cv2
        import PIL

        h = hashlib.sha256(f"v{VERSION} cv2 {cv2.__version__} numpy {np.__version__} PIL {PIL.__version__}".encode())
        for pattern in CODE_FILES:
            for f in sorted(_PKG.glob(pattern)):
                h.update(f.relative_to(_PKG).as_posix().encode())
                h.update(f.read_bytes())
        _code_digest = h.hexdigest()
    return _code_digest


def key(*parts) -> str:
    """A cache key: SHA-256 of the code digest and ``parts`` (JSON-serialisable)."""
    blob = json.dumps([code_digest(), *parts], sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:40]


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _pack_descriptors(d: np.ndarray) -> np.ndarray:
    """SIFT descriptors (float32 with integer values 0..255) stored as uint8 when exact, else as they are."""
    if d.dtype == np.float32 and len(d) and d.min() >= 0 and d.max() <= 255 and np.array_equal(d, np.round(d)):
        return d.astype(np.uint8)
    return d


def load(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache entry, or None (absent or unreadable)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as exc:  # cut short or corrupt: computed again
        log.info("cache entry %s unreadable (%s); computed again", path.name, exc)
        return None
    if "descriptors" in out and out["descriptors"].dtype == np.uint8:
        out["descriptors"] = out["descriptors"].astype(np.float32)
    return out


def save(project, path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a cache entry atomically (a failure to write is logged, not raised: the cache is an aid)."""
    arrays = {k: (_pack_descriptors(v) if k == "descriptors" else v) for k, v in arrays.items()}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)

        def writer(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)

        project.write_with(path, writer)
    except Exception as exc:  # noqa: BLE001 - a full disk or a read-only folder: the run goes on uncached
        log.warning("could not write the cache entry %s (%s)", path, exc)


def prune(directory: Path, keep: set[str]) -> int:
    """Delete the entries of ``directory`` not named in ``keep`` (file names); returns how many."""
    n = 0
    if directory.is_dir():
        for f in directory.glob("*.npz"):
            if f.name not in keep:
                try:
                    f.unlink()
                    n += 1
                except OSError:
                    pass
    return n


# -- the two kinds of entries --------------------------------------------------------------------------------
def references_to_arrays(refs: list, prefix: str = "") -> dict[str, np.ndarray]:
    """Face references (``references.FaceReference``, with or without features) as named arrays."""
    out: dict[str, np.ndarray] = {f"{prefix}faces": np.array([r.face for r in refs], dtype=str).reshape(-1)}
    for i, r in enumerate(refs):
        names = list(r.points)  # in their order (the order of the points written)
        k = f"{prefix}{i}_"
        out.update({k + "image": r.image, k + "px_per_m": np.array(r.px_per_m),
                    k + "point_names": np.array(names, dtype=str).reshape(-1),
                    k + "points": np.array([r.points[n] for n in names], float).reshape(-1, 2),
                    k + "frame": np.vstack([r.origin_m, r.axis_u_m, r.axis_v_m])})
        if r.mask is not None:
            out[k + "mask"] = r.mask
        if r.keypoints is not None:
            out.update({k + "keypoints": r.keypoints, k + "descriptors": _pack_descriptors(r.descriptors),
                        k + "frames": r.frames})
    return out


def references_from_arrays(a: dict[str, np.ndarray], type_id: str, car_number: str, prefix: str = "") -> list:
    refs = []
    for i, face in enumerate(a[f"{prefix}faces"].tolist()):
        k = f"{prefix}{i}_"
        d = a.get(k + "descriptors")
        refs.append(FaceReference(
            type_id, car_number, face, a[k + "image"], float(a[k + "px_per_m"]),
            {n: p for n, p in zip(a[k + "point_names"].tolist(), a[k + "points"])},
            a[k + "frame"][0], a[k + "frame"][1], a[k + "frame"][2],
            keypoints=a.get(k + "keypoints"), descriptors=None if d is None else
            (d.astype(np.float32) if d.dtype == np.uint8 else d), frames=a.get(k + "frames"),
            mask=a.get(k + "mask")))
    return refs
