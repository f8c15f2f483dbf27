"""Camera calibration from chessboard photos (``workbench calibrate``), giving a camera profile.

OpenCV's method (Zhang): ``findChessboardCorners`` (falling back to the sector-based
``findChessboardCornersSB``), ``cornerSubPix``, then ``calibrateCamera`` with the Brown-Conrady model
(k1, k2, p1, p2, k3). OpenCV's pixel convention (pixel (0, 0) is the centre of the top-left pixel) is the
workbench's own (``docs/conventions.md``), so the result is used as it is. The profile is written in the
format of ``docs/formats.md`` (``camera_profile.json``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.io import atomic_write_json
from ..core.settings import options_from_dict
from ..errors import InputError, SettingsError
from ..files.profile import load_camera_profile, validate_profile, write_camera_profile  # noqa: F401 - re-exported

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


@dataclass(frozen=True, kw_only=True)
class CalibrationOptions:
    """Options of :func:`calibrate_chessboard`.

    ``pattern``: inner corners (columns, rows) of the board, e.g. (9, 6) for a board of 10 x 7 squares.
    ``square_mm``: side of one square, millimetres (only scales the board poses, not the intrinsics).
    ``fix_aspect_ratio``: fx = fy (square pixels; OpenCV's ``CALIB_FIX_ASPECT_RATIO``).
    ``fix_k3``: k3 = 0 (fewer parameters; advisable for narrow lenses or few views).
    ``zero_tangent``: p1 = p2 = 0.
    ``subpix_half_window_px``: half size of ``cornerSubPix``'s search window (OpenCV's sample uses 11).
    ``max_view_rms_px``: if set, views whose reprojection RMS exceeds it are dropped and the calibration is
    run again (once); dropped views are reported.
    ``min_views``: fewer usable views than this is an error.
    """

    pattern: tuple[int, int] = (9, 6)
    square_mm: float = 25.0
    fix_aspect_ratio: bool = True
    fix_k3: bool = False
    zero_tangent: bool = False
    subpix_half_window_px: int = 11
    max_view_rms_px: float | None = None
    min_views: int = 3

    def __post_init__(self) -> None:
        p = tuple(self.pattern)
        if len(p) != 2 or any(int(x) != x or x < 2 for x in p):
            raise SettingsError(f"pattern={self.pattern!r}: give the board's inner corners as (columns, rows), "
                                f"each >= 2, e.g. (9, 6)")
        if p[0] == p[1]:
            log.warning("pattern %s is square: the board's orientation is ambiguous (use a board with unequal "
                        "sides)", p)
        object.__setattr__(self, "pattern", (int(p[0]), int(p[1])))
        if not (np.isfinite(self.square_mm) and self.square_mm > 0):
            raise SettingsError(f"square_mm={self.square_mm!r}: the square size must be a positive length in mm")
        if not (1 <= self.subpix_half_window_px <= 50):
            raise SettingsError(f"subpix_half_window_px={self.subpix_half_window_px!r}: must be in 1..50")
        if self.max_view_rms_px is not None and not self.max_view_rms_px > 0:
            raise SettingsError(f"max_view_rms_px={self.max_view_rms_px!r}: must be > 0 (or None)")
        if self.min_views < 3:
            raise SettingsError(f"min_views={self.min_views!r}: a calibration needs at least 3 views")

    @classmethod
    def from_dict(cls, d: dict) -> "CalibrationOptions":
        """From a plain dict; unknown keys are an error."""
        return options_from_dict(cls, d, "calibration options")


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6) (inner corners, columns x rows)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", str(text))
    if not m:
        raise SettingsError(f"--pattern {text!r}: write the board's inner corners as COLSxROWS, e.g. 9x6")
    return int(m.group(1)), int(m.group(2))


def list_images(folder: Path, pattern: str = "*") -> list[Path]:
    """Image files in ``folder`` whose names match the glob ``pattern``, sorted by name; :class:`InputError`
    when there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of chessboard photos")
    images = sorted(p for p in folder.glob(pattern)
                    if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not images:
        raise InputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) matching {pattern!r} in this folder")
    return images


def _board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """(cols * rows, 3) float32 board corners in the board frame, metres (z = 0), row-major as OpenCV finds them."""
    cols, rows = pattern
    g = np.zeros((rows * cols, 3), np.float32)
    g[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return g


def find_corners(gray: np.ndarray, pattern: tuple[int, int], half_window_px: int = 11) -> tuple[np.ndarray | None, str]:
    """Chessboard inner corners (n, 1, 2) float32 px of a (h, w) uint8 image, or None; and the detector used."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if found:
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
        corners = cv2.cornerSubPix(gray, corners, (half_window_px, half_window_px), (-1, -1), crit)
        return corners, "findChessboardCorners"
    found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found:
        return corners.astype(np.float32), "findChessboardCornersSB"
    return None, ""


def _calibrate(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int], opts: CalibrationOptions):
    flags = 0
    K0 = np.eye(3)
    if opts.fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO  # keeps fx / fy of K0 (= 1)
    if opts.fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if opts.zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = cv2.calibrateCameraExtended(
        obj, img, size, K0, np.zeros(5), flags=flags, criteria=crit)
    return float(rms), K, dist.reshape(-1), rvecs, tvecs, std_int.reshape(-1), per_view.reshape(-1)


def calibrate_chessboard(images: list[Path], pattern: tuple[int, int] = (9, 6), square_mm: float = 25.0, *,
                         options: CalibrationOptions | None = None,
                         sensor_width_mm: float | None = None) -> tuple[dict, dict]:
    """Calibrate one camera from photos of a chessboard.

    ``images``: photo paths (all the same size); ``pattern``: inner corners (columns, rows);
    ``square_mm``: square side in mm. ``options`` (if given) overrides ``pattern`` and ``square_mm``.
    Returns ``(profile, stats)``: ``profile`` is the ``camera_profile.json`` object of ``docs/formats.md``
    (pixels, our pixel convention = OpenCV's); ``stats`` has the overall and per-view reprojection RMS (px),
    the 1-sigma of each intrinsic, the views used and those rejected (with the reason).
    Raises :class:`InputError` for unreadable images, mixed sizes or too few boards found.
    """
    opts = options or CalibrationOptions(pattern=tuple(pattern), square_mm=float(square_mm))
    images = [Path(p) for p in images]
    if not images:
        raise InputError("calibrate: no images given")
    board = _board_points(opts.pattern, opts.square_mm / 1000.0)
    obj, img, used, rejected, detectors = [], [], [], [], {}
    size = None
    for p in images:
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError(f"{p}: cannot read this image; replace it or remove it from the folder")
        hw = (gray.shape[1], gray.shape[0])
        if size is None:
            size = hw
        elif hw != size:
            raise InputError(f"{p}: {hw[0]}x{hw[1]} px, but {images[0].name} is {size[0]}x{size[1]}; every "
                             f"calibration photo must come from the same camera at the same size")
        corners, how = find_corners(gray, opts.pattern, opts.subpix_half_window_px)
        if corners is None:
            rejected.append({"image": p.name, "reason": f"no {opts.pattern[0]}x{opts.pattern[1]} chessboard found"})
            log.info("calibrate: %s: board not found", p.name)
            continue
        obj.append(board)
        img.append(corners)
        used.append(p)
        detectors[p.name] = how
    if len(used) < opts.min_views:
        raise InputError(f"calibrate: the {opts.pattern[0]}x{opts.pattern[1]} board was found in {len(used)} of "
                         f"{len(images)} photos, fewer than {opts.min_views}; check --pattern (inner corners, "
                         f"columns x rows) and take more photos of the whole board")
    rms, K, dist, rvecs, tvecs, std_int, per_view = _calibrate(obj, img, size, opts)
    if opts.max_view_rms_px is not None:
        bad = [i for i, e in enumerate(per_view) if e > opts.max_view_rms_px]
        if bad and len(used) - len(bad) >= opts.min_views:
            for i in bad:
                rejected.append({"image": used[i].name,
                                 "reason": f"reprojection RMS {per_view[i]:.2f} px > {opts.max_view_rms_px} px"})
            keep = [i for i in range(len(used)) if i not in bad]
            obj = [obj[i] for i in keep]
            img = [img[i] for i in keep]
            used = [used[i] for i in keep]
            rms, K, dist, rvecs, tvecs, std_int, per_view = _calibrate(obj, img, size, opts)
    intr = CameraIntrinsics.from_K(K, size[0], size[1], dist[:5])
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    sigma = {n: float(std_int[i]) for i, n in enumerate(names)}
    if opts.fix_aspect_ratio:  # fx is tied to fy: OpenCV reports 0 for the tied one
        sigma["fx"] = sigma["fy"] = max(sigma["fx"], sigma["fy"])
    n_points = sum(len(c) for c in img)
    views = []
    for i, p in enumerate(used):
        R, _ = cv2.Rodrigues(rvecs[i])
        views.append({"image": p.name, "rms_px": float(per_view[i]), "detector": detectors[p.name],
                      "board_distance_m": float(np.linalg.norm(tvecs[i])),
                      "board_tilt_deg": float(np.degrees(np.arccos(np.clip(abs(R[2, 2]), 0.0, 1.0))))})
    today = _dt.date.today().isoformat()
    profile = {
        "model": "brown",
        "source": (f"workbench calibrate {today}: {len(used)}/{len(images)} chessboard views "
                   f"({opts.pattern[0]}x{opts.pattern[1]} inner corners, {opts.square_mm:g} mm squares), "
                   f"RMS {rms:.3f} px"),
        "intrinsics": {k: (int(v) if k in ("width", "height") else float(v)) for k, v in intr.to_dict().items()},
    }
    if sensor_width_mm is not None:
        if not sensor_width_mm > 0:
            raise SettingsError(f"sensor_width_mm={sensor_width_mm!r}: must be a positive width in mm")
        profile["sensor_width_mm"] = float(sensor_width_mm)
    stats = {
        "n_images": len(images), "n_used": len(used), "rms_px": rms, "n_points": n_points,
        "image_size": list(size), "sigma": sigma,
        "hfov_deg": float(np.degrees(2 * np.arctan(size[0] / 2.0 / intr.fx))),
        "views": views, "rejected": rejected, "options": {**asdict(opts), "pattern": list(opts.pattern)},
    }
    log.info("calibrate: %d/%d views, RMS %.3f px, fx=%.2f fy=%.2f cx=%.2f cy=%.2f", len(used), len(images), rms,
             intr.fx, intr.fy, intr.cx, intr.cy)
    return profile, stats


def run_calibrate(images_dir: Path, out: Path, *, pattern: str = "9x6", square_mm: float = 25.0,
                  fix_k3: bool = False, max_view_rms_px: float | None = None,
                  sensor_width_mm: float | None = None, stats_out: Path | None = None, glob: str = "*") -> dict:
    """The ``workbench calibrate IMAGES_DIR --pattern 9x6 --square-mm 25 --out profile.json`` command.

    Calibrates from every image in ``images_dir`` whose name matches ``glob`` (e.g. ``"left*.jpg"``), writes the profile to ``out`` (and the statistics to
    ``stats_out``, default ``<out stem>.stats.json`` beside it) atomically, and returns the statistics.
    """
    opts = CalibrationOptions(pattern=parse_pattern(pattern), square_mm=float(square_mm), fix_k3=fix_k3,
                              max_view_rms_px=max_view_rms_px)
    profile, stats = calibrate_chessboard(list_images(Path(images_dir), glob), options=opts,
                                          sensor_width_mm=sensor_width_mm)
    out = Path(out)
    write_camera_profile(out, profile)
    stats_path = Path(stats_out) if stats_out else out.with_name(out.stem + ".stats.json")
    atomic_write_json(stats_path, {"profile": str(out), **stats})
    stats["profile_path"] = str(out)
    stats["stats_path"] = str(stats_path)
    return stats
