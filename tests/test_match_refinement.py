"""inference.match_refinement: matched points of image 2 moved to the sub-pixel NCC peak."""

import cv2
import numpy as np
import pytest

from usp_jax.inference.match_refinement import refine_matches

SHIFT = np.array([1.3, -0.6])


def textured(height=120, width=160, seed=0):
    noise = np.random.default_rng(seed).uniform(0, 255, (height, width)).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.0)


def shifted(image, shift=SHIFT):
    move = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(image, move, image.shape[::-1], flags=cv2.INTER_CUBIC)


def grid_points(step=9.3, low=12, high_x=145, high_y=105):
    xs, ys = np.meshgrid(np.arange(low, high_x, step), np.arange(low, high_y, step))
    return np.stack([xs, ys], axis=-1).reshape(-1, 2)


def test_a_known_sub_pixel_shift_is_found_from_points_a_pixel_off():
    image = textured()
    points1 = grid_points()
    truth = points1 + SHIFT
    off = np.random.default_rng(1).choice([-1.0, 1.0], size=truth.shape)  # 1 px errors
    refined, moved = refine_matches(image, shifted(image), points1, truth + off)
    assert refined.shape == truth.shape and refined.dtype == np.float32
    assert moved.mean() > 0.95
    error = np.linalg.norm(refined[moved] - truth[moved], axis=1)
    assert np.median(error) < 0.1 and np.percentile(error, 90) < 0.15
    assert np.median(np.linalg.norm(off, axis=1)) > 1.4  # from sqrt(2) px off


def test_a_flat_patch_or_a_peak_on_the_search_border_is_left_unmoved():
    image = textured()
    image[40:80, 50:100] = 128.0  # a flat region
    image2 = shifted(image)
    points1 = np.array([[75.0, 60.0], [30.0, 30.0], [30.0, 30.0]])
    points2 = np.array(
        [[75.0 + 1.3, 59.4], [31.3 + 2.0, 29.4], [31.3 + 4.0, 29.4]]
    )  # flat; true peak 2 px off (on the border of a +-2 search); 4 px off (beyond it)
    refined, moved = refine_matches(image, image2, points1, points2, search=2)
    assert not moved.any()
    np.testing.assert_array_equal(refined, points2.astype(np.float32))
    wider, moved_wider = refine_matches(image, image2, points1[1:2], points2[1:2], search=3)
    assert moved_wider.all() and np.abs(wider[0] - (points1[1] + SHIFT)).max() < 0.15


def test_points_whose_patch_leaves_either_image_are_left_unmoved():
    image = textured()
    image2 = shifted(image)
    points1 = np.array([[2.0, 50.0], [80.0, 60.0], [80.0, 60.0], [np.nan, 5.0], [80.0, 60.0]])
    points2 = np.array([[3.3, 49.4], [158.0, 59.4], [81.3, 117.0], [5.0, 5.0], [-40.0, 1e9]])
    refined, moved = refine_matches(image, image2, points1, points2)
    assert not moved.any()
    np.testing.assert_array_equal(refined, points2.astype(np.float32))


def test_no_matches_give_no_points():
    image = textured()
    refined, moved = refine_matches(image, image, np.zeros((0, 2)), np.zeros((0, 2)))
    assert refined.shape == (0, 2) and moved.shape == (0,) and moved.dtype == bool


def test_mismatched_inputs_are_refused():
    image = textured()
    with pytest.raises(ValueError, match="equal M"):
        refine_matches(image, image, np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="at least 1"):
        refine_matches(image, image, np.zeros((1, 2)), np.zeros((1, 2)), search=0)


def test_the_affine_polish_finds_a_point_under_a_turn_and_zoom_that_bias_plain_ncc():
    image = textured(seed=2)
    centre = (80.0, 60.0)
    warp = cv2.getRotationMatrix2D(centre, 8.0, 1.12)  # 8 degrees, 12% zoom
    warp[:, 2] += SHIFT
    image2 = cv2.warpAffine(image, warp, image.shape[::-1], flags=cv2.INTER_CUBIC)
    points1 = grid_points(low=30, high_x=131, high_y=91)
    truth = points1 @ warp[:, :2].T + warp[:, 2]
    start = np.round(truth) + 0.4
    plain, moved = refine_matches(image, image2, points1, start)
    polished, moved_too = refine_matches(image, image2, points1, start, affine_steps=5)
    assert moved.mean() > 0.8 and np.array_equal(moved, moved_too)
    plain_error = np.linalg.norm(plain[moved] - truth[moved], axis=1)
    polished_error = np.linalg.norm(polished[moved] - truth[moved], axis=1)
    assert np.median(polished_error) < 0.1 < np.median(plain_error)
