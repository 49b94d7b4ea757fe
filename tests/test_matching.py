"""inference.matching's nearest neighbours: OpenCV's brute-force matcher is the reference."""

import cv2
import numpy as np
import pytest

from usp_jax.inference.matching import mutual_nearest_neighbours, nearest_neighbours


def opencv_pairs(first, second, norm=cv2.NORM_L2, cross_check=True) -> np.ndarray:
    found = cv2.BFMatcher(norm, crossCheck=cross_check).match(first, second)
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in found], np.int64).reshape(-1, 2)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def noisy_copies(seed=0, dim=32):
    rng = np.random.default_rng(seed)
    first = rng.standard_normal((300, dim)).astype(np.float32)
    second = first[rng.permutation(300)][:250] + rng.normal(0, 1.5, (250, dim)).astype(np.float32)
    return first, second


def test_mutual_nearest_neighbours_equal_opencvs_cross_checked_brute_force():
    first, second = noisy_copies()
    ours = mutual_nearest_neighbours(first, second)
    assert 50 < len(ours) < 250  # some, not all, are mutual
    np.testing.assert_array_equal(ours, opencv_pairs(first, second))
    assert mutual_nearest_neighbours(first[:0], second).shape == (0, 2)


def test_mutual_nearest_neighbours_break_exact_ties_to_the_lower_index_as_opencv_does():
    # Rows 0 and 1 of the first set are one descriptor, as are columns 1 and 2 of the second.
    first = np.array([[0, 0], [0, 0], [5, 5], [9, 0]], np.float32)
    second = np.array([[0.5, 0], [5, 4], [5, 4], [9, 1]], np.float32)
    ours = mutual_nearest_neighbours(first, second)
    np.testing.assert_array_equal(ours, [[0, 0], [2, 1], [3, 3]])
    np.testing.assert_array_equal(ours, opencv_pairs(first, second))


@pytest.mark.parametrize("cross_check", [True, False])
def test_nearest_neighbours_in_l2_are_opencvs_brute_force_pairs(cross_check):
    first, second = noisy_copies(seed=1, dim=128)
    ours = nearest_neighbours(first, second, cv2.NORM_L2, cross_check)
    np.testing.assert_array_equal(ours, opencv_pairs(first, second, cross_check=cross_check))
    assert len(ours) == (len(mutual_nearest_neighbours(first, second)) if cross_check else 300)


def test_nearest_neighbours_of_bit_strings_are_hamming_pairs():
    rng = np.random.default_rng(2)
    first = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    second = first ^ (rng.random((40, 32)) < 0.05).astype(np.uint8)  # a few bits flipped
    ours = nearest_neighbours(first, second, cv2.NORM_HAMMING, cross_check=True)
    np.testing.assert_array_equal(ours, opencv_pairs(first, second, cv2.NORM_HAMMING))
    assert len(ours) == 40


def test_the_ratio_test_keeps_a_match_whose_nearest_is_closer_than_ratio_times_the_second():
    first = np.array([[0.0, 0.0]], np.float32)
    second = np.array([[1.0, 0.0], [0.0, 1.5]], np.float32)  # distances 1 and 1.5
    np.testing.assert_array_equal(mutual_nearest_neighbours(first, second, 0.7), [[0, 0]])
    assert len(mutual_nearest_neighbours(first, second, 0.6)) == 0  # 1 >= 0.6 * 1.5
