"""inference.match_refinement: matched points of image 2 moved to the sub-pixel NCC peak."""

import cv2
import numpy as np
import pytest

from usp_jax.inference.match_refinement import cut_templates, match_templates, refine_matches

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


def _bilinear64(image, x, y):
    """The plain float64 bilinear sample the fast path must reproduce (pixel centres at
    integers, x and y within the image)."""
    x0 = np.clip(np.floor(x).astype(int), 0, image.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, image.shape[0] - 2)
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _reference_ncc(image1, image2, points1, centres2, radius, search):
    """NCC by its definition, float64: each template against each shifted window."""
    grid = np.arange(-radius, radius + 1.0)
    steps = np.arange(-search, search + 1)
    ncc = np.empty((len(points1), len(steps), len(steps)))
    for m, ((x, y), (cx, cy)) in enumerate(zip(points1, centres2, strict=True)):
        template = _bilinear64(image1, x + grid[None, :], y + grid[:, None])
        for i, dy in enumerate(steps):
            for j, dx in enumerate(steps):
                window = image2[cy + dy - radius : cy + dy + radius + 1]
                window = window[:, cx + dx - radius : cx + dx + radius + 1]
                ncc[m, i, j] = np.corrcoef(template.ravel(), window.ravel())[0, 1]
    return ncc


def _reference_polish(image1, image2, points1, points2, radius, steps):
    """The affine Lucas-Kanade polish as first written: float64, np.gradient of all of
    image 2, every sample bilinear from the whole images."""
    gy, gx = np.gradient(image2)
    ox, oy = np.meshgrid(np.arange(-radius, radius + 1.0), np.arange(-radius, radius + 1.0))
    out = []
    for (x1, y1), (x2, y2) in zip(points1, points2, strict=True):
        template = _bilinear64(image1, x1 + ox, y1 + oy)
        template -= template.mean()
        point, linear = np.array([x2, y2]), np.eye(2)
        for _ in range(steps):
            x = point[0] + linear[0, 0] * ox + linear[0, 1] * oy
            y = point[1] + linear[1, 0] * ox + linear[1, 1] * oy
            window = _bilinear64(image2, x, y)
            window -= window.mean()
            ax, ay = _bilinear64(gx, x, y), _bilinear64(gy, x, y)
            columns = np.stack([ax, ay, ax * ox, ax * oy, ay * ox, ay * oy], -1).reshape(-1, 6)
            columns -= columns.mean(axis=0)
            gain = np.sum(window * template) / np.sum(template * template)
            residual = (gain * template - window).ravel()
            step = np.linalg.solve(columns.T @ columns + 1e-6 * np.eye(6), columns.T @ residual)
            point += np.clip(step[:2], -0.5, 0.5)
            linear += np.clip(step[2:], -0.1, 0.1).reshape(2, 2)
        out.append(point)
    return np.array(out)


def test_the_fast_float32_path_computes_what_the_float64_definition_does():
    """NCC from box sums and a shared template in float32, and the polish sampling image 2 and
    its gradient at twelve pixels per sample, against the plain float64 computations."""
    from usp_jax.inference import match_refinement

    image = textured(seed=3).astype(np.float64)
    warp = cv2.getRotationMatrix2D((80.0, 60.0), 6.0, 1.08)
    warp[:, 2] += SHIFT
    image2 = cv2.warpAffine(image, warp, image.shape[::-1], flags=cv2.INTER_CUBIC)
    points1 = grid_points(low=30, high_x=131, high_y=91) + 0.27
    truth = points1 @ warp[:, :2].T + warp[:, 2]
    centres = np.round(truth).astype(np.int64)
    ncc, _ = match_refinement.ncc_scores(image, image2, points1, centres, 5, 3)
    expected = _reference_ncc(image, image2, points1, centres, 5, 3)
    np.testing.assert_allclose(ncc, expected, atol=1e-4)
    start = truth + np.random.default_rng(4).uniform(-0.4, 0.4, truth.shape)
    polished, ok = match_refinement.affine_polish(image, image2, points1, start, 5, 5)
    assert ok.all()
    expected = _reference_polish(image, image2, points1, start, 5, 5)
    assert np.abs(polished - expected).max() < 0.01
    # A window reaching the image's last row and column: np.gradient's one-sided edge.
    edge = np.array([[153.6, 113.7]])  # the window's samples reach x 158.6, y 118.7
    polished, ok = match_refinement.affine_polish(image, image2, edge - 1.2, edge, 5, 1)
    expected = _reference_polish(image, image2, edge - 1.2, edge, 5, 1)
    assert ok.all() and np.abs(polished - expected).max() < 0.01


def test_templates_of_two_images_matched_into_one_in_one_call_refine_as_pair_by_pair():
    image2 = textured(seed=3)
    first, second = shifted(image2, -SHIFT), shifted(image2, SHIFT[::-1])
    points = grid_points()
    off = np.random.default_rng(4).choice([-1.0, 1.0], size=points.shape)
    given = [(first, points - SHIFT + off), (second, points + SHIFT[::-1] + off)]
    given.append((first[:10, :10], points[:5]))  # smaller than a template: nothing usable
    cut = [cut_templates(grey, points1) for grey, points1 in given]
    assert not cut[2][1].any() and not cut[2][0].any()
    refined, moved = match_templates(
        np.concatenate([template for template, _ in cut]),
        np.concatenate([usable for _, usable in cut]),
        image2,
        np.concatenate([points, points, points[:5]]),
        affine_steps=2,
    )
    offsets = np.cumsum([0] + [len(points1) for _, points1 in given])
    for (grey, points1), lo, hi in zip(given, offsets[:-1], offsets[1:]):
        alone, alone_moved = refine_matches(
            grey, image2, points1, points[: hi - lo], affine_steps=2
        )
        np.testing.assert_array_equal(refined[lo:hi], alone)
        np.testing.assert_array_equal(moved[lo:hi], alone_moved)
    assert moved[: offsets[2]].mean() > 0.9 and not moved[offsets[2] :].any()
