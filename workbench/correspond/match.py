"""SIFT matching of face references against a photo, and a homography per face (RANSAC).

Everything geometric happens in the photo's **undistorted** pixel frame (same K, no distortion), where a
planar face maps to the reference by a homography; transferred points are distorted back into the photo
as it is on disk. Pixel (0, 0) is the centre of the top-left pixel (``docs/conventions.md``), as in OpenCV.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from .references import FaceReference, resize_linear_light, sift_features
from .sorting import first_occurrences, sorted_unique
from .undistort import undistorted_image

log = logging.getLogger(__name__)
ECC_CROP_MARGIN_PX = 32  # ECC works on the photo cropped around the face, this much (+ a quarter of its size) beyond
ECC_MASK_MARGIN_PX = 2  # the photo's pixels this close to a reference part that is not on the car are left out too


@dataclass(frozen=True, kw_only=True)
class MatchOptions:
    """Options of the automatic matcher (keyword-only; unknown keys are a TypeError)."""

    px_per_m: float = 25.0  # reference resolution
    # (horizontal, vertical) compressions of the side references (ASIFT-like): along the car, from above/below
    tilts: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.7, 1.0), (3.0, 1.0), (1.0, 2.0), (1.7, 2.0),
                                              (3.0, 2.0), (1.0, 3.5))
    end_tilts: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.7, 1.0), (1.0, 1.7))
    photo_upsample: float = 2.5  # photos are upsampled before SIFT (carriages are small in wide shots) ...
    max_photo_side_px: int = 4000  # ... to at most this long side
    ratio: float = 0.8  # Lowe's ratio test (nearest / second nearest reference descriptor)
    ransac_px: float = 2.0  # RANSAC threshold in (undistorted) photo pixels
    min_inliers: int = 15  # fewer RANSAC inliers (pooled over the type's cars): the face is not reported
    min_support: int = 8  # fewer matches of the car's own livery agreeing with the face: not that car
    min_margin: float = 1.3  # a face goes to a car only with this many times the inliers of any other car
    min_reference_keypoints: int = 25  # a reference with fewer has "no texture"
    refine: bool = True  # guided re-matching and ECC alignment of each accepted face
    max_instances: int = 2  # homographies tried per face reference and photo
    carry_between_photos: bool = True  # panorama sets: carry points into the other photos (rotation homography)
    pose_points: bool = True  # also report the points off every found face's plane, projected from the car's pose
    # pose-guided completion (complete.py): a found car's other faces, aligned by ECC where its pose puts them
    guided: bool = True
    guided_min_cosine: float = 0.2  # the face turns at least this much to the camera (cosine of the angle)
    guided_min_ecc: float = 0.8  # ECC correlation needed to accept a guided face
    guided_max_shift_px: float = 6.0  # ECC may move a corner this far from the prediction (or 1/4 of an edge)
    guided_min_edge_px: float = 6.0  # a face whose predicted outline has a shorter edge is not tried
    # Hough clustering of k-NN matches (Lowe 2004): small faces with a few per cent of their matches right
    hough: bool = True
    hough_k: int = 2  # nearest reference descriptors per photo keypoint
    hough_min_votes: int = 8  # distinct photo keypoints in a bin before it is verified by RANSAC
    hough_max_clusters: int = 60  # bins verified per face reference and photo, strongest first
    hough_min_ecc: float = 0.85  # a Hough face is kept only if ECC aligns the whole face this well
    # chain- and terrain-guided pose search (search.py) for cars not found, next to found neighbours over a
    # held coupling; needs the photo's camera in the scene frame (cameras.json)
    search: bool = True
    search_seeds: int = 12  # best distinct hypotheses verified by ECC
    search_min_ecc: float = 0.8  # ECC correlation needed for a face aligned from a hypothesis
    search_min_faces: int = 2  # faces that must align (non-coplanar: the pose is then fixed) ...
    search_single_face_ecc: float = 0.9  # ... or one face with this correlation ...
    search_single_face_px: float = 400.0  # ... covering this many photo pixels
    search_broken: bool = True  # also from neighbours over a broken coupling (its coupler within a few metres)
    search_held_radius_m: float = 2.0  # a held coupling's coupler within this of the neighbour's (its pose error)
    search_broken_radius_m: float = 8.0  # a broken coupling's coupler within this of the neighbour's
    # a broken coupling: pitches (deg) also tried about the terrain's at the anchor (the car lies metres from
    # it, where the ground's slope can differ), at the best coarse headings of every roll class (search.py)
    search_broken_pitch_deg: tuple[float, ...] = (-4.0, 0.0, 4.0)
    search_yaw_span_deg: float = 90.0  # the car's heading within this of its neighbour's (a consist folds)
    # worker processes for the photos of a set (parallel.py; 0: one per CPU this process may use); the
    # points do not depend on it
    workers: int = 0

    def __post_init__(self) -> None:
        if not self.px_per_m > 0 or not self.photo_upsample > 0 or not 0 < self.ratio < 1:
            raise ValueError(f"bad MatchOptions: {self}")


@dataclass
class PhotoFeatures:
    """A photo prepared for matching: its intrinsics, undistorted grey image and SIFT features."""

    name: str
    intrinsics: CameraIntrinsics
    gray_undistorted: np.ndarray  # (h, w) uint8, pinhole K, photo size
    keypoints: np.ndarray  # (n, 2) undistorted photo px
    descriptors: np.ndarray  # (n, 128) float32
    frames: np.ndarray | None = None  # (n, 2) SIFT size (photo px) and angle (deg) of each keypoint
    cache: dict = field(default_factory=dict, repr=False)  # matches per reference

    def distort_px(self, uv_und: np.ndarray) -> np.ndarray:
        """Undistorted photo px (n, 2) -> px of the photo on disk (n, 2)."""
        K = self.intrinsics
        return K.pixels_from_normalized(K.distort(K.normalized_from_pixels(np.asarray(uv_und, float).reshape(-1, 2))))

    def undistort_px(self, uv: np.ndarray) -> np.ndarray:
        K = self.intrinsics
        return K.pixels_from_normalized(K.undistort(K.normalized_from_pixels(np.asarray(uv, float).reshape(-1, 2))))


def photo_features(name: str, rgb: np.ndarray, K: CameraIntrinsics, opts: MatchOptions) -> PhotoFeatures:
    """Undistort the photo, upsample it and detect SIFT features (keypoints in undistorted photo px)."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    und = undistorted_image(gray, K)
    s = min(opts.photo_upsample, opts.max_photo_side_px / max(und.shape))
    big = und if abs(s - 1) < 1e-6 else cv2.resize(und, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)
    kp, desc, fr = sift_features(big, frames=True)
    kp = (kp + 0.5) / s - 0.5
    return PhotoFeatures(name, K, und, kp, desc, np.column_stack([fr[:, 0] / s, fr[:, 1]]))


@dataclass
class FaceDetection:
    """A face of a car found in a photo: ``photo_from_ref`` (3, 3) homography into undistorted photo px."""

    ref: FaceReference
    photo: str
    photo_from_ref: np.ndarray
    n_inliers: int
    rms_px: float
    ecc: float | None = None  # correlation after ECC alignment (None: not refined)
    inlier_photo_px: np.ndarray | None = None  # (n, 2) undistorted photo px
    inlier_ref_px: np.ndarray | None = None  # (n, 2)
    guided: bool = False  # aligned by ECC where the car's pose predicted it (complete.py), no SIFT inliers
    hough: bool = False  # found by Hough clustering of k-NN matches (hough_detections): ECC must confirm it

    @property
    def confidence(self) -> float:
        if self.guided:
            return float(0.6 * np.clip(self.ecc or 0.0, 0.0, 1.0))
        c = self.n_inliers / (self.n_inliers + 20.0)
        if self.ecc is not None:
            c *= float(np.clip(self.ecc, 0.0, 1.0)) ** 0.5
        return float(np.clip(c, 0.0, 1.0))

    def polygon(self) -> np.ndarray:
        """(4, 2) undistorted photo px of the face's outline."""
        return apply_h(self.photo_from_ref, self.ref.corners())

    def transfer(self, ref_px: np.ndarray) -> np.ndarray:
        return apply_h(self.photo_from_ref, ref_px)


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.asarray(pts, dtype=float).reshape(-1, 2)
    q = np.column_stack([p, np.ones(len(p))]) @ np.asarray(H, float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:]


_NEXT = np.array([1, 2, 3, 0])  # np.roll(x, -1, axis=0) of a quad's 4 rows


def _corners_h(ref: FaceReference) -> np.ndarray:
    """(4, 3) the reference's corners in homogeneous coordinates (cached on the reference per image size)."""
    shape = ref.image.shape[:2]
    v = getattr(ref, "_corners_h", None)
    if v is None or v[0] != shape:
        v = (shape, np.column_stack([ref.corners(), np.ones(4)]))
        ref._corners_h = v  # type: ignore[attr-defined]
    return v[1]


def plausible_homography(H: np.ndarray, ref: FaceReference, size: tuple[int, int]) -> bool:
    """A homography that keeps orientation, maps the face to a convex quad of sane size, mostly in the image."""
    if H is None:
        return False
    H = np.asarray(H, float)
    if not np.isfinite(H).all():
        return False
    # (the same arithmetic as apply_h, np.roll and np.linalg.norm, without their overhead: this runs for every
    # hypothesis of the pose search)
    c = _corners_h(ref) @ H.T
    # the face must not cross the vanishing line: the homogeneous scale keeps its sign over the corners (tested
    # first: then no corner's scale is 0 or NaN, and the division below needs no guard)
    z = c[:, 2]
    if not ((z > 0).all() or (z < 0).all()):
        return False
    poly = c[:, :2] / c[:, 2:]
    if not np.isfinite(poly).all():
        return False
    e = poly[_NEXT] - poly
    en = e[_NEXT]
    cross = e[:, 0] * en[:, 1] - e[:, 1] * en[:, 0]
    if not (cross > 0).all():  # convex and clockwise in image coordinates (v down), like the reference
        return False
    area = 0.5 * abs(np.sum(poly[:, 0] * poly[_NEXT, 1] - poly[_NEXT, 0] * poly[:, 1]))
    w, h = size
    if area < 100 or area > 4 * w * h:
        return False
    # sides of the quad: the shortest at least 3 px, the ratio of opposite sides bounded (no extreme perspective)
    lens = np.sqrt(np.add.reduce(e * e, axis=1))  # np.linalg.norm(e, axis=1), as it computes it
    if lens.min() < 3 or max(lens[0] / lens[2], lens[2] / lens[0], lens[1] / lens[3], lens[3] / lens[1]) > 8:
        return False
    # a long face (a side: 25 m by 2.5 m) foreshortens along its length, hardly across it: its top and bottom
    # edges stay of about equal length in the photo unless the camera is within a few metres
    h_ref, w_ref = ref.image.shape[:2]
    if w_ref > 3 * h_ref and max(lens[0] / lens[2], lens[2] / lens[0]) > 1.5:
        return False
    return True


def _integral(desc: np.ndarray) -> bool:
    """Whether squared L2 distances between these descriptors are computed exactly in float32 by any
    summation order: integer values (OpenCV's SIFT rounds its descriptors to 0..255) whose squared norms
    stay below 2^22 (every partial sum of squares or products then stays an integer below 2^24)."""
    return bool(desc.dtype == np.float32 and len(desc) and np.all(desc >= 0) and np.array_equal(desc, np.round(desc))
                and float(np.max(np.einsum("ij,ij->i", desc, desc))) < 2.0 ** 22)


def _nearest(photo: PhotoFeatures, ref: FaceReference) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Nearest neighbours between the photo's and the reference's descriptors, as OpenCV's brute-force L2
    matcher finds them: (knn (n, 2) the two nearest reference descriptors of every photo descriptor, nearest
    first; their distances (n, 2) float32; back (m,) the nearest photo descriptor of every reference
    descriptor). Ties go to the lower index, as in ``cv2.BFMatcher``. One matrix product gives both
    directions (the matcher computes the distances twice, and once more for the Hough's k-NN).

    The squared distances are exact (``_integral``): the same integers the matcher computes, so the same
    neighbours and the same float32 distances (``sqrt`` of an exact integer). None where that does not hold
    (the caller uses ``cv2.BFMatcher``). Cached per (photo, reference).
    """
    key = ("nn", id(ref))
    if key in photo.cache:
        return photo.cache[key]
    out = None
    P, R = photo.descriptors, ref.descriptors
    if len(P) >= 2 and len(R) >= 2 and _integral_cached(photo, P) and _integral_ref(ref):
        # exact: integer products, partial sums below 2^24; every term and sum below is an integer below 2^24,
        # so computed in place, in any order, it is the same as |p|^2 + |r|^2 - 2 p.r
        D2 = P @ R.T
        D2 *= -2.0
        D2 += _sq_norms(photo, P)[:, None]
        D2 += np.einsum("ij,ij->i", R, R)[None, :]
        rows = np.arange(len(P))
        j1 = np.argmin(D2, axis=1)  # first index among ties
        back = np.argmax(D2 == D2.min(axis=0), axis=0)  # argmin along axis 0 (the first among ties), faster
        d1 = D2[rows, j1].copy()
        D2[rows, j1] = np.inf
        j2 = np.argmin(D2, axis=1)
        d2 = D2[rows, j2]
        knn = np.column_stack([j1, j2])
        dist = np.sqrt(np.maximum(np.column_stack([d1, d2]), 0.0)).astype(np.float32)
        out = (knn, dist, back)
    photo.cache[key] = out
    return out


def _sq_norms(photo: PhotoFeatures, desc: np.ndarray) -> np.ndarray:
    """Squared norms of the photo's descriptors (computed once per photo)."""
    key = ("sq_norms",)
    if key not in photo.cache:
        photo.cache[key] = np.einsum("ij,ij->i", desc, desc)
    return photo.cache[key]


def _integral_cached(photo: PhotoFeatures, desc: np.ndarray) -> bool:
    key = ("integral",)
    if key not in photo.cache:
        photo.cache[key] = _integral(desc)
    return photo.cache[key]


def _integral_ref(ref: FaceReference) -> bool:
    v = getattr(ref, "_integral", None)
    if v is None or v[0] is not ref.descriptors:
        v = (ref.descriptors, _integral(ref.descriptors))
        ref._integral = v  # type: ignore[attr-defined]
    return v[1]


def _matches(photo: PhotoFeatures, ref: FaceReference, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Matches photo -> reference: (photo px (m, 2), reference px (m, 2)).

    A match is kept if it passes Lowe's ratio test against the reference's second-nearest descriptor, or if
    it is a mutual nearest neighbour (photo -> reference and back): the ratio test alone rejects the
    repeated windows of a long side, the mutual test alone keeps too few distinctive features. Cached per
    (photo, reference).
    """
    key = (id(ref), ratio)
    if key in photo.cache:
        return photo.cache[key]
    if len(photo.keypoints) < 2 or ref.descriptors is None or len(ref.descriptors) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    nn = _nearest(photo, ref)
    if nn is not None:
        knn, dist, back = nn
        a, b = dist[:, 0].astype(np.float64), dist[:, 1].astype(np.float64)
        qi = np.nonzero((a < ratio * b) | (back[knn[:, 0]] == np.arange(len(knn))))[0]
        ti = knn[qi, 0]
    else:
        matcher = cv2.BFMatcher(cv2.NORM_L2)
        knn = matcher.knnMatch(photo.descriptors, ref.descriptors, k=2)
        back = {m.queryIdx: m.trainIdx for m in matcher.match(ref.descriptors, photo.descriptors)}
        qi, ti = [], []
        for pair in knn:
            if len(pair) < 2:
                continue
            a, b = pair
            if a.distance < ratio * b.distance or back.get(a.trainIdx) == a.queryIdx:
                qi.append(a.queryIdx)
                ti.append(a.trainIdx)
    out = photo.keypoints[qi], ref.keypoints[ti]
    photo.cache[key] = out
    return out


def _guided(photo: PhotoFeatures, ref: FaceReference, H: np.ndarray, radius_px: float,
            ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Matches restricted to photo keypoints within ``radius_px`` of where ``H`` puts each reference keypoint."""
    proj = apply_h(H, ref.keypoints)
    P, R = [], []
    kp = photo.keypoints
    if len(kp) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    ok = np.all(np.isfinite(proj), axis=1)
    # candidates from a k-d tree (a hair wider than the radius), then the exact test on them, in index order
    if "kdtree" not in photo.cache:
        from scipy.spatial import cKDTree

        photo.cache["kdtree"] = cKDTree(kp)
    cand: list = [None] * len(proj)
    wider = radius_px * (1 + 1e-9) + 1e-9
    for j, near_j in zip(np.nonzero(ok)[0], photo.cache["kdtree"].query_ball_point(proj[ok], wider)):
        cand[j] = near_j
    for j, q in enumerate(proj):
        if not ok[j] or not cand[j]:
            continue
        c = np.sort(np.asarray(cand[j], dtype=np.intp))
        near = c[np.sum((kp[c] - q) ** 2, axis=1) < radius_px ** 2]
        if len(near) == 0:
            continue
        d = np.linalg.norm(photo.descriptors[near] - ref.descriptors[j], axis=1)
        k = int(np.argmin(d))
        if len(near) > 1:
            d2 = np.partition(d, 1)[1]
            if d[k] > ratio * d2:
                continue
        P.append(kp[near[k]])
        R.append(ref.keypoints[j])
    return np.array(P).reshape(-1, 2), np.array(R).reshape(-1, 2)


def ecc_refine(photo: PhotoFeatures, ref: FaceReference, H: np.ndarray,
                min_cc: float | None = None) -> tuple[np.ndarray, float] | None:
    """Dense alignment of the reference to the photo (ECC, homography), started from ``H``.

    The photo is warped into the reference frame (scaled to about the photo's resolution there) and the
    warp is refined; the correlation coefficient is returned with the refined photo_from_ref. With
    ``min_cc``, an alignment whose correlation stays below it (the caller rejects it) is returned after the
    first (blurred) pass, without the second.
    """
    poly = apply_h(H, ref.corners())
    h_ref, w_ref = ref.image.shape[:2]
    # photo pixels per reference pixel along the face (mean edge ratio)
    e = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
    s = float(np.clip(np.mean([e[0] / w_ref, e[2] / w_ref, e[1] / h_ref, e[3] / h_ref]), 0.25, 1.0))
    Wk, Hk = max(16, int(round(w_ref * s))), max(16, int(round(h_ref * s)))
    sx, sy = Wk / w_ref, Hk / h_ref  # the template's exact scales (rounding its size changes them)
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])  # ref px -> working px
    tmpl = cv2.cvtColor(resize_linear_light(ref.image, (Wk, Hk)), cv2.COLOR_RGB2GRAY).astype(np.float32)
    # the photo cropped around the face (with a margin wider than any accepted correction): ECC blurs and
    # differentiates its whole input image on every call, which for a face of a few thousand pixels in a
    # 2 MP photo cost 10-50 times the alignment itself
    gray = photo.gray_undistorted
    lo, hi = poly.min(0), poly.max(0)
    m = ECC_CROP_MARGIN_PX + 0.25 * float(np.max(hi - lo))
    x0, y0 = (int(np.clip(np.floor(v - m), 0, n)) for v, n in zip(lo, (gray.shape[1], gray.shape[0])))
    x1, y1 = (int(np.clip(np.ceil(v + m) + 1, 0, n)) for v, n in zip(hi, (gray.shape[1], gray.shape[0])))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    C = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])  # crop px -> photo px
    photo_from_work = np.linalg.inv(C) @ H @ np.linalg.inv(S)  # (crop px)
    warp = photo_from_work.astype(np.float32) / np.float32(photo_from_work[2, 2])
    img = np.ascontiguousarray(gray[y0:y1, x0:x1], dtype=np.float32)
    mask = None
    if ref.mask is not None:
        # the photo's pixels over the reference's part that is not on the car (a side's corner cut off by a
        # sloped nose) take no part: there the photo shows what lies behind (OpenCV masks the input image, so
        # that part is carried to the photo by the starting warp, with a margin for the correction)
        off = cv2.resize(255 - ref.mask, (Wk, Hk), interpolation=cv2.INTER_NEAREST)
        off = cv2.warpPerspective(off, photo_from_work, (img.shape[1], img.shape[0]), flags=cv2.INTER_NEAREST)
        off = cv2.dilate(off, np.ones((2 * ECC_MASK_MARGIN_PX + 1,) * 2, np.uint8))
        mask = np.where(off > 0, 0, 255).astype(np.uint8)
    try:
        cc, warp = cv2.findTransformECC(tmpl, img, warp, cv2.MOTION_HOMOGRAPHY,
                                        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-5), mask, 3)
    except cv2.error:
        return None
    if min_cc is not None and cc < min_cc:
        Hn = C @ warp.astype(float) @ S
        return Hn / Hn[2, 2], float(cc)
    # then without the 3 x 3 blur: blurred, the photo's pixels along the face's outline mix in what lies
    # beyond the face (the template's do not), which pulls the outline inwards (a vertical compression of
    # 1-3 % on a side 25 px high)
    try:
        cc2, warp2 = cv2.findTransformECC(tmpl, img, warp.copy(), cv2.MOTION_HOMOGRAPHY,
                                          (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-5), mask, 1)
        warp = warp2  # the correlation reported stays the blurred one (the thresholds are set on it)
    except cv2.error as exc:  # the blurred alignment stands
        log.debug("ECC without blur did not converge (%s); the blurred alignment is kept", exc)
    Hn = C @ warp.astype(float) @ S
    return Hn / Hn[2, 2], float(cc)


def detect_faces(photo: PhotoFeatures, refs: list[FaceReference], opts: MatchOptions,
                 max_instances: int | None = None) -> list[FaceDetection]:
    """Instances of a face in ``photo`` by sequential RANSAC, best first.

    ``refs`` are references of the same face of cars of one type (same geometry, different liveries): their
    matches are pooled, since any car's livery shares the windows, doors and stripes of the type. Each
    detection carries ``refs[0]``; which car it is is decided later by :func:`support`. ``n_inliers`` counts
    the distinct matches that RANSAC kept.
    """
    ref = refs[0]
    Ps, Rs = [], []
    for r in refs:
        if r.image.shape != ref.image.shape:
            raise ValueError(f"references of one face must share their geometry: {r.image.shape=} {ref.image.shape=}")
        P, R = _matches(photo, r, opts.ratio)
        Ps.append(P)
        Rs.append(R)
    PR = np.unique(np.round(np.hstack([np.vstack(Ps), np.vstack(Rs)]), 2), axis=0)
    P, R = PR[:, :2], PR[:, 2:]
    size = (photo.intrinsics.width, photo.intrinsics.height)
    out: list[FaceDetection] = []
    remaining = np.ones(len(P), dtype=bool)
    for _ in range(max_instances or opts.max_instances):
        if remaining.sum() < max(6, opts.min_inliers // 2):
            break
        idx = np.nonzero(remaining)[0]
        H, mask = cv2.findHomography(R[idx], P[idx], cv2.USAC_MAGSAC, opts.ransac_px, maxIters=20000,
                                     confidence=0.9999)
        if H is None:
            break
        inl = idx[mask.ravel() > 0]
        remaining[inl] = False
        if len(inl) < opts.min_inliers or not plausible_homography(H, ref, size):
            continue
        resid = np.linalg.norm(apply_h(H, R[inl]) - P[inl], axis=1)
        out.append(FaceDetection(ref, photo.name, H / H[2, 2], int(len(inl)), float(np.sqrt(np.mean(resid ** 2))),
                                 None, P[inl], R[inl]))
    # sides drowned in the photo's other features (match.hough_detections); not the ends, whose few
    # features are alike on every coach of a type
    if opts.hough and ref.face in ("left", "right"):
        for r in refs:
            for det in hough_detections(photo, r, opts):
                # where RANSAC over the distinctive matches found the face, a Hough face overlapping it is
                # the same face or an alias shifted by a window pitch
                if det.n_inliers >= opts.min_inliers and \
                        not any(quad_overlap(det.polygon(), o.polygon()) > 0.3 for o in out):
                    out.append(det)
    out.sort(key=lambda d: -d.n_inliers)
    return out


def support(photo: PhotoFeatures, ref: FaceReference, H: np.ndarray, opts: MatchOptions) -> int:
    """How many of ``ref``'s ratio-test matches agree with ``H`` (within ``opts.ransac_px``): the evidence for
    this car's livery at the place ``H`` describes."""
    P, R = _matches(photo, ref, opts.ratio)
    if len(P) == 0:
        return 0
    return int(np.sum(np.linalg.norm(apply_h(H, R) - P, axis=1) < opts.ransac_px))


def _agrees(Ha: np.ndarray, Hb: np.ndarray, ref_px: np.ndarray, tol_px: float = 4.0) -> bool:
    """Two homographies agree where the evidence is: 90 % of the reference points move by less than tol_px."""
    d = np.linalg.norm(apply_h(Ha, ref_px) - apply_h(Hb, ref_px), axis=1)
    return bool(len(d) and np.percentile(d, 90) < tol_px)


def refine_detection(photo: PhotoFeatures, det: FaceDetection, opts: MatchOptions) -> FaceDetection:
    """Guided re-matching around the RANSAC estimate, a least-squares refit, then ECC (dense) alignment.

    Each step is kept only if it agrees with the previous estimate where the matches are (by under 4 px):
    repeated windows could otherwise pull the face along by one window pitch.
    """
    ref = det.ref
    size = (photo.intrinsics.width, photo.intrinsics.height)
    H, Pi, Ri = det.photo_from_ref, det.inlier_photo_px, det.inlier_ref_px
    Pg, Rg = _guided(photo, ref, H, radius_px=3.0, ratio=0.8)
    if len(Pg) >= len(Pi):
        H2, m2 = cv2.findHomography(Rg, Pg, cv2.RANSAC, opts.ransac_px)
        if H2 is not None and plausible_homography(H2, ref, size) and m2.sum() >= len(Pi) and _agrees(H2, H, Ri):
            H, Pi, Ri = H2, Pg[m2.ravel() > 0], Rg[m2.ravel() > 0]
    ecc = None
    res = ecc_refine(photo, ref, H)
    if res is not None:
        Hn, cc = res
        resid = np.linalg.norm(apply_h(Hn, Ri) - Pi, axis=1)
        if _agrees(Hn, H, Ri) and np.median(resid) < 2.0 and plausible_homography(Hn, ref, size):
            H, ecc = Hn, cc
    resid = np.linalg.norm(apply_h(H, Ri) - Pi, axis=1)
    return FaceDetection(ref, det.photo, H / H[2, 2], det.n_inliers, float(np.sqrt(np.mean(resid ** 2))), ecc,
                         Pi, Ri, hough=det.hough)


def _knn_matches(photo: PhotoFeatures, ref: FaceReference, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (photo keypoint, reference keypoint) of each photo keypoint's ``k`` nearest reference
    descriptors, no ratio test: a repeated window matches every window, and geometry sorts them out."""
    key = ("knn", id(ref), k)
    if key in photo.cache:
        return photo.cache[key]
    if len(photo.keypoints) < 2 or ref.descriptors is None or len(ref.descriptors) < k:
        out = (np.zeros(0, int), np.zeros(0, int))
    elif k == 2 and _nearest(photo, ref) is not None:  # the ratio test's neighbours (_nearest)
        knn = _nearest(photo, ref)[0]
        out = (np.repeat(np.arange(len(knn)), 2), knn.ravel().astype(int))
    else:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(photo.descriptors, ref.descriptors, k=k)
        qi = np.array([m.queryIdx for ms in knn for m in ms], dtype=int)
        ti = np.array([m.trainIdx for ms in knn for m in ms], dtype=int)
        out = (qi, ti)
    photo.cache[key] = out
    return out


def _unique_rows(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(A, axis=0, return_inverse=True)`` of an integer array (n, c), inverse flattened: the same
    rows in the same (lexicographic) order, from one int64 key per row (``np.unique`` with ``axis=0`` sorts
    the rows as structured records, 20-50 times slower)."""
    A = np.asarray(A)
    if len(A) and np.issubdtype(A.dtype, np.integer):
        lo = A.min(0).astype(np.int64)
        span = A.max(0).astype(np.int64) - lo + 1
        if float(np.prod(span.astype(float))) < 2.0 ** 62:
            code = np.zeros(len(A), np.int64)
            for c in range(A.shape[1]):  # mixed radix: lexicographic order of the rows
                code = code * span[c] + (A[:, c].astype(np.int64) - lo[c])
            _, first, inv = np.unique(code, return_index=True, return_inverse=True)
            return A[first], inv.ravel()
    keys, inv = np.unique(A, axis=0, return_inverse=True)
    return keys, inv.ravel()


def _row_codes(A: np.ndarray):
    """One int64 per row of an integer array (n, c) that sorts as the rows do (lexicographically), and the
    function that turns codes back into rows; (None, None) when the rows' span does not fit in an int64."""
    lo = A.min(0).astype(np.int64)
    span = A.max(0).astype(np.int64) - lo + 1
    if float(np.prod(span.astype(float))) >= 2.0 ** 62:
        return None, None
    code = np.zeros(len(A), np.int64)
    for c in range(A.shape[1]):  # mixed radix
        code = code * span[c] + (A[:, c].astype(np.int64) - lo[c])

    def decode(codes: np.ndarray) -> np.ndarray:
        out = np.empty((len(codes), A.shape[1]), dtype=A.dtype)
        rest = codes.copy()
        for c in range(A.shape[1] - 1, -1, -1):
            out[:, c] = rest % span[c] + lo[c]
            rest //= span[c]
        return out

    return code, decode


def hough_clusters(photo: PhotoFeatures, ref: FaceReference, *, k: int = 4, min_votes: int = 8,
                   max_clusters: int = 8) -> list[np.ndarray]:
    """Groups of k-NN matches that agree on where the face is, by Lowe's Hough transform (IJCV 2004, 7.3).

    Each match of a photo keypoint to a reference keypoint predicts, from their SIFT scales and
    orientations (and the reference tilt it was detected at), the face's centre in the photo, its size and
    its rotation; matches vote for the two nearest bins of each (location: a quarter of the predicted size,
    size: an octave, rotation: 30 degrees). Returned: index arrays into ``_knn_matches(photo, ref, k)``, most
    votes first, at least ``min_votes`` distinct photo keypoints each. A small face among thousands of photo
    features, with a few per cent of its matches right, is found this way where RANSAC over all matches
    needs more samples than it can draw.
    """
    if photo.frames is None or ref.frames is None:
        return []
    qi, ti = _knn_matches(photo, ref, k)
    if len(qi) < min_votes:
        return []
    h, w = ref.image.shape[:2]
    fr = ref.frames[ti]
    s = photo.frames[qi, 0] / np.maximum(fr[:, 0], 1e-6)
    theta = np.deg2rad(photo.frames[qi, 1] - fr[:, 1])
    tx, ty = fr[:, 2], fr[:, 3]
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    dq = (centre - ref.keypoints[ti]) / np.column_stack([tx, ty])  # to the centre, in the tilted reference
    c, sn = np.cos(theta), np.sin(theta)
    pred = photo.keypoints[qi] + s[:, None] * np.column_stack([c * dq[:, 0] - sn * dq[:, 1],
                                                               sn * dq[:, 0] + c * dq[:, 1]])
    extent = s * np.maximum(w / tx, h / ty)  # predicted size of the face in the photo, px
    ok = np.isfinite(pred).all(axis=1) & (extent > 8)
    log_e = np.log2(np.maximum(extent, 1e-6))
    votes = []
    for db in (0, 1):
        b = np.floor(log_e - 0.5).astype(int) + db
        L = 0.25 * 2.0 ** (b + 0.5)
        for dx in (0, 1):
            ix = np.floor(pred[:, 0] / L - 0.5).astype(int) + dx
            for dy in (0, 1):
                iy = np.floor(pred[:, 1] / L - 0.5).astype(int) + dy
                for dt in (0, 1):
                    it = (np.floor(np.rad2deg(theta) / 30.0 - 0.5).astype(int) + dt) % 12
                    votes.append(np.column_stack([b, ix, iy, it, np.arange(len(qi))])[ok])
    V = np.vstack(votes)
    # the bins (rows of V[:, :4], in lexicographic order, as np.unique(axis=0) gives them), each vote's bin
    # (inv) and the votes grouped by bin (order, starts, ends): one stable sort of one int64 key per vote
    code, decode = _row_codes(V[:, :4])
    if code is None:  # keys too wide for one int64 (not seen): the general way
        keys, inv = _unique_rows(V[:, :4])
        order = np.argsort(inv, kind="stable")
        starts = np.searchsorted(inv[order], np.arange(len(keys)))
    else:
        order = np.argsort(code, kind="stable")
        sc = code[order]
        first = np.ones(len(sc), dtype=bool)
        first[1:] = sc[1:] != sc[:-1]
        starts = np.nonzero(first)[0]
        keys = decode(sc[starts])
        inv = np.empty(len(code), dtype=np.intp)
        inv[order] = np.cumsum(first) - 1
    ends = np.append(starts[1:], len(order))
    # a bin's strength: the distinct photo keypoints voting for it
    nq = np.int64(max(len(photo.keypoints), 1))
    pair = sorted_unique(inv.astype(np.int64) * nq + qi[V[:, 4]])
    counts = np.bincount(pair // nq, minlength=len(keys))
    # rank bins by how far their votes stand above chance: a bin of a large predicted size covers much of
    # the photo and collects many random votes; the chance count is the band's (size, rotation) votes
    # spread over the band's location cells in the photo
    W, Hh = photo.intrinsics.width, photo.intrinsics.height
    band, band_inv = _unique_rows(keys[:, [0, 3]])
    band_votes = np.bincount(band_inv, weights=counts, minlength=len(band))
    L = 0.25 * 2.0 ** (keys[:, 0] + 0.5)
    cells = np.maximum((W / L + 1) * (Hh / L + 1), 1.0)
    # each match votes in 4 location bins of its band (2 x 2): the chance count of one bin
    expected = 4.0 * band_votes[band_inv] / 16.0 / cells
    score = (counts - expected) / np.sqrt(expected + 1.0)
    out: list[np.ndarray] = []
    taken = np.zeros((max_clusters, len(qi)), dtype=bool)  # the matches of each cluster returned
    ranked = np.argsort(-score)
    for kk in ranked[counts[ranked] >= min_votes]:
        if len(out) >= max_clusters:
            break
        m = sorted_unique(V[order[starts[kk]:ends[kk]], 4])
        if len(out) and np.any(taken[:len(out), m].sum(axis=1) > 0.5 * len(m)):
            continue  # a neighbouring bin of a cluster already returned
        taken[len(out), m] = True
        out.append(m.astype(int))
    return out


def hough_detections(photo: PhotoFeatures, ref: FaceReference, opts: MatchOptions) -> list[FaceDetection]:
    """Face instances from the Hough clusters of ``ref``'s k-NN matches: a RANSAC homography per cluster,
    then every k-NN match within ``ransac_px`` of it (distinct photo and reference keypoints counted)."""
    qi, ti = _knn_matches(photo, ref, opts.hough_k)
    if len(qi) == 0:
        return []
    P, R = photo.keypoints[qi], ref.keypoints[ti]
    size = (photo.intrinsics.width, photo.intrinsics.height)
    out: list[FaceDetection] = []
    for members in hough_clusters(photo, ref, k=opts.hough_k, min_votes=opts.hough_min_votes,
                                  max_clusters=opts.hough_max_clusters):
        if len(members) < 6:
            continue
        H, mask = cv2.findHomography(R[members], P[members], cv2.USAC_MAGSAC, opts.ransac_px, maxIters=5000,
                                     confidence=0.999)
        if H is None or not plausible_homography(H, ref, size):
            continue
        for _ in range(2):  # all matches that agree, and a refit on them
            d = np.linalg.norm(apply_h(H, R) - P, axis=1)
            inl = np.nonzero(d < opts.ransac_px)[0]
            # one photo keypoint, one reference keypoint: keep the closest pairing of each
            inl = inl[np.argsort(d[inl])]
            inl = inl[first_occurrences(qi[inl])]
            inl = inl[first_occurrences(ti[inl])]
            if len(inl) < 6:
                break
            H2, _ = cv2.findHomography(R[inl], P[inl], 0)
            if H2 is None or not plausible_homography(H2, ref, size):
                break
            H = H2
        if len(inl) < opts.min_inliers or not plausible_homography(H, ref, size):
            continue
        resid = np.linalg.norm(apply_h(H, R[inl]) - P[inl], axis=1)
        det = FaceDetection(ref, photo.name, H / H[2, 2], int(len(inl)), float(np.sqrt(np.mean(resid ** 2))),
                            None, P[inl], R[inl], hough=True)
        if any(quad_overlap(det.polygon(), o.polygon()) > 0.7 for o in out):
            continue
        out.append(det)
    return out


def quad_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over the smaller area of two convex quads (4, 2)."""
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    inter, _ = cv2.intersectConvexConvex(a32, b32)
    small = min(abs(cv2.contourArea(a32)), abs(cv2.contourArea(b32)))
    return float(inter / small) if small > 0 else 0.0
