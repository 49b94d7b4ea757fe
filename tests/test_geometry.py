"""Known-answer tests of usp_jax.core.geometry against OpenCV and closed-form cases."""

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from usp_jax.core.geometry import (
    HomographyConfig,
    compose_homographies,
    invert_homography,
    points_inside,
    sample_homography,
    sample_window_homography,
    warp_image,
    warp_points,
    window_origin,
)

HEIGHT, WIDTH = 48, 64
CORNERS = np.float32([[0, 0], [WIDTH - 1, 0], [WIDTH - 1, HEIGHT - 1], [0, HEIGHT - 1]])


def random_homographies(count, seed=0, jitter=12.0):
    """Homographies that move each image corner by up to `jitter` pixels, float64 [count, 3, 3]."""
    rng = np.random.default_rng(seed)
    return np.stack(
        [
            cv2.getPerspectiveTransform(
                CORNERS, CORNERS + rng.uniform(-jitter, jitter, (4, 2)).astype(np.float32)
            )
            for _ in range(count)
        ]
    )


def smooth_image():
    """[48, 64, 3] float32 image whose gradient stays below ~0.1 per pixel (test_warp_image_matches_cv2)."""
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    channels = [0.5 + 0.4 * np.sin(xs / 6 + c) * np.cos(ys / 5 - c) for c in range(3)]
    return np.stack(channels, -1).astype(np.float32)


def cv2_warp(image, homography, size=(WIDTH, HEIGHT)):
    return cv2.warpPerspective(
        image,
        homography,
        size,
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def test_warp_points_matches_cv2():
    rng = np.random.default_rng(1)
    points = rng.uniform(-20, 80, (100, 2)).astype(np.float32)
    for homography in random_homographies(5):
        expected = cv2.perspectiveTransform(points[None], homography)[0]
        np.testing.assert_allclose(warp_points(homography, points), expected, rtol=1e-5, atol=1e-3)


def test_warp_points_keeps_leading_dimensions():
    homography = random_homographies(1)[0]
    points = np.random.default_rng(2).uniform(0, 60, (2, 3, 5, 2)).astype(np.float32)
    expected = cv2.perspectiveTransform(points.reshape(1, -1, 2), homography).reshape(points.shape)
    np.testing.assert_allclose(warp_points(homography, points), expected, rtol=1e-5, atol=1e-3)


def test_warp_points_at_infinity_returns_origin_like_cv2():
    homography = np.array(
        [[1, 0, 0], [0, 1, 0], [1, 0, 0]], np.float32
    )  # w = x: x = 0 maps to infinity
    points = np.float32([[0, 5], [2, 4]])
    expected = cv2.perspectiveTransform(points[None], homography)[0]
    np.testing.assert_allclose(warp_points(homography, points), expected, atol=1e-6)
    np.testing.assert_array_equal(warp_points(homography, points)[0], [0, 0])
    gradient = jax.grad(lambda xy: warp_points(homography, xy).sum())(jnp.asarray(points))
    assert np.all(np.isfinite(gradient))


def test_warp_image_matches_cv2():
    image = smooth_image()
    for homography in random_homographies(3, seed=3):
        expected = cv2_warp(image, homography)
        warped, valid = warp_image(image, homography)
        assert warped.shape == (HEIGHT, WIDTH, 3) and warped.dtype == jnp.float32
        error = np.abs(np.asarray(warped) - expected)
        # OpenCV rounds sampling positions to 1/32 px: error <= 1/64 px * gradient (< 0.1) per axis.
        assert error[np.asarray(valid)].max() < 2e-3
        # At the border the zero-padded neighbours' weights are rounded the same way.
        assert error.max() < 2e-2


def test_warp_image_valid_mask_matches_warped_ones():
    ones = np.ones((HEIGHT, WIDTH, 1), np.float32)
    for homography in random_homographies(3, seed=4):
        _, valid = warp_image(ones, homography)
        full = cv2_warp(ones, homography) >= 1 - 1e-6
        grid = np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT)), -1).astype(np.float32)
        preimage = cv2.perspectiveTransform(grid.reshape(1, -1, 2), np.linalg.inv(homography))
        x, y = preimage.reshape(grid.shape).transpose(2, 0, 1)
        distance_to_edge = np.minimum.reduce(
            [np.abs(x), np.abs(x - (WIDTH - 1)), np.abs(y), np.abs(y - (HEIGHT - 1))]
        )
        decided = (
            distance_to_edge > 1 / 16
        )  # OpenCV's 1/32-px rounding may flip pixels closer than that
        assert 0 < np.asarray(valid).sum() < valid.size
        np.testing.assert_array_equal(np.asarray(valid)[decided], full[decided])


def test_warp_image_translation_with_other_output_shape():
    image = np.random.default_rng(5).uniform(size=(HEIGHT, WIDTH, 2)).astype(np.float32)
    shift = np.array(
        [[1, 0, 3], [0, 1, 2], [0, 0, 1]], np.float32
    )  # output(x, y) = input(x - 3, y - 2)
    warped, valid = warp_image(image, shift, out_shape=(30, 70))
    assert warped.shape == (30, 70, 2) and valid.shape == (30, 70)
    np.testing.assert_allclose(np.asarray(warped)[2:, 3 : WIDTH + 3], image[:28], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(warped)[:2], 0)
    expected_valid = np.zeros((30, 70), bool)
    expected_valid[2:, 3 : WIDTH + 3] = True
    np.testing.assert_array_equal(valid, expected_valid)


def test_warp_image_rejects_non_rank3_image():
    with pytest.raises(ValueError, match=r"\(48, 64\)"):
        warp_image(np.zeros((HEIGHT, WIDTH), np.float32), np.eye(3))


def test_invert_and_compose_round_trip():
    first, second = random_homographies(2, seed=6)
    np.testing.assert_allclose(
        compose_homographies(first, invert_homography(first)), np.eye(3), atol=1e-5
    )
    np.testing.assert_allclose(
        invert_homography(first),
        np.linalg.inv(first) / np.linalg.inv(first)[2, 2],
        rtol=1e-4,
        atol=1e-6,
    )
    points = np.random.default_rng(7).uniform(0, 60, (20, 2)).astype(np.float32)
    # compose_homographies(second, first) applies `first` first.
    composed = compose_homographies(second, first)
    assert composed[2, 2] == 1
    np.testing.assert_allclose(
        warp_points(composed, points),
        warp_points(second, warp_points(first, points)),
        rtol=1e-5,
        atol=1e-3,
    )
    batch = random_homographies(4, seed=8) * 3.0  # scale must not matter
    np.testing.assert_allclose(
        compose_homographies(batch, invert_homography(batch)),
        np.broadcast_to(np.eye(3), batch.shape),
        atol=1e-5,
    )


def test_points_inside_closed_interval_and_border():
    points = np.float32(
        [[0, 0], [WIDTH - 1, HEIGHT - 1], [-0.01, 5], [5, HEIGHT - 0.99], [2, 2], [1.5, 30]]
    )
    np.testing.assert_array_equal(points_inside(points, HEIGHT, WIDTH), [1, 1, 0, 0, 1, 1])
    np.testing.assert_array_equal(
        points_inside(points, HEIGHT, WIDTH, border=2), [0, 0, 0, 0, 1, 0]
    )


def test_sampled_homographies_keep_output_inside_source():
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    homographies = np.asarray(
        jax.jit(jax.vmap(lambda key: sample_homography(key, HEIGHT, WIDTH)))(keys)
    )
    assert homographies.shape == (64, 3, 3) and homographies.dtype == np.float32
    assert np.all(np.isfinite(homographies)) and np.all(homographies[:, 2, 2] == 1)
    assert np.linalg.cond(homographies.astype(np.float64)).max() < 1e6
    # Every output pixel (not only the corners) comes from inside the source image.
    grid = (
        np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT)), -1)
        .reshape(1, -1, 2)
        .astype(np.float64)
    )
    for homography in homographies:
        preimage = cv2.perspectiveTransform(grid, np.linalg.inv(homography.astype(np.float64)))[0]
        assert preimage.min() > -1e-3
        assert np.all(preimage.max(axis=0) < [WIDTH - 1 + 1e-3, HEIGHT - 1 + 1e-3])
    # They vary with the key, and include rotation and perspective (not just the fallback zoom).
    assert len(np.unique(homographies.round(4), axis=0)) == 64
    assert np.abs(homographies[:, 0, 1]).max() > 0.1 and np.abs(homographies[:, 2, :2]).max() > 1e-4


def test_sample_homography_neutral_config_is_identity():
    neutral = HomographyConfig(patch_ratio=1.0, scaling=0.0, max_angle=0.0, perspective=0.0)
    np.testing.assert_allclose(
        sample_homography(jax.random.PRNGKey(3), HEIGHT, WIDTH, neutral), np.eye(3), atol=1e-5
    )


def test_sample_homography_falls_back_to_centred_patch():
    # A full-size patch fits only unrotated, and the angles drawn are never exactly 0.
    impossible = HomographyConfig(
        patch_ratio=1.0, scaling=0.0, max_angle=math.pi / 4, perspective=0.0, num_candidates=4
    )
    np.testing.assert_allclose(
        sample_homography(jax.random.PRNGKey(4), HEIGHT, WIDTH, impossible), np.eye(3), atol=1e-5
    )


def test_homography_config_rejects_out_of_range_values():
    with pytest.raises(ValueError, match="patch_ratio"):
        HomographyConfig(patch_ratio=1.5)
    with pytest.raises(ValueError, match="scaling"):
        HomographyConfig(scaling=1.0)


# The context window of a 48x64 crop: its diagonal, 80 px (usp_jax.training.crops.context_side).
WINDOW = (80, 80)


def rotation_at_centre(homography):
    """In-plane rotation (degrees, OpenCV's sign: counter-clockwise content positive) of H's Jacobian
    at the crop's centre."""
    centre = np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    step = 1e-2
    points = np.array([[centre, centre + [step, 0], centre + [0, step]]], np.float64)
    moved = cv2.perspectiveTransform(points, homography.astype(np.float64))[0]
    jacobian = np.stack([moved[1] - moved[0], moved[2] - moved[0]], axis=1) / step
    return -math.degrees(
        math.atan2(jacobian[1, 0] - jacobian[0, 1], jacobian[0, 0] + jacobian[1, 1])
    )


@pytest.mark.parametrize("angle", [90.0, 180.0, -90.0, 30.0])
def test_window_homography_turns_like_cv2_get_rotation_matrix_2d(angle):
    pure_turn = HomographyConfig(
        patch_ratio=1.0,
        scaling=0.0,
        perspective=0.0,
        translation=0.0,
        rotation_range=(angle, angle),
    )
    homography = sample_window_homography(jax.random.PRNGKey(0), HEIGHT, WIDTH, WINDOW, pure_turn)
    expected = cv2.getRotationMatrix2D(((WIDTH - 1) / 2, (HEIGHT - 1) / 2), angle, 1.0)
    np.testing.assert_allclose(homography, np.vstack([expected, [0, 0, 1]]), atol=1e-4)


def test_window_homographies_turn_over_the_full_circle_and_keep_b_inside_the_window():
    config = HomographyConfig(rotation_range=(-180.0, 180.0))
    keys = jax.random.split(jax.random.PRNGKey(0), 400)
    homographies = np.asarray(
        jax.jit(jax.vmap(lambda key: sample_window_homography(key, HEIGHT, WIDTH, WINDOW, config)))(
            keys
        ),
        np.float64,
    )
    angles = np.array([rotation_at_centre(h) for h in homographies])
    # Uniform over the circle: each quarter holds about a quarter of the draws.
    quarters = np.histogram(angles, bins=4, range=(-180, 180))[0] / len(angles)
    assert quarters.min() > 0.2 and quarters.max() < 0.3
    # Every pixel of B comes from inside the window (A's pixel coordinates shifted by its origin).
    origin = np.array(window_origin(HEIGHT, WIDTH, WINDOW))
    grid = (
        np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT)), -1)
        .reshape(1, -1, 2)
        .astype(np.float64)
    )
    for homography in homographies:
        source = cv2.perspectiveTransform(grid, np.linalg.inv(homography))[0] + origin
        assert source.min() > -1e-3 and np.all(
            source.max(axis=0) < np.array(WINDOW[::-1]) - 1 + 1e-3
        )
    # Keystone and scale still vary (not only the fallback's pure turn).
    assert np.abs(homographies[:, 2, :2]).max() > 1e-4


def test_window_homography_without_a_rotation_range_draws_max_angle():
    config = HomographyConfig(max_angle=0.0, perspective=0.0)
    homographies = jax.vmap(
        lambda key: sample_window_homography(key, HEIGHT, WIDTH, WINDOW, config)
    )(jax.random.split(jax.random.PRNGKey(1), 20))
    assert np.abs([rotation_at_centre(np.asarray(h)) for h in homographies]).max() < 1e-3


def test_only_the_window_sampler_draws_a_rotation_range():
    with pytest.raises(ValueError, match="sample_window_homography"):
        sample_homography(
            jax.random.PRNGKey(0), HEIGHT, WIDTH, HomographyConfig(rotation_range=(-90, 90))
        )
    with pytest.raises(ValueError, match="cannot hold"):
        window_origin(HEIGHT, WIDTH, (40, 80))


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(rotation_range=(10.0, -10.0)), "low <= high"),
        (dict(rotation_range=(0.0, 400.0)), "-360 <= low"),
        (dict(rotation_range="wide"), "in degrees"),
        (dict(rotation_distribution="normal"), "uniform"),
    ],
)
def test_homography_config_rejects_bad_rotation_settings(changes, message):
    with pytest.raises(ValueError, match=message):
        HomographyConfig(**changes)
