"""Matching across any in-plane rotation (``usp_jax.inference.turning``)."""

import cv2
import numpy as np
import pytest

from usp_jax import evaluation
from usp_jax.inference import Detector, Features, turning


@pytest.fixture(scope="module")
def small_photo(photo):
    """The test photo at 256x256: the network's shapes stay cheap to compile."""
    return cv2.resize(photo, (256, 256), interpolation=cv2.INTER_AREA)


def _turned_by(image, angle, scale=1.0):
    """``image`` turned ``angle`` degrees counter-clockwise about its centre, same size, and that
    homography [3, 3]."""
    height, width = image.shape[:2]
    truth = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), angle, scale)
    truth = np.vstack([truth, [0, 0, 1]])
    return cv2.warpPerspective(image, truth, (width, height)), truth


@pytest.mark.parametrize("angle", [37.0, 100.0, -150.0])
def test_turn_is_opencvs_rotation_about_the_centre_on_a_canvas_holding_the_whole_image(angle):
    image = np.random.default_rng(0).integers(1, 256, (24, 40, 3), dtype=np.uint8)
    canvas, affine = turning.turn(image, angle)
    # The diagonal, 46.6 px, rounded up to whole 8 px cells; the image centre at the canvas's.
    assert canvas.shape == (48, 48, 3)
    expected = cv2.getRotationMatrix2D((19.5, 11.5), angle, 1.0) + [[0, 0, 4], [0, 0, 12]]
    np.testing.assert_allclose(affine, expected, atol=1e-12)
    mirrored = cv2.warpAffine(image, expected, (48, 48), borderMode=cv2.BORDER_REFLECT_101)
    np.testing.assert_array_equal(canvas, mirrored)
    corners = cv2.transform(np.float64([[[0, 0], [39, 0], [0, 23], [39, 23]]]), affine)[0]
    assert corners.min() >= 0 and corners.max() <= 47
    assert canvas.min() >= 1  # the canvas around the image mirrors it: no black corners


@pytest.mark.parametrize(
    "angle, affine",
    [
        (0.0, [[1, 0, 0], [0, 1, 0]]),
        # Counter-clockwise on screen: x' = y, y' = 39 - x in a 40x24 (H x W) image.
        (90.0, [[0, 1, 0], [-1, 0, 39]]),
        (180.0, [[-1, 0, 39], [0, -1, 23]]),
        (-90.0, [[0, -1, 23], [1, 0, 0]]),
        (270.0, [[0, -1, 23], [1, 0, 0]]),
    ],
)
def test_a_quarter_turn_moves_every_pixel_whole_into_an_image_of_the_same_size(angle, affine):
    image = np.random.default_rng(1).integers(0, 256, (24, 40, 3), dtype=np.uint8)
    turned, found = turning.turn(image, angle)
    np.testing.assert_array_equal(found, affine)
    # OpenCV's own turn about the centre, shifted onto the turned image, agrees pixel for pixel.
    size = (24, 40) if angle % 180 else (40, 24)
    np.testing.assert_array_equal(turned, cv2.warpAffine(image, np.float64(affine), size))
    ys, xs = np.mgrid[:24, :40]
    moved = cv2.transform(np.stack([xs, ys], -1).reshape(1, -1, 2).astype(np.float64), found)
    moved = moved.reshape(24, 40, 2).astype(int)
    np.testing.assert_array_equal(turned[moved[..., 1], moved[..., 0]], image)


@pytest.mark.parametrize(
    "estimated, used",
    [
        (3.0, 0.0),
        (-9.5, 0.0),
        (85.0, 90.0),
        (-172.0, -180.0),
        (-95.0, -90.0),
        (10.0, 10.0),
        (30.0, 30.0),
        (135.0, 135.0),
        (-79.0, -79.0),
    ],
)
def test_turns_within_the_upright_range_of_a_quarter_turn_snap_to_it(estimated, used):
    assert turning.detectable_turn(estimated) == used


@pytest.mark.parametrize("angle", [37.0, 120.0, -150.0])
def test_in_plane_rotation_reads_the_angle_that_turning_back_undoes(angle):
    _, affine = turning.turn(np.zeros((24, 40), np.uint8), angle)
    homography = np.vstack([affine, [0, 0, 1]])
    assert turning.in_plane_rotation(homography, (24, 40)) == pytest.approx(-angle)
    _, back = turning.turn(np.zeros((24, 40)), turning.in_plane_rotation(homography, (24, 40)))
    np.testing.assert_allclose(back[:, :2] @ affine[:, :2], np.eye(2), atol=1e-12)


class _PlacedPoints(Detector):
    """A Detector whose network returns fixed points of the (canvas) image it is given, best
    first, with descriptors that number them, at most ``top_n``; it records the shape it saw."""

    def __init__(self, points, max_side=0):
        self.points = np.float32(points)
        self.max_side = max_side
        self.top_n = None
        self.upsample = 1
        self.any_scale = False

    def _call(self, padded, sizes, top_n):
        self.shape = tuple(sizes[0])
        top_n = self.top_n if top_n is None else top_n
        n = len(self.points)
        scores = np.linspace(1, 0.5, n, dtype=np.float32)
        found = self.points, scores, np.eye(n, dtype=np.float32)
        return [Features(*(array[:top_n] for array in found))]


@pytest.mark.parametrize("max_side", [0, 100])
def test_turned_detections_come_back_in_the_images_pixels_without_the_canvas_edges(max_side):
    image = np.zeros((200, 300, 3), np.uint8)
    # Shrunk to 100 px on its longer side: 67x100, so x scales back by 3 and y by 200 / 67.
    small_shape, factor = ((67, 100), np.array([3, 200 / 67])) if max_side else ((200, 300), 1)
    _, affine = turning.turn(np.zeros(small_shape, np.uint8), 120.0)
    inside = np.float64([[50, 30], [20, 10]])  # in the (shrunk) image's pixels
    on_canvas = cv2.transform(inside[None], affine)[0]
    edge = cv2.transform(np.float64([[[1, 1]]]), affine)[0]  # within EDGE_MARGIN of a corner
    # The best two lie off the image: [0, 0] in the mirrored canvas corner, then one within
    # EDGE_MARGIN of the image's corner.
    points = [[0, 0], edge[0], on_canvas[0], on_canvas[1]]
    detector = _PlacedPoints(points, max_side)
    found = turning.detect_turned(detector, image, 120.0)
    side = 8 * int(np.ceil(np.hypot(*small_shape) / 8))
    assert detector.shape == (side, side)
    np.testing.assert_allclose(found.keypoints, (inside + 0.5) * factor - 0.5, atol=1e-3)
    np.testing.assert_array_equal(found.descriptors.argmax(axis=1), [2, 3])  # which points
    # The cut to the best point counts only points of the image: the canvas gave them all.
    best = turning.detect_turned(detector, image, 120.0, top_n=1)
    np.testing.assert_array_equal(best.descriptors.argmax(axis=1), [2])
    detector.top_n = 1  # the detector's own cut applies when top_n is not given
    np.testing.assert_array_equal(
        turning.detect_turned(detector, image, 120.0).keypoints, best.keypoints
    )


@pytest.mark.parametrize("upsample", [1, 2])
def test_matching_across_any_rotation_recovers_a_photo_turned_past_the_upright_range(
    small_photo, upsample
):
    detector = Detector.pretrained(top_n=500, upsample=upsample)
    turned, truth = _turned_by(small_photo, -150.0, 0.9)
    upright = detector.detect(small_photo), detector.detect(turned)
    plain = evaluation.corner_error(
        truth, evaluation.match_and_estimate(*upright).homography, (256, 256)
    )
    found = turning.match_any_rotation(detector, small_photo, turned)
    assert plain > 10  # the upright weights alone lose the photo at this angle
    assert found.angle == pytest.approx(150.0, abs=3)
    assert evaluation.corner_error(truth, found.matching.homography, (256, 256)) < 3
    assert int(found.matching.inliers.sum()) >= 20


def test_a_pair_turned_within_the_upright_range_is_detected_as_it_is(small_photo):
    detector = Detector.pretrained(top_n=500)
    turned, _ = _turned_by(small_photo, 5.0)
    features1, features2, angle = turning.detect_pair(
        detector, Detector.pretrained("rotation"), small_photo, turned
    )
    assert angle == 0.0
    np.testing.assert_array_equal(features2.keypoints, detector.detect(turned).keypoints)
    np.testing.assert_array_equal(features1.keypoints, detector.detect(small_photo).keypoints)


@pytest.mark.parametrize("inliers, expected_angle", [(5, 0.0), (50, 90.0)])
def test_an_unsure_guide_costs_detections_not_the_pair(
    small_photo, monkeypatch, inliers, expected_angle
):
    # An upright pair and a guide claiming a quarter turn: trusted with many inliers, searched
    # past with few (the upright detection then wins: it matches the pair).
    monkeypatch.setattr(turning, "estimate_turn", lambda *_: turning.Turn(90.0, inliers))
    detector = Detector.pretrained(top_n=500)
    shifted = np.roll(small_photo, 3, axis=1)
    _, features2, angle = turning.detect_pair(detector, None, small_photo, shifted)
    assert angle == expected_angle
    if expected_angle == 0.0:
        np.testing.assert_array_equal(features2.keypoints, detector.detect(shifted).keypoints)


def test_the_search_finds_an_angle_between_its_turns_that_a_wrong_guide_missed(
    small_photo, monkeypatch
):
    # Turned back by -105 degrees, 15 from the nearest searched turns (every 30 degrees: -90,
    # -120) and past UPRIGHT_BELOW of the quarter turn (at exactly 10 degrees a read of 9.99 would
    # snap to it); the guide says -40 on 6 inliers, as it does on chessboards. The best searched
    # turn's homography reads the angle and a last detection there registers the pair.
    monkeypatch.setattr(turning, "estimate_turn", lambda *_: turning.Turn(-40.0, 6))
    detector = Detector.pretrained(top_n=500)
    turned, truth = _turned_by(small_photo, 105.0)
    found = turning.match_any_rotation(detector, small_photo, turned, guide=detector)
    assert found.angle == pytest.approx(-105.0, abs=2)
    assert found.angle not in (-90.0, -120.0)  # refined past the searched turns
    assert evaluation.corner_error(truth, found.matching.homography, (256, 256)) < 3


def test_the_search_detects_each_turn_once(small_photo, monkeypatch):
    seen = []
    detect_turned = turning.detect_turned

    def counted(detector, image, angle, top_n=None):
        seen.append(angle)
        return detect_turned(detector, image, angle, top_n)

    monkeypatch.setattr(turning, "detect_turned", counted)
    detector = Detector.pretrained(top_n=300)
    features1 = detector.detect(small_photo)
    # A guess of -178 snaps to -180, the same turn as the searched 180.
    turning.search_turn(detector, features1, (256, 256), small_photo, guess=-178.0)
    assert len(seen) == len(set(seen)) == 11  # 12 turns every 30 degrees, 0 not turned
    assert 180.0 in seen and -180.0 not in seen


def test_a_guide_near_a_quarter_turn_turns_image_2_by_the_quarter_turn_alone(
    small_photo, monkeypatch
):
    monkeypatch.setattr(turning, "estimate_turn", lambda *_: turning.Turn(-84.0, 50))
    detector = Detector.pretrained()  # every point: none may be lost to the canvas's cut
    image2 = small_photo[:, :203]  # not square, not whole cells: the quarter turn swaps H and W
    _, features2, angle = turning.detect_pair(detector, None, small_photo, image2)
    assert angle == -90.0
    # Turned clockwise, (x, y) of image 2 lands at (H - 1 - y, x); every point maps back exactly,
    # and none near the edges is dropped (there is no empty canvas).
    direct = detector.detect(np.rot90(image2, -1))
    expected = np.stack([direct.keypoints[:, 1], 255 - direct.keypoints[:, 0]], axis=1)
    np.testing.assert_allclose(features2.keypoints, expected, atol=1e-4)
    np.testing.assert_array_equal(features2.descriptors, direct.descriptors)


@pytest.fixture(scope="module")
def detector500():
    """One detector (one compiled function) for the tests of turning back."""
    return Detector.pretrained(top_n=500)


def test_turning_back_by_the_upright_matches_own_turn_recovers_a_hand_held_turn(
    small_photo, detector500
):
    # 25 degrees: past UPRIGHT_BELOW, inside what the upright matches still read.
    detector = detector500
    turned, truth = _turned_by(small_photo, 25.0)
    upright = evaluation.match_and_estimate(detector.detect(small_photo), detector.detect(turned))
    features1, features2, angle = turning.turn_back_pair(detector, small_photo, turned)
    found = evaluation.match_and_estimate(features1, features2)
    assert angle == pytest.approx(-25.0, abs=2)  # the sense that undoes the turn
    assert found.inliers.sum() > upright.inliers.sum()
    assert evaluation.corner_error(truth, found.homography, (256, 256)) < 2


def test_turning_back_leaves_an_upright_pair_and_a_pair_without_matches_as_they_are(
    small_photo, detector500
):
    detector = detector500
    for image2 in (np.roll(small_photo, 3, axis=1), np.full_like(small_photo, 128)):
        features1, features2, angle = turning.turn_back_pair(detector, small_photo, image2)
        assert angle == 0.0
        np.testing.assert_array_equal(features2.keypoints, detector.detect(image2).keypoints)
        np.testing.assert_array_equal(features1.keypoints, detector.detect(small_photo).keypoints)


def test_turning_back_keeps_image_2_upright_when_the_turned_copy_matches_worse(
    small_photo, detector500, monkeypatch
):
    # A homography that reads a turn the pair does not have (a chance fit on a 3-D scene): the
    # turned detection matches worse and is dropped.
    detector = detector500
    shifted = np.roll(small_photo, 3, axis=1)
    monkeypatch.setattr(turning, "in_plane_rotation", lambda *_: 40.0)
    _, features2, angle = turning.turn_back_pair(detector, small_photo, shifted)
    assert angle == 0.0
    np.testing.assert_array_equal(features2.keypoints, detector.detect(shifted).keypoints)
