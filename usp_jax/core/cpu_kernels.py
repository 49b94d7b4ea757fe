"""Kernels for the CPU backend: the same results as the library operations they replace, faster
on XLA:CPU. Used by the model only when JAX runs on CPU (:func:`enabled`); on accelerators the
model runs the plain Flax/XLA operations, whose kernels there need no help.

- :func:`max_pool_2x2`: the backbone's 2x2 max-pool with a hand-written gradient.
- :func:`conv_few_outputs`: the score and position heads' last 3x3 convolutions (1 and 2 outputs).
- :func:`compiler_options`: XLA:CPU options for every jitted program that runs the network.

``tests/test_cpu_kernels.py`` checks each against the plain operation, and the whole network
through both paths. The measurements behind each are in ``benchmarks/README.md``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

# XLA:CPU hands convolutions and reductions to YNNPACK by default. For this network Eigen's
# convolutions are faster (train step 4.4 -> 3.5 s, forward 76 -> 64 ms on 2 AVX-512 cores,
# benchmarks/README.md), while YNNPACK's reductions (the BatchNorm statistics) beat XLA's own.
_XLA_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_REDUCE"}


def enabled() -> bool:
    """Whether the model uses these kernels by default: on the CPU backend only."""
    return jax.default_backend() == "cpu"


def _quadrants(x: jax.Array) -> tuple[jax.Array, ...]:
    """The four strided sub-grids of [B, H, W, C] in window order: top-left, top-right, ..."""
    return x[:, 0::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 0::2], x[:, 1::2, 1::2]


@jax.custom_vjp
def max_pool_2x2(x: jax.Array) -> jax.Array:
    """2x2 max-pool with stride 2, [B, H, W, C] -> [B, H / 2, W / 2, C] (H, W even).

    Same values and gradients as ``nn.max_pool(x, (2, 2), strides=(2, 2))`` (the first maximum
    in window order takes the gradient), with a hand-written gradient: on CPU, reduce_window's
    becomes a scatter with full-size index arrays, and autodiff of this maximum of sub-grids
    recomputes the layer's forward to compare against. Here the forward records the winner
    (int8, a quarter of the input's size) and the backward places the gradient there.
    """
    a, b, c, d = _quadrants(x)
    return jnp.maximum(jnp.maximum(a, b), jnp.maximum(c, d))


def _max_pool_forward(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    a, b, c, d = _quadrants(x)
    pooled = jnp.maximum(jnp.maximum(a, b), jnp.maximum(c, d))
    winner = jnp.where(a == pooled, 0, jnp.where(b == pooled, 1, jnp.where(c == pooled, 2, 3)))
    return pooled, winner.astype(jnp.int8)


def _max_pool_backward(winner: jax.Array, grad: jax.Array) -> tuple[jax.Array]:
    a, b, c, d = (jnp.where(winner == k, grad, 0) for k in range(4))
    batch, h, w, channels = grad.shape
    rows = jnp.stack([jnp.stack([a, b], axis=3), jnp.stack([c, d], axis=3)], axis=2)
    return (rows.reshape(batch, 2 * h, 2 * w, channels),)


max_pool_2x2.defvjp(_max_pool_forward, _max_pool_backward)


def conv_few_outputs(inputs: jax.Array, kernel: jax.Array, strides, padding, **_) -> jax.Array:
    """The score and position heads' last 3x3 "SAME" convs (1 and 2 outputs), called by nn.Conv.

    inputs: [B, h, w, C]; kernel: [3, 3, C, O] -> [B, h, w, O]. A library convolution cannot
    use its matrix kernels for so few outputs; one [B h w, C] x [C, 9 O] matmul and nine shifted
    adds do the same sums 3-5x faster on CPU, forward and backward.
    """
    if tuple(strides) != (1, 1) or padding != "SAME" or kernel.shape[:2] != (3, 3):
        raise ValueError(f"3x3 'SAME' stride-1 only, got {kernel.shape[:2]} {padding} {strides}")
    batch, h, w, channels = inputs.shape
    outputs = kernel.shape[-1]
    per_tap = kernel.transpose(2, 0, 1, 3).reshape(channels, 9 * outputs)
    taps = (inputs.reshape(-1, channels) @ per_tap).reshape(batch, h, w, 3, 3, outputs)
    # Output pixel (y, x) sums the taps (ky, kx) of input pixel (y + ky - 1, x + kx - 1).
    taps = jnp.pad(taps, ((0, 0), (1, 1), (1, 1), (0, 0), (0, 0), (0, 0)))
    return sum(taps[:, ky : ky + h, kx : kx + w, ky, kx] for ky in range(3) for kx in range(3))


@functools.cache
def compiler_options() -> dict[str, str]:
    """``jax.jit(..., compiler_options=...)`` for programs running the network: _XLA_CPU_OPTIONS.

    Empty off CPU, and for an XLA that does not know these experimental options (it rejects them
    at compile time, so one tiny compile checks them once per process).
    """
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(jnp.negative).lower(1.0).compile(compiler_options=_XLA_CPU_OPTIONS)
    except jax.errors.JaxRuntimeError:
        return {}
    return dict(_XLA_CPU_OPTIONS)
