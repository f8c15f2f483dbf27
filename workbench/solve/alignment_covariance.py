"""The face alignments' share of the automatic points' error in the solve's covariance (issue 21).

The correspond stage gives each point it placed by a face's homography a *loading* (2, 8): the point moves by
``L xi`` with one ``xi ~ N(0, I_8)`` per alignment (carriage, face, view), the homography's error from its matches
(``workbench.correspond.alignment``; docs/correspondences.md, "What a face's alignment measures"). Here that
covariance enters the sandwich ``H^-1 G H^-1`` of :func:`.uncertainty.covariance_model` as correlated blocks.
"""

from __future__ import annotations

import numpy as np


def alignment_term(J: np.ndarray, block: np.ndarray, loading: np.ndarray, w: np.ndarray,
                   extra: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """``sum_b A_b A_b^T`` (P, P) with ``A_b = sum_{i in b} J_i^T w_i L_i`` (P, 8): the gradient covariance (per
    pixel^2 of the weighted rows' scale) of the face alignments' errors. ``J``: weighted rows (2M, P); ``block``
    (M,) each point's alignment (carriage, face, view), -1 for none; ``loading`` (M, 2, 8) px; ``w`` (M,) row
    weights. A point placed by a face's homography moves with that homography's 8 parameters, so the points of
    one alignment are correlated (their covariance ``L L^T`` has rank 8 at most) and two alignments are
    independent (``workbench.correspond.alignment``). ``extra``: block -> (P, 8) more rows' share of that block's
    ``A_b`` (the pose predictions', :mod:`.pose_covariance`)."""
    P = J.shape[1]
    out = np.zeros((P, P))
    Jr = J.reshape(-1, 2, P)
    for b in np.unique(block[block >= 0]):
        idx = np.nonzero(block == b)[0]
        A = np.einsum("nip,nik->pk", Jr[idx], loading[idx] * w[idx, None, None])
        if extra is not None and int(b) in extra:
            A = A + extra[int(b)]
        out += A @ A.T
    return out


def views_per_face(block: np.ndarray, groups: np.ndarray, views: np.ndarray) -> np.ndarray:
    """(M,) for each aligned point the number of photos its carriage's face is aligned in (0 for a point without
    an alignment). A face's alignment error is mostly the same in every photo (the same reference against the same
    livery: measured against the truth, the same point's errors in two photos have a mean cosine of 0.63-0.85),
    while each photo's alignment is computed from that photo's matches alone; photos from one place see the face
    alike, so an error shared by ``n`` of them is not averaged down, and each photo's block counts ``n`` times its
    stated variance (the average of ``n`` fully correlated photos keeps one photo's variance)."""
    n = np.zeros(len(block))
    on = block >= 0
    for g in np.unique(groups[on]):
        idx = on & (groups == g)
        n[idx] = len(np.unique(views[idx]))
    return n


def photo_affine_modes(d: np.ndarray) -> np.ndarray:
    """(n, 2, 6) the six affine modes of a face's points in the photo's axes, each of unit RMS size: a shift in u
    and in v, and ``d_u / s_u``, ``d_v / s_v`` in u and in v, with ``d`` (n, 2) px the points less their centroid
    and ``s`` their RMS spreads (only the shifts for fewer than 3 points, or along an axis they do not spread)."""
    n = len(d)
    B = np.zeros((n, 2, 6))
    B[:, 0, 0] = B[:, 1, 1] = 1.0
    s = np.sqrt(np.mean(d**2, axis=0))
    for j in range(2 if n >= 3 else 0):
        if s[j] > 1e-6:
            B[:, 0, 2 + j] = B[:, 1, 4 + j] = d[:, j] / s[j]
    return B


# The misfit of a face aligned by ECC without matches of its own (a guided face), per affine mode along the face,
# as a share of its ECC misfit (uncertainty.face_misfit_px). Measured against the truth on the guided sides of
# seeds 240000-, 241000-, 242000- (189 alignments; docs/calibration.md, "Session 31"): the shift along the face
# 0.72, its stretch along 0.68 of that misfit; the modes across it 0.21-0.28 (guided_loadings takes them from the
# face's shape)
GUIDED_ALONG = 0.7


def guided_loadings(block: np.ndarray, loading: np.ndarray, guided: np.ndarray, groups: np.ndarray,
                    views: np.ndarray, uv: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``block`` (M,) and ``loading`` (M, 2, 8) with each guided face's alignment added: the points ``guided``
    (M,) bool of one face (``groups``) in one photo (``views``) become one alignment (a new block), their loading
    the face's misfit ``tau`` (M,) px (the root mean square over the face's points) in six affine modes taken in
    the face's own axes in that photo (the principal axes of its points ``uv`` (M, 2) px): a shift along the face,
    its stretch along and its shear, each :data:`GUIDED_ALONG` of ``tau``, and the three across it (a shift, a
    turn and a stretch) that times ``sqrt(s_across / s_along)``, the points' spreads across and along.

    ECC pins a displacement by the outline's edges across it: a displacement across a side by its long edges, one
    along it by its short ones, so the across modes are the better determined by the square root of the ratio of
    their lengths (measured on the generated sides, whose spreads differ 13-fold: 0.21-0.28 of ``tau`` across
    against 0.7 along). A face of fewer than 3 points, or whose points lie on a line, takes the misfit whole in
    the photo's axes, as a face's shared misfit (:func:`.uncertainty._shared_misfit`).
    As an alignment from matches, a guided face's error moves the pose the correspond stage fitted to it and the
    points it predicted from that pose (:mod:`.pose_covariance`). Returns the new ``block``, ``loading`` and the
    points given a guided alignment (M,) bool."""
    block, loading = np.array(block, dtype=int, copy=True), np.array(loading, dtype=float, copy=True)
    out = np.zeros(len(block), dtype=bool)
    nxt = int(block.max()) + 1 if len(block) else 0
    for g in np.unique(groups[guided]):
        on_face = guided & (groups == g)
        t = float(np.sqrt(np.mean(np.square(tau[on_face]))))
        for v in np.unique(views[on_face]):
            idx = np.nonzero(on_face & (views == v))[0]
            d = uv[idx] - uv[idx].mean(0)
            L = np.zeros((len(idx), 2, 8))
            ev, V = np.linalg.eigh(d.T @ d / len(idx))
            if len(idx) >= 3 and ev[0] > 1e-6:
                a, c = V[:, 1], V[:, 0]  # along the face, across it
                s_a, s_c = float(np.sqrt(ev[1])), float(np.sqrt(ev[0]))
                k_a = GUIDED_ALONG
                k_c = GUIDED_ALONG * np.sqrt(s_c / s_a)
                r_a, r_c = (d @ a / s_a)[:, None], (d @ c / s_c)[:, None]
                L[:, :, 0], L[:, :, 1] = k_a * a, k_c * c
                L[:, :, 2], L[:, :, 3] = k_a * r_a * a, k_a * r_c * a
                L[:, :, 4], L[:, :, 5] = k_c * r_a * c, k_c * r_c * c
            else:  # no axes to take: the six modes in the photo's axes at the whole misfit, as uncertainty's
                L[:, :, :6] = photo_affine_modes(d)
            loading[idx] = t * L
            block[idx] = nxt
            out[idx] = True
            nxt += 1
    return block, loading, out
