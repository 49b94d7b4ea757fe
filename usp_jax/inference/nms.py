"""Radius non-maximum suppression ("NMS = 4" in the paper's tables): by decreasing score, a point
is kept unless a kept point lies within the radius (Euclidean, inclusive).

Two implementations of the one rule: :func:`radius_nms` inside the detector's compiled function,
on the network's grid of one candidate per cell, and :func:`radius_nms_host` in NumPy for any
detector's points (the evaluation applies it to every method alike). Tests hold them equal.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.model import CELL


def _neighbours(values: jax.Array, cells_h: int, cells_w: int, reach: int, fill) -> jax.Array:
    """The values of every other cell within ``reach`` cells, [M, ...] -> [O, M, ...].

    O = (2 reach + 1)^2 - 1 offsets; cells outside the grid read ``fill``.
    """
    rest = values.shape[1:]
    grid = values.reshape(cells_h, cells_w, *rest)
    pad = ((reach, reach), (reach, reach)) + ((0, 0),) * len(rest)
    padded = jnp.pad(grid, pad, constant_values=fill)
    offsets = [
        (dy, dx)
        for dy in range(-reach, reach + 1)
        for dx in range(-reach, reach + 1)
        if (dy, dx) != (0, 0)
    ]
    return jnp.stack(
        [
            padded[reach + dy : reach + dy + cells_h, reach + dx : reach + dx + cells_w].reshape(
                cells_h * cells_w, *rest
            )
            for dy, dx in offsets
        ]
    )


#: Largest neighbourhood (in cells each way) :func:`radius_nms` compares cell by cell; beyond,
#: its memory ((2 reach + 1)^2 M) would grow with the radius, and the greedy loop takes over.
NEIGHBOUR_REACH = 3


def radius_nms(
    keypoints: jax.Array,
    scores: jax.Array,
    valid: jax.Array,
    cells_h: int,
    cells_w: int,
    radius: float,
    cell: float = CELL,
    limit: int | None = None,
    slack: float = 0.0,
) -> jax.Array:
    """Greedy radius NMS of one image's M candidates (one per cell), the paper's "NMS = 4".

    keypoints [M, 2], scores [M], valid [M] bool (row-major cells) -> keep [M] bool. Same result
    as :func:`radius_nms_host` on the valid points: by decreasing score (ties: lower index
    first), a point is kept unless a kept point lies within ``radius`` px (inclusive).
    ``limit``: stop once this many points are kept (the strongest of the full result; for a
    top-N cut after NMS, N). Raises ValueError for a radius that is negative, NaN or infinite.

    ``cell`` is a cell's side in the keypoints' pixels (8; 8 / s for a network run on the image
    enlarged s times). A point stays within ``slack`` px of its cell (0 for the network's
    points; a refined point moves up to ``refine.REACH``), so points d cells apart are at least
    ``cell * (d - 1) - 2 slack`` px apart and only cells within
    ``floor((radius + 2 slack) / cell) + 1`` can interact (3x3 cells for radius 4 at 8 px
    without slack), never more than the grid. Up to ``NEIGHBOUR_REACH`` cells
    each way, every cell is compared with those neighbours at once, and the greedy result is the
    unique fixed point of ``keep_i = valid_i and no kept stronger neighbour``: iterating that
    map from ``keep = valid`` settles one more level of the dependency chain per step, so the
    loop stops after (longest chain of suppressions) steps, usually a handful. For a larger
    radius (or with ``limit``) it runs the greedy order itself, one kept point per step: memory
    O(M) whatever the radius, and the larger the radius the fewer points, so the fewer steps.
    """
    radius = float(radius)
    if not (math.isfinite(radius) and radius >= 0):
        raise ValueError(f"NMS radius must be a finite number >= 0, got {radius}")
    m = scores.shape[0]
    reach = min(int((radius + 2 * slack) // cell) + 1, max(cells_h, cells_w) - 1)
    if reach < 1:  # a single cell: nothing to suppress
        return (
            jnp.asarray(valid, bool)
            if limit is None
            else greedy_radius_nms(keypoints, scores, valid, radius, limit)
        )
    if reach > NEIGHBOUR_REACH or limit is not None:
        return greedy_radius_nms(keypoints, scores, valid, radius, limit)

    def around(values, fill):
        return _neighbours(values, cells_h, cells_w, reach, fill)

    index = jnp.arange(m)
    other_index = around(index, m)
    other_scores = around(scores, -jnp.inf)
    stronger = (other_scores > scores) | ((other_scores == scores) & (other_index < index))
    close = jnp.sum((around(keypoints, jnp.inf) - keypoints) ** 2, axis=-1) <= radius**2
    suppressors = around(valid, False) & stronger & close  # [O, M]

    def step(state):
        keep, _ = state
        new = valid & ~jnp.any(suppressors & around(keep, False), axis=0)
        return new, jnp.any(new != keep)

    keep, _ = jax.lax.while_loop(lambda state: state[1], step, (valid, jnp.bool_(True)))
    return keep


def greedy_radius_nms(keypoints, scores, valid, radius: float, limit: int | None) -> jax.Array:
    """:func:`radius_nms` in the greedy order itself, for points on any grid or none (the
    pyramid's levels): each step keeps the strongest point not yet
    suppressed and suppresses every point within ``radius`` of it. O(M) memory; as many steps
    as points kept (at most ``limit``)."""
    keypoints, valid = jnp.asarray(keypoints), jnp.asarray(valid, bool)
    m = scores.shape[0]
    # Rank in the greedy order: decreasing score, ties by lower index (as a stable argsort).
    order = jnp.argsort(-jnp.asarray(scores), stable=True)
    rank = jnp.zeros(m, jnp.int32).at[order].set(jnp.arange(m, dtype=jnp.int32))

    def running(state):
        _, remaining, count = state
        going = jnp.any(remaining)
        return going if limit is None else going & (count < limit)

    def step(state):
        keep, remaining, count = state
        best = jnp.argmin(jnp.where(remaining, rank, m))
        close = jnp.sum((keypoints - keypoints[best]) ** 2, axis=-1) <= radius**2
        return (keep.at[best].set(True), remaining & ~close & (jnp.arange(m) != best), count + 1)

    keep, _, _ = jax.lax.while_loop(
        running, step, (jnp.zeros(m, bool), valid, jnp.zeros((), jnp.int32))
    )
    return keep


def radius_nms_host(keypoints: np.ndarray, scores: np.ndarray, radius: float) -> np.ndarray:
    """:func:`radius_nms` in NumPy for any detector's points: keypoints [N, 2], scores [N] ->
    int indices of the kept points [K], highest score first (ties: lower index first).

    SuperPoint's ``nms_fast`` suppresses a square window on integer-rounded positions instead;
    a disc on the exact positions treats sub-pixel detectors fairly.
    """
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(-np.asarray(scores), kind="stable")
    candidates = keypoints[order]
    suppressed = np.zeros(len(order), dtype=bool)
    kept = []
    for i in range(len(order)):
        if suppressed[i]:
            continue
        kept.append(order[i])
        suppressed[i:] |= np.sum((candidates[i:] - candidates[i]) ** 2, axis=1) <= radius**2
    return np.asarray(kept, dtype=np.int64)
