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
    """

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray


def to_cv2(features: Features) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """OpenCV keypoints (``pt`` = (x, y), ``size`` = one 8 px cell, ``response`` = score) and the
    float32 [N, F] descriptors, ready for ``cv2.BFMatcher(cv2.NORM_L2)``."""
    keypoints = [
        cv2.KeyPoint(float(x), float(y), float(CELL), response=float(score))
        for (x, y), score in zip(features.keypoints, features.scores)
    ]
    return keypoints, np.ascontiguousarray(features.descriptors, dtype=np.float32)
