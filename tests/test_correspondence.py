import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.correspondence import (
    correspondence_matrix,
    find_correspondences,
    pairwise_distances,
)
from usp_jax.core.model import relative_to_pixels

H, W = 32, 48


def grid_points(seed=0):
    rel = np.random.default_rng(seed).uniform(size=((H // 8) * (W // 8), 2))
    return relative_to_pixels(jnp.asarray(rel, jnp.float32), H // 8, W // 8)


def test_distance_matrix_matches_numpy():
    a, b = np.random.default_rng(0).uniform(0, 50, size=(2, 7, 2)).astype(np.float32)
    expected = np.linalg.norm(a[:, None] - b[None], axis=-1)
    np.testing.assert_allclose(
        pairwise_distances(jnp.asarray(a), jnp.asarray(b)), expected, atol=1e-3
    )


def test_identity_pairs_every_point_with_itself():
    xy = grid_points()
    corr = find_correspondences(xy, xy, xy, H, W)
    np.testing.assert_array_equal(corr.nearest, np.arange(len(xy)))
    np.testing.assert_allclose(corr.d, 0.0, atol=1e-6)
    assert bool(corr.paired.all())


def test_pairs_need_distance_within_eps_and_keep_the_nearest():
    b = jnp.array([[10.0, 10.0], [30.0, 10.0], [10.0, 25.0]])
    a_in_b = jnp.array([[12.0, 10.0], [30.0, 15.0], [20.0, 10.0]])  # 2 px, 5 px, 10 px away.
    corr = find_correspondences(a_in_b, b, b, H, W, eps_correspond=4.0)
    np.testing.assert_array_equal(corr.nearest, [0, 1, 0])
    np.testing.assert_allclose(corr.d, [2.0, 5.0, 10.0], atol=1e-5)
    np.testing.assert_array_equal(corr.paired, [True, False, False])


def test_points_outside_the_other_view_are_masked():
    b = jnp.array([[10.0, 10.0], [40.0, 20.0]])
    a_in_b = jnp.array([[10.5, 10.0], [-3.0, 10.0]])  # second A point leaves image B
    b_in_a = jnp.array([[10.0, 10.0], [100.0, 20.0]])  # second B point's preimage leaves image A
    corr = find_correspondences(a_in_b, b_in_a, b, H, W)
    np.testing.assert_array_equal(corr.valid_a, [True, False])
    np.testing.assert_array_equal(corr.valid_b, [True, False])
    np.testing.assert_array_equal(corr.paired, [True, False])


def test_correspondence_matrix_uses_eight_pixels_inclusive():
    b = jnp.array([[0.0, 0.0], [8.0, 0.0], [8.1, 0.0]])
    corr = find_correspondences(jnp.zeros((1, 2)), b, b, H, W)
    np.testing.assert_array_equal(correspondence_matrix(corr), [[1.0, 1.0, 0.0]])


def test_gradient_of_d_is_finite_when_points_coincide():
    xy = grid_points()
    grad = jax.grad(lambda p: find_correspondences(p, xy, xy, H, W).d.sum())(xy)
    assert np.all(np.isfinite(grad))
