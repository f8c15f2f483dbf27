"""Sorted distinct values of integer arrays, as ``np.unique`` gives them, from one sort.

NumPy 2's ``np.unique`` hashes the values before it sorts the distinct ones: on the Hough transform's votes
(``match.hough_clusters``: some 10^5 int64 codes per face reference and photo, and hundreds of small bins) that
took half of the clustering's time. These give the same arrays.
"""

from __future__ import annotations

import numpy as np


def _changes(s: np.ndarray) -> np.ndarray:
    """Where a sorted array takes a new value (the first element included)."""
    keep = np.empty(len(s), dtype=bool)
    keep[:1] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return keep


def sorted_unique(a: np.ndarray) -> np.ndarray:
    """``np.unique(a)`` of a 1-D array: its distinct values, sorted."""
    s = np.sort(a)
    return s[_changes(s)]


def first_occurrences(a: np.ndarray) -> np.ndarray:
    """``np.sort(np.unique(a, return_index=True)[1])``: where each distinct value of a 1-D array first occurs, in
    increasing order (NumPy finds them by a stable sort too)."""
    o = np.argsort(a, kind="stable")
    return np.sort(o[_changes(a[o])])


__all__ = ["sorted_unique", "first_occurrences"]
