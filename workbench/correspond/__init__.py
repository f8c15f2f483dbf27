"""Marked points of each carriage in the photos: SIFT against per-car face references, joint assignment to
the consist, manual correspondences (validated, overriding), and the ``correspond`` stage (:mod:`.stage`).
See docs/correspondences.md."""
