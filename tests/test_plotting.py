"""The figures are written as PNGs of the documented size."""

import cv2
import numpy as np
import pytest
import skimage.data

from usp_jax.evaluation import Features, match_and_estimate, plotting, project_points

HOMOGRAPHY = np.array([[1.0, 0.05, 3.0], [-0.02, 1.0, 2.0], [0.0, 0.0, 1.0]])


def images():
    image1 = cv2.resize(skimage.data.astronaut(), (64, 48))
    return image1, cv2.warpPerspective(image1, HOMOGRAPHY, (64, 48))


def png_shape(path):
    assert path.stat().st_size > 0
    return cv2.imread(str(path)).shape


def test_plot_keypoints_writes_a_two_panel_png(tmp_path):
    image1, image2 = images()
    points = np.random.default_rng(0).uniform(0, 40, size=(30, 2))
    path = plotting.plot_keypoints(
        image1, points, image2, project_points(points, HOMOGRAPHY), tmp_path / "kp.png", HOMOGRAPHY
    )
    height, width, _ = png_shape(path)
    assert width == 2 * plotting.PANEL_INCHES * plotting.DPI and height > 0


def test_plot_keypoints_draws_both_panels_at_one_size_with_points_on_the_far_edge(tmp_path):
    """A target point at x = W (the far edge of the last pixel) used to widen that panel's limits
    and draw it smaller and lower than the reference panel."""
    red = np.zeros((48, 64, 3), np.uint8)
    red[..., 0] = 255
    edge = np.array([[64.0, 47.9], [0.0, 0.0]])
    path = plotting.plot_keypoints(red, edge[1:], red, edge, tmp_path / "kp.png")
    is_red = np.all(cv2.imread(str(path)) == (0, 0, 255), axis=-1)
    half = is_red.shape[1] // 2
    rows = [np.flatnonzero(side.sum(axis=1) > 20) for side in (is_red[:, :half], is_red[:, half:])]
    assert (rows[0].min(), rows[0].max()) == (rows[1].min(), rows[1].max())


def test_plot_keypoints_without_homography_or_points(tmp_path):
    image1, image2 = images()
    path = plotting.plot_keypoints(
        image1[..., 0], np.zeros((0, 2)), image2, np.zeros((0, 2)), tmp_path / "a" / "kp.png"
    )
    assert png_shape(path)[1] == 2 * plotting.PANEL_INCHES * plotting.DPI


def test_plot_detections_draws_one_image_with_its_points(tmp_path):
    """``detect --out``: one panel (not the image twice), a green cross on each keypoint."""
    black = np.zeros((48, 64, 3), np.uint8)
    path = plotting.plot_detections(black, np.array([[16.0, 12.0], [48.0, 36.0]]), tmp_path / "d")
    assert path == tmp_path / "d.png"
    drawn = cv2.imread(str(path))
    assert drawn.shape[1] == plotting.PANEL_INCHES * plotting.DPI
    green = np.all(np.abs(drawn.astype(int) - (0x2C, 0xA0, 0x2C)) < 40, axis=-1)
    columns = np.flatnonzero(green.any(axis=0))
    # The crosses sit a quarter and three quarters across the one panel.
    assert len(columns) and abs(columns.min() / drawn.shape[1] - 0.25) < 0.05
    assert abs(columns.max() / drawn.shape[1] - 0.75) < 0.05


def test_plot_matches_draws_estimated_and_failed_homographies(tmp_path):
    image1, image2 = images()
    points = np.random.default_rng(0).uniform(5, 40, size=(20, 2)).astype(np.float32)
    descriptors = np.eye(20, dtype=np.float32)
    f1 = Features(points, np.ones(20, np.float32), descriptors)
    f2 = Features(
        project_points(points, HOMOGRAPHY).astype(np.float32), np.ones(20, np.float32), descriptors
    )
    matching = match_and_estimate(f1, f2)
    for name, estimate in (("est.png", matching.homography), ("none.png", None)):
        path = plotting.plot_matches(
            image1,
            image2,
            f1.keypoints,
            f2.keypoints,
            matching.matches,
            matching.inliers,
            HOMOGRAPHY,
            estimate,
            tmp_path / name,
        )
        assert png_shape(path)[1] == 2 * plotting.PANEL_INCHES * plotting.DPI


def test_plot_histograms_writes_png_of_fixed_size(tmp_path):
    rng = np.random.default_rng(0)
    values = {
        "without uniform loss": rng.beta(0.5, 0.5, 500),
        "with uniform loss": rng.uniform(size=300),
    }
    path = plotting.plot_histograms(
        values, tmp_path / "h.png", bins=20, xlabel="relative x", title="Figure 4"
    )
    width, height = (round(inches * plotting.DPI) for inches in plotting.HISTOGRAM_INCHES)
    assert png_shape(path) == (height, width, 3)


def test_plot_training_curves_draws_logged_metrics_and_skips_missing_keys(tmp_path):
    rng = np.random.default_rng(0)
    rows = [
        {
            "step": 10 * (i + 1),
            "loss/usp": 300 - i + rng.normal(),
            "loss/uni_xy": 100.0,
            "loss/desc": 80.0,
            "usp/mean_d": 2.6 - 0.01 * i,
            "desc/sim_negative": 0.3,
        }
        for i in range(40)
    ]
    path = plotting.plot_training_curves(
        rows, tmp_path / "curves.png", smooth=5, stage_starts=[200]
    )
    assert png_shape(path) == (round(7.0 * plotting.DPI), round(11.0 * plotting.DPI), 3)


def test_plot_speed_quality_has_a_column_per_size_and_rejects_no_points(tmp_path):
    points = [
        {"label": m, "size": s, "images_per_s": r, "ha3": 0.8, "ms": 0.6, "ours": m == "fast"}
        for s in ("240x320", "480x640")
        for m, r in (("fast", 50.0), ("ORB", 160.0))
    ]
    path = plotting.plot_speed_quality(points, tmp_path / "tradeoff.png")
    assert png_shape(path) == (round(8.0 * plotting.DPI), round(11.0 * plotting.DPI), 3)
    one_size = plotting.plot_speed_quality(points[:2], tmp_path / "one.png")
    assert png_shape(one_size) == (round(8.0 * plotting.DPI), round(5.5 * plotting.DPI), 3)
    with pytest.raises(ValueError, match="no points"):
        plotting.plot_speed_quality([], tmp_path / "none.png")
