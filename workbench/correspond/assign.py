"""Joint assignment of detected faces to the consist's carriages, and the marked points they give.

Identical coaches differ only by their painted number and their grime, so every car has its own face
references. In one photo, detections of the same type and face that overlap are one *region*; each region
is scored against every car of that type by the car's own livery (:func:`match.support`), and regions are
assigned to cars jointly (Hungarian), then improved by pairwise swaps under the consist's chain: a held
coupling puts car k's rear coupler next to car k+1's front coupler, which the per-face poses (planar PnP
with the photo's intrinsics) can check.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..rolling_stock import CarriageType
from .alignment import alignment_covariance
from .complete import guided_face, joint_pose
from .ground import FIT_DOF, FacePose, Ground, planar_pose
from .match import FaceDetection, MatchOptions, PhotoFeatures, quad_overlap, detect_faces, refine_detection, support
from .references import FACES, FaceReference, face_reference
from .threads import ordered_map

log = logging.getLogger(__name__)

EXTRAPOLATE = 0.1  # share of a face's length a homography may be extrapolated beyond its matches
CHAIN_WEIGHT = 1.0  # inliers of support worth one metre of coupler gap in a held link
CHAIN_CAP_M = 10.0


@dataclass
class CarInPhoto:
    """A car's face found in a photo: the refined detection and its pose (cam_from_carriage, 4 x 4) or None, and,
    for a face posed on its own, what chose its pose's branch (``"fit"``: the face's residuals; ``"ground"``: the
    terrain overruled them, :mod:`.ground`; None: a face aligned from a pose, guided or searched)."""

    number: str
    detection: FaceDetection
    support: int
    cam_from_carriage: np.ndarray | None
    branch: str | None = None


@dataclass
class PointObservation:
    carriage: str
    point: str
    view: str
    uv: tuple[float, float]  # px of the photo on disk
    confidence: float
    sigma_px: float
    face: str
    how: str  # "homography" (on the face plane), "pose" (off the plane, from the face's pose) or "carried"
    # a homography point's loading (2, 8): its share of the face alignment's error (alignment.py), px on disk
    loading: np.ndarray | None = None
    n_matches: int = 0  # the matches the face's homography rests on (with a loading)
    ecc: float | None = None  # a "homography" point's face alignment's ECC correlation (None: not refined)


POSE_LATTICE = (13, 5)  # a face aligned by ECC gives its pose through this lattice (along, across) of its matched part


def _on_lattice(det: FaceDetection) -> bool:
    """Whether the face's pose rests on a lattice mapped by its ECC-aligned homography (else on its matches)."""
    return det.ecc is not None and det.inlier_ref_px is not None and len(det.inlier_ref_px) >= 6


def pose_correspondences(det: FaceDetection) -> tuple[np.ndarray, np.ndarray]:
    """(reference px, undistorted photo px) that a face's pose rests on: for a face aligned by ECC (dense,
    sub-pixel over the whole face), a lattice over the part of the face its matches span, mapped by the
    aligned homography; else its matches themselves (SIFT keypoints, a pixel or so of noise each, which
    tilts a one-face pose about the face's long axis: points off the plane move by pixels)."""
    Ri, Pi = det.inlier_ref_px, det.inlier_photo_px
    if not _on_lattice(det):
        return Ri, Pi
    h, w = det.ref.image.shape[:2]
    lo, hi = Ri.min(0), Ri.max(0)
    if det.guided:  # a guided face's lattice already covers the whole face
        lo, hi = np.zeros(2), np.array([w - 1.0, h - 1.0])
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], POSE_LATTICE[0]),
                             np.linspace(lo[1], hi[1], POSE_LATTICE[1])), -1).reshape(-1, 2)
    return g, det.transfer(g)


def _pose(det: FaceDetection, K, ct: CarriageType | None = None, ground: Ground | None = None) -> FacePose | None:
    """A face's pose (planar PnP in undistorted pixels, :func:`pose_correspondences`; of its two branches the one
    its fit and, given ``ground`` and the car's type ``ct``, the terrain prefer: :mod:`.ground`), or None."""
    if det.inlier_ref_px is None or len(det.inlier_ref_px) < 6:
        return None
    R_px, P_px = pose_correspondences(det)
    dof = FIT_DOF if _on_lattice(det) else 2.0 * len(R_px) - 6.0  # a homography's lattice, or raw matches
    return planar_pose(det.ref.carriage_from_ref(R_px), P_px, K.K, dof=dof, ct=ct, ground=ground)


def _posed(c: CarInPhoto, photo: PhotoFeatures, types: dict[str, CarriageType], ground: Ground | None
           ) -> CarInPhoto:
    """``c`` with the pose of its face (:func:`_pose`) and what chose its branch."""
    fp = _pose(c.detection, photo.intrinsics, types.get(c.number), ground)
    c.cam_from_carriage, c.branch = (None, None) if fp is None else (fp.cam_from_carriage, fp.chosen_by)
    if c.branch == "ground":
        log.info("%s: car %s: its %s face's other branch, which the terrain prefers (clearance %s m, face "
                 "residual %s px)", photo.name, c.number, c.detection.ref.face,
                 " / ".join(f"{x:.2f}" for x in fp.clearance_m), " / ".join(f"{x:.3f}" for x in fp.rms_px))
    return c


def find_cars(photo: PhotoFeatures, refs: dict[str, list[FaceReference]], consist: list[tuple[str, str, str | None]],
              types: dict[str, CarriageType], opts: MatchOptions,
              ref_cache: dict[tuple[str, str], FaceReference] | None = None,
              ground: Ground | None = None) -> list[CarInPhoto]:
    """The cars' faces in one photo, assigned jointly, completed by their pose-guided faces.

    ``refs``: car number -> its face references; ``consist``: (number, type id, coupling_to_next) front to
    rear; ``types``: car number -> CarriageType; ``ref_cache``: references of the faces not matched by SIFT
    (the roof), kept between the photos of a set; ``ground``: the photo's camera in the scene and the terrain,
    which judge a one-face pose's two branches with the face's fit (:mod:`.ground`; None: the fit alone).
    """
    by_number = {n: {r.face: r for r in rs} for n, rs in refs.items()}
    usable = [r for rs in refs.values() for r in rs
              if r.descriptors is not None and len(r.descriptors) >= opts.min_reference_keypoints]
    # 1. candidates: every car's every face, by its own livery
    # (each reference's on its own, ``threads.ordered_map``, in the references' order)
    cands: list[FaceDetection] = [d for ds in ordered_map(lambda ref: detect_faces(photo, [ref], opts), usable)
                                  for d in ds]
    # 2. regions: overlapping candidates of the same type and face group (a side's instances compete
    #    with the other side's: their layouts are alike)
    regions: list[list[FaceDetection]] = []
    for d in sorted(cands, key=lambda d: -d.n_inliers):
        poly = d.polygon()
        for reg in regions:
            r0 = reg[0]
            if r0.ref.type_id == d.ref.type_id and _group(r0.ref.face) == _group(d.ref.face) \
                    and quad_overlap(poly, r0.polygon()) > 0.3:
                reg.append(d)
                break
        else:
            regions.append([d])
    # 3. cars to regions jointly (Hungarian on the evidence), per type: a region's evidence for a car is
    #    the best inlier count of that car's own references there
    chosen: list[tuple[FaceDetection, str, int]] = []
    for type_id in sorted({r.ref.type_id for reg in regions for r in reg}):
        idx = [i for i, reg in enumerate(regions) if reg[0].ref.type_id == type_id]
        cars = [n for n, t, _ in consist if t == type_id and n in by_number]
        S = np.zeros((len(idx), len(cars)))
        best: dict[tuple[int, int], FaceDetection] = {}
        for a, i in enumerate(idx):
            for d in regions[i]:
                b = cars.index(d.ref.car_number)
                # a Hough face's k-NN inliers are shared by every coach of the type (their windows are
                # alike): its evidence for this car is the car's own distinctive matches that agree
                ev = support(photo, d.ref, d.photo_from_ref, opts) if d.hough else d.n_inliers
                if ev > S[a, b]:
                    S[a, b], best[(a, b)] = ev, d
            # cars without a detection of their own here: how many of their matches agree with the region's
            # homography (their evidence, for the margin test; identical coaches share most features)
            d0 = regions[i][0]
            for b, n in enumerate(cars):
                if (a, b) in best:
                    continue
                for f in _group(d0.ref.face):
                    r = by_number[n].get(f)
                    if r is None or r.image.shape != d0.ref.image.shape:
                        continue
                    sup = support(photo, r, d0.photo_from_ref, opts)
                    if sup > S[a, b]:
                        S[a, b] = sup
                        best[(a, b)] = FaceDetection(r, photo.name, d0.photo_from_ref, d0.n_inliers, d0.rms_px,
                                                     None, d0.inlier_photo_px, d0.inlier_ref_px, hough=d0.hough)
        # two regions of one face group cannot both be one car: the Hungarian gives each car one region
        # per group; run it per group
        for group in FACE_GROUPS:
            rows_g = [a for a, i in enumerate(idx) if _group(regions[i][0].ref.face) == group]
            if not rows_g:
                continue
            Sg = S[rows_g]
            rows, cols = linear_sum_assignment(-Sg)
            for a, b in zip(rows, cols):
                det = best.get((rows_g[a], b))
                if det is None:
                    continue
                if det.hough:
                    # the face's presence is its geometric inliers (and the ECC check after refinement); the
                    # car's identity is its own distinctive matches, as many as a RANSAC face needs, and
                    # needed only among coaches of one type (a few matches of a far car's number and grime
                    # named the wrong coach on a 480 px photo)
                    if det.n_inliers < opts.min_inliers or (len(cars) > 1 and Sg[a, b] < opts.min_inliers):
                        continue
                elif Sg[a, b] < opts.min_inliers:
                    continue
                # the winner must stand out from the other cars (identical coaches differ by little)
                others = np.delete(Sg[a], b)
                if len(others) and Sg[a, b] < opts.min_margin * others.max():
                    log.info("%s: a %s face of type %s is ambiguous (%d vs %d inliers); left out", photo.name,
                             group, type_id, Sg[a, b], others.max())
                    continue
                chosen.append((det, cars[b], int(Sg[a, b])))
    # 4. poses, and pairwise swaps of same-type assignments that shorten the held couplings
    found = [_posed(CarInPhoto(n, det, s, None), photo, types, ground) for det, n, s in chosen]
    found = _improve_by_chain(found, consist, types, photo, by_number, opts)
    # 5. refine the accepted faces
    if opts.refine:
        for c in found:
            c.detection = refine_detection(photo, c.detection, opts)
            if c.cam_from_carriage is not None:
                _posed(c, photo, types, ground)
    # a face found only by Hough clustering (few distinctive matches) must be confirmed by the dense
    # alignment of the whole face (without refinement there is none: the face is not kept)
    found = [c for c in found if not c.detection.hough or (c.detection.ecc or 0.0) >= opts.hough_min_ecc]
    # 6. each found car's other faces where its pose predicts them, and one pose from all its faces
    if opts.guided:
        found = _complete(found, photo, types, by_number, opts, {} if ref_cache is None else ref_cache)
    return found


def _complete(found: list[CarInPhoto], photo: PhotoFeatures, types: dict[str, CarriageType],
              by_number: dict[str, dict[str, FaceReference]], opts: MatchOptions,
              ref_cache: dict[tuple[str, str], FaceReference]) -> list[CarInPhoto]:
    """Add the guided faces of every found car with a pose (:mod:`.complete`) and give its entries the joint
    pose of all its faces."""
    out = list(found)
    for number in dict.fromkeys(c.number for c in found):
        mine = [c for c in found if c.number == number]
        posed = [c for c in mine if c.cam_from_carriage is not None]
        if not posed:
            continue
        best = max(posed, key=lambda c: c.detection.n_inliers)
        ct = types[number]
        have = {c.detection.ref.face for c in mine}
        by_face = by_number.get(number, {})
        added = []
        for face in FACES:
            if face in have:
                continue
            ref = by_face.get(face) or face_reference_cached(ct, number, face, opts, ref_cache)
            det = guided_face(photo, ref, best.cam_from_carriage, ct, opts)
            if det is not None:
                added.append(det)
        if not added:
            continue
        dets = [c.detection for c in mine if c.detection.inlier_ref_px is not None] + added
        M = joint_pose(dets, photo.intrinsics, best.cam_from_carriage)
        if M is None:
            log.info("%s: car %s: guided faces %s disagree with its pose; not used", photo.name, number,
                     [d.ref.face for d in added])
            continue
        log.info("%s: car %s: guided faces %s", photo.name, number, [d.ref.face for d in added])
        for c in mine:
            c.cam_from_carriage = M
        out += [CarInPhoto(number, d, 0, M) for d in added]
    return out


def face_reference_cached(ct: CarriageType, number: str, face: str, opts: MatchOptions,
               cache: dict[tuple[str, str], FaceReference]) -> FaceReference:
    """A face reference for alignment (no features), cached per (car, face) in ``cache``."""
    key = (number, face)
    if key not in cache:
        cache[key] = face_reference(ct, number, face, opts.px_per_m)
    return cache[key]


FACE_GROUPS = (("left", "right"), ("front", "rear"), ("roof",))  # faces of like layout, never seen together


def _group(face: str) -> tuple[str, str]:
    return next(g for g in FACE_GROUPS if face in g)


def _gap_cost(found: list[CarInPhoto], consist, types) -> float:
    pose = {}
    for c in found:
        if c.cam_from_carriage is not None and c.number not in pose:
            pose[c.number] = c.cam_from_carriage
    cost = 0.0
    for (n0, _, coupling), (n1, _, _) in zip(consist, consist[1:]):
        if coupling != "held" or n0 not in pose or n1 not in pose:
            continue
        a = pose[n0][:3, :3] @ types[n0].coupler_rear + pose[n0][:3, 3]
        b = pose[n1][:3, :3] @ types[n1].coupler_front + pose[n1][:3, 3]
        cost += min(float(np.linalg.norm(a - b)), CHAIN_CAP_M)
    return cost


def _improve_by_chain(found: list[CarInPhoto], consist, types, photo, by_number, opts) -> list[CarInPhoto]:
    """Swap the cars of two same-type, same-face detections while that raises support - weight * gaps."""
    if len(found) < 2:
        return found

    def score(fs):
        return sum(c.support for c in fs) - CHAIN_WEIGHT * _gap_cost(fs, consist, types)

    best = score(found)
    improved = True
    while improved:
        improved = False
        for i, j in itertools.combinations(range(len(found)), 2):
            a, b = found[i], found[j]
            if a.detection.ref.type_id != b.detection.ref.type_id or \
                    a.detection.ref.image.shape != b.detection.ref.image.shape or \
                    a.detection.ref.face not in by_number[b.number] or b.detection.ref.face not in by_number[a.number]:
                continue
            trial = list(found)
            new = []
            for c, other in ((a, b.number), (b, a.number)):
                ref = by_number[other][c.detection.ref.face]
                s = support(photo, ref, c.detection.photo_from_ref, opts)
                det = FaceDetection(ref, photo.name, c.detection.photo_from_ref, c.detection.n_inliers,
                                    c.detection.rms_px, None, c.detection.inlier_photo_px, c.detection.inlier_ref_px,
                                    hough=c.detection.hough)
                new.append(CarInPhoto(other, det, s, c.cam_from_carriage, c.branch))
            trial[i], trial[j] = new
            sc = score(trial)
            if sc > best + 1e-9 and min(x.support for x in new) >= opts.min_support:
                log.info("%s: swapped cars %s and %s (chain)", photo.name, a.number, b.number)
                found, best, improved = trial, sc, True
                break
    return found


def _in_sight(ct: CarriageType, cam_from_carriage: np.ndarray, X: np.ndarray, margin_m: float = 0.05) -> bool:
    """Whether a point that stands off the car's body (a coupler, beyond the end) is in the camera's sight
    although none of its faces turns to the camera: it lies outside every collision box of the car (body,
    bogies, equipment) by ``margin_m`` and the line of sight from the camera to it crosses none of them.
    A point on the body's surface (a corner) is not: its faces' facing test decides."""
    boxes = ct.collision_boxes()
    C = -cam_from_carriage[:3, :3].T @ cam_from_carriage[:3, 3]  # camera centre, carriage frame
    d = X - C
    for c, h in boxes:
        if np.all(np.abs(X - c) < h + margin_m):
            return False  # on (or in) a box: not a protruding point
    for c, h in boxes:
        # slab test of the segment C + s d, s in [0, 1 - margin], against the box
        s0, s1 = 0.0, 1.0 - margin_m / max(float(np.linalg.norm(d)), 1e-9)
        lo, hi = c - h - C, c + h - C
        for k in range(3):
            if abs(d[k]) < 1e-12:
                if lo[k] > 0 or hi[k] < 0:
                    s0, s1 = 1.0, 0.0
                    break
                continue
            a, b = lo[k] / d[k], hi[k] / d[k]
            s0, s1 = max(s0, min(a, b)), min(s1, max(a, b))
        if s0 < s1:
            return False
    return True


def observations_of(found: list[CarInPhoto], photo: PhotoFeatures, types: dict[str, CarriageType], *,
                    pose_points: bool = True, margin_px: float = 2.0) -> list[PointObservation]:
    """Marked points from the found faces, one per (car, point): on a face's plane by its homography, the
    other points of a car (couplers, corners of an unseen face) from its pose when their face turns to the
    camera, or, for a point standing off the body (a coupler beyond its end), when the line of sight to it
    passes the car's body (:func:`_in_sight`). A point seen by two faces keeps the face with more inliers."""
    K = photo.intrinsics
    best: dict[tuple[str, str], PointObservation] = {}
    for c in sorted(found, key=lambda c: -c.detection.n_inliers):
        det, ct = c.detection, types[c.number]
        conf = det.confidence
        sigma = float(np.clip(det.rms_px, 0.5, 3.0)) if det.ecc is None else 0.5
        # the homography is trusted near its evidence only: a face seen in part (the rest hidden, or out of
        # the photo) is not extrapolated beyond its matches by more than EXTRAPOLATE of its length
        w_ref = det.ref.image.shape[1]
        u_in = det.inlier_ref_px[:, 0] if det.inlier_ref_px is not None and len(det.inlier_ref_px) else np.zeros(1)
        lo, hi = float(u_in.min()) - EXTRAPOLATE * w_ref, float(u_in.max()) + EXTRAPOLATE * w_ref
        names = [n for n in det.ref.points if lo <= det.ref.points[n][0] <= hi]
        if names:
            ref_px = np.array([det.ref.points[n] for n in names])
            uv = photo.distort_px(det.transfer(ref_px))
            cov = alignment_covariance(det, ref_px, photo.distort_px)
            for i, (n, p) in enumerate(zip(names, uv)):
                if (c.number, n) in best or not np.all(np.isfinite(p)) or not K.in_image(p[None], margin_px)[0]:
                    continue
                best[(c.number, n)] = PointObservation(c.number, n, photo.name, (float(p[0]), float(p[1])),
                                                       round(conf, 3), round(sigma, 2), det.ref.face, "homography",
                                                       None if cov is None else cov.loading_px[i],
                                                       0 if cov is None else cov.n_matches, det.ecc)
        if not pose_points or c.cam_from_carriage is None or (hi - lo) < (0.5 + 2 * EXTRAPOLATE) * w_ref:
            continue  # a pose from a short stretch of one face is too weak to place the car's other points
        M = c.cam_from_carriage
        for n, X in ct.marked_points.items():
            if (c.number, n) in best or n in det.ref.points:  # a plane point is the homography's, or none
                continue
            Xc = M[:3, :3] @ X + M[:3, 3]
            facing = any(float((M[:3, :3] @ ct.face_normal(f)) @ Xc) < 0 for f in ct.marked_point_faces[n])
            if Xc[2] <= 0 or not (facing or _in_sight(ct, M, X)):
                continue
            p = K.project(Xc[None])[0]
            if not np.all(np.isfinite(p)) or not K.in_image(p[None], margin_px)[0]:
                continue
            best[(c.number, n)] = PointObservation(c.number, n, photo.name, (float(p[0]), float(p[1])),
                                                   round(0.5 * conf, 3), 2.0, det.ref.face, "pose")
    return list(best.values())
