"""Non-spatial (photometric) augmentation applied independently to each branch (paper sections 3 and 5).

Section 5: "standard non-spatial augmentations for each branch such as noise, blur and brightness. The
magnitude of each augmentation was uniformly distributed within restricted intervals." Every operation
here draws its magnitude uniformly from an interval of the config and is applied with a probability.
Pure jnp, jit-/vmap-able (vmap over keys and images for a batch); the config is static.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

# ITU-R BT.601 luma, the grey level torchvision's and PIL's colour jitter blend with.
_LUMA = (0.299, 0.587, 0.114)


@dataclasses.dataclass(frozen=True)
class PhotometricConfig:
    """Intervals and probabilities of the photometric augmentation; all-zero magnitudes give the identity.

    Defaults are milder than KP2D's colour jitter (brightness .5, contrast .5, saturation .2): both branches
    are augmented independently, so their photometric gap is about twice one draw.

    Attributes:
      gamma: image raised to the power 2 ** g, g ~ U(-gamma, gamma): a camera's response curve or a
        changed exposure, which brightens or darkens the shadows more than the highlights (the
        other operations are linear); >= 0, 0 is off (the default, so configs written before it
        draw exactly what they drew then).
      brightness: image multiplied by b ~ U(1 - brightness, 1 + brightness); in [0, 1].
      contrast: image blended with its mean grey level, factor c ~ U(1 - contrast, 1 + contrast); in [0, 1].
      saturation: image blended with its grey image, factor s ~ U(1 - saturation, 1 + saturation); in [0, 1].
      noise_std: additive Gaussian noise with standard deviation ~ U(0, noise_std) (image in [0, 1]).
      blur_sigma: Gaussian blur with sigma ~ U(0, blur_sigma) pixels; the separable kernel has the fixed
        radius ceil(3 * blur_sigma) so that shapes do not depend on the draw.
      p_gamma, p_brightness, p_contrast, p_saturation, p_noise, p_blur: probability of applying each
        operation.
    """

    gamma: float = 0.0
    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.2
    noise_std: float = 0.03
    blur_sigma: float = 1.0
    p_gamma: float = 0.5
    p_brightness: float = 0.5
    p_contrast: float = 0.5
    p_saturation: float = 0.5
    p_noise: float = 0.5
    p_blur: float = 0.5

    def __post_init__(self):
        for name in ("brightness", "contrast", "saturation"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"PhotometricConfig.{name}={getattr(self, name)!r} must lie in [0, 1]"
                )
        for name in ("gamma", "noise_std", "blur_sigma"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"PhotometricConfig.{name}={getattr(self, name)!r} must be >= 0")
        for name in ("p_gamma", "p_brightness", "p_contrast", "p_saturation", "p_noise", "p_blur"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"PhotometricConfig.{name}={getattr(self, name)!r} is not a probability"
                )

    @property
    def blur_radius(self) -> int:
        """Half-width of the blur kernel, enough for three sigmas of the largest blur."""
        return math.ceil(3 * self.blur_sigma)


def gaussian_blur(image: jax.Array, sigma: jax.Array, radius: int) -> jax.Array:
    """Separable Gaussian blur of an [H, W, C] image with a [2 * radius + 1] kernel, reflecting at the border.

    Equals cv2.GaussianBlur(image, (2r+1, 2r+1), sigma) (BORDER_REFLECT_101). `sigma` may be traced;
    sigma = 0 is the identity (the kernel degenerates to a unit impulse). Returns [H, W, C].
    """
    taps = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
    # A tiny floor keeps exp finite at sigma = 0 while still zeroing every tap but the centre.
    weights = jnp.exp(-0.5 * (taps / jnp.maximum(sigma, 1e-3)) ** 2)
    weights = weights / weights.sum()
    height, width, _ = image.shape
    padded = jnp.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="reflect")
    # Weighted sums of shifted views, rows then columns: XLA fuses each into one pass, where a
    # depthwise convolution (a few taps, 3 channels) runs an order of magnitude slower on CPU.
    rows = sum(weights[k] * padded[k : k + height] for k in range(2 * radius + 1))
    return sum(weights[k] * rows[:, k : k + width] for k in range(2 * radius + 1))


def photometric_augment(
    key: jax.Array, image: jax.Array, config: PhotometricConfig = PhotometricConfig()
) -> jax.Array:
    """Random gamma, brightness, contrast, saturation, blur and noise, in that order, then clipping to [0, 1].

    The response curve and colour changes come first and sensor noise last, the order in which they
    arise in a camera; the single clip at the end keeps the colour blends exact (a neutral factor leaves
    the image bit-identical).

    Args:
      key: PRNG key.
      image: [H, W, 3] float RGB in [0, 1].
      config: intervals and probabilities (static).
    Returns:
      float32 [H, W, 3] in [0, 1].
    """
    image = jnp.asarray(image, jnp.float32)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(
            f"photometric_augment expects an [H, W, 3] image, got shape {tuple(image.shape)}"
        )
    keys = iter(jax.random.split(key, 6))

    def draw(low: float, high: float, probability: float, neutral: float) -> jax.Array:
        """Magnitude ~ U(low, high) with the given probability, else the neutral value."""
        key_magnitude, key_apply = jax.random.split(next(keys))
        magnitude = jax.random.uniform(key_magnitude, minval=low, maxval=high)
        return jnp.where(jax.random.uniform(key_apply) < probability, magnitude, neutral)

    brightness = draw(1 - config.brightness, 1 + config.brightness, config.p_brightness, 1.0)
    contrast = draw(1 - config.contrast, 1 + config.contrast, config.p_contrast, 1.0)
    saturation = draw(1 - config.saturation, 1 + config.saturation, config.p_saturation, 1.0)
    blur_sigma = draw(0.0, config.blur_sigma, config.p_blur, 0.0)
    noise_std = draw(0.0, config.noise_std, config.p_noise, 0.0)
    luma = jnp.array(_LUMA, jnp.float32)

    if config.gamma > 0:
        # A key of its own rather than a seventh split of `key`: configs without gamma keep the
        # random stream, hence the crops' augmentations, of the runs trained before it existed.
        key_gamma = jax.random.fold_in(key, 7)
        exponent = jax.random.uniform(key_gamma, minval=-config.gamma, maxval=config.gamma)
        applied = jax.random.uniform(jax.random.fold_in(key_gamma, 1)) < config.p_gamma
        # Gamma needs a non-negative base; inputs are promised in [0, 1], clip guards the rest.
        image = jnp.where(applied, jnp.clip(image, 0.0, 1.0) ** (2.0**exponent), image)
    image = image * brightness
    # Blends as x * f + reference * (1 - f) rather than (x - reference) * f + reference: exact for f = 1.
    image = image * contrast + (image @ luma).mean() * (1 - contrast)
    image = image * saturation + (image @ luma)[..., None] * (1 - saturation)
    image = gaussian_blur(image, blur_sigma, config.blur_radius)
    image = image + noise_std * jax.random.normal(next(keys), image.shape)
    return jnp.clip(image, 0.0, 1.0)
