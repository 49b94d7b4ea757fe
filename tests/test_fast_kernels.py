"""The hand-written fast paths of the network equal the library operations they replace."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.model import _conv_few_outputs, max_pool_2x2


def test_max_pool_matches_flax_values_and_gradients_including_ties():
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(2, 6, 8, 3)).astype(np.float32))
    x = x.at[0, 0, 0, 0].set(x[0, 0, 1, 0])  # a tie: reduce_window gives the first the gradient
    x = x.at[1, 2:4, 2:4, 1].set(0.5)  # a window of four equal values
    grad = jnp.asarray(rng.normal(size=(2, 3, 4, 3)).astype(np.float32))
    pooled, vjp = jax.vjp(max_pool_2x2, x)
    expected, expected_vjp = jax.vjp(lambda v: nn.max_pool(v, (2, 2), strides=(2, 2)), x)
    np.testing.assert_array_equal(pooled, expected)
    np.testing.assert_array_equal(vjp(grad)[0], expected_vjp(grad)[0])


def test_few_output_conv_matches_lax_conv_values_and_gradients():
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(2, 5, 7, 16)).astype(np.float32))
    kernel = jnp.asarray(rng.normal(size=(3, 3, 16, 2)).astype(np.float32))
    grad = jnp.asarray(rng.normal(size=(2, 5, 7, 2)).astype(np.float32))

    def reference(x, kernel):
        return jax.lax.conv_general_dilated(x, kernel, (1, 1), "SAME",
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))

    out, vjp = jax.vjp(lambda x, k: _conv_few_outputs(x, k, (1, 1), "SAME"), x, kernel)
    expected, expected_vjp = jax.vjp(reference, x, kernel)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)
    for got, want in zip(vjp(grad), expected_vjp(grad)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4)
