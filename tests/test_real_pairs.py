"""Real pairs (``usp_jax.evaluation.real_pairs``): the truth's mapping against NumPy and OpenCV,
known-answer counts, bad pair folders, and ``usp-jax evaluate --real`` end to end on a real pair
that a package ships (scikit-image's stereo motorcycle with its true disparity)."""

import json

import cv2
import numpy as np
import pytest
import skimage.data

from usp_jax import cli
from usp_jax.evaluation import real_pairs
from usp_jax.evaluation.real_pairs import RealPair
from usp_jax.inference.features import Features

RNG = np.random.default_rng(0)


def _texture(height=120, width=160):
    return RNG.integers(0, 256, (height, width, 3), dtype=np.uint8)


def _features(points, descriptors, scores=None):
    points = np.asarray(points, np.float32).reshape(-1, 2)
    scores = np.linspace(1, 0.5, len(points)) if scores is None else scores
    return Features(points, np.asarray(scores, np.float32), np.asarray(descriptors, np.float32))


def _homography_pair(homography):
    image = _texture()
    return RealPair("h", image, image, "homography", "homography", homography=homography)


def _disparity_pair(disparity):
    image = _texture(*disparity.shape)
    return RealPair("d", image, image, "disparity", "fundamental", disparity=disparity)


def test_true_positions_under_a_homography_are_opencvs():
    homography = np.array([[0.9, 0.1, 5.0], [-0.05, 1.1, 3.0], [1e-4, 2e-4, 1.0]])
    points = RNG.uniform(0, 100, (20, 2))
    expected = cv2.perspectiveTransform(points[None], homography)[0]
    found = real_pairs.true_positions(_homography_pair(homography), points)
    np.testing.assert_allclose(found, expected, atol=1e-9)


def test_a_disparity_moves_a_point_left_by_the_disparity_at_its_nearest_pixel():
    disparity = np.full((20, 30), np.nan)
    disparity[5, 10], disparity[6, 11] = 4.0, 7.5
    found = real_pairs.true_positions(
        _disparity_pair(disparity), [[10.2, 4.8], [10.6, 6.4], [1.0, 1.0], [-3.0, 5.0]]
    )
    np.testing.assert_allclose(found[0], [6.2, 4.8])
    np.testing.assert_allclose(found[1], [3.1, 6.4])
    assert np.isnan(found[2:]).all()  # an unknown disparity, a point off the map


def test_known_counts_on_a_shifted_pair():
    """Eight image-1 points; the truth shifts them 5 px left. Image 2 holds the true places of
    the first six (descriptors equal to theirs for the first four, swapped for the next two)
    and two points far away: 4 correct mutual matches, repeatability 6/8, 4 of 6 right by
    nearest neighbour."""
    disparity = np.full((60, 80), 5.0)
    points1 = np.array([[10 + 8 * i, 20.0] for i in range(8)])
    eye = np.eye(8)
    places = points1[:6] - [5, 0]
    points2 = np.concatenate([places, [[70.0, 50.0], [75.0, 55.0]]])
    descriptors2 = eye[[0, 1, 2, 3, 5, 4, 6, 7]]
    result = real_pairs.score_pair(
        _disparity_pair(disparity),
        "m",
        _features(points1, eye),
        _features(points2, descriptors2),
        cv2.NORM_L2,
    )
    assert result.matches == 8 and result.correct == 4
    assert result.precision == pytest.approx(0.5)
    assert (result.visible, result.repeatable, result.nn_correct) == (8, 6, 4)
    assert result.repeatability == pytest.approx(0.75)


def test_known_counts_under_a_homography_with_points_a_pixel_off():
    homography = np.array([[1.0, 0.0, 12.0], [0.0, 1.0, -4.0], [0.0, 0.0, 1.0]])
    points1 = RNG.uniform(20, 100, (30, 2))
    points2 = real_pairs.true_positions(_homography_pair(homography), points1)
    points2[:20] += RNG.uniform(-2, 2, (20, 2))  # within 3 px: correct
    points2[20:] += [500.0, 0.0]  # far from every true place: wrong
    descriptors = np.eye(30)
    result = real_pairs.score_pair(
        _homography_pair(homography),
        "m",
        _features(points1, descriptors),
        _features(points2, descriptors),
        cv2.NORM_L2,
        orders=3,
    )
    assert (result.matches, result.correct) == (30, 20)
    assert (result.visible, result.repeatable, result.nn_correct) == (30, 20, 20)


def test_wilson_interval_of_half_of_100_trials():
    low, high = real_pairs.wilson_interval(50, 100)
    assert low == pytest.approx(0.4038, abs=1e-3) and high == pytest.approx(0.5962, abs=1e-3)
    assert real_pairs.wilson_interval(0, 0) == (0.0, 1.0)


def test_inliers_of_a_fundamental_matrix_count_matches_that_keep_the_epipolar_constraint():
    """50 views of 3-D points by two cameras with a baseline, and 10 random points: the 50."""
    camera = np.array([[200.0, 0, 100], [0, 200, 100], [0, 0, 1]])
    scene = np.column_stack([RNG.uniform(-2, 2, (60, 2)), RNG.uniform(4, 8, 60)])
    turn, _ = cv2.Rodrigues(np.array([0.0, 0.08, 0.02]))
    points1 = cv2.projectPoints(scene, np.zeros(3), np.zeros(3), camera, None)[0][:, 0]
    points2 = cv2.projectPoints(
        scene, cv2.Rodrigues(turn)[0], np.array([0.5, 0.1, 0.0]), camera, None
    )[0][:, 0]
    points2[50:] = RNG.uniform(0, 200, (10, 2))
    counts = real_pairs.count_inliers(points1, points2, "fundamental", orders=4)
    assert counts.shape == (4,) and np.all(counts >= 50) and np.all(counts <= 52)


def _write_pair(folder, image1, image2, spec, disparity=None):
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "a.png"), cv2.cvtColor(image1, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(folder / "b.png"), cv2.cvtColor(image2, cv2.COLOR_RGB2BGR))
    if disparity is not None:
        np.save(folder / "disparity.npy", disparity)
    (folder / "pair.json").write_text(json.dumps({"image1": "a.png", "image2": "b.png"} | spec))
    return folder


def _motorcycle(tmp_path, scale=0.25):
    """scikit-image's real stereo pair, shrunk (disparity scaled alike), as a pair folder."""
    left, right, disparity = skimage.data.stereo_motorcycle()
    size = (round(left.shape[1] * scale), round(left.shape[0] * scale))
    shrink = [cv2.resize(image, size, interpolation=cv2.INTER_AREA) for image in (left, right)]
    small = cv2.resize(disparity, size, interpolation=cv2.INTER_NEAREST) * scale
    spec = {"truth": "disparity", "disparity": "disparity.npy", "ransac": "fundamental"}
    return _write_pair(tmp_path / "pairs" / "motorcycle", *shrink, spec, small)


@pytest.mark.parametrize(
    "spec, disparity_shape, message",
    [
        (
            {"truth": "disparity", "disparity": "gone.png"},
            None,
            "disparity file gone.png is missing",
        ),
        ({"truth": "disparity", "disparity": "disparity.npy"}, (10, 10), r"image1 is \(40, 30\)"),
        ({"truth": "homography", "homography": "b.png"}, None, "holds no 3x3 homography"),
        ({"truth": "guess"}, None, "truth must be one of"),
        ({"truth": "disparity", "disparity": "a.png", "disparity_scale": 0}, None, "positive"),
    ],
)
def test_a_bad_pair_folder_fails_in_one_line_naming_it(tmp_path, spec, disparity_shape, message):
    disparity = None if disparity_shape is None else np.ones(disparity_shape)
    folder = _write_pair(tmp_path / "bad", _texture(30, 40), _texture(30, 40), spec, disparity)
    with pytest.raises(ValueError, match=message) as error:
        real_pairs.read_real_pair(folder)
    assert str(error.value).startswith("real pair bad:") and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "matrix, message",
    [(np.zeros((3, 3)), r"singular \(rank 0\)"), (np.full((3, 3), np.nan), "NaN or infinite")],
)
def test_a_singular_or_non_finite_true_homography_fails_naming_the_pair(tmp_path, matrix, message):
    spec = {"truth": "homography", "homography": "H.txt"}
    folder = _write_pair(tmp_path / "bad", _texture(30, 40), _texture(30, 40), spec)
    np.savetxt(folder / "H.txt", matrix)
    with pytest.raises(ValueError, match=message) as error:
        real_pairs.read_real_pair(folder)
    assert str(error.value).startswith("real pair bad: H.txt:")


def test_an_unreadable_disparity_image_fails_in_one_line(tmp_path):
    spec = {"truth": "disparity", "disparity": "d.png"}
    folder = _write_pair(tmp_path / "bad", _texture(30, 40), _texture(30, 40), spec)
    (folder / "d.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="d.png is not a readable disparity image"):
        real_pairs.read_real_pair(folder)


def test_a_folder_without_pairs_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no real pair"):
        real_pairs.scan_real_pairs(tmp_path)


def test_a_blank_image_without_points_fails_in_one_line_and_writes_nothing(tmp_path, capsys):
    blank = np.full((200, 240, 3), 128, np.uint8)
    _write_pair(tmp_path / "pairs" / "blank", _texture(200, 240), blank, {"truth": "none"})
    out = tmp_path / "real.json"
    argv = ["evaluate", "--real", str(tmp_path / "pairs"), "--baselines-only"]
    argv += ["--baselines", "orb", "--json", str(out), "--no-progress"]
    assert cli.main(argv) == 2
    assert "ORB found no point in image 2" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_evaluate_real_end_to_end_on_a_real_stereo_pair(tmp_path, capsys):
    _motorcycle(tmp_path)
    out = tmp_path / "real.json"
    argv = ["evaluate", "--real", str(tmp_path / "pairs"), "--baselines", "orb", "--top", "300"]
    argv += ["--ransac-orders", "3", "--json", str(out), "--no-progress"]
    assert cli.main(argv) in (0, None)
    shown = capsys.readouterr().out
    assert "motorcycle (truth: disparity, fundamental RANSAC)" in shown
    rows = {row["method"]: row for row in json.loads(out.read_text())["pairs"]}
    assert set(rows) == {"UnsuperPoint", "ORB"}
    for row in rows.values():
        # A real pair with its true disparity: most mutual matches of either method are right.
        assert row["points"][0] == 300 and row["correct"] > 0.4 * row["matches"]
        assert 0 < row["repeatability"] <= 1 and 0 < row["nn_share"] <= 1
