"""Chain- and terrain-guided pose search for carriages that SIFT did not find in a photo.

A carriage lying on its side shows the camera its roof (few features) and its small, alike ends, so SIFT
does not find it; yet its neighbours often are found, and the chain and the ground leave it few places to
be. With the photo's camera in the scene frame (``cameras.json``: ``cam_from_world``) and the terrain
(``Project.terrain_model``), per photo, for every car not found next to one that is:

* **anchors**: the neighbour's coupler (its pose from its found faces, ``CarInPhoto.cam_from_carriage``,
  used only when it rests on two faces or on one matched over 70 % of its length). A held coupling puts the
  car's coupler there within centimetres, but a neighbour's pose from one face can be a metre or two off at
  its far coupler: the coupler is searched within ``search_held_radius_m`` (2 m); a broken coupling within
  ``search_broken_radius_m`` (8 m: the samples' broken couplings are 3.0-3.2 m apart, a fresh seed-2 incident's
  6.3 m, and the generator draws 1.5-8 m). Over a broken coupling the car lies metres from the anchor, where
  the terrain's slope can differ: at the best ``PITCH_KEEP`` (2) coarse headings of every roll class the pitch
  is also tried ``search_broken_pitch_deg`` (+-4 deg) about the terrain's, and the headings around them are
  scored at the pitch that won;
* **hypotheses**: heading every 2 deg within ``search_yaw_span_deg`` (90) of the neighbour's, roll every
  45 deg (upright, on either side, upside down and between), pitch from the terrain (the other coupler as high
  above the ground as the anchored one), the coupler at the anchor, the car lowered or raised until its
  lowest collision-box corner touches the terrain. The heading grid is scored coarse to fine: every
  ``HEADING_STRIDE``-th heading first, then the grid's headings around the best ``STRIDE_KEEP`` of every roll
  class;
* **scoring**: each hypothesis predicts every face turned to the camera (``complete.predicted_homography``);
  they are painted from the car's own references into a template (a photo down-sampled so that the car is
  about 150 px long, blurred), and the template is matched over the image shifts that keep the coupler
  within the anchor's radius. Long faces (sides, roof) are scored in thirds: the score is the sum over the
  tiles of their positive zero-mean normalised correlation times the square root of their area, so a third
  hidden by a building adds nothing instead of diluting the rest. The best shift moves the pose across
  the line of sight. The best hypotheses of every roll class are refined at full resolution (roll +-10 deg in
  5 deg steps, then heading +-1 deg at the best roll) and moved along the coupler's line of sight to where the car touches the terrain;
* **verification**: every facing face is aligned by ECC from the hypothesis as the pose-guided completion
  does (``complete.guided_face``: correlation of at least ``search_min_ecc``, corners moved by at most
  ``guided_max_shift_px`` or a quarter of an edge); a long face that does not align whole is tried in part
  (the largest of ``CROPS`` that aligns: a face partly hidden). The pose is re-estimated from the aligned
  faces (``complete.joint_pose``: PnP on their lattices, 3 px RMS). A hypothesis is kept only if
  ``search_min_faces`` (2) faces align (or one face of ``search_single_face_px`` pixels with a correlation
  of ``search_single_face_ecc``), none of them lies on a face of another car found in the photo, the
  refined pose keeps a coupler within the anchor's radius, and every aligned face agrees with it to 3 px.
  When two verified hypotheses disagree (an aligned face 4 px apart, or a marked point 10 px apart), the
  car is left out as ambiguous.

The faces found this way are reported as the completion's are: points on an aligned face's plane by its
homography (``sigma_px`` 0.5 after ECC), the car's other points projected from the refined pose
(``method = "pose"``, predictions). Pixels are undistorted photo pixels (``match.PhotoFeatures``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import find_objects

from ..rolling_stock import CarriageType
from .assign import CarInPhoto, face_reference_cached
from .complete import guided_face, joint_pose, predicted_homography
from .match import MatchOptions, PhotoFeatures, apply_h, quad_overlap, plausible_homography
from .references import FACES, FaceReference
from .resting import collision_corners, pitch_on_terrain, pitches_on_terrain, rest, rest_on_ray, rested
from .threads import ordered_map

_corners, _rest = collision_corners, rest  # (their names here before resting.py)

log = logging.getLogger(__name__)

COARSE_HEADING_DEG = 2.0
FINE_HEADING_DEG = 1.0
SEEDS_PER_ROLL = 4  # coarse hypotheses refined per roll class
COARSE_ROLL_DEG = 45.0
HEADING_STRIDE = 3  # the coarse heading grid is first scored at every third heading ...
STRIDE_KEEP = 5  # ... and completed around the best five of every roll class
PITCH_KEEP = 2  # a broken coupling: the other pitches (search_broken_pitch_deg) tried at the best two of them
TILES = 3  # a long face (side, roof) is scored in thirds along its length
PAD_PX = 128  # working image padding
CROPS = ((0.0, 0.8), (0.2, 1.0), (0.0, 0.6), (0.4, 1.0))  # parts of a face tried where the whole does not align
DISTINCT_PX = 4.0  # two verified poses that put a marked point this far apart in the photo are different answers
BLUR_PX = 2.0  # photo blur (sigma, px) for the scoring: a basin wider than the hypothesis grid


def _rot(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """world_from_carriage rotation: Rz(yaw) Ry(-pitch) Rx(roll), radians (docs/conventions.md; yaw = 90 deg -
    heading)."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    cy, sy = np.cos(-pitch), np.sin(-pitch)
    cx, sx = np.cos(roll), np.sin(roll)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return Rz @ Ry @ Rx


@dataclass
class Anchor:
    """Where the chain puts one of the car's couplers: ``end`` ("front" / "rear"), the point in the scene
    frame (3,), the neighbour it comes from and the coupling (``held``: within centimetres, but the
    neighbour's pose from its faces can be a metre or two off there; ``broken``: within a few metres)."""

    end: str
    world: np.ndarray
    neighbour: str
    coupling: str = "held"
    yaw: float | None = None  # the neighbour's yaw (rad, scene frame): the car's is within ``MatchOptions.search_yaw_span_deg`` of it


def anchors_of(k: int, consist: list[tuple[str, str, str | None]], types: dict[str, CarriageType],
               poses_world: dict[str, np.ndarray], broken: bool = True) -> list[Anchor]:
    """The anchors of car ``k`` from its neighbours with a pose (world_from_carriage, 4 x 4), held couplings
    first."""
    out = []
    if k > 0 and consist[k - 1][0] in poses_world and consist[k - 1][2] in (("held", "broken") if broken else ("held",)):
        prev = consist[k - 1][0]
        P = poses_world[prev]
        out.append(Anchor("front", P[:3, :3] @ types[prev].coupler_rear + P[:3, 3], prev, consist[k - 1][2],
                          float(np.arctan2(P[1, 0], P[0, 0]))))
    if k + 1 < len(consist) and consist[k + 1][0] in poses_world and \
            consist[k][2] in (("held", "broken") if broken else ("held",)):
        nxt = consist[k + 1][0]
        P = poses_world[nxt]
        out.append(Anchor("rear", P[:3, :3] @ types[nxt].coupler_front + P[:3, 3], nxt, consist[k][2],
                          float(np.arctan2(P[1, 0], P[0, 0]))))
    return sorted(out, key=lambda a: a.coupling != "held")


def _pose_at(ct: CarriageType, a: Anchor, yaw: float, pitch: float, roll: float) -> np.ndarray:
    R = _rot(yaw, pitch, roll)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = a.world - R @ (ct.coupler_front if a.end == "front" else ct.coupler_rear)
    return T


_KERNEL3 = np.ones((3, 3), np.uint8)


@lru_cache(maxsize=64)
def _outside_disc(r: int) -> np.ndarray:
    """(2r + 1, 2r + 1) mask of the shifts farther than r from the centre (read-only)."""
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    out = (xx ** 2 + yy ** 2) > r * r
    out.setflags(write=False)
    return out


MIN_STD = 1.0  # grey levels: a tile, or the photo under it, flatter than this correlates with nothing


def masked_ncc(img: np.ndarray, img_sq: np.ndarray, tmpl: np.ndarray, inside: np.ndarray) -> np.ndarray | None:
    """Zero-mean normalised correlation of ``tmpl`` (h, w) over its pixels ``inside`` (h, w, bool) with the photo
    ``img`` (H, W, float32; ``img_sq`` its square) at every shift: (H - h + 1, W - w + 1), in [-1, 1]; 0 where the
    photo under the mask varies by less than ``MIN_STD`` (the padding past the photo's border); None for a
    template that flat.

    OpenCV's masked ``TM_CCOEFF_NORMED`` computes the same figure (to 1e-4: both checked against float64 sums on
    4000 of the search's tiles) at about 1.7 times the cost; here from three plain correlations, with t the
    template's masked zero-mean values (0 outside the mask) and n the mask's size:
    ncc = sum(t I) / sqrt(sum(t^2) (sum_mask(I^2) - sum_mask(I)^2 / n)). The photo should be centred on its mean
    (the correlation does not change) so that the variance's difference keeps its digits in float32."""
    m = inside.astype(np.float32)
    n = float(np.count_nonzero(inside))
    t = (tmpl - np.float32(np.dot(tmpl.ravel(), m.ravel()) / n)) * m
    tt = float(np.dot(t.ravel(), t.ravel()))
    if tt < n * MIN_STD ** 2:
        return None
    num = cv2.matchTemplate(img, t, cv2.TM_CCORR)
    s1 = cv2.matchTemplate(img, m, cv2.TM_CCORR)
    var_n = cv2.matchTemplate(img_sq, m, cv2.TM_CCORR) - s1 * s1 / np.float32(n)  # n x the photo's variance there
    ok = var_n > n * MIN_STD ** 2
    out = np.zeros(num.shape, np.float32)
    out[ok] = num[ok] / np.sqrt(var_n[ok] * np.float32(tt))
    return out


class _Renderer:
    """The car's faces as a hypothesis shows them, matched against the blurred photo over image shifts."""

    def __init__(self, photo: PhotoFeatures, refs: dict[str, FaceReference], ct: CarriageType, down: int):
        self.K = photo.intrinsics.without_distortion()
        self.refs = {f: r for f, r in refs.items()}
        self.gray = {f: cv2.GaussianBlur(cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), 1.0)
                     for f, r in refs.items()}
        self.ct = ct
        self.d = down
        self._label_cache: dict[tuple[str, int, int], np.ndarray] = {}
        img = cv2.GaussianBlur(photo.gray_undistorted.astype(np.float32), (0, 0), BLUR_PX * down / 2)
        img = cv2.resize(img, None, fx=1 / down, fy=1 / down, interpolation=cv2.INTER_AREA) if down > 1 else img
        # centred on its mean (masked_ncc) and padded by it (0, which correlates with nothing): a search area may
        # reach past the border
        self.pad = PAD_PX
        self.img = cv2.copyMakeBorder(img - np.float32(img.mean()), PAD_PX, PAD_PX, PAD_PX, PAD_PX,
                                      cv2.BORDER_CONSTANT, value=0.0)
        self.img_sq = self.img * self.img
        D = np.diag([1 / down, 1 / down, 1.0])
        D[0, 2] = D[1, 2] = 0.5 / down - 0.5
        self.D = D  # photo px -> working px
        # per face: its centre and outward normal (carriage frame), for the facing test of every hypothesis
        self.centre_normal = {}
        for f, r in self.refs.items():
            h, w = r.image.shape[:2]
            self.centre_normal[f] = (r.carriage_from_ref(np.array([[(w - 1) / 2, (h - 1) / 2]]))[0],
                                     np.asarray(ct.face_normal(r.face), float))

    def _labels(self, f: str, n: int, tiles: int) -> np.ndarray:
        """The face's tile labels n + 1 ... n + tiles over its reference (a third of a long face each)."""
        key = (f, n, tiles)
        if key not in self._label_cache:
            hh, ww = self.gray[f].shape
            self._label_cache[key] = np.repeat(
                (n + 1 + np.minimum(np.arange(ww) * tiles // ww, tiles - 1))[None].astype(np.uint8), hh, 0)
        return self._label_cache[key]

    def faces(self, cam_from_carriage: np.ndarray, min_cos: float) -> list[tuple[str, np.ndarray]]:
        out = []
        R, t = cam_from_carriage[:3, :3], cam_from_carriage[:3, 3]
        for f, r in self.refs.items():
            c, nrm = self.centre_normal[f]  # complete.facing_cosine, without recomputing the face's centre
            Xc = R @ c + t
            # |Xc| as np.linalg.norm computes it (the square root of Xc.dot(Xc)), without its overhead
            if -float((R @ nrm) @ Xc) / max(math.sqrt(float(Xc.dot(Xc))), 1e-9) < min_cos:
                continue
            H = predicted_homography(cam_from_carriage, r, self.K)
            if not plausible_homography(H, r, (self.K.width, self.K.height)):
                continue
            out.append((f, H))
        return out

    def match(self, cam_from_carriage: np.ndarray, min_cos: float, radius_px: float) -> tuple[float, np.ndarray, float]:
        """(score, best shift (2,) photo px, area px) of the hypothesis's facing faces over shifts within
        ``radius_px``; score = the sum over the faces' tiles of their positive correlation x sqrt(tile area, px)."""
        faces = self.faces(cam_from_carriage, min_cos)
        if not faces:
            return -np.inf, np.zeros(2), 0.0
        polys = [apply_h(self.D @ H, self.refs[f].corners()) for f, H in faces]
        allp = np.vstack(polys)
        lo, hi = np.floor(allp.min(0)).astype(int) - 1, np.ceil(allp.max(0)).astype(int) + 1
        size = (int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
        if size[0] < 4 or size[1] < 4 or size[0] * size[1] > 400000:
            return -np.inf, np.zeros(2), 0.0
        r = int(np.ceil(radius_px / self.d))
        x0, y0 = int(lo[0]) - r + self.pad, int(lo[1]) - r + self.pad
        Hh, Ww = self.img.shape
        if x0 < 0 or y0 < 0 or x0 + size[0] + 2 * r > Ww or y0 + size[1] + 2 * r > Hh:
            return -np.inf, np.zeros(2), 0.0  # the search area reaches far outside the photo
        Tc = np.array([[1.0, 0, -lo[0]], [0, 1, -lo[1]], [0, 0, 1]])
        tmpl = np.zeros((size[1], size[0]), np.float32)
        label = np.zeros((size[1], size[0]), np.uint8)  # 0: no face; else the tile (a third of a long face)
        n = 0
        for (f, H), poly in zip(faces, polys):
            M = Tc @ self.D @ H
            w = cv2.warpPerspective(self.gray[f], M, size, flags=cv2.INTER_AREA)
            tiles = TILES if f in ("left", "right", "roof") else 1
            m = cv2.warpPerspective(self._labels(f, n, tiles), M, size, flags=cv2.INTER_NEAREST)
            n += tiles
            m = cv2.erode(m, _KERNEL3)  # off the face's edges (erosion of labels: min)
            sel = m > 0
            tmpl[sel] = w[sel]
            label[sel] = m[sel]
        # per tile, zero-mean normalised correlation over the shifts; a tile hidden (a building, another car)
        # correlates with nothing and adds nothing, instead of diluting the whole face's correlation
        total = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
        area = 0.0
        # every tile's pixel count and bounding box in one pass (np.nonzero(label == t) per tile, in effect)
        counts = np.bincount(label.ravel(), minlength=n + 1)
        boxes = find_objects(label, max_label=n)
        for t in range(1, n + 1):
            if counts[t] < 20:
                continue
            (b0, b1), (a0, a1) = ((sl.start, sl.stop) for sl in boxes[t - 1])
            win = np.s_[y0 + b0:y0 + b1 + 2 * r, x0 + a0:x0 + a1 + 2 * r]
            res = masked_ncc(self.img[win], self.img_sq[win], tmpl[b0:b1, a0:a1], label[b0:b1, a0:a1] == t)
            if res is None:
                continue
            at = float(counts[t]) * self.d ** 2
            total += np.maximum(res, 0) * np.float32(np.sqrt(at))
            area += at
        if area == 0:
            return -np.inf, np.zeros(2), 0.0
        total[_outside_disc(r)] = -1
        k = int(np.argmax(total))
        dy, dx = np.unravel_index(k, total.shape)
        return float(total[dy, dx]), np.array([dx - r, dy - r], float) * self.d, area


def _shifted(cam_from_carriage: np.ndarray, c: np.ndarray, shift: np.ndarray, K) -> np.ndarray:
    """The pose moved so that its coupler ``c`` (carriage frame) moves by ``shift`` px in the photo, at the
    same depth (across the line of sight: an image shift says nothing about the depth, which the joint pose
    of the aligned faces fixes afterwards)."""
    X = cam_from_carriage[:3, :3] @ c + cam_from_carriage[:3, 3]
    uv = K.K @ X
    uv = uv[:2] / uv[2] + shift
    ray = np.linalg.inv(K.K) @ np.array([uv[0], uv[1], 1.0])
    M = cam_from_carriage.copy()
    M[:3, 3] += ray * (X[2] / ray[2]) - X
    return M


def _distinct(poses: list[tuple[float, np.ndarray]], k: int, min_sep_m: float, ct: CarriageType
              ) -> list[tuple[float, np.ndarray]]:
    """The k best (score, pose) whose couplers and roof are at least ``min_sep_m`` from any better one's."""
    probe = np.array([ct.coupler_front, ct.coupler_rear, [0.0, 0.0, ct.height_m]])
    out, pts = [], []
    for sc, M in sorted(poses, key=lambda x: -x[0]):
        if not np.isfinite(sc):
            break
        p = (M[:3, :3] @ probe.T).T + M[:3, 3]
        if any(np.max(np.linalg.norm(p - q, axis=1)) < min_sep_m for q in pts):
            continue
        out.append((sc, M))
        pts.append(p)
        if len(out) >= k:
            break
    return out


class _PoseSearch:
    """One car's pose search in one photo: per anchor, the coarse grid of hypotheses scored against the photo,
    and the best of every roll class refined at full resolution (``candidates``)."""

    def __init__(self, photo: PhotoFeatures, ct: CarriageType, refs: dict[str, FaceReference],
                 cam_from_world: np.ndarray, terrain, opts: MatchOptions):
        self.photo, self.ct, self.refs = photo, ct, refs
        self.cam_from_world, self.terrain, self.opts = cam_from_world, terrain, opts
        self.K = photo.intrinsics.without_distortion()
        self.L = float(np.linalg.norm(ct.coupler_front - ct.coupler_rear))
        self.min_cos = opts.guided_min_cosine
        self.corners = collision_corners(ct)

    def candidates(self, a: Anchor) -> list[tuple[float, np.ndarray, float]]:
        """(score, cam_from_carriage, roll class) of the refined hypotheses coupled at anchor ``a``."""
        cam_from_world, opts, ct = self.cam_from_world, self.opts, self.ct
        Xc = cam_from_world[:3, :3] @ a.world + cam_from_world[:3, 3]
        if Xc[2] <= 1.0:
            return []
        px_per_m = self.K.fx / Xc[2]
        radius_m = opts.search_held_radius_m if a.coupling == "held" else opts.search_broken_radius_m
        down = int(np.clip(np.floor(self.L * px_per_m / 150.0), 1, 4))
        coarse = _Renderer(self.photo, self.refs, ct, down)
        c = ct.coupler_front if a.end == "front" else ct.coupler_rear
        hyps = self._coarse(a, c, coarse, px_per_m, radius_m)
        if not hyps:
            return []
        hyps.sort(key=lambda h: -h[0])
        # the best of every roll class (upright, on either side, ...): a partly hidden face scores low, and
        # the verification, not the score, decides
        seed_ids = set()
        for roll in {round(h[4], 3) for h in hyps}:
            cls = [(h[0], h[1]) for h in hyps if round(h[4], 3) == roll]
            seed_ids |= {id(M) for _, M in _distinct(cls, SEEDS_PER_ROLL, 1.0, ct)}
        fine = _Renderer(self.photo, self.refs, ct, 1)
        seeds = [h for h in hyps if id(h[1]) in seed_ids]
        return ordered_map(lambda h: self._refine(fine, a, c, h, down, radius_m), seeds)

    def _coarse(self, a: Anchor, c: np.ndarray, coarse: _Renderer, px_per_m: float, radius_m: float) -> list[tuple]:
        """The coarse hypotheses (score, cam_from_carriage, yaw, pitch, roll) with a finite score, in the order
        scored: heading and roll on the grid, pitch from the terrain (and, over a broken coupling, about it).

        Each roll class (a column of the grid) is scored on its own (``threads.ordered_map``) and the columns'
        hypotheses are joined in the roll's order: the same list as scoring them one after the other."""
        ct, cam_from_world, terrain, opts, L = self.ct, self.cam_from_world, self.terrain, self.opts, self.L
        yaws = np.deg2rad(np.arange(0.0, 360.0, COARSE_HEADING_DEG) if a.yaw is None else
                          np.rad2deg(a.yaw) + np.arange(-opts.search_yaw_span_deg, opts.search_yaw_span_deg + 1e-6,
                                                        COARSE_HEADING_DEG))
        rolls = np.deg2rad(np.arange(-180.0, 180.0, COARSE_ROLL_DEG))
        scores = np.full((len(yaws), len(rolls)), np.nan)  # nan: not evaluated

        # a broken coupling's car lies metres from the anchor, where the ground's slope can differ: other
        # pitches about the terrain's are tried at the best PITCH_KEEP headings of every roll class
        dps = [] if a.coupling == "held" else [float(np.deg2rad(x)) for x in opts.search_broken_pitch_deg if x != 0]
        best_dp = np.zeros(scores.shape)  # the pitch offset that scored best at each (heading, roll)
        # coarse to fine over the heading: every HEADING_STRIDE-th heading of the grid first, then the grid's
        # headings around the best STRIDE_KEEP of every roll class (the score's basin is wider than the stride),
        # at the pitch that scored best there
        n_y = len(yaws)
        first = sorted(set(range(0, n_y, HEADING_STRIDE)) | {n_y - 1})
        # the terrain's pitch at every heading scored (those of the first pass in every roll class; the others
        # when first needed: a pure function of the heading, whichever thread computes it)
        pitches: dict[int, float] = dict(zip(first, pitches_on_terrain(a, [float(yaws[i]) for i in first], L,
                                                                        terrain)))

        def pitch(i: int) -> float:
            if i not in pitches:
                pitches[i] = pitch_on_terrain(a, float(yaws[i]), L, terrain)
            return pitches[i]

        def column(j: int) -> list[tuple]:
            hyps: list[tuple] = []
            # the first pass's poses rested on the terrain together (one terrain read for the column)
            first_poses = dict(zip(first, rested([_pose_at(ct, a, float(yaws[i]), pitches[i] + 0.0, float(rolls[j]))
                                                  for i in first], self.corners, terrain)))

            def trial(i: int, dp: float) -> float:
                p = pitch(i)
                W = first_poses.pop(i) if dp == 0.0 and i in first_poses else \
                    rest(_pose_at(ct, a, float(yaws[i]), p + dp, float(rolls[j])), self.corners, terrain)
                M0 = cam_from_world @ W
                sc, sh, _ = coarse.match(M0, self.min_cos, radius_m * px_per_m)
                if np.isfinite(sc):
                    hyps.append((sc, _shifted(M0, c, sh, self.K), float(yaws[i]), p + dp, float(rolls[j])))
                return sc

            def evaluate(i: int, dp: float = 0.0) -> None:
                if np.isnan(scores[i, j]):
                    scores[i, j], best_dp[i, j] = trial(i, dp), dp

            for i in first:
                evaluate(i)
            col = scores[:, j]
            ok = np.nonzero(np.isfinite(col))[0]
            for rank, i in enumerate(ok[np.argsort(-col[ok])][:STRIDE_KEEP]):
                for dp in dps if rank < PITCH_KEEP else []:
                    sc = trial(i, dp)
                    if sc > scores[i, j]:
                        scores[i, j], best_dp[i, j] = sc, dp
                for di in range(-(HEADING_STRIDE - 1), HEADING_STRIDE):
                    if 0 <= i + di < n_y:
                        evaluate(int(i + di), float(best_dp[i, j]))
            return hyps

        return [h for hyps in ordered_map(column, range(len(rolls))) for h in hyps]

    def _refine(self, fine: _Renderer, a: Anchor, c: np.ndarray, hyp: tuple, down: int, radius_m: float
                ) -> tuple[float, np.ndarray, float]:
        """Finer orientations around a seed hypothesis, each at its best shift (full resolution); the best,
        rested on the terrain along its coupler's line of sight, with the seed's roll class."""
        ct, cam_from_world, K = self.ct, self.cam_from_world, self.K
        _, M0, yaw, pitch, roll = hyp
        M0 = rest_on_ray(M0, c, cam_from_world, self.corners, self.terrain, radius_m)
        world0 = np.linalg.inv(cam_from_world) @ M0
        cw = world0[:3, :3] @ c + world0[:3, 3]
        a0 = Anchor(a.end, cw, a.neighbour, a.coupling)
        best = (-np.inf, M0)

        def refine(dy: float, dr: float) -> None:
            nonlocal best
            # about the seed's coupler, where the photo put it (not rested again: a vertical move is an
            # image shift at a grazing view)
            M1 = cam_from_world @ _pose_at(ct, a0, yaw + dy, pitch, roll + dr)
            sc, sh, _ = fine.match(M1, self.min_cos, 2.0 * down + 2.0)
            if sc > best[0]:
                best = (sc, _shifted(M1, c, sh, K))
                best_at[:] = [dy, dr]

        # roll first (+-10 deg in 5 deg steps), then the heading (+-1 deg) at the best roll
        best_at = [0.0, 0.0]
        for dr in np.deg2rad(np.arange(-10.0, 10.1, 5.0)):
            refine(0.0, float(dr))
        dr_best = best_at[1]
        for dy in np.deg2rad([-FINE_HEADING_DEG, FINE_HEADING_DEG]):
            refine(float(dy), dr_best)
        return best[0], rest_on_ray(best[1], c, cam_from_world, self.corners, self.terrain, radius_m), round(roll, 3)


def search_car(photo: PhotoFeatures, number: str, ct: CarriageType, refs: dict[str, FaceReference],
               anchors: list[Anchor], cam_from_world: np.ndarray, terrain, opts: MatchOptions,
               taken: list[np.ndarray] | None = None) -> list[CarInPhoto]:
    """The car's faces found by the chain- and terrain-guided pose search, or [] (not convincingly there)."""
    search = _PoseSearch(photo, ct, refs, cam_from_world, terrain, opts)
    cands = [cand for a in anchors for cand in search.candidates(a)]
    if not cands:
        return []
    # verified: the best refined candidates of every roll class, best first
    chosen = []
    for roll in {c[2] for c in cands}:
        chosen += _distinct([(sc, M) for sc, M, r in cands if r == roll], SEEDS_PER_ROLL, 1.0, ct)
    chosen = _distinct(chosen, opts.search_seeds, 1.0, ct)
    accepted = []
    # each candidate verified as alone (on two threads: ECC dominates), the results taken in their order
    verified = ordered_map(lambda cand: _verify(photo, number, ct, refs, anchors, cand[1], cam_from_world, opts,
                                                taken or []), chosen)
    for (sc, M), res in zip(chosen, verified):
        if log.isEnabledFor(logging.DEBUG):
            _log_candidate(photo, number, sc, M, cam_from_world, res)
        if res is not None:
            accepted.append(res)
    if not accepted or _ambiguous(photo, number, ct, accepted):
        return []
    M, dets = accepted[0]
    log.info("%s: car %s found by the chain/terrain pose search: faces %s (ECC %s)", photo.name, number,
             [d.ref.face for d in dets], [round(d.ecc, 3) for d in dets])
    return [CarInPhoto(number, d, 0, M) for d in dets]


def _log_candidate(photo: PhotoFeatures, number: str, sc: float, M: np.ndarray, cam_from_world: np.ndarray,
                   res: tuple[np.ndarray, list] | None) -> None:
    W = np.linalg.inv(cam_from_world) @ M
    R = W[:3, :3]
    log.debug("%s: car %s: candidate score %.1f origin %s heading %.1f pitch %.1f roll %.1f -> %s", photo.name,
              number, sc, np.round(W[:3, 3], 2).tolist(), (90 - np.degrees(np.arctan2(R[1, 0], R[0, 0]))) % 360,
              np.degrees(np.arcsin(np.clip(R[2, 0], -1, 1))), np.degrees(np.arctan2(R[2, 1], R[2, 2])),
              None if res is None else [d.ref.face for d in res[1]])


def _ambiguous(photo: PhotoFeatures, number: str, ct: CarriageType, accepted: list[tuple[np.ndarray, list]]) -> bool:
    """Do two verified poses put the car's faces or marked points in different places (then it is left out)?"""
    K = photo.intrinsics.without_distortion()
    probe = np.array(list(ct.marked_points.values()))

    def where(M):
        return K.project((M[:3, :3] @ probe.T).T + M[:3, 3])

    def apart(a, b):
        # the faces both aligned: their outlines; every marked point: where the two poses put it (predictions,
        # looser: a wrong point is 10 px off)
        fa = {d.ref.face: d for d in a[1]}
        d_face = max([0.0] + [float(np.max(np.linalg.norm(fa[d.ref.face].transfer(d.ref.corners()) - d.polygon(), axis=1)))
                              for d in b[1] if d.ref.face in fa and d.ref.image.shape == fa[d.ref.face].ref.image.shape])
        d_pose = float(np.max(np.linalg.norm(where(a[0]) - where(b[0]), axis=1)))
        return d_face > DISTINCT_PX or d_pose > 2.5 * DISTINCT_PX

    first = accepted[0]
    for other in accepted[1:]:
        if apart(first, other):
            log.info("%s: car %s: the pose search found %d different poses (faces %s and %s, %.1f px apart); left out",
                     photo.name, number, len(accepted), [d.ref.face for d in first[1]], [d.ref.face for d in other[1]],
                     np.max(np.linalg.norm(where(first[0]) - where(other[0]), axis=1)))
            return True
    return False


def _verify(photo: PhotoFeatures, number: str, ct: CarriageType, refs: dict[str, FaceReference],
            anchors: list[Anchor], M0: np.ndarray, cam_from_world: np.ndarray, opts: MatchOptions,
            taken: list[np.ndarray]) -> tuple[np.ndarray, list] | None:
    """ECC of every facing face from the hypothesis, the joint pose, and the checks; (pose, faces) or None."""
    sub = MatchOptions(**{**{k: getattr(opts, k) for k in opts.__dataclass_fields__},
                          "guided_min_ecc": opts.search_min_ecc})
    dets = []
    for f, r in refs.items():
        d = guided_face(photo, r, M0, ct, sub)
        if d is None and f in ("left", "right", "roof"):
            # a long face partly hidden (a building, another car): its visible part, the largest that aligns
            for u0, u1 in CROPS:
                d = guided_face(photo, crop_reference(r, u0, u1), M0, ct, sub)
                if d is not None:
                    break
        if d is not None:
            # a face of another car already found there: the search locked on a neighbour (identical
            # coaches); rejected at once, before the car's other faces are aligned
            if any(quad_overlap(d.polygon(), q) > 0.3 for q in taken):
                log.info("%s: car %s: search face %s lies on a face of another car; rejected", photo.name, number,
                         d.ref.face)
                return None
            dets.append(d)
    if not dets:
        return None
    M = joint_pose(dets, photo.intrinsics, M0)
    if M is None:
        return None
    area = sum(_area(d.polygon()) for d in dets)
    if len(dets) < opts.search_min_faces:
        d = dets[0]
        if not (d.ecc >= opts.search_single_face_ecc and area >= opts.search_single_face_px):
            return None
    # the refined pose meets the chain: a coupler near its anchor (held: the neighbour's pose error; broken:
    # a few metres)
    W = np.linalg.inv(cam_from_world) @ M
    gaps = []
    for a in anchors:
        c = ct.coupler_front if a.end == "front" else ct.coupler_rear
        tol = opts.search_held_radius_m if a.coupling == "held" else opts.search_broken_radius_m
        gaps.append(float(np.linalg.norm(W[:3, :3] @ c + W[:3, 3] - a.world)) / tol)
    if min(gaps) > 1.0:
        log.info("%s: car %s: search pose off its anchors (gap / tolerance %s); rejected", photo.name, number,
                 [round(g, 2) for g in gaps])
        return None
    # every face aligned must agree with the refined pose (ECC did not drift)
    K = photo.intrinsics.without_distortion()
    for d in dets:
        Hp = predicted_homography(M, d.ref, K)
        moved = np.linalg.norm(apply_h(Hp, d.ref.corners()) - d.polygon(), axis=1)
        if moved.max() > 3.0:
            return None
    return M, dets


def crop_reference(ref: FaceReference, u0: float, u1: float) -> FaceReference:
    """The part of a face reference between the shares ``u0`` and ``u1`` of its length (same plane mapping)."""
    w = ref.image.shape[1]
    a, b = int(round(u0 * w)), int(round(u1 * w))
    pts = {n: p - [a, 0.0] for n, p in ref.points.items() if a - 0.5 <= p[0] <= b - 0.5}
    return FaceReference(ref.type_id, ref.car_number, ref.face, np.ascontiguousarray(ref.image[:, a:b]), ref.px_per_m,
                         pts, ref.origin_m + a * ref.axis_u_m, ref.axis_u_m, ref.axis_v_m,
                         mask=None if ref.mask is None else np.ascontiguousarray(ref.mask[:, a:b]))


def _reliable(entries: list[CarInPhoto]) -> bool:
    """A found car's pose is an anchor only if it rests on more than one face, or on one face matched over at
    least 70 % of its length (a pose from a short stretch of a side is metres off at the couplers)."""
    if len({c.detection.ref.face for c in entries}) >= 2:
        return True
    d = entries[0].detection
    if d.inlier_ref_px is None or len(d.inlier_ref_px) < 6:
        return False
    u = d.inlier_ref_px[:, 0]
    return bool(u.max() - u.min() >= 0.7 * d.ref.image.shape[1])


def _area(poly: np.ndarray) -> float:
    return float(0.5 * abs(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])))


def chain_search(photo: PhotoFeatures, found: list[CarInPhoto], consist: list[tuple[str, str, str | None]],
                 types: dict[str, CarriageType], by_number: dict[str, dict[str, FaceReference]],
                 cam_from_world: np.ndarray, terrain, opts: MatchOptions,
                 ref_cache: dict[tuple[str, str], FaceReference]) -> list[CarInPhoto]:
    """``found`` completed with the cars found by the pose search (repeated while a new car gives a new
    anchor)."""
    out = list(found)
    world_from_cam = np.linalg.inv(cam_from_world)
    tried: set[tuple[str, tuple]] = set()
    while True:
        poses = {}
        for number in dict.fromkeys(c.number for c in out):
            mine = [c for c in out if c.number == number and c.cam_from_carriage is not None]
            if mine and _reliable(mine):
                poses[number] = world_from_cam @ mine[0].cam_from_carriage
        have = {c.number for c in out}
        new = []
        for k, (number, _, _) in enumerate(consist):
            if number in have or number not in by_number:  # not in by_number: no reference imagery, not searched
                continue
            anchors = anchors_of(k, consist, types, poses, broken=opts.search_broken)
            if not anchors:
                continue
            key = (number, tuple(a.neighbour for a in anchors))
            if key in tried:
                continue
            tried.add(key)
            ct = types[number]
            refs = {f: by_number.get(number, {}).get(f) or face_reference_cached(ct, number, f, opts, ref_cache) for f in FACES}
            taken = [c.detection.polygon() for c in out]
            new = search_car(photo, number, ct, refs, anchors, cam_from_world, terrain, opts, taken)
            if new:
                break
        if not new:
            return out
        out += new
