"""Simulated relative incidents (no survey): a consist seen in one photo, its hand picks, no control points.

For the tests and the calibration benchmark of the relative route (docs/gis.md, "Relative incidents"):
:func:`write_relative_incident` writes an incident folder from a :class:`~workbench.solve.simulate.SimProblem`
(one photo of the right size, the picks the simulation made, a camera profile when the focal is known);
:func:`levelled_truth` gives the truth in the frame the relative route reconstructs (origin at the camera, z up,
y along the ray through the photo's centre pixel); :func:`tilt_world` tilts a simulated scene's track against
gravity (the photo unchanged: the world and the camera turn together), the grade and cant the levelling cannot
see and states as ``solver.level_sigma_common_deg``.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import piexif
from PIL import Image

from ..core.geometry import exp_so3, rot_z
from ..solve.simulate import TYPE_CYCLE, SimProblem, simulate_consist

__all__ = ["relative_sim", "write_relative_incident", "levelled_truth", "tilt_world"]

WIDTH, HEIGHT = 1600, 1200


def centre_ray(intr) -> np.ndarray:
    """(3,) the camera-frame ray through the photo's centre pixel, the relative frame's y (as the solve takes it)."""
    return intr.rays(np.array([[(intr.width - 1) / 2.0, (intr.height - 1) / 2.0]]))[0]


def relative_sim(seed: int, n_cars: int = 3, pixel_sigma_px: float = 0.5,
                 principal_point_sigma_px: float | None = None) -> SimProblem:
    """A consist on a level track, one 1600 x 1200 photo from 12 m up, no distortion (a fallback camera's
    model), ``pixel_sigma_px`` pick noise. ``principal_point_sigma_px``: the camera's principal point drawn
    N(0, that) per axis off the photo's centre (a camera the solve does not know, which takes it at the centre:
    :mod:`workbench.solve.principal_point`) instead of :func:`simulate_consist`'s uniform +-10 px, the picks moved
    with it (exact: no distortion). :class:`RuntimeError` when a car falls outside the photo."""
    sim = simulate_consist(n_cars, seed=seed, slope_deg=0.0, width=WIDTH, height=HEIGHT, focal_px=1300.0,
                           distortion=(0.0, 0.0), pixel_sigma_px=pixel_sigma_px, camera_height_m=12.0)
    if principal_point_sigma_px is None:
        return sim
    view = sim.views[0]
    intr = view.intrinsics
    c = np.array([(intr.width - 1) / 2.0, (intr.height - 1) / 2.0])
    c = c + np.random.default_rng([seed, 1]).normal(0.0, principal_point_sigma_px, 2)
    shift = c - [intr.cx, intr.cy]
    for cin in sim.carriages:
        obs = cin.observations[view.name]
        uv = np.array([obs[p] for p in obs]) + shift
        if not np.all(intr.in_image(uv, margin=1.0)):
            raise RuntimeError(f"relative_sim(seed={seed}): car {cin.number} is not fully in the image")
        cin.observations[view.name] = {p: tuple(map(float, x)) for p, x in zip(obs, uv)}
    sim.clean_pixels = [{p: (u + shift[0], v + shift[1]) for p, (u, v) in d.items()} for d in sim.clean_pixels]
    sim.views[0] = replace(view, intrinsics=replace(intr, cx=float(c[0]), cy=float(c[1])))
    return sim


def tilt_world(sim: SimProblem, rng: np.random.Generator, sigma_deg: float) -> tuple[list[np.ndarray], np.ndarray]:
    """(the carriages' true poses, the camera's true ``cam_from_world``) with the whole scene turned by a tilt
    drawn per horizontal axis from N(0, ``sigma_deg``) about the origin: the track is then that far off level,
    and the photo (the picks) unchanged."""
    w = np.radians(rng.normal(0.0, sigma_deg, 2))
    Q = np.eye(4)
    Q[:3, :3] = exp_so3(np.array([w[0], w[1], 0.0]))
    truth = [Q @ np.asarray(M, float) for M in sim.truth]
    cam = np.asarray(sim.views[0].cam_from_world, float) @ np.linalg.inv(Q)
    return truth, cam


def levelled_truth(sim: SimProblem, cam_from_world: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) levelled_from_world of the simulation: origin at the camera, z up, y along the ray through the
    photo's centre pixel (the relative route's frame). ``cam_from_world``: the camera's (default the view's)."""
    M = np.asarray(sim.views[0].cam_from_world if cam_from_world is None else cam_from_world, float)
    C = -M[:3, :3].T @ M[:3, 3]
    f = M[:3, :3].T @ centre_ray(sim.views[0].intrinsics)
    f[2] = 0.0
    f /= np.linalg.norm(f)
    yaw = math.atan2(f[0], f[1])
    L = np.eye(4)
    L[:3, :3] = rot_z(yaw)
    L[:3, 3] = -L[:3, :3] @ C
    return L


def write_relative_incident(root: Path, sim: SimProblem, *, focal_known: bool, solver: str = "") -> Path:
    """An incident folder at ``root`` (created): ``project.toml`` (the consist, finder off, ``slack_held_m``
    0.03 as simulated, plus the ``[solver]`` lines in ``solver``), one grey photo, the simulation's picks as
    ``correspondences.json``, and a camera profile with the true intrinsics when ``focal_known`` (else the focal
    is estimated: ``camera.source = "unknown"``). Returns ``root``."""
    root = Path(root)
    root.mkdir(parents=True)
    n = len(sim.carriages)
    cars = [f'[[consist]]\nnumber = "{c.number}"\ntype = "{TYPE_CYCLE[i % len(TYPE_CYCLE)]}"\n'
            + ('coupling_to_next = "held"\n' if i < n - 1 else "") for i, c in enumerate(sim.carriages)]
    intr = sim.views[0].intrinsics
    camera = ('[camera]\nsource = "calibrated"\nprofile = "camera_profile.json"\nphotos = "photos/p"\n'
              if focal_known else '[camera]\nsource = "unknown"\nphotos = "photos/p"\n')
    (root / "project.toml").write_text(
        '[incident]\nname = "relative test"\ndate = 2024-05-01\n\n'
        '[location]\nlat = 35.53\nlon = 139.70\ncrs = "EPSG:32654"\n\n' + "\n".join(cars) + "\n" + camera
        + '\n[correspond]\nfinder = "off"\n\n[solver]\nslack_held_m = 0.03\n' + solver, encoding="utf-8")
    if focal_known:
        (root / "camera_profile.json").write_text(json.dumps({"model": "brown", "source": "simulated",
                                                               "intrinsics": intr.to_dict()}))
    (root / "photos" / "p").mkdir(parents=True)
    Image.new("RGB", (intr.width, intr.height), (120, 120, 120)).save(root / "photos" / "p" / "photo.jpg")
    view = sim.views[0].name
    obs = [{"carriage": c.number, "point": p, "view": "photo.jpg", "uv": list(uv)}
           for c in sim.carriages for p, uv in c.observations[view].items()]
    (root / "correspondences.json").write_text(json.dumps({"observations": obs}), encoding="utf-8")
    return root


def write_gps_exif(photo: Path, lon_deg: float, lat_deg: float, alt_m: float | None, direction_deg: float | None,
                   h_error_m: float | None = None) -> None:
    """Write a phone's EXIF GPS block into ``photo`` (JPEG, rewritten in place): position, altitude, the true-north
    direction of the image (``GPSImgDirection``, ref ``T``) and ``GPSHPositioningError``, where given."""
    def dms(x: float) -> tuple:
        x = abs(x)
        d = int(x)
        m = int((x - d) * 60)
        s = (x - d - m / 60.0) * 3600.0
        return ((d, 1), (m, 1), (int(round(s * 10000)), 10000))

    G = piexif.GPSIFD
    gps = {G.GPSLatitudeRef: b"N" if lat_deg >= 0 else b"S", G.GPSLatitude: dms(lat_deg),
           G.GPSLongitudeRef: b"E" if lon_deg >= 0 else b"W", G.GPSLongitude: dms(lon_deg)}
    if alt_m is not None:
        gps[G.GPSAltitudeRef] = 0 if alt_m >= 0 else 1
        gps[G.GPSAltitude] = (int(round(abs(alt_m) * 100)), 100)
    if direction_deg is not None:
        gps[G.GPSImgDirectionRef] = b"T"
        gps[G.GPSImgDirection] = (int(round((direction_deg % 360.0) * 100)), 100)
    if h_error_m is not None:
        gps[G.GPSHPositioningError] = (int(round(h_error_m * 100)), 100)
    with Image.open(photo) as im:
        im.load()
        im.save(photo, exif=piexif.dump({"0th": {}, "Exif": {}, "GPS": gps, "1st": {}}))


def truth_gps(sim: SimProblem, frame, rng: np.random.Generator, sigma_h_m: float, sigma_v_m: float,
              sigma_deg: float) -> tuple[float, float, float, float]:
    """(lon, lat, altitude, compass azimuth) a phone would write for the simulation's camera: its centre with
    Gaussian noise (``sigma_h_m`` per horizontal axis, ``sigma_v_m`` up) in WGS84 through ``frame``, and the true
    azimuth of the ray through the photo's centre pixel plus N(0, ``sigma_deg``)."""
    M = np.asarray(sim.views[0].cam_from_world, float)
    C = -M[:3, :3].T @ M[:3, 3] + rng.normal(0.0, 1.0, 3) * [sigma_h_m, sigma_h_m, sigma_v_m]
    lon, lat, alt = frame.wgs84_from_enu(C[None])[0]
    f = M[:3, :3].T @ centre_ray(sim.views[0].intrinsics)
    az = math.degrees(math.atan2(f[0], f[1])) + rng.normal(0.0, sigma_deg)
    return float(lon), float(lat), float(alt), az % 360.0
