"""``cameras.json``: every view in the scene frame (format in ``docs/pipeline.md``).

The one reader and writer of the file. ``georef`` writes ``out/georef/cameras.json``; a file of the same format
written by hand in the incident folder takes its place (known cameras). Every stage reads it through
:meth:`workbench.project.Project.cameras`, which calls :func:`read_cameras`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.io import atomic_write_json, matrix_from_json, read_json
from ..errors import InputError

ROUTES = ("panorama", "multiview", "single")
SEE = "see docs/pipeline.md (cameras.json)"


@dataclass(frozen=True)
class CameraView:
    """One photo's camera: ``intrinsics`` of the photo as on disk, ``cam_from_world`` (4, 4) from the scene
    frame (ENU metres) to the camera (x right, y down, z forward); ``focal_known`` False when the focal is only a
    starting value that the solve estimates."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_world: np.ndarray
    image: str | None = None
    focal_known: bool = True
    record: dict = field(default_factory=dict, compare=False, repr=False)  # the view's entry as written

    @property
    def center_enu(self) -> np.ndarray:
        """(3,) the camera centre in the scene frame, metres."""
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        return -R.T @ t

    def entry(self) -> dict:
        """The view as a ``cameras.json`` entry (the keys of ``record`` kept, the geometry written anew)."""
        M = np.asarray(self.cam_from_world, float)
        out = dict(self.record)
        out.update({"name": self.name, "image": self.image if self.image is not None else self.name,
                    "intrinsics": self.intrinsics.to_dict(), "focal_known": bool(self.focal_known),
                    "cam_from_world": M.tolist(), "center_enu": self.center_enu.tolist()})
        return out


@dataclass(frozen=True)
class Cameras:
    """A ``cameras.json``: its views (in file order), the route that placed them and the whole document (for
    the blocks a stage reads on its own: ``georegistration``, ``panorama``, per-view uncertainty)."""

    path: Path
    route: str
    views: tuple[CameraView, ...]
    doc: dict = field(compare=False, repr=False)

    def __getitem__(self, name: str) -> CameraView:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)

    def __contains__(self, name: object) -> bool:
        return any(v.name == name for v in self.views)

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    @property
    def relative(self) -> bool:
        """True for the relative route's cameras (no survey): a provisional local frame at the camera."""
        return self.doc.get("frame") == "relative"

    @property
    def focal_unknown(self) -> list[str]:
        """Names of the views whose focal the solve estimates."""
        return [v.name for v in self.views if not v.focal_known]


@dataclass(frozen=True)
class PoseUncertainty:
    """``georegistration.pose_uncertainty`` of the multi-view route (docs/formats.md): the views' pose errors,
    each a 6-vector (scene rotation vector of ``world_from_cam`` in rad, centre in m, ENU).

    ``model_covariance``: SfM model -> (7, 7) covariance of its similarity's error (log scale, rotation vector,
    translation), (7 + r) square where the SfM poses' own error is stated (then ``I_r``); ``jacobian``: view ->
    (its model, (6, 7) or (6, 7 + r)): the view's error is ``J @ e_model``, the same ``e_model`` for every view of
    that model (their errors are correlated); ``own_covariance``: view -> (6, 6)
    for a view whose error is its own (independent of every other view's); ``not_modelled``: views placed
    without a stated pose covariance; ``intrinsics_jacobian``: view -> (its model, the intrinsics' names (fields
    of :class:`CameraIntrinsics`, ``f`` for fx and fy together), (k, 7 + r)): the error of the SfM intrinsics the
    view is projected with, ``J_k @ e_model`` (the SfM model's own error ``z`` moves its poses and intrinsics
    together)."""

    model_covariance: dict[str, np.ndarray]
    jacobian: dict[str, tuple[str, np.ndarray]]
    own_covariance: dict[str, np.ndarray]
    not_modelled: tuple[str, ...]
    intrinsics_jacobian: dict[str, tuple[str, tuple[str, ...], np.ndarray]] = field(default_factory=dict)

    def view_covariance(self, name: str) -> np.ndarray | None:
        """(6, 6) marginal covariance of one view's pose error, or None when it is not modelled."""
        if name in self.jacobian:
            label, J = self.jacobian[name]
            return J @ self.model_covariance[label] @ J.T
        return self.own_covariance.get(name)


def _finite_matrix(x: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    M = matrix_from_json(x, shape, where)
    if not np.all(np.isfinite(M)):
        raise InputError(f"{where}: must hold finite numbers")
    return M


def parse_pose_uncertainty(doc: dict, path: Path | str) -> PoseUncertainty | None:
    """The ``georegistration.pose_uncertainty`` block of a cameras document, checked (None when absent);
    :class:`InputError` naming the key. A model whose covariance is null (the fit left it undetermined) leaves
    its views not modelled. A model with ``sfm_rank`` r (its SfM poses' own covariance stated) has its covariance
    extended to (7 + r) square (the similarity's, then ``I_r``) and each of its views' Jacobian to (6, 7 + r)
    (``[jacobian, sfm_factor]``), so the views' SfM errors stay shared and correlated as the similarity's."""
    block = (doc.get("georegistration") or {}).get("pose_uncertainty") if isinstance(doc, dict) else None
    if block is None:
        return None
    where = f"{path}: georegistration.pose_uncertainty"
    if not isinstance(block, dict) or not isinstance(block.get("models", {}), dict) \
            or not isinstance(block.get("views", {}), dict):
        raise InputError(f"{where}: must be an object with 'models' and 'views' objects; {SEE}")
    cov: dict[str, np.ndarray] = {}
    ranks: dict[str, int] = {}
    for label, m in block.get("models", {}).items():
        if not isinstance(m, dict):
            raise InputError(f"{where}.models.{label}: must be an object with a 'covariance' (7 x 7 or null)")
        r = m.get("sfm_rank")
        if r is not None and (not isinstance(r, int) or isinstance(r, bool) or r < 1):
            raise InputError(f"{where}.models.{label}.sfm_rank = {r!r}: must be a positive integer or null")
        if m.get("covariance") is not None:
            C = _finite_matrix(m["covariance"], (7, 7), f"{where}.models.{label}.covariance")
            cov[label] = 0.5 * (C + C.T)
            if r:  # the SfM poses' own error: r more shared parameters z ~ N(0, I), beside the similarity's 7
                ranks[label] = r
                cov[label] = np.block([[cov[label], np.zeros((7, r))], [np.zeros((r, 7)), np.eye(r)]])
    jac: dict[str, tuple[str, np.ndarray]] = {}
    jac_k: dict[str, tuple[str, tuple[str, ...], np.ndarray]] = {}
    own: dict[str, np.ndarray] = {}
    missing = []
    for name, v in block.get("views", {}).items():
        w = f"{where}.views.{name}"
        if not isinstance(v, dict):
            raise InputError(f"{w}: must be an object (source, model, jacobian, covariance_rotation_centre)")
        label = v.get("model")
        if label is not None:
            if label not in block.get("models", {}):
                raise InputError(f"{w}.model = {label!r} is not one of the models ({', '.join(block['models'])})")
            J = _finite_matrix(v.get("jacobian"), (6, 7), f"{w}.jacobian")
            if label in ranks:  # [J, F]: the similarity's error and the view's share of the SfM poses' error
                F = np.zeros((6, ranks[label])) if v.get("sfm_factor") is None else \
                    _finite_matrix(v["sfm_factor"], (6, ranks[label]), f"{w}.sfm_factor")
                J = np.hstack([J, F])
                if v.get("sfm_intrinsics_factor") is not None and label in cov:
                    params, K = intrinsics_factor_checked(v["sfm_intrinsics_factor"], ranks[label], f"{w}.sfm_intrinsics_factor")
                    jac_k[name] = (label, params, np.hstack([np.zeros((len(params), 7)), K]))
            if label in cov:
                jac[name] = (label, J)
            else:
                missing.append(name)
        elif v.get("covariance_rotation_centre") is not None:
            C = _finite_matrix(v["covariance_rotation_centre"], (6, 6), f"{w}.covariance_rotation_centre")
            own[name] = 0.5 * (C + C.T)
        else:
            missing.append(name)
    return PoseUncertainty(cov, jac, own, tuple(sorted(missing)), jac_k)


INTRINSIC_PARAMS = ("f", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2")


def intrinsics_factor_checked(block: Any, r: int, where: str) -> tuple[tuple[str, ...], np.ndarray]:
    """An ``{"params": [...], "factor": k x r}`` object checked: (the params, the factor)."""
    params = block.get("params") if isinstance(block, dict) else None
    if not isinstance(params, list) or not params or any(p not in INTRINSIC_PARAMS for p in params) \
            or len(set(params)) != len(params):
        raise InputError(f"{where}.params = {params!r}: must list distinct names of {', '.join(INTRINSIC_PARAMS)}")
    return tuple(params), _finite_matrix(block.get("factor"), (len(params), r), f"{where}.factor")


def rotation_checked(R: np.ndarray, where: str) -> np.ndarray:
    """``R`` (3, 3) if it is a rotation (orthonormal, determinant +1); :class:`InputError` naming ``where``."""
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise InputError(f"{where}: not a rotation (orthonormal with determinant +1)")
    return R


def intrinsics_checked(d: Any, where: str) -> CameraIntrinsics:
    """A :class:`CameraIntrinsics` from a JSON object; :class:`InputError` naming ``where``."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: needs an 'intrinsics' object (camera_profile.json model)")
    try:
        return CameraIntrinsics.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def _view(v: Any, i: int, where: str, names: set[str]) -> CameraView:
    w = f"{where}: views[{i}]"
    if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not v["name"]:
        raise InputError(f"{w}: needs a 'name' (the photo's file name)")
    w = f"{where}: views[{i}] ({v['name']!r})"
    if v["name"] in names:
        raise InputError(f"{w}: the name is used twice")
    names.add(v["name"])
    intr = intrinsics_checked(v.get("intrinsics"), f"{w}.intrinsics")
    M = matrix_from_json(v.get("cam_from_world"), (4, 4), f"{w}.cam_from_world")
    rotation_checked(M[:3, :3], f"{w}.cam_from_world")
    if not np.allclose(M[3], [0, 0, 0, 1]):
        raise InputError(f"{w}.cam_from_world: last row must be 0 0 0 1")
    if "center_enu" in v:
        c = matrix_from_json(v["center_enu"], (3,), f"{w}.center_enu")
        if np.linalg.norm(c + M[:3, :3].T @ M[:3, 3]) > 1e-3:
            raise InputError(f"{w}.center_enu = {v['center_enu']} disagrees with cam_from_world (its centre is "
                             f"{(-M[:3, :3].T @ M[:3, 3]).round(4).tolist()}); fix one of them")
    known = v.get("focal_known", True)
    if not isinstance(known, bool):
        raise InputError(f"{w}.focal_known = {known!r}: give true (the focal is calibrated) or false (the solve "
                         f"estimates it)")
    image = v.get("image")
    if image is not None and (not isinstance(image, str) or not image):
        raise InputError(f"{w}.image = {image!r}: give the photo's path relative to the incident folder")
    return CameraView(v["name"], intr, M, image, known, v)


def parse_cameras(doc: Any, path: Path | str) -> Cameras:
    """Check a parsed ``cameras.json`` document; :class:`InputError` naming the file and the entry."""
    where = str(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("views"), list) or not doc["views"]:
        raise InputError(f"{where}: needs a non-empty 'views' list; {SEE}")
    if doc.get("route") not in ROUTES:
        raise InputError(f"{where}: route = {doc.get('route')!r}; give 'panorama', 'multiview' or 'single'")
    names: set[str] = set()
    views = tuple(_view(v, i, where, names) for i, v in enumerate(doc["views"]))
    pano = doc.get("panorama")
    if pano is not None:
        if not isinstance(pano, dict):
            raise InputError(f"{where}: 'panorama' must be an object or null")
        if "world_from_pano" in pano:
            M = matrix_from_json(pano["world_from_pano"], (4, 4), f"{where}: panorama.world_from_pano")
            rotation_checked(M[:3, :3], f"{where}: panorama.world_from_pano")
    parse_pose_uncertainty(doc, where)  # checked where it enters; the solve reads it with the same function
    return Cameras(Path(path), doc["route"], views, doc)


def read_cameras(path: Path) -> Cameras:
    """Read and check ``cameras.json`` at ``path``."""
    return parse_cameras(read_json(Path(path)), path)


def write_cameras(path: Path, doc: dict) -> Path:
    """Check ``doc`` as :func:`parse_cameras` does, then write it atomically."""
    parse_cameras(doc, path)
    return atomic_write_json(Path(path), doc)
