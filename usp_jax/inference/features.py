"""What a detector returns for one image, and its OpenCV form."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.core.model import CELL


class Features(NamedTuple):
    """What a detector returns for one image (any order; the evaluation sorts by score).

    keypoints: float32 ``[N, 2]`` (x, y), OpenCV pixel-centre convention.
    scores: float32 ``[N]``, higher is better.
    descriptors: ``[N, D]``, float32 (compared with L2) or uint8 packed bits (Hamming).
    scales: float32 ``[N]``, each point's size in px (``cv2.KeyPoint.size``): the cell of the
    pyramid level it was found at, ``CELL / scale`` (``Detector(any_scale=True)``); None: one
    cell, ``CELL``.
    """

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray | None = None


def to_cv2(features: Features) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """OpenCV keypoints (``pt`` = (x, y), ``size`` = ``features.scales``, one 8 px cell without
    them, ``response`` = score) and the float32 [N, F] descriptors, ready for
    ``cv2.BFMatcher(cv2.NORM_L2)``."""
    sizes = np.full(len(features.scores), CELL) if features.scales is None else features.scales
    keypoints = [
        cv2.KeyPoint(float(x), float(y), float(size), response=float(score))
        for (x, y), score, size in zip(features.keypoints, features.scores, sizes)
    ]
    return keypoints, np.ascontiguousarray(features.descriptors, dtype=np.float32)
