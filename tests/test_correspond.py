"""The correspond stage: SIFT marked points against synthetic ground truth, manual files, overrides."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics
from workbench.files import correspondences as mf
from workbench.correspond import stage as cs
from workbench.correspond.match import MatchOptions, detect_faces, photo_features, refine_detection
from workbench.correspond.references import FACES, build_references, face_reference
from workbench.errors import InputError
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.rolling_stock import get_type
from workbench.runner import Runner

pytestmark = pytest.mark.slow


# ---------------------------------------------------------------------------------------------------------
# references and homographies, no incident needed
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("type_id", ["shoreliner", "acs-64", "amfleet-i"])
def test_reference_pixels_round_trip_to_marked_points(type_id):
    ct = get_type(type_id)
    seen = set()
    for face in FACES:
        ref = face_reference(ct, "1234", face, 30.0)
        h, w = ref.image.shape[:2]
        for name, uv in ref.points.items():
            seen.add(name)
            assert -1.0 <= uv[0] <= w and -1.0 <= uv[1] <= h, (face, name, uv, (w, h))
            xyz = ref.carriage_from_ref(uv[None])[0]
            assert np.linalg.norm(xyz - ct.marked_points[name]) < 0.01, (face, name, xyz, ct.marked_points[name])
        # one pixel step is 1 / px_per_m metres, in the face's plane
        assert abs(np.linalg.norm(ref.axis_u_m) - 1 / 30.0) < 2e-3 and abs(np.linalg.norm(ref.axis_v_m) - 1 / 30.0) < 2e-3
        n = ct.face_normal(face)
        assert abs(ref.axis_u_m @ n) < 1e-9 and abs(ref.axis_v_m @ n) < 1e-9
    # every side point of a coach is on some face's plane (couplers protrude: they come from the pose)
    assert {n for n, fs in ct.marked_point_faces.items() if {"left", "right"} & set(fs)} <= seen


def test_homography_recovers_a_known_warp():
    """A reference warped into a blank photo by a known homography: the face is found and its points
    transferred within a fraction of a pixel."""
    ct = get_type("shoreliner")
    opts = MatchOptions()
    ref = build_references(ct, "6100", px_per_m=opts.px_per_m, tilts=opts.tilts)[0]
    assert ref.face == "left"
    h, w = ref.image.shape[:2]
    src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    dst = np.float32([[40, 200], [600, 170], [610, 215], [45, 262]])  # seen at an angle
    H = cv2.getPerspectiveTransform(src, dst)
    photo = np.full((480, 640, 3), (90, 140, 80), np.uint8)
    photo = cv2.warpPerspective(ref.image, H, (640, 480), dst=photo, borderMode=cv2.BORDER_TRANSPARENT,
                                flags=cv2.INTER_AREA)
    K = CameraIntrinsics(width=640, height=480, fx=700.0, fy=700.0, cx=319.5, cy=239.5)
    pf = photo_features("warp.png", photo, K, opts)
    dets = detect_faces(pf, [ref], opts)
    assert len(dets) == 1 and dets[0].n_inliers >= opts.min_inliers
    det = refine_detection(pf, dets[0], opts)
    names = list(ref.points)
    want = cv2.perspectiveTransform(np.float32([ref.points[n] for n in names])[None], H)[0]
    got = det.transfer(np.array([ref.points[n] for n in names]))
    err = np.linalg.norm(got - want, axis=1)
    assert err.max() < 0.8, err
    assert 0.0 < det.confidence <= 1.0


def _warp_into(photo: np.ndarray, image: np.ndarray, H: np.ndarray) -> np.ndarray:
    return cv2.warpPerspective(image, H, (photo.shape[1], photo.shape[0]), dst=photo,
                               borderMode=cv2.BORDER_TRANSPARENT, flags=cv2.INTER_AREA)


def test_hough_finds_a_small_side_among_clutter():
    """A coach side 200 px long (its wall 16 px high), rotated by 50 degrees, in a photo whose other
    features (three other coaches' sides, large) outnumber its own: the Hough clustering of k-NN matches
    finds it, within a pixel after the ECC refinement the stage applies."""
    from workbench.correspond.match import apply_h, _knn_matches, hough_clusters, hough_detections

    ct = get_type("shoreliner")
    opts = MatchOptions()
    refs = {n: build_references(ct, n, px_per_m=opts.px_per_m, tilts=opts.tilts)[0] for n in ("6100", "6223")}
    ref = refs["6100"]
    h, w = ref.image.shape[:2]
    rng = np.random.default_rng(0)
    photo = (rng.integers(60, 160, (720, 1280, 1)) * np.ones((1, 1, 3))).astype(np.uint8)
    photo = cv2.GaussianBlur(photo, (0, 0), 3)
    # distractors: the other coach's side (same windows, another number), big, three times
    other = refs["6223"].image
    for k, y in enumerate((40, 250, 470)):
        src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
        dst = np.float32([[30 + 40 * k, y], [1150, y + 10], [1150, y + 90], [30 + 40 * k, y + 80]])
        photo = _warp_into(photo, other, cv2.getPerspectiveTransform(src, dst))
    # the face: 200 px long, rotated 50 degrees, slightly foreshortened
    a = np.deg2rad(50.0)
    Rm = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    quad = np.array([[0, 0], [200, 0], [196, 16], [2, 17]], float) @ Rm.T + [900, 360]
    H = cv2.getPerspectiveTransform(np.float32([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]),
                                    np.float32(quad))
    photo = _warp_into(photo, ref.image, H)
    K = CameraIntrinsics(width=1280, height=720, fx=1400.0, fy=1400.0, cx=639.5, cy=359.5)
    pf = photo_features("clutter.png", photo, K, opts)
    qi, ti = _knn_matches(pf, ref, opts.hough_k)
    right = np.linalg.norm(apply_h(H, ref.keypoints[ti]) - pf.keypoints[qi], axis=1) < 2.0
    assert 0 < right.mean() < 0.2, right.mean()  # a small share of the matches is right
    clusters = hough_clusters(pf, ref, k=opts.hough_k, min_votes=opts.hough_min_votes)
    assert clusters and max(right[c].sum() for c in clusters) >= 8
    dets = [d for d in hough_detections(pf, ref, opts) if d.hough]
    corners = ref.corners()
    errs = [np.abs(d.polygon() - apply_h(H, corners)).max() for d in dets]
    assert errs and min(errs) < 3.0, errs  # the outline's corners, from matches on a 16 px wall
    best = refine_detection(pf, dets[int(np.argmin(errs))], opts)  # as the stage does: ECC on the whole face
    assert best.ecc is not None and best.ecc >= opts.hough_min_ecc
    assert np.abs(best.polygon() - apply_h(H, corners)).max() < 1.0


def test_guided_completion_aligns_the_other_faces():
    """A coach posed in front of a camera, its left side and front end painted into the photo by their
    exact homographies: given the pose from the side (perturbed by 0.5 degree and 5 cm), the front end is
    aligned by ECC to within a pixel at its corners, the joint pose is closer to the truth than the start, and a face
    that is not in the photo (the roof, left blank) is not reported."""
    from workbench.correspond.complete import guided_face, joint_pose, predicted_homography
    from workbench.correspond.match import FaceDetection, apply_h

    ct = get_type("shoreliner")
    opts = MatchOptions()
    K = CameraIntrinsics(width=1280, height=960, fx=1500.0, fy=1500.0, cx=639.5, cy=479.5)
    # camera looking at the car's left side and front end from 35 m, at 40 degrees
    yaw = np.deg2rad(40.0)
    R_wc = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])  # world_from_carriage
    eye = np.array([12.0, 35.0, 6.0])
    from workbench.core.camera import look_at
    cam_from_world = look_at(eye, np.array([4.0, 8.0, 2.0]))
    M = np.eye(4)
    M[:3, :3] = cam_from_world[:3, :3] @ R_wc
    M[:3, 3] = cam_from_world[:3, 3]
    photo = np.full((960, 1280, 3), (110, 150, 90), np.uint8)
    refs = {f: face_reference(ct, "6100", f, opts.px_per_m) for f in ("left", "front", "roof")}
    for f in ("left", "front"):
        photo = _warp_into(photo, refs[f].image, predicted_homography(M, refs[f], K))
    from workbench.correspond.match import PhotoFeatures
    from workbench.correspond.undistort import undistorted_image
    gray = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    pf = PhotoFeatures("posed.png", K, undistorted_image(gray, K), np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    # the start: the true pose, turned by 0.5 degree about the vertical and shifted 5 cm
    d = np.deg2rad(0.5)
    turn = np.array([[np.cos(d), -np.sin(d), 0], [np.sin(d), np.cos(d), 0], [0, 0, 1]])
    start = M.copy()
    start[:3, :3] = M[:3, :3] @ turn
    start[:3, 3] += [0.05, 0.0, 0.0]
    front = guided_face(pf, refs["front"], start, ct, opts)
    assert front is not None and front.guided and front.ecc >= opts.guided_min_ecc
    corners = refs["front"].corners()
    err = np.abs(front.polygon() - apply_h(predicted_homography(M, refs["front"], K), corners)).max()
    assert err < 1.0, err  # the outline's corners: the face's edges, blurred by the warp
    assert guided_face(pf, refs["roof"], start, ct, opts) is None
    # the left side as a detection at its true homography, then the joint pose from both faces
    g = np.stack(np.meshgrid(np.linspace(0, refs["left"].image.shape[1] - 1, 9),
                             np.linspace(0, refs["left"].image.shape[0] - 1, 3)), -1).reshape(-1, 2)
    Hl = predicted_homography(M, refs["left"], K)
    left = FaceDetection(refs["left"], "posed.png", Hl, len(g), 0.0, 1.0, apply_h(Hl, g), g)
    J = joint_pose([left, front], K, start)
    assert J is not None
    ang = lambda A: np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ M[:3, :3]) - 1) / 2, -1, 1)))  # noqa: E731
    assert ang(J) < 0.5 * ang(start) and np.linalg.norm(J[:3, 3] - M[:3, 3]) < 0.05


def test_ecc_on_the_cropped_photo_agrees_with_the_whole_photo(monkeypatch):
    """``match.ecc_refine`` aligns on the photo cropped around the face (ECC filters its whole input image
    on every call): from a start 2 px off, the face lands where the known warp put it, and where ECC on the
    whole photo puts it (the crop's offset carried back), with the same correlation."""
    from workbench.correspond import match as mm
    from workbench.correspond.match import PhotoFeatures, apply_h, ecc_refine
    from workbench.correspond.undistort import undistorted_image

    ct = get_type("shoreliner")
    ref = face_reference(ct, "6100", "left", MatchOptions().px_per_m)
    h, w = ref.image.shape[:2]
    src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    dst = np.float32([[700, 500], [1180, 470], [1185, 512], [704, 556]])  # far from the photo's origin
    H = cv2.getPerspectiveTransform(src, dst).astype(float)
    photo = _warp_into(np.full((960, 1280, 3), (90, 140, 80), np.uint8), ref.image, H)
    K = CameraIntrinsics(width=1280, height=960, fx=1500.0, fy=1500.0, cx=639.5, cy=479.5)
    pf = PhotoFeatures("warp.png", K, undistorted_image(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY), K),
                       np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    start = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -1.5], [0.0, 0.0, 1.0]]) @ H
    Hc, cc_c = ecc_refine(pf, ref, start)
    monkeypatch.setattr(mm, "ECC_CROP_MARGIN_PX", 1e6)  # the crop is the whole photo
    Hw, cc_w = ecc_refine(pf, ref, start)
    corners = ref.corners()
    truth = apply_h(H, corners)
    assert np.abs(apply_h(Hc, corners) - truth).max() < 0.5
    assert np.abs(apply_h(Hc, corners) - apply_h(Hw, corners)).max() < 0.05
    assert cc_c > 0.9 and abs(cc_c - cc_w) < 1e-3


def test_a_sloped_nose_is_left_out_of_the_side_it_cuts():
    """A locomotive's sloped nose cuts the top front corner off its side's window (the reference paints it; the
    car has nothing there): the reference's mask marks exactly the pixels off the car, and ECC leaves them out.
    In a photo showing water behind the slope, the nose's points land within 0.4 px of the known warp from a
    start 2 px off; with the mask dropped they are pulled 2-3 px inwards (seed 237015's 4126, 33 deg off)."""
    import dataclasses

    import trimesh

    from workbench.correspond.match import PhotoFeatures, apply_h, ecc_refine
    from workbench.correspond.undistort import undistorted_image

    ct = get_type("p32ac-dm")
    ref = face_reference(ct, "4126", "left", MatchOptions().px_per_m)
    h, w = ref.image.shape[:2]
    assert ref.mask is not None and ref.mask.shape == (h, w) and 0.01 < np.mean(ref.mask == 0) < 0.05
    assert face_reference(get_type("shoreliner"), "6100", "left", 25.0).mask is None  # flat ends: all on the car
    from workbench.correspond import cache

    back = cache.references_from_arrays(cache.references_to_arrays([ref]), ct.id, "4126")[0]
    assert np.array_equal(back.mask, ref.mask)  # kept in the stage's cache
    # the mask against the model's surface: a pixel is on the car iff its point on the side's plane is
    rng = np.random.default_rng(5)
    uv = rng.uniform([0, 0], [w - 1, h - 1], (400, 2)).round()
    _, dist, _ = trimesh.proximity.closest_point(ct.mesh("4126", textured=False), ref.carriage_from_ref(uv))
    on = ref.mask[uv[:, 1].astype(int), uv[:, 0].astype(int)] > 0
    margin = 1.5 / ref.px_per_m  # a pixel's size from the slope's edge either way
    assert np.all(dist[on] < margin) and np.all(dist[~on] > 0.0) and (~on).sum() >= 5
    src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    H = cv2.getPerspectiveTransform(src, np.float32([[300, 300], [560, 290], [562, 312], [302, 330]])).astype(float)
    car = cv2.warpPerspective(ref.image, H, (1280, 960), flags=cv2.INTER_AREA).astype(float)
    alpha = cv2.warpPerspective(ref.mask, H, (1280, 960), flags=cv2.INTER_AREA)[..., None] / 255.0
    photo = np.round(car * alpha + np.array([60.0, 80.0, 90.0]) * (1.0 - alpha)).astype(np.uint8)
    K = CameraIntrinsics(width=1280, height=960, fx=1500.0, fy=1500.0, cx=639.5, cy=479.5)
    pf = PhotoFeatures("nose.png", K, undistorted_image(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY), K),
                       np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    nose = np.array([ref.points["nose_front_left"], ref.points["body_bottom_front_left"]])
    start = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -1.5], [0.0, 0.0, 1.0]]) @ H
    masked, cc = ecc_refine(pf, ref, start)
    assert np.linalg.norm(apply_h(masked, nose) - apply_h(H, nose), axis=1).max() < 0.4 and cc > 0.95
    bare, _ = ecc_refine(pf, dataclasses.replace(ref, mask=None), start)
    assert np.linalg.norm(apply_h(bare, nose) - apply_h(H, nose), axis=1).min() > 1.5


def test_nearest_neighbours_are_the_brute_force_matchers():
    """The matches from one matrix product (match._nearest) are OpenCV's brute-force matcher's, ties included:
    the ratio-test / mutual-neighbour matches and the Hough's 2-NN, index for index."""
    from workbench.correspond.match import PhotoFeatures, _knn_matches, _matches, _nearest
    from workbench.correspond.references import FaceReference

    rng = np.random.default_rng(3)
    # SIFT-like descriptors: integers 0..255 of norm about 512; duplicated rows make exact ties
    ref_d = np.round(np.clip(rng.gamma(1.0, 30.0, (300, 128)), 0, 255)).astype(np.float32)
    ref_d[50:60] = ref_d[40:50]
    photo_d = np.round(np.clip(rng.gamma(1.0, 30.0, (900, 128)), 0, 255)).astype(np.float32)
    photo_d[:100] = ref_d[rng.integers(0, 300, 100)] + rng.integers(0, 3, (100, 128))
    photo_d[100:110] = photo_d[:10]
    ref = FaceReference("t", "1", "left", np.zeros((10, 40, 3), np.uint8), 25.0, {}, np.zeros(3), np.eye(3)[0],
                        np.eye(3)[2], keypoints=rng.random((300, 2)) * 40, descriptors=ref_d)
    pf = PhotoFeatures("p", CameraIntrinsics(width=100, height=100, fx=100, fy=100, cx=50, cy=50), None,
                       rng.random((900, 2)) * 100, photo_d)
    assert _nearest(pf, ref) is not None
    P, R = _matches(pf, ref, 0.8)
    qi, ti = _knn_matches(pf, ref, 2)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(photo_d, ref_d, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(ref_d, photo_d)}
    keep = [(a.queryIdx, a.trainIdx) for a, b in knn
            if a.distance < 0.8 * b.distance or back.get(a.trainIdx) == a.queryIdx]
    assert np.array_equal(P, pf.keypoints[[q for q, _ in keep]])
    assert np.array_equal(R, ref.keypoints[[t for _, t in keep]])
    assert np.array_equal(qi, [m.queryIdx for ms in knn for m in ms])
    assert np.array_equal(ti, [m.trainIdx for ms in knn for m in ms])
    assert np.array_equal(_nearest(pf, ref)[1], [[m.distance for m in ms] for ms in knn])


def test_unique_rows_as_numpy():
    from workbench.correspond.match import _unique_rows

    A = np.random.default_rng(0).integers(-5, 6, (2000, 4))
    keys, inv = _unique_rows(A)
    k2, i2 = np.unique(A, axis=0, return_inverse=True)
    assert np.array_equal(keys, k2) and np.array_equal(inv, i2.ravel())



def test_sorted_unique_and_first_occurrences_as_numpy():
    """The Hough's np.unique and np.unique(return_index=True) from one sort (correspond/sorting.py)."""
    from workbench.correspond.sorting import first_occurrences, sorted_unique

    rng = np.random.default_rng(1)
    for n in (0, 1, 2, 7, 300, 20000):
        for hi in (1, 3, 60, 10 ** 9):
            a = rng.integers(-hi, hi, n)
            assert np.array_equal(sorted_unique(a), np.unique(a))
            assert np.array_equal(first_occurrences(a), np.sort(np.unique(a, return_index=True)[1]))


def test_photos_in_parallel_in_order_with_progress():
    from workbench.correspond.parallel import map_photos

    def work(item, note):
        note("features", f"item {item}")
        time.sleep(0.05 * (3 - item))  # the first finishes last
        note("done", "")
        return item * item

    for workers in (1, 2):
        seen = []
        assert map_photos(work, [0, 1, 2, 3], workers, lambda i, step, msg: seen.append((i, step))) == [0, 1, 4, 9]
        assert sorted(seen) == sorted((i, s) for i in range(4) for s in ("features", "done"))

    def fails(item, note):
        raise ValueError(f"photo {item} is bad")

    with pytest.raises(ValueError, match="photo [01] is bad"):  # the first to fail
        map_photos(fails, [0, 1], 2, lambda *a: None)


def test_photos_held_back_are_queued_when_released_results_in_the_items_order(tmp_path):
    """``map_photos(hold=...)`` (the stage holds back a photo whose features the prefetch computes): a held item's
    first task is queued as soon as ``hold`` turns false for it (here once the last other item's first task ran),
    ahead of the second tasks not queued yet; ``hold`` is told when a worker has nothing to do; each item's second
    task after its first; the results, ``on_first`` tokens and ``on_result`` values are the items' own, returned in
    the items' order. With one worker the held items go last."""
    from workbench.correspond.parallel import map_photos

    log, flag = tmp_path / "starts.txt", tmp_path / "flag"

    def first(item, note):
        with open(log, "a") as f:
            f.write(f"1 {item} {time.monotonic()}\n")
        if item == 4:
            flag.touch()
        time.sleep(0.1)
        return item + 10

    def second(item, note, token):
        with open(log, "a") as f:
            f.write(f"2 {item} {time.monotonic()}\n")
        time.sleep(0.2)
        return (item, token)

    def starts():
        return {(int(a), int(b)): float(c) for a, b, c in (ln.split() for ln in log.read_text().splitlines())}

    items = list(range(5))
    for workers in (1, 2):
        log.write_text("")
        flag.unlink(missing_ok=True)
        firsts, results, idles = {}, {}, []

        def hold(i, idle):
            idles.append(idle)
            return i == 0 and not flag.exists()

        out = map_photos(second, items, workers, lambda *a: None, first=first, hold=hold,
                         on_first=firsts.__setitem__, on_result=results.__setitem__)
        assert out == [(i, i + 10) for i in items]
        assert firsts == {i: i + 10 for i in items} and results == {i: (i, i + 10) for i in items}
        t = starts()
        assert len(t) == 10
        assert all(t[(2, i)] > t[(1, i)] for i in items), t
        assert t[(1, 0)] > t[(1, 4)], t  # released once item 4's first task ran
        if workers == 2:  # ahead of the last second tasks
            assert t[(1, 0)] < max(t[(2, i)] for i in items[1:]), t
        if workers == 1:
            assert sorted(t, key=t.get) == [(p, i) for i in items[1:] + [0] for p in (1, 2)]
    # every item held while no worker is idle: asked at the start (no worker idle yet), then with both idle
    log.write_text("")
    idles = []
    out = map_photos(second, items, 2, lambda *a: None, first=first,
                     hold=lambda i, idle: idles.append(idle) or not idle)
    assert out == [(i, i + 10) for i in items]
    assert idles[:5] == [False] * 5 and idles[5:] == [True] * 5, idles


def test_the_parents_work_runs_beside_the_held_items_release_and_its_failure_is_raised(tmp_path):
    """``map_photos(before_second=...)`` runs the parent's own work (the references) on a thread of its own: held
    items released meanwhile start their first tasks before it ends, no second task starts before it ends, and an
    exception it raises is the map's."""
    from workbench.correspond.parallel import map_photos

    log = tmp_path / "starts.txt"
    log.write_text("")

    def stamp(what):
        with open(log, "a") as f:
            f.write(f"{what} {time.monotonic()}\n")

    def first(item, note):
        stamp(f"1-{item}")
        return item

    def second(item, note, token):
        stamp(f"2-{item}")
        return item

    def parent():
        time.sleep(1.0)
        stamp("parent")

    out = map_photos(second, [0, 1, 2], 2, lambda *a: None, first=first, before_second=parent,
                     hold=lambda i, idle: not idle)
    assert out == [0, 1, 2]
    t = {a: float(b) for a, b in (ln.split() for ln in log.read_text().splitlines())}
    assert max(t[f"1-{i}"] for i in range(3)) < t["parent"] < min(t[f"2-{i}"] for i in range(3)), t

    def fails():
        raise ValueError("no references")

    with pytest.raises(ValueError, match="no references"):
        map_photos(second, [0, 1, 2], 2, lambda *a: None, first=first, before_second=fails)


# ---------------------------------------------------------------------------------------------------------
# a small synthetic incident through the stage
# ---------------------------------------------------------------------------------------------------------
_AS_COMPUTED: dict[str, bytes] = {}  # the fixture's correspondences.json as its stage wrote it


@pytest.fixture(scope="module")
def incident(tmp_path_factory):
    from workbench.synth.generate import SynthOptions, generate_incident

    root = tmp_path_factory.mktemp("correspond") / "inc"
    t0 = time.perf_counter()
    generate_incident(root, SynthOptions(scenario="spuyten-duyvil", seed=1, n_cars=3, photo_width=640,
                                         photo_height=480, n_panorama=3, n_multiview=0))
    t_synth = time.perf_counter() - t0
    project = Project(root)
    t0 = time.perf_counter()
    cv2.setRNGSeed(5)  # as test_features_computed_ahead_give_the_same_points seeds its run (which this run stands for)
    Runner(project, [s for s in STAGES if s.name in ("inputs", "correspond")]).run(only=["inputs", "correspond"])
    t_stage = time.perf_counter() - t0
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    _AS_COMPUTED["correspondences"] = cs.output_path(project).read_bytes()
    doc = json.loads(_AS_COMPUTED["correspondences"])
    print(f"synth {t_synth:.1f} s, correspond stage {t_stage:.1f} s")
    return project, truth, doc


def _truth_uv(truth, view):
    ph = next(p for p in truth["photos"] if Path(p["photo"]).name == view)
    return ph["observations"]


def test_points_found_against_truth(incident):
    project, truth, doc = incident
    obs = doc["observations"]
    assert obs and all(o["source"] == "sift" for o in obs)
    n_vis = found = wrong = 0
    errs = []
    got = {(o["carriage"], o["point"], o["view"]): o for o in obs}
    for o in obs:
        t = _truth_uv(truth, o["view"])[o["carriage"]][o["point"]]
        e = float(np.hypot(*(np.asarray(o["uv"]) - t["uv"])))
        errs.append(e)
        wrong += e > 10
        assert 0 < o["confidence"] <= 1 and o["sigma_px"] > 0
    for ph in truth["photos"]:
        view = Path(ph["photo"]).name
        for car, pts in ph["observations"].items():
            for name, t in pts.items():
                if t["visible"]:
                    n_vis += 1
                    o = got.get((car, name, view))
                    found += o is not None and np.hypot(*(np.asarray(o["uv"]) - t["uv"])) <= 3
    share = found / n_vis
    # measured 0.51 (21 of 41) on this incident: the two nearer coaches' sides and couplers, not the far
    # end-on one; a regression below 0.3 or a broken truth comparison (above 1) fails
    assert 0.3 <= share <= 1.0, (found, n_vis)
    assert wrong == 0, errs
    assert 0.02 < float(np.median(errs)) < 1.5, errs


def test_identical_coaches_are_not_confused(incident):
    """No reported point belongs to another carriage: each lies nearer its own true point than any other
    carriage's point, unless it is within 5 px of its own truth (a mix-up of identical coaches puts a point a
    window pitch or a car length away; the touching ends of two coupled coaches lie 2-3 px apart in this
    640 px photo, so a point 3 px off its own corner can be nearer the neighbour's, and that is accuracy,
    which test_points_found_against_truth checks, not identity)."""
    _, truth, doc = incident
    n_checked = 0
    for o in doc["observations"]:
        tv = _truth_uv(truth, o["view"])
        uv = np.asarray(o["uv"])
        own = float(np.hypot(*(uv - tv[o["carriage"]][o["point"]]["uv"])))
        other = min((float(np.hypot(*(uv - t["uv"]))), car, name) for car, pts in tv.items()
                    if car != o["carriage"] for name, t in pts.items() if t["uv"] is not None)
        assert own <= 5.0 or own < other[0], (o, own, other)
        n_checked += 1
    assert n_checked > 0


def test_stage_statistics_and_references(incident):
    project, _, doc = incident
    stats = json.loads((project.stage_dir("correspond") / "stats.json").read_text())
    assert stats["n_sift"] == len(doc["observations"]) and stats["n_manual"] == 0
    assert set(stats["photos"]) == {p.name for p in project.photo_paths()}
    refs = json.loads((project.stage_dir("correspond") / "references" / "references.json").read_text())
    assert set(refs) == {c.number for c in project.settings.consist}
    for car in doc["needs_manual"]:
        assert car["carriage"] in refs and car["reason"]
    # each face's ECC correlation, as its stats give it, on the points its homography placed (the solve takes a
    # face's misfit from it: docs/calibration.md, "Session 23")
    ecc = {(v, f["carriage"], f["face"]): f["ecc"] for v, ph in stats["photos"].items() for f in ph["faces"]}
    hom = [o for o in doc["observations"] if o.get("method") == "homography"]
    for o in hom:
        e = ecc[(o["view"], o["carriage"], o["face"])]
        assert o.get("ecc") is None if e is None else abs(o["ecc"] - e) < 6e-4, (o, e)
    assert any(o.get("ecc") is not None for o in hom)
    assert not any("ecc" in o for o in doc["observations"] if o.get("method") != "homography")


# ---------------------------------------------------------------------------------------------------------
# manual correspondences
# ---------------------------------------------------------------------------------------------------------
def _write_manual(project, obs, **extra):
    path = project.root / mf.FILE_NAME
    path.write_text(json.dumps({"observations": obs, **extra}))
    return path


@pytest.fixture
def manual_file(incident):
    project = incident[0]
    yield project
    (project.root / mf.FILE_NAME).unlink(missing_ok=True)


@pytest.mark.parametrize("bad, message", [
    ({"carriage": "9999"}, "unknown carriage '9999'"),
    ({"point": "roof_hatch"}, "no marked point 'roof_hatch'"),
    ({"uv": [640.0, 10.0]}, "outside view 'pano_00.jpg'"),
    ({"uv": [-1.0, 10.0]}, "outside view"),
    ({"view": "pano_09.jpg"}, "unknown view 'pano_09.jpg'"),
    ({"confidence": 1.5}, "confidence"),
    ({"extra_key": 1}, "extra_key"),
])
def test_manual_file_errors_name_the_item(manual_file, bad, message):
    good = {"carriage": "6100", "point": "coupler_front", "view": "pano_00.jpg", "uv": [100.0, 200.0],
            "source": "manual"}
    path = _write_manual(manual_file, [good, {**good, "point": "coupler_rear", **bad}])
    with pytest.raises(InputError, match=message) as exc:
        cs.load_manual(manual_file)
    assert str(path) in str(exc.value)


def test_the_format_keeps_a_faces_ecc_on_its_homography_points_only():
    """``ecc`` (a homography point's face alignment's ECC correlation) is written back as read, and refused on a
    point of another method or outside [-1, 1]."""
    o = {"carriage": "6100", "point": "body_top_front_left", "view": "pano_00.jpg", "uv": [100.0, 200.0],
         "source": "sift", "method": "homography", "face": "left", "ecc": 0.9712}
    assert mf.Observation(**o).to_json()["ecc"] == 0.9712
    assert "ecc" not in mf.Observation(**{**o, "ecc": None}).to_json()
    for bad, words in (({"method": "pose"}, "homography"), ({"ecc": 1.2}, "ecc")):
        with pytest.raises(ValueError, match=words):
            mf.Observation(**{**o, **bad})


def test_manual_file_nan_and_duplicates(manual_file):
    good = {"carriage": "6100", "point": "coupler_front", "view": "pano_00.jpg", "uv": [100.0, 200.0]}
    path = manual_file.root / mf.FILE_NAME
    path.write_text('{"observations": [{"carriage": "6100", "point": "coupler_front", "view": "pano_00.jpg", '
                    '"uv": [NaN, 3.0]}]}')
    # the reader refuses NaN as JSON (manual.py); an earlier reader let it through to "not finite"
    with pytest.raises(InputError, match="not finite|NaN is not a number"):
        cs.load_manual(manual_file)
    _write_manual(manual_file, [good, dict(good)])
    with pytest.raises(InputError, match=r"duplicate of observations\[0\]"):
        cs.load_manual(manual_file)
    path.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        cs.load_manual(manual_file)


def test_manual_point_overrides_automatic(incident, manual_file, monkeypatch):
    project, _, doc = incident
    auto = [mf.Observation(**o) for o in doc["observations"]]
    first = auto[0]
    moved = {"carriage": first.carriage, "point": first.point, "view": first.view,
             "uv": [first.uv[0] + 5.0, first.uv[1] - 3.0], "source": "manual", "sigma_px": 1.5}
    extra = {"carriage": "6227", "point": "coupler_front", "view": "pano_02.jpg", "uv": [10.0, 20.0]}
    _write_manual(project, [moved, extra], note="test picks")
    # the automatic part is the fixture's (the matcher itself is tested above); the merge is the stage's
    monkeypatch.setattr(cs, "automatic", lambda *a, **k: (auto, [{"carriage": "6227", "reason": "no face"}], {}))
    res = cs.run_correspond(project, lambda f, m="": None)
    out = json.loads(res.outputs["correspondences"].read_text())
    by_key = {(o["carriage"], o["point"], o["view"]): o for o in out["observations"]}
    k = (first.carriage, first.point, first.view)
    assert by_key[k]["source"] == "manual" and by_key[k]["uv"] == moved["uv"] and by_key[k]["sigma_px"] == 1.5
    assert by_key[("6227", "coupler_front", "pano_02.jpg")]["source"] == "manual"
    assert len(out["observations"]) == len(auto) + 1
    assert res.stats["n_overridden"] == 1 and res.stats["n_manual"] == 2
    assert out["needs_manual"] == []  # 6227 has a manual point now
    # leave the fixture's output as the stage wrote it
    cs.output_path(project).write_text(json.dumps(doc))


def test_stage_cache_gives_what_it_computes(incident):
    """The stage keeps each car's references and each photo's features in out/correspond/cache/ (cache.py): an
    entry read back is what the code computes, array for array, and an entry of another input is never read
    (its name is the hash of the inputs)."""
    from workbench.correspond import cache

    project, _, _ = incident
    cdir = project.stage_dir("correspond") / "cache"
    names = sorted(f.name for f in cdir.glob("*.npz"))
    n_photos = len(project.photo_paths())
    assert len([n for n in names if n.startswith("photo_")]) == n_photos
    assert len([n for n in names if n.startswith("references_")]) == len(project.settings.consist)
    opts = MatchOptions()
    types = project.carriage_types()
    number = project.settings.consist[0].number
    used: set[str] = set()
    cached, aligned = cs._cached_references(project, types[number], number, opts, cdir, used)
    fresh = build_references(types[number], number, px_per_m=opts.px_per_m, tilts=opts.tilts, end_tilts=opts.end_tilts)
    assert len(used) == 1 and next(iter(used)) in names
    assert [r.face for r in aligned] == ["roof"]
    for a, b in zip(cached + aligned, fresh + [face_reference(types[number], number, "roof", opts.px_per_m)],
                    strict=True):
        assert (a.type_id, a.car_number, a.face, a.px_per_m) == (b.type_id, b.car_number, b.face, b.px_per_m)
        assert list(a.points) == list(b.points) and all(np.array_equal(a.points[n], b.points[n]) for n in a.points)
        for f in ("image", "origin_m", "axis_u_m", "axis_v_m", "keypoints", "descriptors", "frames"):
            if getattr(b, f) is None:
                assert getattr(a, f) is None, f
                continue
            assert np.array_equal(getattr(a, f), getattr(b, f)) and getattr(a, f).dtype == getattr(b, f).dtype, f
    photo = project.photo_paths()[0]
    intr, _ = cs.photo_intrinsics(project, [photo])
    name = cs._photo_cache_name(photo, intr[photo.name], opts)
    assert name in names and cs._photo_cache_name(photo, intr[photo.name].scaled(1.01), opts) != name
    a = cs._cached_photo_features(project, photo, intr[photo.name], opts, cdir / name)
    b = photo_features(photo.name, cs._read_rgb(photo), intr[photo.name], opts)
    for f in ("gray_undistorted", "keypoints", "descriptors", "frames"):
        assert np.array_equal(getattr(a, f), getattr(b, f)) and getattr(a, f).dtype == getattr(b, f).dtype, f
    assert cache.load(cdir / "photo_absent.npz") is None


def test_features_computed_ahead_give_the_same_points(incident, tmp_path):
    """The photos' features computed ahead of the stage (correspond/prefetch.py, a forked process started when a run
    begins) are the entries the stage reads: the same correspondences.json as the stage computing them itself (the
    fixture's run: no prefetch, an empty feature cache); the photos not begun when the stage starts are the stage's,
    one being computed is waited for. (OpenCV's generator of this thread seeded before each run: the panorama
    carry's FLANN trees draw from it, and in one process a stage run earlier has moved it.)"""
    import shutil

    from workbench.correspond import prefetch

    project, _, _ = incident
    root = tmp_path / "inc_ahead"
    shutil.copytree(project.root, root, ignore=shutil.ignore_patterns("out"))
    copy = Project(root)
    Runner(copy, [s for s in STAGES if s.name == "inputs"]).run(only=["inputs"])
    cv2.setRNGSeed(5)
    cs.prefetch_features(copy)
    status = prefetch._STATE["status"]
    t0 = time.perf_counter()
    while status[0] != prefetch.DONE and time.perf_counter() - t0 < 120:
        time.sleep(0.05)
    assert copy.photo_paths()[0].name in prefetch.stop()["done"]
    res = cs.run_correspond(copy, lambda f, m="": None)
    assert not prefetch._STATE
    assert Path(res.outputs["correspondences"]).read_bytes() == _AS_COMPUTED["correspondences"]


def test_the_stage_takes_the_prefetch_on_one_process_computes_every_photo(incident, tmp_path, monkeypatch):
    """A prefetch whose entries are the stage's goes on when the stage starts (``prefetch.adopt``): it computes
    every photo's features, the stage's workers wait for them instead of computing any themselves (each process
    computing one would fault in the ~3 GB SIFT allocates afresh), and the points are the same as the stage
    computing them (the fixture's run). (At niceness 0 and a starvation share of 2 % here, so that the suite's
    own load on the cores cannot make the stage take the photos back.)"""
    import shutil

    from workbench.correspond import prefetch

    project, _, _ = incident
    root = tmp_path / "inc_adopted"
    shutil.copytree(project.root, root, ignore=shutil.ignore_patterns("out"))
    copy = Project(root)
    Runner(copy, [s for s in STAGES if s.name == "inputs"]).run(only=["inputs"])
    monkeypatch.setattr(prefetch, "NICE", 0)
    monkeypatch.setattr(prefetch, "STARVED_SHARE", 0.02)
    cv2.setRNGSeed(5)
    cs.prefetch_features(copy)
    assert prefetch._STATE
    messages = []
    res = cs.run_correspond(copy, lambda f, m="": messages.append(m))
    assert not prefetch._STATE
    n = len(copy.photo_paths())
    assert sum("features computed by the features process" in m for m in messages) == n, messages
    assert not any(m.endswith(" features") for m in messages), messages
    assert Path(res.outputs["correspondences"]).read_bytes() == _AS_COMPUTED["correspondences"]


def test_a_starved_prefetch_is_left_and_ended(tmp_path, monkeypatch):
    """A worker that reaches the photo the prefetch is computing waits while the prefetch gets a core; one that gets
    none (here it sleeps; on a loaded machine, at niceness 19, it may get none for minutes) is left after a window of
    STARVED_WINDOW_S (here 0.5 s), and the stage's end ends it instead of waiting for it. One that computes is waited
    for (here at niceness 0 and a share of 2 %, so that the suite's own load cannot starve it)."""
    from workbench.correspond import prefetch

    def spin(p):  # a prefetch that gets its core: computes for 1 s, then writes the entry
        t = time.perf_counter()
        while time.perf_counter() - t < 1.0:
            pass
        p.with_suffix(".npz").write_bytes(b"x")

    monkeypatch.setattr(prefetch, "STARVED_WINDOW_S", 0.5)
    for compute, starved in ((lambda p: time.sleep(60), True), (spin, False)):
        if not starved:
            monkeypatch.setattr(prefetch, "NICE", 0)
            monkeypatch.setattr(prefetch, "STARVED_SHARE", 0.02)
        photo = tmp_path / "a.jpg"
        entry = photo.with_suffix(".npz")
        entry.unlink(missing_ok=True)
        prefetch.start([photo], {photo.name: entry}, compute)
        try:
            status = prefetch._STATE["status"]
            t0 = time.perf_counter()
            while status[0] != prefetch.BUSY and time.perf_counter() - t0 < 30:
                time.sleep(0.01)
            prefetch.stop()
            assert prefetch.computing(photo.name, entry) and not prefetch.computing(photo.name, tmp_path / "b.npz")
            t0 = time.perf_counter()
            prefetch.wait_for(photo.name, entry)
            waited = time.perf_counter() - t0
            if starved:
                assert status[0] == prefetch.BUSY and prefetch.STARVED_WINDOW_S <= waited < 5.0, waited
            else:
                assert status[0] == prefetch.DONE and entry.is_file() and 0.5 < waited < 4.0, waited
        finally:
            proc = prefetch._STATE.get("proc")
            t0 = time.perf_counter()
            prefetch.finish()
        assert time.perf_counter() - t0 < 5.0 and proc is not None and not proc.is_alive()


def test_reference_without_texture_needs_manual_points(incident):
    project, truth, _ = incident
    photos = project.photo_paths()[:1]
    intr, _ = cs.photo_intrinsics(project, photos)
    obs, needs, _ = cs.automatic(project, photos, intr, MatchOptions(min_reference_keypoints=10 ** 6),
                                 lambda f, m="": None)
    assert obs == []
    assert {n["carriage"] for n in needs} == {c.number for c in project.settings.consist}
    assert all("no texture" in n["reason"] for n in needs)


def test_intrinsics_from_profile_or_known_cameras(incident):
    project, truth, _ = incident
    photos = project.photo_paths()
    intr, src = cs.photo_intrinsics(project, photos)
    ph = {Path(p["photo"]).name: p for p in truth["photos"]}
    for name, K in intr.items():
        assert K.to_dict() == pytest.approx(ph[name]["intrinsics"])
    assert src == "camera_profile.json"
    # known cameras (the incident's cameras.json) take precedence over the profile
    views = [{"name": n, "intrinsics": {**ph[n]["intrinsics"], "fx": 555.0, "fy": 555.0},
              "cam_from_world": np.eye(4).tolist()} for n in intr]
    cams = project.root / "cameras.json"
    cams.write_text(json.dumps({"route": "panorama", "views": views}))
    try:
        intr2, src2 = cs.photo_intrinsics(project, photos)
    finally:
        cams.unlink()
    assert src2 == "cameras.json" and all(K.fx == 555.0 for K in intr2.values())


class _FlatGround:
    """A terrain stand-in: the plane z = 0 (``height_at`` as TerrainModel's)."""

    def height_at(self, xy):
        return np.zeros(len(np.asarray(xy).reshape(-1, 2)))


def _on_its_side_scene(pitch_deg: float = 0.0):
    """A coach (6223) lying on its left side behind an upright one (6100), coupled (held), on flat ground,
    seen from 70 m and 12 m up: the photo, its PhotoFeatures, the camera and the true poses (world_from_carriage).
    ``pitch_deg``: the coach on its side pitched so (one end on debris)."""
    from workbench.core.camera import look_at
    from workbench.correspond import search as se
    from workbench.correspond.complete import facing_cosine, predicted_homography
    from workbench.correspond.match import PhotoFeatures
    from workbench.correspond.undistort import undistorted_image

    ct = get_type("shoreliner")
    opts = MatchOptions()
    K = CameraIntrinsics(width=1280, height=960, fx=1500.0, fy=1500.0, cx=639.5, cy=479.5)
    ground = _FlatGround()
    corners = se._corners(ct)
    yaw = np.deg2rad(20.0)
    Wb = np.eye(4)
    Wb[:3, :3] = se._rot(yaw, np.deg2rad(pitch_deg), np.deg2rad(-90.0))  # on its left side
    Wb = se._rest(Wb, corners, ground)
    front_b = Wb[:3, :3] @ ct.coupler_front + Wb[:3, 3]
    Wa = np.eye(4)
    Wa[:3, :3] = se._rot(yaw + np.deg2rad(12.0), 0.0, 0.0)
    Wa[:3, 3] = front_b - Wa[:3, :3] @ ct.coupler_rear  # held: 6100's rear coupler on 6223's front one
    Wa = se._rest(Wa, corners, ground)
    cam_from_world = look_at(np.array([-8.0, 68.0, 12.0]), np.array([0.0, 0.0, 1.0]))
    rng = np.random.default_rng(3)
    photo = (rng.integers(70, 150, (960, 1280, 1)) * np.ones((1, 1, 3))).astype(np.uint8)
    photo = cv2.GaussianBlur(photo, (0, 0), 4)
    clean = photo.copy()
    for number, W in (("6100", Wa), ("6223", Wb)):
        M = cam_from_world @ W
        for f in FACES:
            ref = face_reference(ct, number, f, opts.px_per_m)
            if facing_cosine(M, ct, ref) > 0.05:
                photo = _warp_into(photo, ref.image, predicted_homography(M, ref, K))
        if number == "6100":
            clean = photo.copy()  # the same photo without the coach on its side

    def features(img, name):
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        return PhotoFeatures(name, K, undistorted_image(gray, K), np.zeros((0, 2)), np.zeros((0, 128), np.float32))

    return ct, K, cam_from_world, Wa, Wb, features(photo, "side.png"), features(clean, "clean.png"), ground


def test_pose_search_finds_a_coach_on_its_side():
    """The chain/terrain pose search (search.py) finds a coach lying on its side (roof to the camera, SIFT's
    blind spot) from its neighbour's rear coupler, 0.6 m off as a neighbour's pose from one face can be:
    its marked points within 1.5 px of their true pixels (on aligned faces) and 6 px (projected from its pose),
    at least four within 3 px; on the same
    photo without that coach it reports nothing."""
    from workbench.correspond import search as se
    from workbench.correspond.assign import observations_of

    ct, K, cam_from_world, Wa, Wb, pf, pf_clean, ground = _on_its_side_scene()
    opts = MatchOptions(search_yaw_span_deg=20.0)  # headings within 20 deg of the neighbour's (12 deg off): faster
    refs = {f: face_reference(ct, "6223", f, opts.px_per_m) for f in FACES}
    anchor_at = Wa[:3, :3] @ ct.coupler_rear + Wa[:3, 3] + np.array([0.4, -0.3, 0.3])
    anchor = se.Anchor("front", anchor_at, "6100", "held", float(np.arctan2(Wa[1, 0], Wa[0, 0])))
    # the neighbour's faces, as the stage passes them: a face there is not the coach searched for
    from workbench.correspond.complete import facing_cosine, predicted_homography
    from workbench.correspond.match import apply_h

    Ma = cam_from_world @ Wa
    taken = []
    for f in FACES:
        ref = face_reference(ct, "6100", f, opts.px_per_m)
        if facing_cosine(Ma, ct, ref) > 0.05:
            taken.append(apply_h(predicted_homography(Ma, ref, K), ref.corners()))
    t0 = time.perf_counter()
    found = se.search_car(pf, "6223", ct, refs, [anchor], cam_from_world, ground, opts, taken)
    print(f"pose search {time.perf_counter() - t0:.1f} s")
    assert found, "the coach on its side was not found"
    assert "roof" in {c.detection.ref.face for c in found}
    M = found[0].cam_from_carriage
    W = np.linalg.inv(cam_from_world) @ M
    roll = np.degrees(np.arctan2(W[2, 1], W[2, 2]))
    assert abs(roll - (-90.0)) < 3.0, roll
    assert np.linalg.norm(W[:3, 3] - Wb[:3, 3]) < 0.3, W[:3, 3] - Wb[:3, 3]
    obs = observations_of(found, pf, {"6223": ct})
    assert len(obs) >= 4
    Mt = cam_from_world @ Wb
    errs = []
    for o in obs:
        X = ct.marked_points[o.point]
        truth = K.project((Mt[:3, :3] @ X + Mt[:3, 3])[None])[0]
        err = float(np.hypot(*(np.asarray(o.uv) - truth)))
        errs.append(err)
        # on an aligned face: its homography; elsewhere (the coach's marked points are on its sides' edges and
        # couplers, off the roof's and the end's planes): a prediction from the pose, sigma 2 px
        assert err < (1.5 if o.how == "homography" else 6.0), (o, err)
    assert sum(e <= 3.0 for e in errs) >= 4, errs
    # the same photo without the coach: nothing
    assert se.search_car(pf_clean, "6223", ct, refs, [anchor], cam_from_world, ground, opts, taken) == []


def test_coupler_in_sight_from_the_side():
    """A coupler protrudes beyond its end: seen from the side at an angle towards that end it is in sight
    although the end turns away (the ray passes the body's end), and reported from the car's pose; seen
    square to the side from near the car, the body hides it. Corners on the body are left to the facing test."""
    from workbench.core.camera import look_at
    from workbench.correspond.assign import CarInPhoto, _in_sight, observations_of
    from workbench.correspond.match import FaceDetection, PhotoFeatures

    ct = get_type("shoreliner")
    L = ct.length_m
    # the car at the origin of the scene, x forward, the camera on its left (y > 0)
    front = ct.coupler_front
    oblique = look_at(np.array([0.35 * L, 25.0, front[2]]), front)  # between the end planes, towards the front
    square = look_at(np.array([0.0, 4.0, 3.0]), front)  # close to the side, above it: the body is in the way
    n_front = ct.face_normal("front")
    for M in (oblique, square):
        C = -M[:3, :3].T @ M[:3, 3]
        assert (C - front) @ n_front < 0  # the front end turns away from the camera in both
    assert _in_sight(ct, oblique, front)
    assert not _in_sight(ct, square, front)
    assert not _in_sight(ct, oblique, ct.marked_points["body_top_front_left"])  # on the body: the faces decide
    # reported from a side's pose (the detection spans the whole side, so its pose places the car's points)
    K = CameraIntrinsics(width=1600, height=1200, fx=1800.0, fy=1800.0, cx=799.5, cy=599.5)
    ref = face_reference(ct, "6100", "left", 25.0)
    h, w = ref.image.shape[:2]
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 3)), -1).reshape(-1, 2)
    from workbench.correspond.complete import predicted_homography
    from workbench.correspond.match import apply_h

    H = predicted_homography(oblique, ref, K)
    det = FaceDetection(ref, "p.png", H, len(g), 0.3, 0.99, apply_h(H, g), g)
    pf = PhotoFeatures("p.png", K, np.zeros((1200, 1600), np.uint8), np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    obs = {o.point: o for o in observations_of([CarInPhoto("6100", det, 30, oblique)], pf, {"6100": ct})}
    assert "coupler_front" in obs and obs["coupler_front"].how == "pose"
    truth = K.project((oblique[:3, :3] @ front + oblique[:3, 3])[None])[0]
    assert np.hypot(*(np.asarray(obs["coupler_front"].uv) - truth)) < 0.1


def test_pose_of_an_aligned_face_rests_on_its_homography():
    """A face aligned by ECC gives its pose through its homography (a lattice over its matched part), not
    through its SIFT keypoints: with the keypoints 1 px off at random and the homography exact, the pose
    places the far coupler (1.5 m off the side's plane) within 0.5 px; from the keypoints it is worse."""
    from workbench.core.camera import look_at
    from workbench.correspond.assign import _pose
    from workbench.correspond.complete import predicted_homography
    from workbench.correspond.match import FaceDetection, apply_h

    ct = get_type("shoreliner")
    K = CameraIntrinsics(width=1600, height=1200, fx=1800.0, fy=1800.0, cx=799.5, cy=599.5)
    M = look_at(np.array([5.0, 90.0, 8.0]), np.array([0.0, 0.0, 2.0]))  # a far coach, seen from its left
    ref = face_reference(ct, "6100", "left", 25.0)
    h, w = ref.image.shape[:2]
    H = predicted_homography(M, ref, K)
    rng = np.random.default_rng(1)
    R_px = rng.uniform([0, 0], [w - 1, h - 1], (300, 2))
    P_px = apply_h(H, R_px) + rng.normal(0.0, 1.0, (300, 2))
    X = ct.coupler_rear
    truth = K.project((M[:3, :3] @ X + M[:3, 3])[None])[0]

    def err(det):
        P = _pose(det, K).cam_from_carriage
        return float(np.hypot(*(K.project((P[:3, :3] @ X + P[:3, 3])[None])[0] - truth)))

    aligned = FaceDetection(ref, "p.png", H, 300, 1.0, 0.99, P_px, R_px)
    raw = FaceDetection(ref, "p.png", H, 300, 1.0, None, P_px, R_px)
    assert err(aligned) < 0.5, err(aligned)
    assert err(raw) > err(aligned)


def test_pose_search_over_a_broken_coupling_tries_pitches():
    """Over a broken coupling the car lies metres from its anchor, where the terrain's slope need not be the
    anchor's: a coach on its side, pitched 3.5 deg (one end on debris; the ground is flat, so the terrain gives
    0 deg), its neighbour's coupler 6 m from its own (beyond the former 5 m radius), is found by the search with
    the pitches tried about the terrain's (``search_broken_pitch_deg``), its coupler within the broken radius
    (8 m), and nothing is found on the photo without it."""
    from workbench.correspond import search as se

    ct, K, cam_from_world, Wa, Wb, pf, pf_clean, ground = _on_its_side_scene(pitch_deg=3.5)
    opts = MatchOptions(search_yaw_span_deg=20.0)
    assert opts.search_broken_radius_m >= 6.5 and len(opts.search_broken_pitch_deg) > 1
    refs = {f: face_reference(ct, "6223", f, opts.px_per_m) for f in FACES}
    anchor_at = Wa[:3, :3] @ ct.coupler_rear + Wa[:3, 3] + np.array([4.5, -4.0, 0.0])  # 6.0 m off
    anchor = se.Anchor("front", anchor_at, "6100", "broken", float(np.arctan2(Wa[1, 0], Wa[0, 0])))
    t0 = time.perf_counter()
    found = se.search_car(pf, "6223", ct, refs, [anchor], cam_from_world, ground, opts, [])
    print(f"pose search {time.perf_counter() - t0:.1f} s")
    assert found, "the pitched coach was not found over the broken coupling"
    W = np.linalg.inv(cam_from_world) @ found[0].cam_from_carriage
    assert np.linalg.norm(W[:3, 3] - Wb[:3, 3]) < 0.3, W[:3, 3] - Wb[:3, 3]
    pitch = np.degrees(np.arcsin(np.clip(W[2, 0], -1, 1)))
    assert abs(pitch - 3.5) < 1.0, pitch
    assert se.search_car(pf_clean, "6223", ct, refs, [anchor], cam_from_world, ground, opts, []) == []
