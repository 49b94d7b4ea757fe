"""The CPU backend's kernels equal the library operations they replace, alone and in the network."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from conftest import SMALL_FAST, SMALL_MODEL

from usp_jax.core.cpu_kernels import conv_few_outputs, max_pool_2x2
from usp_jax.core.model import UnsuperPoint, init_variables


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
        return jax.lax.conv_general_dilated(
            x, kernel, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
        )

    out, vjp = jax.vjp(lambda x, k: conv_few_outputs(x, k, (1, 1), "SAME"), x, kernel)
    expected, expected_vjp = jax.vjp(reference, x, kernel)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)
    for got, want in zip(vjp(grad), expected_vjp(grad)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4)


def test_the_network_gives_the_same_outputs_and_gradients_on_the_plain_and_the_cpu_path():
    """Both backbones, in training mode (BatchNorm batch statistics) as in a train step."""
    rng = np.random.default_rng(2)
    images = jnp.asarray(rng.uniform(size=(2, 32, 48, 3)).astype(np.float32))
    for config in (
        SMALL_MODEL,
        SMALL_FAST,
    ):
        variables = init_variables(jax.random.PRNGKey(0), config)

        def loss(params, cpu):
            model = UnsuperPoint(config, use_cpu_kernels=cpu)
            pred, _ = model.apply(
                {**variables, "params": params}, images, train=True, mutable=["batch_stats"]
            )
            return sum(jnp.sum(x * x) for x in pred), pred

        # Compiled: op by op, the backward pass of the network took 30 s.
        both = jax.jit(jax.value_and_grad(loss, has_aux=True), static_argnums=1)
        (_, plain), plain_grad = both(variables["params"], False)
        (_, cpu), cpu_grad = both(variables["params"], True)
        for got, want in zip(jax.tree.leaves(cpu), jax.tree.leaves(plain)):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
        # Float rounding differs between the two paths; gradients that are zero in exact
        # arithmetic (conv biases ahead of BatchNorm) are compared against the largest one.
        scale = max(float(np.abs(g).max()) for g in jax.tree.leaves(plain_grad))
        for got, want in zip(jax.tree.leaves(cpu_grad), jax.tree.leaves(plain_grad)):
            np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-5 * scale)
