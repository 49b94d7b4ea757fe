"""``Detector(any_scale=True)``: the image pyramid inside the compiled detector."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL_MODEL
from test_inference import calibrated_variables

from usp_jax.core.model import CELL
from usp_jax.inference import Detector, Features, pyramid, to_cv2


@pytest.fixture(scope="module")
def variables(photo):
    return calibrated_variables(SMALL_MODEL, photo)


@pytest.fixture(scope="module")
def image(photo):
    """A 131x163 crop of a real photo: three levels (1, 1/sqrt 2, 1/2), none a whole number of
    cells, so padding and rounding of the levels' sides are exercised."""
    return np.ascontiguousarray(photo[150:281, 180:343])


def by_position(features: Features) -> Features:
    order = np.lexsort(features.keypoints.T)
    return Features(*(None if a is None else a[order] for a in features))


def test_level_scales_shrink_by_the_step_down_to_the_minimum_side():
    scales = pyramid.level_scales(240, 320)
    np.testing.assert_allclose(scales, [1, 2**-0.5, 0.5, 2**-1.5])
    assert pyramid.level_shape(240, 320, scales[-1]) == (85, 113)
    assert pyramid.level_scales(80, 80) == (1.0,)


def test_resize_level_is_an_antialiased_opencv_resize(photo):
    """Pixel centres aligned as cv2.resize's; shrinking averages like INTER_AREA (an exact 2:1
    shrink of a box-filtered image differs from it only by the filter's width)."""
    crop = np.ascontiguousarray(photo[150:214, 180:276])
    small = np.asarray(pyramid.resize_level(jnp.asarray(crop[None]), (32, 48))[0])
    area = cv2.resize(crop, (48, 32), interpolation=cv2.INTER_AREA).astype(float)
    error = np.abs(small - area).mean()
    assert error < 2 and error < 0.5 * np.abs(crop[::2, ::2] - area).mean()


@pytest.mark.parametrize("refine", [False, True])
@pytest.mark.slow
def test_each_level_equals_detect_on_the_image_resized_to_it(variables, image, refine, monkeypatch):
    # Refined, each point's patch is read from its own level's image (pyramid._level_moves).
    # The pyramid re-scores refined points with a spread weight of its own; given the
    # single-scale one, its scores are the single-scale detector's (each Detector compiles anew).
    from usp_jax.inference import refine as refine_lib

    monkeypatch.setattr(pyramid, "SPREAD_WEIGHT", refine_lib.SPREAD_WEIGHT)
    # The single-scale detector merges refined points that stack (refine.DUPLICATE_RADIUS); the
    # pyramid keeps its levels' points as they are, so the levels compare with the merge off.
    monkeypatch.setattr(refine_lib, "DUPLICATE_RADIUS", 0.0)
    features = Detector(variables, SMALL_MODEL, any_scale=True, refine=refine).detect(image)
    single = Detector(variables, SMALL_MODEL, refine=refine)
    height, width = image.shape[:2]
    scales = pyramid.level_scales(height, width)
    assert len(scales) == 3
    for scale in scales:
        shape = pyramid.level_shape(height, width, scale)
        resized = np.asarray(pyramid.resize_level(jnp.asarray(image[None]), shape)[0])
        expected = by_position(single.detect(resized))
        mine = np.isclose(features.scales, CELL / scale)
        factors = np.array([width / shape[1], height / shape[0]])
        level = by_position(
            Features(
                (features.keypoints[mine] + 0.5) / factors - 0.5,
                features.scores[mine],
                features.descriptors[mine],
            )
        )
        np.testing.assert_allclose(level.keypoints, expected.keypoints, atol=2e-3)
        np.testing.assert_allclose(level.scores, expected.scores, atol=1e-4)
        np.testing.assert_allclose(level.descriptors, expected.descriptors, atol=1e-3)


def test_points_are_sorted_inside_the_image_and_the_top_n_over_all_levels(variables, image):
    detector = Detector(variables, SMALL_MODEL, any_scale=True)
    every = detector.detect(image)
    assert np.all(np.diff(every.scores) <= 0)
    height, width = image.shape[:2]
    assert np.all(every.keypoints >= -0.5) and np.all(every.keypoints < [width - 0.5, height - 0.5])
    top = detector.detect(image, top_n=50)
    np.testing.assert_allclose(top.scores, every.scores[:50], atol=1e-6)
    assert len(np.unique(top.scales)) > 1  # the best points come from several levels


def test_nms_across_levels_keeps_points_apart_in_input_pixels(variables, image):
    """The greedy radius NMS over the points of all levels (the evaluation's NumPy one)."""
    from usp_jax.inference.nms import radius_nms_host

    every = Detector(variables, SMALL_MODEL, any_scale=True).detect(image)
    kept = Detector(variables, SMALL_MODEL, any_scale=True, nms_radius=6).detect(image, top_n=40)
    expected = radius_nms_host(every.keypoints, every.scores, 6)[:40]
    np.testing.assert_allclose(kept.keypoints, every.keypoints[expected], atol=1e-5)
    np.testing.assert_allclose(kept.scales, every.scales[expected])


def test_to_cv2_sizes_follow_the_levels(variables, image):
    features = Detector(variables, SMALL_MODEL, any_scale=True).detect(image, top_n=200)
    keypoints, _ = to_cv2(features)
    sizes = np.array([k.size for k in keypoints])
    np.testing.assert_allclose(sizes, features.scales, rtol=1e-6)
    height, width = image.shape[:2]
    levels = [CELL / s for s in pyramid.level_scales(height, width)]
    np.testing.assert_allclose(np.unique(sizes), levels, rtol=1e-5)
    single = Detector(variables, SMALL_MODEL).detect(image, top_n=5)
    assert single.scales is None and {k.size for k in to_cv2(single)[0]} == {CELL}


def test_a_shrunk_photo_scales_its_point_sizes_back(variables, photo):
    features = Detector(variables, SMALL_MODEL, any_scale=True, max_side=128).detect(photo)
    np.testing.assert_allclose(np.unique(features.scales), [32, 32 * 2**0.5, 64], rtol=1e-5)


def test_one_compiled_pyramid_per_input_size(variables, image):
    """All levels in one function, compiled once per input size (and batch size)."""
    detector = Detector(variables, SMALL_MODEL, any_scale=True)
    first = detector.detect(image)
    detector.detect(image[:-1])
    assert detector._forward._cache_size() == 2  # two sizes, though both pad to one shape
    again = detector.detect(image.copy())
    assert detector._forward._cache_size() == 2
    np.testing.assert_allclose(first.keypoints, again.keypoints)


def test_a_textured_image_and_its_2x_enlargement_share_their_strongest_points(photo):
    """With trained weights: the strongest points of an image and those of its 2x enlargement
    (found at the enlargement's half-size level) coincide within 1 px for nearly all of them;
    the enlargement's own scale (its first level, the single-scale detector) matches far fewer."""
    small = np.ascontiguousarray(photo[100:164, 150:246])
    large = cv2.resize(small, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
    detector = Detector.pretrained("fast", any_scale=True)
    points = detector.detect(small, top_n=30).keypoints
    found = detector.detect(large)

    def agreement(keypoints):
        keypoints = (keypoints + 0.5) / 2 - 0.5  # into the small image's pixels
        distance = np.linalg.norm(points[:, None] - keypoints[None], axis=-1).min(axis=1)
        return np.mean(distance <= 1.0)

    single_scale = agreement(found.keypoints[found.scales == CELL])
    assert agreement(found.keypoints) >= 0.9 > single_scale + 0.2


def test_any_scale_combines_with_turning(variables, image):
    """``--any-rotation`` detects image 2 turned (``turning.detect_turned``): with the pyramid,
    a quarter turn gives the points of every level of the turned image, sizes kept."""
    from usp_jax.inference.turning import detect_turned

    detector = Detector(variables, SMALL_MODEL, any_scale=True)
    turned = detect_turned(detector, image, 90.0)
    expected = detector.detect(np.ascontiguousarray(np.rot90(image)), top_n=10**6)
    assert len(turned.keypoints) == len(expected.keypoints)
    np.testing.assert_allclose(np.sort(turned.scales), np.sort(expected.scales), rtol=1e-6)
    height, width = image.shape[:2]
    assert np.all(turned.keypoints > -1) and np.all(turned.keypoints < [width, height])


def test_an_exported_any_scale_detector_returns_the_same_points_and_sizes(
    variables, image, tmp_path
):
    from usp_jax.inference.export import export, load_exported

    detector = Detector(variables, SMALL_MODEL, any_scale=True, top_n=50)
    export(detector, tmp_path / "pyramid.bin", *image.shape[:2])
    (exported,) = load_exported(tmp_path / "pyramid.bin")(image[None])
    expected = detector.detect(image)
    np.testing.assert_allclose(exported.keypoints, expected.keypoints, atol=1e-4)
    np.testing.assert_allclose(exported.scales, expected.scales)
