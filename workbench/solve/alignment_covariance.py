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

