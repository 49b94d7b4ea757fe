"""Detection across zoom (``Detector(any_scale=True)``): an image pyramid inside the compiled
detector.

The network finds points at one scale: a corner seen twice as large in image 2 falls in other
cells and gets another descriptor, so zoom breaks matching. SIFT, AKAZE and ORB search a scale
space; here the same network runs on the image shrunk by ``STEP`` = 1/sqrt(2) per level while
the shorter side stays at least ``MIN_SIDE`` px. Shrinking only (no enlarged level) keeps the
cost below twice a single-scale detection: the levels add 1/2 + 1/4 + ... of its pixels.

Everything runs in one jitted function per input size (the levels' shapes follow from it): each
level is the input resized (:func:`resize_level`: antialiased linear, rounded to uint8, so a
level's points are exactly what ``Detector.detect`` finds on that uint8 image), edge-padded to
whole 8x8 cells and detected by the single-scale function; its points are mapped back to the
input's pixels, radius NMS runs across levels in those pixels, then top-N by score over all
levels. Each point keeps the descriptor of its own level, and its size (``Features.scales``) is
its level's cell in input pixels, ``CELL / scale``, so that ``to_cv2`` fills
``cv2.KeyPoint.size``. The features of an image do not depend on any other image.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.cpu_kernels import compiler_options
from usp_jax.core.model import CELL
from usp_jax.inference.nms import greedy_radius_nms

#: Ratio of the sides of consecutive levels (SIFT's octave holds two such steps).
STEP = 1 / math.sqrt(2)
#: Smallest shorter side of a level in px: below, a level has too few cells to hold points.
MIN_SIDE = 64


def level_scales(height: int, width: int, step: float = STEP, min_side: int = MIN_SIDE):
    """Scale of every level of an H x W input, 1 first, then ``step ** l`` while the level's
    shorter side (:func:`level_shape`) stays at least ``min_side`` (and ``CELL``) px."""
    scales = [1.0]
    while min(level_shape(height, width, scales[-1] * step)) >= max(min_side, CELL):
        scales.append(scales[-1] * step)
    return tuple(scales)


def level_shape(height: int, width: int, scale: float) -> tuple[int, int]:
    """(h, w) of the level at ``scale``: the input's sides times ``scale``, rounded."""
    return round(height * scale), round(width * scale)


def resize_level(images: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """uint8 [B, H, W, C] -> uint8 [B, h, w, C]: linear interpolation with pixel centres aligned
    (as ``cv2.resize``), antialiased when shrinking (a triangle filter as wide as the step, like
    ``INTER_AREA``: plain sampling would alias fine texture into false corners), rounded."""
    if tuple(images.shape[1:3]) == tuple(shape):
        return images
    size = (images.shape[0], *shape, images.shape[3])
    pixels = jax.image.resize(images.astype(jnp.float32), size, "linear", antialias=True)
    return jnp.clip(jnp.round(pixels), 0, 255).astype(jnp.uint8)


def _pad_to_cells(images: jax.Array) -> jax.Array:
    """Edge-pad uint8 [B, h, w, C] at the bottom/right to whole cells (``detector`` docstring)."""
    pad_h, pad_w = -images.shape[1] % CELL, -images.shape[2] % CELL
    return jnp.pad(images, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")


def candidates(height: int, width: int, upsample: int = 1, any_scale: bool = False) -> int:
    """Most points a detector can return for an H x W image: one per cell of the padded,
    ``upsample``-d image, of every level with ``any_scale``."""
    scales = level_scales(height, width) if any_scale else (1.0,)
    return sum(
        math.prod(math.ceil(side * upsample / CELL) for side in level_shape(height, width, scale))
        for scale in scales
    )


def detect_pyramid(
    variables: dict,
    images: jax.Array,
    *,
    detect_level: Callable,
    top_n: int | None,
    nms_radius: float,
    border: float,
) -> tuple[jax.Array, ...]:
    """All levels of uint8 [B, H, W, 3] images (any H, W >= 8, unpadded) -> keypoints [B, K, 2]
    in input pixels, scores [B, K] sorted descending, descriptors [B, K, F], counts [B] (only
    the first counts[b] entries are points) and sizes [B, K] (``CELL / scale`` of each point's
    level).

    ``detect_level(variables, padded [B, h8, w8, 3], sizes [B, 2], top_n=n, nms_radius=0,
    border=b)`` is the single-scale detection (``detector._detect_padded`` with its model bound):
    a level's strongest points, sorted, its first counts[b] valid; all of them (n None) when
    NMS across levels needs them. ``border`` is in input pixels.
    """
    batch, height, width = images.shape[:3]
    parts = []
    for scale in level_scales(height, width):
        shape = level_shape(height, width, scale)
        factors = (width / shape[1], height / shape[0])  # (x, y)
        sizes = jnp.broadcast_to(jnp.array(shape, jnp.int32), (batch, 2))
        keypoints, scores, descriptors, counts = detect_level(
            variables,
            _pad_to_cells(resize_level(images, shape)),
            sizes,
            # Without NMS a level's points beyond its own top N cannot make the top N of all.
            top_n=top_n if nms_radius == 0 else None,
            nms_radius=0.0,
            border=border / max(factors),
        )
        valid = jnp.arange(scores.shape[1]) < counts[:, None]
        # Pixel centres at integers: level pixel x spans input [(x - 0.5) f, (x + 0.5) f] - 0.5.
        keypoints = (keypoints + 0.5) * jnp.array(factors, jnp.float32) - 0.5
        level_sizes = jnp.full(scores.shape, CELL / scale, jnp.float32)
        parts.append(
            (keypoints, jnp.where(valid, scores, -jnp.inf), descriptors, valid, level_sizes)
        )
    keypoints, scores, descriptors, valid, sizes = (
        jnp.concatenate(arrays, axis=1) for arrays in zip(*parts)
    )
    k = scores.shape[1] if top_n is None else min(top_n, scores.shape[1])
    keep = valid
    if nms_radius > 0:
        # The levels' points lie on no common grid: the greedy order itself, stopped at the k
        # points the top-k cut below takes anyway (greedy_radius_nms).
        keep = jax.vmap(greedy_radius_nms, in_axes=(0, 0, 0, None, None))(
            keypoints, scores, valid, nms_radius, None if top_n is None else k
        )
    ranked, order = jax.lax.top_k(jnp.where(keep, scores, -jnp.inf), k)
    counts = jnp.minimum(jnp.sum(keep, axis=-1), k)
    keypoints, descriptors, sizes = (take_points(x, order) for x in (keypoints, descriptors, sizes))
    return keypoints, ranked, descriptors, counts, sizes


def take_points(values: jax.Array, order: jax.Array) -> jax.Array:
    """The rows ``order`` [B, K] of per-point values [B, M, ...] -> [B, K, ...]."""
    return jnp.take_along_axis(values, order.reshape(order.shape + (1,) * (values.ndim - 2)), 1)


def pyramid_function(detect_level: Callable, nms_radius: float, border: float) -> Callable:
    """:func:`detect_pyramid` as ``(variables, images, top_n=...)`` (for ``jax.export``, which
    jits it itself)."""
    return functools.partial(
        detect_pyramid, detect_level=detect_level, nms_radius=nms_radius, border=border
    )


def compile_pyramid(detect_level: Callable, nms_radius: float, border: float) -> Callable:
    """:func:`pyramid_function` jitted: one compilation per input shape and ``top_n``."""
    return jax.jit(
        pyramid_function(detect_level, nms_radius, border),
        static_argnames="top_n",
        compiler_options=compiler_options(),
    )


def detect_by_size(
    forward: Callable,
    variables: dict,
    padded: np.ndarray,
    sizes: np.ndarray,
    top_n: int | None,
    unbatch: Callable,
) -> list:
    """``unbatch(forward(variables, images, top_n=top_n))`` for each group of same-size images
    of a padded uint8 [B, Hp, Wp, 3] stack with their sizes [B, 2] (cropped back: the levels'
    shapes follow from the unpadded size). Results in input order."""
    results = [None] * len(padded)
    for size in np.unique(np.asarray(sizes), axis=0):
        members = np.flatnonzero(np.all(sizes == size, axis=1))
        stack = padded[members, : size[0], : size[1]]
        for i, features in zip(members, unbatch(forward(variables, stack, top_n=top_n))):
            results[i] = features
    return results
