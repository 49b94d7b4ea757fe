"""The UnsuperPoint network (paper section 2) as a Flax Linen module.

Coordinate convention (the one place it is defined): pixel coordinates are (x, y) with x to the
right, y down and pixel *centres* at integers, exactly as in OpenCV. The paper's mapping
(eq. 1), ``P_map = (cell + P_relative) * 8``, is written in pixel-*edge* coordinates where pixel i
spans [i, i + 1]; in centre coordinates it is ``(cell + P_relative) * 8 - 0.5``. A relative
position of 0 is the outer edge of the cell's first pixel, 1 the outer edge of its last pixel and
0.5 the cell centre ``8 c + 3.5``. The descriptor map entry of cell c sits at that centre, so a
pixel coordinate x reads the descriptor map at ``(x + 0.5) / 8 - 0.5``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from usp_jax.core import cpu_kernels

CELL = 8  # Three 2x2 max-pools: one point per 8x8 cell.
# Paper section 5: "subtracting 0.5 and multiplying with 0.225". We divide, the usual reading
# (0.225 is ImageNet's per-channel std): multiplying would shrink the inputs to +-0.11.
_MEAN, _STD = 0.5, 0.225

BACKBONES = ("vgg", "fast")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Network shape. Defaults are the paper's (section 2); :func:`fast_config` is the fast one."""

    # "vgg": the paper's backbone, 4 pairs of 3x3 convs with a 2x2 max-pool after the first
    # three pairs (13.6 GFLOP per 240x320 image). "fast": :class:`FastBackbone`, built from the
    # components the paper's conclusion proposes (residual blocks, skips from higher-resolution
    # features), with small channel counts at high resolution as in XFeat and ALIKE.
    backbone: str = "vgg"
    # vgg: the 8 convs' output channels; fast: one width per resolution 1, 1/2, 1/4, 1/8.
    backbone_channels: tuple[int, ...] = (32, 32, 64, 64, 128, 128, 256, 256)
    head_channels: int = 256
    descriptor_dim: int = 256
    # Width of the descriptor head's hidden conv; 0 = head_channels (the paper's: 256 for all).
    descriptor_head_channels: int = 0
    # Kernel side of that hidden conv (the paper's: 3). The fast network's is 1: its output conv
    # is 3x3 already, a 3x3 hidden conv would add 0.27 GFLOP (14%), and at 1,500 steps it
    # matched translated crops no better (experiments/notes/choices.md, "The fast network").
    descriptor_head_kernel: int = 3
    # C1-C4 of the paper's Table 1 sample the descriptor map at the predicted position; C0 reads
    # the coarse entry of the cell.
    interpolate_descriptors: bool = True
    # Compute dtype of the convolutions ("bfloat16" on accelerators); parameters stay float32.
    dtype: str = "float32"
    leaky_relu_slope: float = 0.01
    # Variance scale of the heads' last conv kernels (centred, see _zero_mean_init). For the
    # position head, 7 makes the pre-sigmoid outputs roughly Logistic(0, 1) under training
    # BatchNorm, so P_relative starts close to U(0, 1): the uniform loss (x100) then starts near
    # its minimum instead of swamping the other terms in the first steps, as peers reported.
    # The paper does not specify an initialisation.
    position_init_scale: float = 7.0
    batch_norm_momentum: float = 0.9

    def __post_init__(self):
        if self.backbone not in BACKBONES:
            raise ValueError(
                f"backbone must be one of {', '.join(BACKBONES)}, got {self.backbone!r}"
            )
        expected = {"vgg": (8, "4 pairs of convs"), "fast": (4, "one per resolution")}
        count, meaning = expected[self.backbone]
        if len(self.backbone_channels) != count:
            raise ValueError(
                f"backbone_channels of the {self.backbone} backbone needs {count} entries"
                f" ({meaning}), got {self.backbone_channels}"
            )


def fast_config(**changes) -> ModelConfig:
    """The fast network: :class:`FastBackbone` (8/24/48/96 channels), 64-wide score and position
    heads, a 128-wide 1x1 descriptor head and 128-d descriptors; 1.96 GFLOP per 240x320 image
    against the paper network's 13.3 (``benchmarks/common.py`` ``forward_gflop``)."""
    fields = dict(
        backbone="fast",
        backbone_channels=(8, 24, 48, 96),
        head_channels=64,
        descriptor_head_channels=128,
        descriptor_head_kernel=1,
        descriptor_dim=128,
    )
    return ModelConfig(**{**fields, **changes})


class Predictions(NamedTuple):
    """Per-image network outputs; M = (H / 8) * (W / 8) points in row-major cell order.

    scores:      [..., M]     in [0, 1] (score head + sigmoid).
    relative:    [..., M, 2]  (x, y) position inside the cell in [0, 1] (position head + sigmoid).
    keypoints:   [..., M, 2]  (x, y) pixel coordinates, module docstring convention.
    descriptors: [..., M, F]  L2-normalised; None from ``UnsuperPoint(sparse_descriptors=True)``.
    """

    scores: jax.Array
    relative: jax.Array
    keypoints: jax.Array
    descriptors: jax.Array | None


def check_image_size(height: int, width: int) -> None:
    if height % CELL or width % CELL or height < CELL or width < CELL:
        raise ValueError(
            f"image size {height}x{width} (HxW) is not a positive multiple of {CELL} on both sides;"
            " pad or resize it first (usp_jax.Detector pads automatically)"
        )


def cell_origins(cells_h: int, cells_w: int) -> jax.Array:
    """(c, r) index of every cell in row-major order, [M, 2] float32."""
    rows, cols = jnp.meshgrid(jnp.arange(cells_h), jnp.arange(cells_w), indexing="ij")
    return jnp.stack([cols.ravel(), rows.ravel()], axis=-1).astype(jnp.float32)


def relative_to_pixels(relative: jax.Array, cells_h: int, cells_w: int) -> jax.Array:
    """Paper eq. 1 in pixel-centre coordinates: ``(cell + P_relative) * 8 - 0.5``.

    relative: [..., M, 2] in [0, 1]  ->  [..., M, 2] pixel (x, y).
    """
    return (cell_origins(cells_h, cells_w) + relative) * CELL - 0.5


def bilinear_sample(feature_map: jax.Array, xy: jax.Array) -> jax.Array:
    """Bilinearly samples ``feature_map`` [h, w, C] at pixel positions xy [N, 2] -> [N, C].

    Pixel (x, y) reads feature coordinate ((x + 0.5) / 8 - 0.5, (y + 0.5) / 8 - 0.5) (module
    docstring); outside the centres of the border cells the border value is repeated. The weights
    are differentiable in xy, which is what lets the descriptor loss train positions (section 2.4).
    """
    h, w, _ = feature_map.shape
    u0, v0, du, dv = _bilinear_corner(xy, h, w)
    u1 = jnp.minimum(u0 + 1, w - 1)
    v1 = jnp.minimum(v0 + 1, h - 1)
    du, dv = du[:, None], dv[:, None]
    corners = jnp.stack([v0 * w + u0, v0 * w + u1, v1 * w + u0, v1 * w + u1], axis=1)  # [N, 4]
    # One gather for all four corners. The clips keep every index inside the map, so the gather
    # may skip its bounds handling (a select over the whole result, and the larger share of the
    # sampler's cost on CPU).
    values = feature_map.reshape(h * w, -1).at[corners].get(mode="promise_in_bounds")
    # Written out rather than a sum over the corner axis, which XLA:CPU hands to a slow reduction.
    top = values[:, 0] * (1 - du) + values[:, 1] * du
    bottom = values[:, 2] * (1 - du) + values[:, 3] * du
    return top * (1 - dv) + bottom * dv


def _bilinear_corner(xy: jax.Array, h, w) -> tuple[jax.Array, ...]:
    """The top-left cell (u0, v0) [N] int32 that pixel positions xy [N, 2] read from an h x w
    map (:func:`bilinear_sample`; h, w scalars or [N]), and the weights (du, dv) [N] of the cells
    right of and below it."""
    u = jnp.clip((xy[:, 0] + 0.5) / CELL - 0.5, 0.0, w - 1.0)
    v = jnp.clip((xy[:, 1] + 0.5) / CELL - 0.5, 0.0, h - 1.0)
    u0 = jnp.clip(jnp.floor(u), 0, jnp.maximum(w - 2, 0)).astype(jnp.int32)
    v0 = jnp.clip(jnp.floor(v), 0, jnp.maximum(h - 2, 0)).astype(jnp.int32)
    return u0, v0, u - u0, v - v0


def pad_descriptor_features(features: jax.Array) -> jax.Array:
    """[B, h, w, C] -> [B, (h + 3) (w + 3), C]: zero-padded by one cell above and left and two
    below and right (the last 3x3 convolution's "SAME" zeros, and room for the 4x4 block of
    :func:`descriptor_neighbourhoods` at any corner), rows flattened."""
    padded = jnp.pad(features, ((0, 0), (1, 2), (1, 2), (0, 0)))
    return padded.reshape(padded.shape[0], -1, padded.shape[-1])


def descriptor_neighbourhoods(padded: jax.Array, xy: jax.Array, h, w, offset=0) -> jax.Array:
    """The 3x3 input neighbourhoods [N, 3, 3, C] of the descriptor head's last convolution,
    bilinearly interpolated at pixel positions xy [N, 2] as :func:`bilinear_sample` reads that
    convolution's output (section 2.3's interpolated descriptors).

    ``padded`` [P, C]: rows of :func:`pad_descriptor_features` of one image, where each point's
    h x w map starts at row ``offset`` (h, w, offset: scalars or [N], so that points of several
    maps, a pyramid's levels, are read in one gather). The convolution is linear and the
    bilinear weights sum to 1, so ``conv(neighbourhood) = bilinear_sample(conv(map))``: the
    descriptors of N points cost N cells' convolution, not the whole map's (:func:`describe`).
    """
    u0, v0, du, dv = _bilinear_corner(xy, h, w)
    steps = jnp.arange(4)
    # The 4x4 block of padded cells whose 3x3 windows at (v0, u0), (v0, u0 + 1), (v0 + 1, u0)
    # and (v0 + 1, u0 + 1) are the four corners' neighbourhoods (padded row v0 = map row v0 - 1).
    rows = (v0[:, None] + steps) * (jnp.asarray(w) + 3)[..., None]
    block = jnp.asarray(offset)[..., None, None] + rows[:, :, None] + u0[:, None, None] + steps
    values = padded.at[block].get(mode="promise_in_bounds")  # [N, 4, 4, C]
    du, dv = du[:, None, None, None], dv[:, None, None, None]
    top = values[:, :3, :3] * (1 - du) + values[:, :3, 1:] * du
    bottom = values[:, 1:, :3] * (1 - du) + values[:, 1:, 1:] * du
    return top * (1 - dv) + bottom * dv


def describe(params: dict, neighbourhoods: jax.Array, dtype: str = "float32") -> jax.Array:
    """L2-normalised descriptors [..., F] from :func:`descriptor_neighbourhoods` [..., 3, 3, C]:
    the descriptor head's last 3x3 convolution (``params["descriptor"]``) applied at those
    points only, in ``dtype`` as the network computes it."""
    kernel, bias = params["descriptor"]["kernel"], params["descriptor"]["bias"]
    dtype = jnp.dtype(dtype)
    flat = neighbourhoods.reshape(*neighbourhoods.shape[:-3], -1).astype(dtype)
    out = flat @ kernel.reshape(-1, kernel.shape[-1]).astype(dtype) + bias.astype(dtype)
    return l2_normalize(out.astype(jnp.float32))


def describe_points(
    params: dict, padded: jax.Array, anchors: jax.Array, maps: tuple, dtype: str = "float32"
) -> jax.Array:
    """:func:`describe` of points of a batch: descriptors [B, K, F] read at anchors [B, K, 2]
    from :func:`pad_descriptor_features` rows [B, P, C]; ``maps``: each point's map height,
    width and first row in ``padded`` (:func:`descriptor_neighbourhoods`), [B, K] each."""
    read = jax.vmap(descriptor_neighbourhoods)
    neighbourhoods = read(padded, anchors, *(jnp.asarray(x, jnp.int32) for x in maps))
    return describe(params, neighbourhoods, dtype)


def max_pool_2x2(x: jax.Array) -> jax.Array:
    """2x2 max-pool with stride 2, [B, H, W, C] -> [B, H / 2, W / 2, C]: the paper's pooling."""
    return nn.max_pool(x, (2, 2), strides=(2, 2))


def _kernels(cpu: bool | None):
    """(2x2 max-pool, conv for the heads' 1- and 2-output last layers): the CPU backend's own
    (``cpu_kernels``) when ``cpu``, else the plain ones; None decides by the backend."""
    if cpu_kernels.enabled() if cpu is None else cpu:
        return cpu_kernels.max_pool_2x2, cpu_kernels.conv_few_outputs
    return max_pool_2x2, None


def l2_normalize(x: jax.Array, axis: int = -1) -> jax.Array:
    return x / jnp.sqrt(jnp.maximum(jnp.sum(x * x, axis=axis, keepdims=True), 1e-12))


def _zero_mean_init(scale: float):
    """LeCun-normal kernels with ``scale`` x the variance, centred over their inputs.

    The head's input is a leaky ReLU output with a positive mean; centring each output channel's
    kernel removes the random offset that mean would add, so outputs start centred on 0.
    """
    base = nn.initializers.variance_scaling(scale, "fan_in", "truncated_normal")

    def init(key, shape, dtype=jnp.float32):
        w = base(key, shape, dtype)
        return w - jnp.mean(w, axis=(0, 1, 2), keepdims=True)

    return init


def _conv_bn_act(
    x, channels, *, train, config, dtype, kernel=(3, 3), strides=1, padding="SAME", act=True
):
    """3x3 conv, BatchNorm and leaky ReLU: the block every layer of both backbones is made of."""
    x = nn.Conv(channels, kernel, strides=strides, padding=padding, dtype=dtype)(x)
    x = nn.BatchNorm(
        use_running_average=not train, momentum=config.batch_norm_momentum, dtype=dtype
    )(x)
    return nn.leaky_relu(x, config.leaky_relu_slope) if act else x


class FastBackbone(nn.Module):
    """A backbone at about a seventh of the paper's FLOPs (its section 6 lists the components).

    Widths c1, c2, c4, c8 = ``config.backbone_channels`` at resolutions 1, 1/2, 1/4, 1/8. As
    in XFeat and ALIKE, the high resolutions get few channels (a 3x3 conv costs pixels x c_in x
    c_out) and depth goes where pixels are few: one conv at 1/1 and 1/2, a conv and a residual
    block at 1/4 and 1/8. Downsampling is the paper's 2x2 max-pool, not a strided conv, so that
    every 1/8 feature stays centred on its cell (pixel 8c + 3.5, module docstring); a stride-2
    3x3 "SAME" conv shifts the grid by half an input pixel per level.

    No coarser level: two earlier versions upsampled a 1/16 residual block into the descriptor
    head (XFeat's pyramid fusion) and trained descriptors that told cells apart by where they
    sit in the 128x160 training crop, reading the zero padding through a receptive field of
    about 200 px, instead of by what they show. On crops they worked; on larger images, where
    most cells are far from any border, the descriptors collapsed (mean cosine between cells of
    one image 0.46 at 480x640) and held-out viewpoint pairs matched at MS 0.05. The receptive
    field here is the paper network's (about 100 px) and the outputs are exactly
    translation-equivariant in steps of one cell away from the border (experiments/notes/choices.md,
    "The fast network").

    images [B, H, W, 3] (normalised) -> (full [B, H, W, c1], cells [B, H/8, W/8, c8]): the
    full-resolution features that the score and position heads read through a patch conv (the
    paper's "skip connections from higher resolution"), and the cell features.
    """

    config: ModelConfig
    # The CPU backend's kernels (``cpu_kernels``): None uses them on CPU only.
    use_cpu_kernels: bool | None = None

    @nn.compact
    def __call__(self, x: jax.Array, train: bool) -> tuple[jax.Array, jax.Array]:
        cfg = self.config
        pool, _ = _kernels(self.use_cpu_kernels)
        block = functools.partial(_conv_bn_act, train=train, config=cfg, dtype=jnp.dtype(cfg.dtype))

        def residual(x):
            y = block(block(x, x.shape[-1]), x.shape[-1], act=False)
            return nn.leaky_relu(x + y, cfg.leaky_relu_slope)

        c1, c2, c4, c8 = cfg.backbone_channels
        full = block(x, c1)
        x = block(pool(full), c2)
        x = residual(block(pool(x), c4))
        return full, residual(block(pool(x), c8))


class UnsuperPoint(nn.Module):
    """Backbone + score, position and descriptor heads (paper Fig. 1, section 2).

    Input: images [B, H, W, 3] float in [0, 1], H and W multiples of 8.
    Output: ``Predictions`` with a leading batch axis; with ``sparse_descriptors``, (Predictions
    without descriptors, the descriptor head's hidden features [B, H/8, W/8, C], anchors
    [B, M, 2]: where each cell's descriptor is read, its keypoint or, without
    ``interpolate_descriptors``, its centre), from which :func:`describe_points` computes chosen
    points' descriptors.
    """

    config: ModelConfig = ModelConfig()
    # The CPU backend's kernels (``cpu_kernels``, same results): None uses them on CPU only.
    use_cpu_kernels: bool | None = None
    # Inference that keeps few points: skip the descriptor head's last convolution and return
    # its input, for :func:`describe` at the kept points.
    sparse_descriptors: bool = False

    @nn.compact
    def __call__(
        self, images: jax.Array, train: bool = False
    ) -> Predictions | tuple[Predictions, jax.Array, jax.Array]:
        cfg = self.config
        pool, few_outputs_conv = _kernels(self.use_cpu_kernels)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"expected images [B, H, W, 3], got shape {tuple(images.shape)}")
        batch, height, width, _ = images.shape
        check_image_size(height, width)
        dtype = jnp.dtype(cfg.dtype)
        conv_bn_act = functools.partial(_conv_bn_act, train=train, config=cfg, dtype=dtype)

        x = ((images - _MEAN) / _STD).astype(dtype)
        if cfg.backbone == "vgg":
            for i, channels in enumerate(cfg.backbone_channels):
                x = conv_bn_act(x, channels)
                if i in (1, 3, 5):
                    x = pool(x)
            point_input = descriptor_input = x
        else:
            full, cells = FastBackbone(cfg, self.use_cpu_kernels, name="backbone")(x, train)
            descriptor_input = cells
            # Each cell's own 8x8 full-resolution features, as one patch conv: the score and
            # the position inside the cell read the pixels they localise.
            patch = conv_bn_act(
                full, cfg.head_channels, kernel=(CELL, CELL), strides=CELL, padding="VALID"
            )
            point_input = jnp.concatenate([cells, patch], axis=-1)

        def head(
            inputs,
            out_channels,
            name,
            init_scale=1.0,
            hidden_channels=cfg.head_channels,
            hidden_kernel=3,
        ):
            hidden = conv_bn_act(inputs, hidden_channels, kernel=(hidden_kernel, hidden_kernel))
            if name == "descriptor" and self.sparse_descriptors:
                return hidden
            out = nn.Conv(
                out_channels,
                (3, 3),
                dtype=dtype,
                kernel_init=_zero_mean_init(init_scale),
                name=name,
                conv_general_dilated=few_outputs_conv if out_channels <= 2 else None,
            )(hidden)
            return out.astype(jnp.float32)

        cells_h, cells_w = height // CELL, width // CELL
        m = cells_h * cells_w
        scores = nn.sigmoid(head(point_input, 1, "score")).reshape(batch, m)
        relative = nn.sigmoid(head(point_input, 2, "position", cfg.position_init_scale)).reshape(
            batch, m, 2
        )
        descriptor_map = head(
            descriptor_input,
            cfg.descriptor_dim,
            "descriptor",
            hidden_channels=cfg.descriptor_head_channels or cfg.head_channels,
            hidden_kernel=cfg.descriptor_head_kernel,
        )
        keypoints = relative_to_pixels(relative, cells_h, cells_w)
        if self.sparse_descriptors:
            centres = relative_to_pixels(jnp.full_like(relative, 0.5), cells_h, cells_w)
            anchors = keypoints if cfg.interpolate_descriptors else centres
            return Predictions(scores, relative, keypoints, None), descriptor_map, anchors
        if cfg.interpolate_descriptors:
            descriptors = jax.vmap(bilinear_sample)(descriptor_map, keypoints)
        else:
            descriptors = descriptor_map.reshape(batch, m, cfg.descriptor_dim)
        # The hinge margins m_p = 1, m_n = 0.2 (section 4.3) are cosine similarities, as in
        # SuperPoint whose descriptor loss the paper adopts: unit-length descriptors.
        return Predictions(scores, relative, keypoints, l2_normalize(descriptors))


# Compiled: dispatched op by op, initialising even the tests' small network took 15 s of a run's
# start-up on a 2-core CPU; compiled it takes 8 s once, then comes from the compilation cache.
@functools.partial(jax.jit, static_argnames=("config", "height", "width"))
def init_variables(key: jax.Array, config: ModelConfig = ModelConfig(), height=64, width=64):
    """Parameters and BatchNorm statistics: ``{"params": ..., "batch_stats": ...}``.

    The network is fully convolutional, so the variables do not depend on the image size.
    """
    model = UnsuperPoint(config)
    return model.init(key, jnp.zeros((1, height, width, 3), jnp.float32), train=False)
