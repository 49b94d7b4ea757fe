"""Point-pair correspondences between the two siamese branches (paper section 4, eqs. 2-3, 11).

All shapes are fixed (masks instead of variable-length sets) so everything jits and vmaps.
Shapes are for one image pair; vmap over the batch.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from usp_jax.core.geometry import points_inside


class Correspondences(NamedTuple):
    """Nearest-neighbour point-pairs from branch A to branch B.

    distances:  [MA, MB] G of eq. 2 (A points warped by T vs B points), float32.
    valid_a:    [MA] A point lands inside image B after warping by T.
    valid_b:    [MB] B point's preimage under T lies inside image A.
    nearest:    [MA] index j of A point i's nearest valid B point.
    d:          [MA] d_k (eq. 3): distance to that neighbour, differentiable in both positions.
    paired:     [MA] point i forms a point-pair: valid and d <= eps_correspond.
    """

    distances: jax.Array
    valid_a: jax.Array
    valid_b: jax.Array
    nearest: jax.Array
    d: jax.Array
    paired: jax.Array


def pairwise_distances(xy_a: jax.Array, xy_b: jax.Array) -> jax.Array:
    """Euclidean distance matrix, [MA, 2] x [MB, 2] -> [MA, MB].

    Written on the coordinate differences: XLA fuses them and the square root into one pass over
    the matrix (``|a|^2 + |b|^2 - 2 a.b`` costs more, as a dot with two terms is a broadcast and a
    reduction), and they are exact for nearby points, where that form cancels. The square root is
    guarded so its gradient stays finite where two points coincide (an identity T pairs every
    point with itself).
    """
    dx = xy_a[:, None, 0] - xy_b[None, :, 0]
    dy = xy_a[:, None, 1] - xy_b[None, :, 1]
    return safe_sqrt(dx * dx + dy * dy)


def safe_sqrt(sq: jax.Array, tiny: float = 1e-12) -> jax.Array:
    """sqrt with a zero (not infinite) gradient at 0."""
    positive = sq > tiny
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def find_correspondences(
    xy_a_in_b: jax.Array,
    xy_b_in_a: jax.Array,
    xy_b: jax.Array,
    height: int,
    width: int,
    eps_correspond: float = 4.0,
) -> Correspondences:
    """Point-pairs of section 4: A point i pairs with its nearest B point j if g_ij <= eps.

    xy_a_in_b: [MA, 2] branch-A points warped by T into image B (``T p^A``).
    xy_b_in_a: [MB, 2] branch-B points warped by T^-1 into image A (only for the mask).
    xy_b:      [MB, 2] branch-B points.
    Points without a counterpart in the other view are masked out of the nearest-neighbour search,
    so they can neither pair nor attract a pair (peers note: unmasked borders drift).
    """
    # Keypoints reach the outer pixel edges (-0.5 and W - 0.5), hence the negative border.
    valid_a = points_inside(xy_a_in_b, height, width, border=-0.5)
    valid_b = points_inside(xy_b_in_a, height, width, border=-0.5)
    distances = pairwise_distances(xy_a_in_b, xy_b)
    search = jnp.where(valid_b[None, :], jax.lax.stop_gradient(distances), jnp.inf)
    # jnp.argmin(search, axis=1) as two plain min-reductions, which XLA:CPU vectorises; its
    # (value, index) pair reduction runs element by element, the slowest fused kernel of the step.
    closest = jnp.min(search, axis=1, keepdims=True)
    candidates = jnp.arange(search.shape[1])
    nearest = jnp.min(jnp.where(search == closest, candidates, search.shape[1]), axis=1)
    # Recompute d_k from the gathered points: cheaper to differentiate than the full matrix.
    d = safe_sqrt(jnp.sum((xy_a_in_b - xy_b[nearest]) ** 2, axis=-1))
    paired = valid_a & valid_b[nearest] & (d <= eps_correspond)
    return Correspondences(distances, valid_a, valid_b, nearest, d, paired)


def correspondence_matrix(corr: Correspondences, eps_descriptor: float = 8.0) -> jax.Array:
    """C of eq. 11: c_ij = 1 if g_ij <= 8, as float32 [MA, MB]."""
    return (jax.lax.stop_gradient(corr.distances) <= eps_descriptor).astype(jnp.float32)
