"""Known-answer tests of usp_jax.core.augment."""

import cv2
import jax
import numpy as np
import pytest

from usp_jax.core.augment import PhotometricConfig, gaussian_blur, photometric_augment

ALWAYS = dict(p_brightness=1.0, p_contrast=1.0, p_saturation=1.0, p_noise=1.0, p_blur=1.0)
ZERO = dict(brightness=0.0, contrast=0.0, saturation=0.0, noise_std=0.0, blur_sigma=0.0)


def image():
    return np.random.default_rng(0).uniform(0.05, 0.95, (32, 48, 3)).astype(np.float32)


def augment_batch(config, images, seed=0):
    keys = jax.random.split(jax.random.PRNGKey(seed), len(images))
    return np.asarray(
        jax.jit(jax.vmap(lambda key, x: photometric_augment(key, x, config)))(keys, images)
    )


def test_zero_magnitudes_are_identity():
    images = np.stack([image()] * 4)
    np.testing.assert_array_equal(
        augment_batch(PhotometricConfig(**ZERO, **ALWAYS), images), images
    )


def test_output_in_unit_range_and_changes_image():
    images = np.stack([image()] * 6)
    images[0] = 1.0  # saturated input must stay saturated, not exceed 1
    augmented = augment_batch(PhotometricConfig(**ALWAYS), images)
    assert augmented.shape == images.shape and augmented.dtype == np.float32
    assert augmented.min() >= 0.0 and augmented.max() <= 1.0
    assert np.all(np.abs(augmented - images).mean(axis=(1, 2, 3))[1:] > 1e-3)
    assert (
        len(np.unique(augmented[1:].mean(axis=(1, 2, 3)))) == 5
    )  # each key draws its own magnitudes


def test_brightness_alone_scales_every_pixel_by_one_factor():
    config = PhotometricConfig(**{**ZERO, "brightness": 0.3}, **ALWAYS)
    source = image() * 0.7  # stays below 1 after a gain of at most 1.3: no clipping
    augmented = augment_batch(config, source[None])[0]
    gain = augmented / source
    np.testing.assert_allclose(gain, gain.flat[0], rtol=1e-5)
    assert 0.7 <= gain.flat[0] <= 1.3 and gain.flat[0] != 1.0


def test_gamma_alone_raises_every_pixel_to_one_power_within_its_interval():
    config = PhotometricConfig(**{**ZERO, "gamma": 1.0}, p_gamma=1.0)
    sources = np.stack([image()] * 8)
    augmented = augment_batch(config, sources)
    for source, result in zip(sources, augmented):
        exponent = np.log(result) / np.log(source)
        np.testing.assert_allclose(exponent, exponent.flat[0], rtol=1e-4)
        assert 0.5 <= exponent.flat[0] <= 2.0
        np.testing.assert_allclose(result, source ** exponent.flat[0], rtol=1e-5)
    assert len(np.unique(np.round(augmented.mean(axis=(1, 2, 3)), 6))) == 8


def test_adding_gamma_leaves_the_other_operations_draws_unchanged():
    # A gamma that is never applied must give what a config without gamma gives, bit for bit:
    # the runs trained before gamma existed stay reproducible.
    images = np.stack([image()] * 4)
    without = augment_batch(PhotometricConfig(**ALWAYS), images, seed=3)
    never_applied = augment_batch(
        PhotometricConfig(**ALWAYS, gamma=1.0, p_gamma=0.0), images, seed=3
    )
    np.testing.assert_array_equal(never_applied, without)
    applied = augment_batch(PhotometricConfig(**ALWAYS, gamma=1.0, p_gamma=1.0), images, seed=3)
    assert np.abs(applied - without).mean() > 1e-3


def test_gaussian_blur_matches_cv2():
    source = image()
    for sigma in (0.5, 1.3):
        radius = int(np.ceil(3 * sigma))
        expected = cv2.GaussianBlur(source, (2 * radius + 1, 2 * radius + 1), sigma)
        np.testing.assert_allclose(
            gaussian_blur(source, np.float32(sigma), radius), expected, atol=1e-5
        )
    np.testing.assert_array_equal(gaussian_blur(source, np.float32(0.0), 3), source)


def test_rejects_non_rgb_image():
    with pytest.raises(ValueError, match=r"\(32, 48\)"):
        photometric_augment(jax.random.PRNGKey(0), image()[..., 0])


def test_config_rejects_out_of_range_values():
    with pytest.raises(ValueError, match="contrast"):
        PhotometricConfig(contrast=1.5)
    with pytest.raises(ValueError, match="p_noise"):
        PhotometricConfig(p_noise=2.0)
    with pytest.raises(ValueError, match="gamma"):
        PhotometricConfig(gamma=-0.5)
    assert (
        PhotometricConfig(blur_sigma=1.0).blur_radius == 3
        and PhotometricConfig(**ZERO).blur_radius == 0
    )
