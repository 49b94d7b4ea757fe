"""Matching two images' features: mutual nearest neighbours in descriptor space and a RANSAC
homography, the paper's homography estimation procedure (what ``usp-jax match`` runs and what
the evaluation's homography accuracy is measured on).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.inference.features import Features
from usp_jax.inference.threads import one_blas_thread

#: RANSAC settings of the protocol for ``cv2.findHomography``.
RANSAC_THRESHOLD = 3.0
RANSAC_MAX_ITERS = 5000
#: Fewest RANSAC inliers of a homography that means something. Four always fit one exactly,
#: and images of different scenes (or a blank one) reach a few more by chance; on the design
#: pairs (experiments/notes/choices.md, "MIN_INLIERS") such chance fits stayed under this,
#: true pairs far above it.
MIN_INLIERS = 15


class Matching(NamedTuple):
    """Result of the homography estimation procedure.

    matches: int ``[K, 2]`` indices (into features 1, into features 2) of mutual nearest
    neighbours in descriptor space. inliers: bool ``[K]``, RANSAC's inlier mask.
    homography: float64 [3, 3] estimate mapping image 1 to image 2, or None when it failed.
    """

    matches: np.ndarray
    inliers: np.ndarray
    homography: np.ndarray | None

    @property
    def reliable(self) -> bool:
        """Whether the homography rests on at least ``MIN_INLIERS`` inliers; when not, it is
        what RANSAC fits to chance matches and should not be used."""
        return self.homography is not None and int(self.inliers.sum()) >= MIN_INLIERS


def nearest_neighbours(
    descriptors1: np.ndarray, descriptors2: np.ndarray, norm: int, cross_check: bool
) -> np.ndarray:
    """Brute-force nearest neighbours, int ``[K, 2]`` (index in 1, index in 2), sorted by index
    in 1: ``cv2.BFMatcher(norm, crossCheck=cross_check)``'s pairs. Float descriptors in L2 come
    from one matrix product (:func:`mutual_nearest_neighbours`; 8x faster at 1000 points, the
    same pairs), bit strings through OpenCV."""
    if len(descriptors1) == 0 or len(descriptors2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if norm == cv2.NORM_L2:
        if cross_check:
            return mutual_nearest_neighbours(descriptors1, descriptors2)
        nearest = _closeness(descriptors1, descriptors2).argmax(axis=1)
        return np.stack([np.arange(len(nearest)), nearest], axis=1).astype(np.int64)
    dtype = np.uint8 if norm == cv2.NORM_HAMMING else np.float32
    matcher = cv2.BFMatcher(norm, crossCheck=cross_check)
    matches = matcher.match(
        np.ascontiguousarray(descriptors1, dtype), np.ascontiguousarray(descriptors2, dtype)
    )
    return np.array([(m.queryIdx, m.trainIdx) for m in matches], dtype=np.int64).reshape(-1, 2)


def _closeness(descriptors1: np.ndarray, descriptors2: np.ndarray) -> np.ndarray:
    """float32 ``[N1, N2]``: -|a - b|^2 / 2 of every pair of rows of ``[N1, D]``, ``[N2, D]``.
    As a.b - |a|^2 / 2 - |b|^2 / 2, with the norms as two extra columns of one matrix product:
    no [N1, N2] temporary beside it (a third of the time at 2000 points). On one BLAS thread:
    the next detection's cores stay free (``inference.threads``)."""
    a = np.asarray(descriptors1, np.float32)
    b = np.asarray(descriptors2, np.float32)
    half_a = -0.5 * np.einsum("nd,nd->n", a, a)[:, None]
    half_b = -0.5 * np.einsum("nd,nd->n", b, b)[:, None]
    ones_a, ones_b = np.ones_like(half_a), np.ones_like(half_b)
    with one_blas_thread:
        return np.hstack([a, half_a, ones_a]) @ np.hstack([b, ones_b, half_b]).T


def mutual_nearest_neighbours(
    descriptors1: np.ndarray, descriptors2: np.ndarray, ratio: float = 1.0
) -> np.ndarray:
    """Mutual nearest neighbours in L2 of float descriptors ``[N1, D]``, ``[N2, D]``: int
    ``[K, 2]`` (index in 1, index in 2), sorted by index in 1. With ``ratio`` 1 the pairs
    ``cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)`` finds (ties to the lower index, as it does),
    from one matrix product instead of two brute-force passes; below 1, only those
    whose distance is under ``ratio`` times that of the point's second-nearest neighbour in
    image 2 (Lowe's ratio test, as COLMAP's SIFT matcher applies it)."""
    if len(descriptors1) == 0 or len(descriptors2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    closeness = _closeness(descriptors1, descriptors2)
    forward = closeness.argmax(axis=1)
    # A column's max, not its argmax: NumPy's argmax down columns of a row-major matrix is 30x
    # slower. Row i is the nearest to its nearest j when it reaches j's max and no lower row does.
    column_best = closeness.max(axis=0)
    keep = closeness[np.arange(len(closeness)), forward] == column_best[forward]
    tied = np.flatnonzero(keep)[
        np.count_nonzero(closeness == column_best, axis=0)[forward[keep]] > 1
    ]
    for i in tied:  # exact ties only (repeated descriptors): the lowest row wins
        keep[i] = np.argmax(closeness[:, forward[i]] == column_best[forward[i]]) == i
    if ratio < 1 and closeness.shape[1] > 1:
        best_two = -np.partition(-closeness, 1, axis=1)[:, :2]
        nearest, second = np.sqrt(np.maximum(-2 * best_two, 0)).T
        keep &= nearest < ratio * second
    mutual = np.flatnonzero(keep)
    return np.stack([mutual, forward[mutual]], axis=1).astype(np.int64)


def estimate_homography(
    points1: np.ndarray, points2: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray]:
    """The protocol's RANSAC estimate from matched points ``[M, 2]`` (x, y), image 1 -> 2:
    ``cv2.findHomography(points1, points2, cv2.RANSAC, 3, maxIters=5000)``. Returns (the float64
    [3, 3] homography, or None when fewer than 4 points or OpenCV finds none; bool ``[M]`` inlier
    mask, all False without a homography)."""
    no_inliers = np.zeros(len(points1), dtype=bool)
    if len(points1) < 4:
        return None, no_inliers
    estimate, mask = cv2.findHomography(
        np.asarray(points1, np.float64),
        np.asarray(points2, np.float64),
        cv2.RANSAC,
        RANSAC_THRESHOLD,
        maxIters=RANSAC_MAX_ITERS,
    )
    if estimate is None or estimate.shape != (3, 3):
        return None, no_inliers
    return estimate, mask.ravel().astype(bool)


def matched_points(
    features1: Features, features2: Features, matches: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints of ``matches`` (int ``[K, 2]``), float64 ``[K, 2]`` each."""
    return (
        np.asarray(features1.keypoints, np.float64).reshape(-1, 2)[matches[:, 0]],
        np.asarray(features2.keypoints, np.float64).reshape(-1, 2)[matches[:, 1]],
    )


def match_and_estimate(
    features1: Features, features2: Features, norm: int = cv2.NORM_L2
) -> Matching:
    """The paper's homography estimation procedure: mutual nearest neighbours in descriptor
    space (:func:`nearest_neighbours` with ``cross_check``), then :func:`estimate_homography`.

    Fewer than 4 matches, or no homography from OpenCV, gives ``homography=None`` and no inliers.
    """
    matches = nearest_neighbours(
        features1.descriptors, features2.descriptors, norm, cross_check=True
    )
    estimate, inliers = estimate_homography(*matched_points(features1, features2, matches))
    return Matching(matches, inliers, estimate)
