"""A PyTorch CPU reference of UnsuperPoint's training step and inference, for side-by-side timing.

Not part of the library (``pip install torch==2.13.0`` gives the CPU build). It is the same
network as ``usp_jax.core.model.UnsuperPoint`` layer for layer (``load_flax_variables`` copies a Flax
checkpoint into it, and ``bench_train.py --check`` compares the two), the same losses as
``usp_jax.core.losses.total_loss`` and the same augmentation as ``usp_jax.training.step.make_branches``, written
the way a PyTorch user would: NCHW tensors in channels-last memory (oneDNN's fast path), built-in
``grid_sample`` for warps and descriptor interpolation, ``torch.optim.Adam``.

The random homographies are drawn by the JAX sampler and passed in (drawing 64 candidate 3x3
matrices per image is negligible work, and identical homographies make the check exact); the warp,
photometric augmentation, forward of both branches, losses, backward and Adam update all run in
PyTorch inside the timed step.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from usp_jax import config as config_lib
from usp_jax.core.augment import PhotometricConfig
from usp_jax.core.losses import LossConfig
from usp_jax.core.model import CELL, ModelConfig

_MEAN, _STD = 0.5, 0.225
_LUMA = (0.299, 0.587, 0.114)


class ConvBnAct(nn.Sequential):
    def __init__(self, cin: int, cout: int, config: ModelConfig):
        # Flax's BatchNorm momentum m keeps m of the old statistics; PyTorch's keeps 1 - m.
        super().__init__(
            nn.Conv2d(cin, cout, 3, padding=1),
            nn.BatchNorm2d(cout, eps=1e-5, momentum=1 - config.batch_norm_momentum),
            nn.LeakyReLU(config.leaky_relu_slope),
        )


class TorchUnsuperPoint(nn.Module):
    """Backbone + score, position and descriptor heads, as usp_jax.core.model.UnsuperPoint.

    forward: images [B, 3, H, W] float in [0, 1] -> (scores [B, M], relative [B, M, 2],
    keypoints [B, M, 2], descriptors [B, M, F]), M = (H / 8) * (W / 8) in row-major cell order.
    """

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        layers, cin = [], 3
        for i, cout in enumerate(config.backbone_channels):
            layers.append(ConvBnAct(cin, cout, config))
            cin = cout
            if i in (1, 3, 5):
                layers.append(nn.MaxPool2d(2))
        self.backbone = nn.Sequential(*layers)

        def head(out):
            hidden = ConvBnAct(cin, config.head_channels, config)
            return nn.Sequential(hidden, nn.Conv2d(config.head_channels, out, 3, padding=1))

        self.score = head(1)
        self.position = head(2)
        self.descriptor = head(config.descriptor_dim)

    def forward(self, images: torch.Tensor):
        x = self.backbone((images - _MEAN) / _STD)
        batch, _, cells_h, cells_w = x.shape
        m = cells_h * cells_w
        scores = torch.sigmoid(self.score(x)).reshape(batch, m)
        relative = torch.sigmoid(self.position(x)).permute(0, 2, 3, 1).reshape(batch, m, 2)
        rows, cols = torch.meshgrid(torch.arange(cells_h), torch.arange(cells_w), indexing="ij")
        cells = torch.stack([cols.reshape(-1), rows.reshape(-1)], -1).to(relative.dtype)
        keypoints = (cells + relative) * CELL - 0.5
        descriptor_map = self.descriptor(x)
        if self.config.interpolate_descriptors:
            # grid_sample's align_corners=False puts -1 and 1 at the outer edges of the map, so
            # pixel x reads feature column (x + 0.5) / 8 - 0.5, the convention of usp_jax.core.model;
            # "border" repeats the border cells like its clip.
            size = torch.tensor([cells_w, cells_h], dtype=keypoints.dtype)
            grid = (2 * (keypoints + 0.5) / (CELL * size) - 1)[:, None]
            sampled = F.grid_sample(
                descriptor_map, grid, mode="bilinear", padding_mode="border", align_corners=False
            )
            descriptors = sampled[:, :, 0].transpose(1, 2)
        else:
            descriptors = descriptor_map.flatten(2).transpose(1, 2)
        norm = torch.sqrt(torch.clamp((descriptors * descriptors).sum(-1, keepdim=True), min=1e-12))
        return scores, relative, keypoints, descriptors / norm


def load_flax_variables(model: TorchUnsuperPoint, variables) -> None:
    """Copies Flax ``{"params", "batch_stats"}`` of usp_jax.core.model.UnsuperPoint into ``model``."""
    params, stats = variables["params"], variables["batch_stats"]
    blocks = [m for m in model.backbone if isinstance(m, ConvBnAct)]
    blocks += [model.score[0], model.position[0], model.descriptor[0]]
    pairs = [(block[0], block[1], f"Conv_{i}", f"BatchNorm_{i}") for i, block in enumerate(blocks)]
    outputs = [
        (model.score[1], "score"),
        (model.position[1], "position"),
        (model.descriptor[1], "descriptor"),
    ]

    def tensor(x):
        return torch.from_numpy(np.array(x, np.float32))

    with torch.no_grad():
        for conv, bn, conv_name, bn_name in pairs:
            outputs.append((conv, conv_name))
            bn.weight.copy_(tensor(params[bn_name]["scale"]))
            bn.bias.copy_(tensor(params[bn_name]["bias"]))
            bn.running_mean.copy_(tensor(stats[bn_name]["mean"]))
            bn.running_var.copy_(tensor(stats[bn_name]["var"]))
        for conv, name in outputs:
            conv.weight.copy_(tensor(params[name]["kernel"]).permute(3, 2, 0, 1))  # HWIO -> OIHW
            conv.bias.copy_(tensor(params[name]["bias"]))


# ------------------------------------------------------------------------------------------------
# Augmentation (usp_jax.core.geometry.warp_image, usp_jax.core.augment.photometric_augment)


def warp_images(images: torch.Tensor, homographies: torch.Tensor) -> torch.Tensor:
    """Bilinear warp of [B, 3, H, W] by [B, 3, 3] (image -> output), zeros outside."""
    _, _, height, width = images.shape
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=images.dtype),
        torch.arange(width, dtype=images.dtype),
        indexing="ij",
    )
    grid = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)
    source = grid @ torch.linalg.inv(homographies).transpose(1, 2)  # [B, HW, 3]
    source = source[..., :2] / source[..., 2:]
    # align_corners=True puts -1 and 1 at the centres of the border pixels.
    scale = torch.tensor([width - 1, height - 1], dtype=images.dtype)
    normalised = (2 * source / scale - 1).reshape(-1, height, width, 2)
    return F.grid_sample(
        images, normalised, mode="bilinear", padding_mode="zeros", align_corners=True
    )


def _gaussian_blur(images: torch.Tensor, sigma: torch.Tensor, radius: int) -> torch.Tensor:
    """Separable blur of [B, 3, H, W] with a per-image sigma [B], reflecting at the border."""
    batch, channels, height, width = images.shape
    taps = torch.arange(-radius, radius + 1, dtype=images.dtype)
    weights = torch.exp(-0.5 * (taps / torch.clamp(sigma, min=1e-3)[:, None]) ** 2)
    weights = (weights / weights.sum(1, keepdim=True)).repeat_interleave(channels, 0)
    x = F.pad(images.reshape(1, batch * channels, height, width), (radius,) * 4, mode="reflect")
    x = F.conv2d(x, weights[:, None, :, None], groups=batch * channels)
    x = F.conv2d(x, weights[:, None, None, :], groups=batch * channels)
    return x.reshape(batch, channels, height, width)


def photometric_augment(
    images: torch.Tensor, config: PhotometricConfig, generator: torch.Generator
) -> torch.Tensor:
    """Brightness, contrast, saturation, blur and noise of [B, 3, H, W], as usp_jax.core.augment."""
    batch = images.shape[0]

    def draw(low, high, probability, neutral):
        magnitude = low + (high - low) * torch.rand(batch, generator=generator)
        applied = torch.rand(batch, generator=generator) < probability
        return torch.where(applied, magnitude, torch.full_like(magnitude, neutral))

    brightness = draw(1 - config.brightness, 1 + config.brightness, config.p_brightness, 1.0)
    contrast = draw(1 - config.contrast, 1 + config.contrast, config.p_contrast, 1.0)
    saturation = draw(1 - config.saturation, 1 + config.saturation, config.p_saturation, 1.0)
    blur_sigma = draw(0.0, config.blur_sigma, config.p_blur, 0.0)
    noise_std = draw(0.0, config.noise_std, config.p_noise, 0.0)
    luma = torch.tensor(_LUMA, dtype=images.dtype)[None, :, None, None]

    def per_image(v):
        return v[:, None, None, None]

    x = images * per_image(brightness)
    grey = (x * luma).sum(1, keepdim=True)
    x = x * per_image(contrast) + grey.mean((2, 3), keepdim=True) * per_image(1 - contrast)
    grey = (x * luma).sum(1, keepdim=True)
    x = x * per_image(saturation) + grey * per_image(1 - saturation)
    x = _gaussian_blur(x, blur_sigma, config.blur_radius)
    x = x + per_image(noise_std) * torch.randn(x.shape, generator=generator)
    return torch.clamp(x, 0.0, 1.0)


# ------------------------------------------------------------------------------------------------
# Losses (usp_jax.core.losses, usp_jax.core.correspondence)


def _safe_sqrt(sq: torch.Tensor) -> torch.Tensor:
    positive = sq > 1e-12
    return torch.where(
        positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), torch.zeros_like(sq)
    )


def _warp_points(homographies: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    projected = xy @ homographies[:, :, :2].transpose(1, 2) + homographies[:, None, :, 2]
    w = projected[..., 2:]
    finite = w.abs() > float(np.finfo(np.float32).eps)
    return torch.where(
        finite,
        projected[..., :2] / torch.where(finite, w, torch.ones_like(w)),
        torch.zeros_like(projected[..., :2]),
    )


def _inside(xy: torch.Tensor, height: int, width: int, border: float) -> torch.Tensor:
    x, y = xy[..., 0], xy[..., 1]
    return (x >= border) & (x <= width - 1 - border) & (y >= border) & (y <= height - 1 - border)


def _uniform(values: torch.Tensor) -> torch.Tensor:
    n = values.shape[-1]
    line = torch.arange(n, dtype=values.dtype) / max(n - 1, 1)
    return ((torch.sort(values, -1).values - line) ** 2).sum(-1)


def _decorrelation(descriptors: torch.Tensor, mode: str) -> torch.Tensor:
    centered = descriptors - descriptors.mean(1, keepdim=True)
    norms = torch.sqrt(torch.clamp((centered**2).sum(1), min=1e-12))
    r = centered.transpose(1, 2) @ centered / (norms[:, :, None] * norms[:, None, :])
    off = r * (1 - torch.eye(r.shape[-1], dtype=r.dtype))
    return (off**2).sum((1, 2)) if mode == "squared" else off.sum((1, 2))


def total_loss(
    pred_a,
    pred_b,
    homographies: torch.Tensor,
    height: int,
    width: int,
    config: LossConfig = LossConfig(),
) -> torch.Tensor:
    """usp_jax.core.losses.total_loss, batched: per-pair eq. 4 averaged over the batch."""
    scores_a, relative_a, keypoints_a, desc_a = pred_a
    scores_b, relative_b, keypoints_b, desc_b = pred_b
    a_in_b = _warp_points(homographies, keypoints_a)
    inverse = torch.linalg.inv(homographies)
    b_in_a = _warp_points(inverse / inverse[:, 2:3, 2:3], keypoints_b)
    valid_a = _inside(a_in_b, height, width, -0.5)
    valid_b = _inside(b_in_a, height, width, -0.5)
    sq = (
        (a_in_b**2).sum(-1)[:, :, None]
        + (keypoints_b**2).sum(-1)[:, None, :]
        - 2 * a_in_b @ keypoints_b.transpose(1, 2)
    )
    distances = _safe_sqrt(sq)
    search = torch.where(
        valid_b[:, None, :], distances.detach(), torch.full_like(distances, np.inf)
    )
    nearest = search.argmin(2)
    gathered = torch.gather(keypoints_b, 1, nearest[..., None].expand(-1, -1, 2))
    d = _safe_sqrt(((a_in_b - gathered) ** 2).sum(-1))
    paired = (valid_a & torch.gather(valid_b, 1, nearest) & (d <= config.eps_correspond)).float()

    # Eqs. 5-9.
    paired_scores_b = torch.gather(scores_b, 1, nearest)
    k = paired.sum(1)
    mean_d = (paired * d).sum(1) / torch.clamp(k, min=1.0)
    position = (paired * d).sum(1)
    score = (paired * (scores_a - paired_scores_b) ** 2).sum(1)
    joint = 0.5 * (scores_a + paired_scores_b)
    usp_term = (paired * joint * (d - mean_d[:, None])).sum(1)
    usp = config.alpha_position * position + config.alpha_score * score + usp_term

    uni_xy = sum(_uniform(r[..., axis]) for r in (relative_a, relative_b) for axis in (0, 1))
    uni_score = _uniform(scores_a) + _uniform(scores_b)
    m = scores_a.shape[1]
    score_mean = m * ((scores_a.mean(1) - 0.5) ** 2 + (scores_b.mean(1) - 0.5) ** 2)

    c = (distances.detach() <= config.eps_descriptor).float()
    mask = (valid_a[:, :, None] & valid_b[:, None, :]).float()
    sim = desc_a @ desc_b.transpose(1, 2)
    positive = config.lambda_d * c * torch.clamp(config.margin_positive - sim, min=0.0)
    negative = (1 - c) * torch.clamp(sim - config.margin_negative, min=0.0)
    desc = (mask * (positive + negative)).sum((1, 2))
    decorr = _decorrelation(desc_a, config.decorrelation) + _decorrelation(
        desc_b, config.decorrelation
    )
    per_pair = (
        config.alpha_usp * usp
        + config.alpha_uni_xy * uni_xy
        + config.alpha_score_mean * score_mean
        + config.alpha_uni_score * uni_score
        + config.alpha_desc * desc
        + config.alpha_decorr * decorr
    )
    return per_pair.mean()


# ------------------------------------------------------------------------------------------------
# Training step and inference


class TrainStep:
    """One optimisation step on a uint8 batch, as usp_jax.training.step.train_step (without its
    finiteness guard): branches, one forward over both, the losses, backward, Adam."""

    def __init__(self, config: config_lib.Config, seed: int = 0):
        self.config = config
        self.model = TorchUnsuperPoint(config.model).to(memory_format=torch.channels_last)
        self.model.train()
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.optim.learning_rate)
        self.generator = torch.Generator().manual_seed(seed)

    def branches(self, images: torch.Tensor, homographies: torch.Tensor):
        """images: uint8 [B, H, W, 3] -> (branch A, branch B), float [B, 3, H, W] channels-last."""
        x = (
            images.permute(0, 3, 1, 2)
            .float()
            .div_(255)
            .contiguous(memory_format=torch.channels_last)
        )
        warped = warp_images(x, homographies)
        images_a = photometric_augment(x, self.config.photometric, self.generator)
        images_b = photometric_augment(warped, self.config.photometric, self.generator)
        return images_a, images_b

    def loss(
        self, images_a: torch.Tensor, images_b: torch.Tensor, homographies: torch.Tensor
    ) -> torch.Tensor:
        batch, _, height, width = images_a.shape
        both = torch.cat([images_a, images_b]).contiguous(memory_format=torch.channels_last)
        pred = self.model(both)
        pred_a = [p[:batch] for p in pred]
        pred_b = [p[batch:] for p in pred]
        return total_loss(pred_a, pred_b, homographies, height, width, self.config.loss)

    def __call__(self, images: torch.Tensor, homographies: torch.Tensor) -> torch.Tensor:
        loss = self.loss(*self.branches(images, homographies), homographies)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return loss.detach()


def detect(model: TorchUnsuperPoint, images: torch.Tensor, top_n: int):
    """Inference: float [B, 3, H, W] -> the top_n scores, keypoints and descriptors per image."""
    with torch.inference_mode():
        scores, _, keypoints, descriptors = model(images)
        top, index = torch.topk(scores, min(top_n, scores.shape[1]), dim=1)

        def take(x):
            return torch.gather(x, 1, index[..., None].expand(-1, -1, x.shape[-1]))

        return top, take(keypoints), take(descriptors)
