"""The sub-pixel refinement stage (``inference.refine``) and its place in the compiled detector."""

import jax
import numpy as np
import pytest
from conftest import SMALL_MODEL, gaussian_blob

from usp_jax.core.model import init_variables
from usp_jax.inference import Detector, refine


@pytest.fixture(scope="module")
def wild_params(tmp_path_factory):
    """Random OffsetNet weights scaled up so that the logits are extreme: moves that reach the
    window's edge, where a missing bound would show."""
    params = jax.tree.map(lambda x: 40 * x, refine.init_params(jax.random.PRNGKey(3)))
    path = tmp_path_factory.mktemp("refine") / "wild.npz"
    refine.save_params(path, params)
    return params, str(path)  # a str, as a user passes it


def test_soft_argmax_reads_a_peaked_window_as_its_offset():
    logits = np.full((1, 2 * refine.REACH + 1, 2 * refine.REACH + 1), -50.0, np.float32)
    logits[0, refine.REACH - 3, refine.REACH + 2] = 50.0  # row (y) -3, column (x) +2
    np.testing.assert_allclose(refine.soft_argmax(logits), [[2.0, -3.0]], atol=1e-4)


def test_patches_are_read_centred_on_the_point_against_opencv():
    image = np.random.default_rng(0).random((30, 40)).astype(np.float32)
    point = np.array([[17.3, 12.6]], np.float32)
    patch = np.asarray(refine.sample_patches(image, point))[0]
    expected = cv2_patch(image, point[0])
    np.testing.assert_allclose(patch, expected, atol=1e-5)


def cv2_patch(image, centre):
    import cv2

    return cv2.getRectSubPix(image, (refine.PATCH, refine.PATCH), tuple(float(c) for c in centre))


def test_a_move_never_exceeds_half_a_cell(wild_params):
    params, _ = wild_params
    rng = np.random.default_rng(1)
    image = rng.random((48, 64)).astype(np.float32)
    keypoints = rng.uniform([0, 0], [64, 48], (200, 2)).astype(np.float32)
    moves = np.abs(np.asarray(refine.offsets(params, image, keypoints)))
    assert moves.max() <= refine.REACH + 1e-4
    assert moves.max() > 0.9 * refine.REACH  # the weights do push points to the window's edge


def test_the_detector_moves_points_at_most_half_a_cell_of_the_network(wild_params):
    # At upsample 2 a cell is 4 input px: a point may move at most 2 px per axis.
    _, path = wild_params
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    image = np.random.default_rng(2).integers(0, 256, (40, 48, 3), dtype=np.uint8)
    raw = Detector(variables, SMALL_MODEL, upsample=2, refine=False).detect(image)
    moved = Detector(variables, SMALL_MODEL, upsample=2, border=0, refine=path).detect(image)
    by_score = {float(s): p for s, p in zip(raw.scores, raw.keypoints)}
    shifts = np.array([p - by_score[float(s)] for s, p in zip(moved.scores, moved.keypoints)])
    limit = refine.REACH / 2
    assert np.abs(shifts).max() <= limit + 1e-4
    assert np.abs(shifts).max() > 0.5 * limit


def test_the_shipped_refinement_follows_a_sub_pixel_shift_the_raw_start_misses():
    # The training asks only that both views agree, so the refined point is a repeatable spot
    # of the blob (about 2 px up-right of a bright blob's centre), not its centre: the known
    # answer is how far it moves when the blob moves by a known sub-pixel shift. The starts,
    # like cells that do not see the shift, stay where they are: off by the whole shift.
    centre, shift = np.array([20.0, 17.0]), np.array([0.4, -0.3])
    angles = np.arange(8) * np.pi / 4
    starts = (centre + np.stack([np.cos(angles), np.sin(angles)], axis=1)).astype(np.float32)
    params = refine.load_params()
    found = []
    for c in (centre, centre + shift):
        image = gaussian_blob(c, (40, 44), sigma=2.0)[..., 0].astype(np.float32) / 255
        found.append(starts + np.asarray(refine.offsets(params, image, starts)))
    assert np.linalg.norm(shift) == pytest.approx(0.5)  # the raw starts' error
    assert np.abs(found[1] - found[0] - shift).max() < 0.25
    assert np.abs(found[0] - found[0].mean(axis=0)).max() < 0.25  # every start, one spot


def test_the_refining_detector_is_one_compiled_function():
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    images = np.random.default_rng(3).integers(0, 256, (2, 40, 48, 3), dtype=np.uint8)
    detector = Detector(variables, SMALL_MODEL, refine=True)
    refined = [detector.detect(image) for image in images]
    assert detector._forward._cache_size() == 1
    raw = Detector(variables, SMALL_MODEL, refine=False).detect(images[0])
    np.testing.assert_array_equal(raw.scores, refined[0].scores)
    assert not np.allclose(raw.keypoints, refined[0].keypoints)


@pytest.mark.parametrize(
    "command",
    [
        ["detect", "a.png"],
        ["match", "a.png", "b.png"],
        ["evaluate", "--hpatches", "pairs"],
        ["benchmark"],
        ["export", "--save-weights", "w.npz"],
    ],
)
def test_every_detecting_command_takes_refine_and_no_refine(command):
    from usp_jax.cli_options import parse_args

    assert parse_args(command).refine is None  # the weights' own default
    assert parse_args([*command, "--no-refine"]).refine is False
    assert parse_args([*command, "--refine"]).refine is True


def test_the_refinement_is_on_by_default_for_the_paper_network_only():
    # It was trained on the paper network's points; the others keep theirs unless asked (on the
    # distilled network's it gains as much, at 2-3x that network's time).
    assert Detector.pretrained().refiner is not None
    assert Detector.pretrained("distilled").refiner is None
    assert Detector.pretrained("distilled", refine=True).refiner is not None
    assert Detector.pretrained("fast").refiner is None
    assert Detector.pretrained("paper", refine=False).refiner is None
    assert Detector.pretrained("rotation", refine=True).refiner is not None
