"""The pose metric: essential-matrix pose of exact matches, the errors, and SuperGlue's AUC."""

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from usp_jax.evaluation import pose
from usp_jax.inference.features import Features


def _rotation(axis, degrees):
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * math.radians(degrees))[0]


def _synthetic_pair(count=200, seed=0):
    """Points in front of two cameras 0.5 m apart, turned 12 degrees: exact pixels in both."""
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    R, t = _rotation((0.2, 1.0, 0.1), 12.0), np.array([-0.5, 0.05, 0.1])
    points = rng.uniform((-2, -1.5, 3), (2, 1.5, 8), (count, 3))
    first = points @ K.T
    second = (points @ R.T + t) @ K.T
    return K, R, t, first[:, :2] / first[:, 2:], second[:, :2] / second[:, 2:]


def test_exact_matches_give_the_exact_pose_and_auc_one():
    K, R, t, points1, points2 = _synthetic_pair()
    R_found, t_found, inliers = pose.estimate_pose(points1, points2, K, K)
    rotation, translation = pose.pose_errors(R, t, R_found, t_found)
    assert rotation < 1e-3 and translation < 1e-3 and inliers.all()
    assert pose.pose_auc([max(rotation, translation)] * 10) == pytest.approx([1, 1, 1], abs=1e-4)


def test_pose_errors_are_the_rotation_angle_and_the_folded_direction_angle():
    R = _rotation((0, 0, 1), 30.0)
    t = np.array([1.0, 0.0, 0.0])
    turned = _rotation((1, 0, 0), 7.0) @ R
    assert pose.pose_errors(R, t, turned, t) == pytest.approx((7.0, 0.0))
    assert pose.pose_errors(R, t, R, np.array([1.0, 1.0, 0.0]))[1] == pytest.approx(45.0)
    # E fixes t only up to sign: the opposite direction is no error.
    assert pose.pose_errors(R, t, R, -3 * t)[1] == pytest.approx(0.0, abs=1e-6)


def test_one_pair_ten_degrees_off_gives_superglues_auc():
    # Recall 0 at 0 degrees, 1 at 10, linear between (SuperGlue's curve): the area up to 20 is
    # 5 + 10 = 15 of 20; none of it lies below 5 or 10.
    assert pose.pose_auc([10.0]) == pytest.approx([0.0, 0.0, 0.75])


def test_auc_of_several_errors_against_a_hand_computed_curve():
    # Errors 2, 4, inf: recall (0,0) (2,1/3) (4,2/3) then flat at 2/3.
    # Up to 5: 1/3 + (1/3 + 2/3) + 2/3 = 2, over 5 = 0.4. Up to 10: 2 + 5 * 2/3 = 16/3, /10.
    assert pose.pose_auc([4.0, math.inf, 2.0], (5.0, 10.0)) == pytest.approx([0.4, 16 / 30])


def test_too_few_matches_or_none_give_no_pose_and_an_infinite_error():
    K, R, t, points1, points2 = _synthetic_pair(count=4)
    assert pose.estimate_pose(points1, points2, K, K) is None
    empty = Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 8)))
    pair = pose.PosePair("p", None, None, K, K, R, t)
    row = pose.pair_row("m", pair, empty, empty, cv2.NORM_L2)
    assert row["error"] == math.inf and row["inliers"] == 0
    assert pose.pose_auc([math.inf, math.inf]) == [0.0, 0.0, 0.0]


def test_summary_ranks_an_exact_method_above_a_noisy_one_with_intervals():
    K, R, t, points1, points2 = _synthetic_pair(count=300)
    descriptors = np.eye(300, dtype=np.float32)

    class Fixed:
        def __init__(self, noise):
            self.noise, self.calls = noise, 0

        def detect(self, image):
            self.calls += 1
            points = points1 if self.calls % 2 else points2
            jitter = np.random.default_rng(self.calls).normal(0, self.noise, points.shape)
            return Features((points + jitter).astype(np.float32), np.ones(300), descriptors)

    pairs = [pose.PosePair(f"p{i}", None, None, K, K, R, t) for i in range(6)]
    rows = pose.evaluate_pose(pairs, {"exact": Fixed(0.0), "noisy": Fixed(4.0)})
    table = pose.summarize(rows, rounds=200)
    exact, noisy = table["exact"]["auc"][5.0], table["noisy"]["auc"][5.0]
    assert exact[0] > 0.99 and exact[1][0] > 0.99
    assert noisy[0] < exact[0] and noisy[1][0] <= noisy[0] <= noisy[1][1]
    assert "| exact |" in pose.format_table(table)
    difference, (low, high) = pose.auc_difference(rows, "exact", "noisy", rounds=200, threshold=5)
    assert difference == pytest.approx(exact[0] - noisy[0]) and 0 < low <= difference <= high


@pytest.mark.parametrize(
    ("R", "t", "message"),
    [
        (np.eye(2), np.ones(3), "R \\[3, 3\\]"),
        (np.eye(3), np.ones(4), "t \\[3\\]"),
        (2 * np.eye(3), np.ones(3), "not a rotation"),
        (np.diag([1.0, 1.0, -1.0]), np.ones(3), "not a rotation"),
        (np.eye(3), np.zeros(3), "does not move"),
        (np.eye(3), np.array([1.0, np.nan, 0.0]), "not finite"),
    ],
)
def test_a_bad_pose_is_refused_with_what_is_wrong(R, t, message):
    with pytest.raises(ValueError, match=message):
        pose.check_pose(R, t)


def _written(tmp_path):
    K, R, t, *_ = _synthetic_pair()
    image = np.zeros((8, 8, 3), np.uint8)
    pairs = [pose.PosePair(f"p{i}", image, image + i, K, K, R, t) for i in range(2)]
    pose.write_pairs(tmp_path / "pairs", pairs)
    return tmp_path / "pairs", pairs


def test_pairs_written_read_back_equal(tmp_path):
    folder, pairs = _written(tmp_path)
    found = pose.read_pairs(folder)
    assert [p.name for p in found] == ["p0", "p1"] and not (tmp_path / "pairs.partial").exists()
    for a, b in zip(found, pairs, strict=True):
        assert np.array_equal(a.image2, b.image2) and np.allclose(a.R, b.R)
        assert np.allclose(a.t, b.t) and np.allclose(a.K1, b.K1)
    with pytest.raises(ValueError, match="exists"):
        pose.write_pairs(folder, pairs)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda path: (path / "pose.json").unlink(), "without its poses"),
        (lambda path: (path / "pose.json").write_text('{"R": [[1, 0], [0, 1]]}'), "needs K1"),
        (
            lambda path: (path / "pose.json").write_text(
                '{"K1": [[1,0,0],[0,1,0],[0,0,1]], "K2": [[1,0,0],[0,1,0],[0,0,1]],'
                ' "R": [[1, 0], [0, 1]], "t": [1, 0, 0]}'
            ),
            "R \\[3, 3\\]",
        ),
    ],
)
def test_a_pair_without_a_valid_pose_is_named(tmp_path, edit, message):
    folder, _ = _written(tmp_path)
    edit(folder / "p1")
    with pytest.raises(ValueError, match=f"p1.*{message}"):
        pose.read_pairs(folder)


def _poses(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return Rotation.random(count, random_state=seed).as_matrix(), rng.normal(0, 2, (count, 3))


def test_relative_pose_errors_ignore_the_gauge_and_measure_a_known_turn():
    rotations, centres = _poses(4)
    # Another world frame and scale: X' = 3 Q X + T, so R' = R Q^T and c' = 3 Q c + T.
    q = Rotation.from_euler("xyz", [20, -50, 70], degrees=True).as_matrix()
    moved = (rotations @ q.T, 3 * centres @ q.T + [1.0, -2.0, 5.0])
    rotation, direction = pose.relative_pose_errors(*moved, rotations, centres)
    np.testing.assert_allclose(rotation, 0, atol=1e-5)
    np.testing.assert_allclose(direction, 0, atol=1e-5)
    # Camera 0 turned 2 degrees more about its own x axis: each of its 3 pairs is off by 2.
    turned = rotations.copy()
    turned[0] = Rotation.from_euler("x", 2, degrees=True).as_matrix() @ rotations[0]
    rotation, _ = pose.relative_pose_errors(turned, centres, rotations, centres)
    np.testing.assert_allclose(rotation, [2, 2, 2, 0, 0, 0], atol=1e-6)


def test_translation_direction_error_is_the_angle_between_baselines_in_camera_j():
    eye = np.stack([np.eye(3)] * 2)
    true_centres = np.array([[0.0, 0, 0], [1, 0, 0]])
    found = np.array([[0.0, 0, 0], [1, 1, 0]])  # the second camera 45 degrees off the line
    _, direction = pose.relative_pose_errors(eye, found, eye, true_centres)
    np.testing.assert_allclose(direction, [45.0])
