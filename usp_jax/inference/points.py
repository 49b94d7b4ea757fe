"""Fixed-size point sets inside the compiled detector: the border test, gathers by rank and the
map from the network's pixels to the input's, shared by the single-scale detector and the
pyramid (``inference.pyramid``).

Coordinates follow the project's convention (``usp_jax.core.model``): (x, y), pixel centres at
integers, so an image of width w spans [-0.5, w - 0.5].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: A top-N detector computes the descriptors of its N points alone (``model.describe_points``)
#: while N is at most this share of its candidates; for more, the whole descriptor map costs
#: less. At 240x320 (1,200 cells) and 300 points that saved 3.8% of `paper`'s time and 4.1% of
#: `distilled`'s (6.6% with the pyramid); for all 1,200 points `paper` was level and
#: `distilled` 18% slower (experiments/notes/choices.md).
SPARSE_SHARE = 0.25


def describes_sparsely(top_n: int | None, candidates: int) -> bool:
    """Whether a detector keeping ``top_n`` of ``candidates`` points computes their descriptors
    alone (:data:`SPARSE_SHARE`)."""
    return top_n is not None and top_n <= SPARSE_SHARE * candidates


def take(values: jax.Array, order: jax.Array) -> jax.Array:
    """The rows ``order`` [B, K] of per-point values [B, M, ...] -> [B, K, ...]."""
    return jnp.take_along_axis(values, order.reshape(order.shape + (1,) * (values.ndim - 2)), 1)


def inside(keypoints: jax.Array, extent: jax.Array, border: float | jax.Array) -> jax.Array:
    """keypoints [B, M, 2] at least ``border`` px inside images of extent (width, height)
    -> bool [B, M]. ``extent`` broadcasts against the keypoints ([B, 1, 2] per image, [B, M, 2]
    per point), ``border`` against [B, M, 1]; a negative ``border`` reaches that far outside."""
    extent = jnp.asarray(extent, jnp.float32)
    return jnp.all((keypoints >= border - 0.5) & (keypoints < extent - 0.5 - border), axis=-1)


def to_input(keypoints: jax.Array, upsample: int) -> jax.Array:
    """Keypoints in the network's pixels -> the input's, which the network saw ``upsample``
    times enlarged: input pixel x spans [x - 0.5, x + 0.5], ``upsample`` network pixels."""
    return keypoints if upsample == 1 else (keypoints + 0.5) / upsample - 0.5
