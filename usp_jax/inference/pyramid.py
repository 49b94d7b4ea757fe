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
whole 8x8 cells and run through the network; the candidates of all levels are then selected
together, as the single-scale detector selects one level's: sub-pixel refinement (each point on
its own level's image), the border test, radius NMS across levels in input pixels, then top-N by
score over all levels (the refined points' scores times the certainty of their moves, weighted
by ``SPREAD_WEIGHT``). Without NMS only the strongest candidates of all levels, plus every
level's edge cells, are refined: 810 of 2,303 at 240x320 / 300 (``refine.refined_count``). Each
point keeps the descriptor of its own level, and its size (``Features.scales``) is its level's
cell in input pixels, ``CELL / scale``, so that ``to_cv2`` fills ``cv2.KeyPoint.size``. The
features of an image do not depend on any other image.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.model import CELL, pad_descriptor_features
from usp_jax.inference import points, refine
from usp_jax.inference.nms import greedy_radius_nms

#: Ratio of the sides of consecutive levels (SIFT's octave holds two such steps).
STEP = 1 / math.sqrt(2)
#: Smallest shorter side of a level in px: below, a level has too few cells to hold points.
MIN_SIDE = 64
#: ``refine.SPREAD_WEIGHT`` for the pyramid's points: three times the single-scale one. With
#: a point's copies on several levels to choose from, ranking the better placed ones first
#: raised HA@3 on the zoomed design pairs from 0.660 to 0.729 (experiments/notes/choices.md).
SPREAD_WEIGHT = 0.3


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
    network: Callable,
    descriptors: Callable,
    top_n: int | None,
    nms_radius: float,
    border: float,
    upsample: int = 1,
    refiner: dict | None = None,
) -> tuple[jax.Array, ...]:
    """All levels of uint8 [B, H, W, 3] images (any H, W >= 8, unpadded) -> keypoints [B, K, 2]
    in input pixels, scores [B, K] sorted descending, descriptors [B, K, F], counts [B] (only
    the first counts[b] entries are points) and sizes [B, K] (``CELL / scale`` of each point's
    level).

    ``network(variables, padded [B, h8, w8, 3], sparse=...)`` -> (its input [B, s h8, s w8, 3],
    Predictions in its pixels, descriptor anchors, descriptor features) is
    ``detector._network`` with its model and ``upsample`` s bound, ``descriptors``
    ``model.describe_points`` with its dtype: when few points are kept
    (``points.describes_sparsely``) their descriptors are computed at the end, each from its own
    level's features, in one gather over all levels. A level's border is ``border`` input px,
    its own in its pixels. With a ``refiner`` the candidates of all levels are cut together
    before the refinement, as ``detector._detect_padded`` cuts one level's: without NMS the
    strongest ``top_n`` plus every level's ``refine.edge_cells`` (the moved, re-scored points of
    all levels compete for one top N), each point read from its own level.
    """
    batch, height, width = images.shape[:3]
    sparse = points.describes_sparsely(top_n, candidates(height, width, upsample, any_scale=True))
    levels, origins, features, edges = _run_levels(
        variables, images, network, border=border, upsample=upsample, sparse=sparse
    )
    # What the kept points' descriptors come from: their anchors, or the model's descriptors.
    keypoints, scores, carried = (
        jnp.concatenate(x, axis=1) for x in zip(*((p.keypoints, p.scores, a) for _, p, a in levels))
    )
    m = scores.shape[1]
    origin = jax.tree.map(
        lambda *x: jnp.broadcast_to(np.concatenate(x), (batch, m, *x[0].shape[1:])), *origins
    )

    def inside(keypoints, origin, slack=0.0):  # keypoints in their levels' network pixels
        level_pixels = points.to_input(keypoints, upsample)
        return points.inside(level_pixels, origin.extent, origin.margin[..., None] - slack)

    if refiner is not None:
        count = refine.refined_count(m, edges, top_n, nms_radius)
        if count < m:
            possible = inside(keypoints, origin, refine.REACH / upsample)
            _, order = jax.lax.top_k(jnp.where(possible, scores, -jnp.inf), count)
            keypoints, scores, carried, origin = jax.tree.map(
                lambda x: points.take(x, order), (keypoints, scores, carried, origin)
            )
        level_pixels = [pixels for pixels, _, _ in levels]
        moves, factors = _level_moves(refiner, level_pixels, keypoints, origin.level)
        keypoints, scores = keypoints + moves, scores * factors
    keep = inside(keypoints, origin)
    # Pixel centres at integers: level pixel x spans input [(x - 0.5) f, (x + 0.5) f] - 0.5.
    keypoints = (points.to_input(keypoints, upsample) + 0.5) * origin.factors - 0.5
    k = scores.shape[1] if top_n is None else min(top_n, scores.shape[1])
    if nms_radius > 0:
        # The levels' points lie on no common grid: the greedy order itself, stopped at the k
        # points the top-k cut below takes anyway (greedy_radius_nms).
        keep = jax.vmap(greedy_radius_nms, in_axes=(0, 0, 0, None, None))(
            keypoints, scores, keep, nms_radius, None if top_n is None else k
        )
    ranked, order = jax.lax.top_k(jnp.where(keep, scores, -jnp.inf), k)
    counts = jnp.minimum(jnp.sum(keep, axis=-1), k)
    keypoints, carried, sizes, maps = (
        points.take(x, order) for x in (keypoints, carried, origin.size, origin.features)
    )
    if sparse:
        padded = jnp.concatenate(features, axis=1)
        maps = tuple(jnp.moveaxis(maps, -1, 0))
        carried = descriptors(variables["params"], padded, carried, maps)
    return keypoints, ranked, carried, counts, sizes


def _run_levels(
    variables: dict,
    images: jax.Array,
    network: Callable,
    *,
    border: float,
    upsample: int,
    sparse: bool,
) -> tuple[list, list, list, int]:
    """The network on every level of uint8 [B, H, W, 3] images (:func:`detect_pyramid`'s
    ``network``): per level (its network pixels, Predictions, its descriptors' source: anchors
    when ``sparse``, else the descriptors) and its candidates' :class:`_Origin`; the levels'
    padded descriptor features when ``sparse``; and how many edge cells all levels hold
    (``refine.edge_cells``)."""
    height, width = images.shape[1:3]
    levels, origins, features, edges, rows = [], [], [], 0, 0
    for index, scale in enumerate(level_scales(height, width)):
        shape = level_shape(height, width, scale)
        pixels, predictions, anchors, level_features = network(
            variables, _pad_to_cells(resize_level(images, shape)), sparse=sparse
        )
        cells_h, cells_w = pixels.shape[1] // CELL, pixels.shape[2] // CELL
        factors = (width / shape[1], height / shape[0])  # (x, y)
        margin = border / max(factors)
        levels.append((pixels, predictions, anchors if sparse else predictions.descriptors))
        first_row = rows
        if sparse:
            features.append(pad_descriptor_features(level_features))
            rows += features[-1].shape[1]
        origins.append(
            _Origin.of_level(
                index,
                scale,
                shape,
                margin,
                factors,
                (cells_h, cells_w, first_row),
                cells_h * cells_w,
            )
        )
        edges += refine.edge_cells(cells_h, cells_w, margin, upsample)
    return levels, origins, features, edges


class _Origin(NamedTuple):
    """Where each of M candidates comes from, per point (static, float32): its level's index
    [M], (width, height) [M, 2], border in its pixels [M], (x, y) factors to the input's
    pixels [M, 2], cell side in input pixels (``Features.scales``) [M] and its level's
    descriptor features [M, 3]: their height and width in cells and first row in the levels'
    padded features, one after another (``model.describe_points``)."""

    level: np.ndarray
    extent: np.ndarray
    margin: np.ndarray
    factors: np.ndarray
    size: np.ndarray
    features: np.ndarray

    @classmethod
    def of_level(cls, index, scale, shape, margin, factors, features, count) -> _Origin:
        values = (index, shape[::-1], margin, factors, CELL / scale, features)
        return cls(*(np.full((count, *np.shape(v)), v, np.float32) for v in values))


def _level_moves(
    refiner: dict, pixels: list[jax.Array], keypoints: jax.Array, level: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """``refine.patch_moves`` (moves [B, K, 2], score factors [B, K]) of keypoints [B, K, 2],
    each in the network pixels of its own level (``level`` [B, K], the index into ``pixels``,
    each [B, h, w, 3]): every point's patch is read from its level, then the offset network runs
    once on all K."""
    side = refine.patch_side(refine.channels_of(refiner))
    read = jax.vmap(refine.sample_patches, in_axes=(0, 0, None))
    patches = jnp.zeros((*keypoints.shape[:2], side, side), jnp.float32)
    for index, image in enumerate(pixels):
        mine = (level == index)[..., None, None]
        patches = jnp.where(mine, read(refine.grey(image), keypoints, side), patches)
    return jax.vmap(refine.patch_moves, in_axes=(None, 0, None))(refiner, patches, SPREAD_WEIGHT)


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
