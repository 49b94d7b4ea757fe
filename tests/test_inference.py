import dataclasses
import functools

import cv2
import flax
import jax
import numpy as np
import optax
import pytest
from conftest import SMALL_MODEL

from usp_jax import evaluation, inference
from usp_jax.config import Config
from usp_jax.core.model import UnsuperPoint, fast_config, init_variables
from usp_jax.inference import Detector, Features, nms
from usp_jax.inference import detector as detector_lib
from usp_jax.inference import weights as weights_lib
from usp_jax.training import checkpoint

SMALL_FAST = fast_config(
    backbone_channels=(4, 8, 8, 16), head_channels=8, descriptor_head_channels=8, descriptor_dim=16
)


def calibrated_variables(config, photo):
    """Random weights with BatchNorm statistics of one real batch, so that, as at the start of
    training, positions spread over their cells and scores over (0, 1); the untouched running
    statistics of a fresh init would put every point near its cell centre."""
    # Jitted, the initialisation is one compile that the persistent cache (conftest) keeps.
    random = init_variables(jax.random.PRNGKey(0), config)
    batch = np.stack([photo[:64, :64], photo[200:264, 200:264], photo[300:364, 100:164]])
    calibrate = UnsuperPoint(dataclasses.replace(config, batch_norm_momentum=0.0))
    apply = jax.jit(functools.partial(calibrate.apply, train=True, mutable=["batch_stats"]))
    _, stats = apply(random, batch / np.float32(255))
    return {"params": random["params"], "batch_stats": stats["batch_stats"]}


@pytest.fixture(scope="module")
def variables(photo):
    return calibrated_variables(SMALL_MODEL, photo)


@pytest.fixture(scope="module")
def fast_variables(photo):
    return calibrated_variables(SMALL_FAST, photo)


@pytest.fixture(scope="module")
def detector(variables):
    return Detector(variables, SMALL_MODEL)


@pytest.fixture(scope="module")
def image(photo):
    """A 40x56 crop of a real photo (a multiple of 8 on both sides)."""
    return np.ascontiguousarray(photo[200:240, 200:256])


def assert_same_features(a, b, atol=1e-5):
    np.testing.assert_allclose(a.keypoints, b.keypoints, atol=atol)
    np.testing.assert_allclose(a.scores, b.scores, atol=atol)
    np.testing.assert_allclose(a.descriptors, b.descriptors, atol=atol)


def select(features, index):
    """The points ``index`` picks, every field alike (``scales`` is None off the pyramid)."""
    return evaluation.Features(*(None if a is None else a[index] for a in features))


def inside(keypoints, height, width, border=0.0):
    """Pixel-centre convention: the image spans [-0.5, size - 0.5) on each axis."""
    x, y = keypoints[:, 0], keypoints[:, 1]
    low = border - 0.5
    return (x >= low) & (x < width - 0.5 - border) & (y >= low) & (y < height - 0.5 - border)


def test_detect_odd_size_returns_sorted_unit_points_inside_image(detector, image):
    odd = image[:37, :53]
    features = detector.detect(odd)
    n = len(features.scores)
    assert 0 < n <= 5 * 7
    assert features.keypoints.dtype == features.scores.dtype == np.float32
    assert features.descriptors.dtype == np.float32
    assert features.keypoints.shape == (n, 2) and features.descriptors.shape == (n, 16)
    assert np.all(inside(features.keypoints, 37, 53))
    assert np.all(np.diff(features.scores) <= 0)
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, rtol=1e-5)


def test_detect_returns_the_networks_points_sorted_by_score(detector, variables, image):
    features = detector.detect(image)
    predictions = UnsuperPoint(SMALL_MODEL).apply(
        variables, image[None] / np.float32(255), train=False
    )
    order = np.argsort(-np.asarray(predictions.scores[0]), kind="stable")
    np.testing.assert_allclose(features.keypoints, predictions.keypoints[0][order], atol=1e-4)
    np.testing.assert_allclose(features.descriptors, predictions.descriptors[0][order], atol=1e-4)


def test_gray_image_is_detected_as_replicated_rgb(detector, image):
    gray = cv2.cvtColor(image[:37, :53], cv2.COLOR_RGB2GRAY)
    assert_same_features(detector.detect(gray), detector.detect(np.stack([gray] * 3, axis=-1)))


def test_padding_does_not_move_points(detector, image):
    # An image whose last rows/columns already replicate its 37x53 top-left part, as padding
    # does: the 37x53 crop must give exactly the full image's points that lie inside the crop.
    cropped = image[:37, :53]
    full = np.pad(cropped, ((0, 3), (0, 3), (0, 0)), mode="edge")
    everywhere = detector.detect(full)
    shared = inside(everywhere.keypoints, 37, 53)
    assert 0 < shared.sum() < len(shared)
    assert_same_features(
        detector.detect(cropped),
        select(everywhere, shared),
    )


@pytest.mark.parametrize("top_n", [0, -1])
def test_a_top_n_below_one_is_rejected_at_construction_and_per_call(detector, image, top_n):
    with pytest.raises(ValueError, match="top_n must be a positive integer"):
        detector.detect(image, top_n=top_n)
    with pytest.raises(ValueError, match="top_n must be a positive integer"):
        Detector(detector.variables, detector.model_config, top_n=top_n)


def test_top_n_keeps_the_highest_scores(detector, image):
    everything = detector.detect(image)
    best = detector.detect(image, top_n=5)
    assert_same_features(best, select(everything, slice(5)))


@pytest.mark.parametrize("radius, cell", [(4.0, 8.0), (12.0, 8.0), (4.0, 4.0), (9.0, 4.0)])
def test_radius_nms_matches_evaluation_nms_radius(radius, cell):
    # cell 4: the candidates of a network run on the image enlarged twice, in input pixels.
    cells_h, cells_w = 6, 7
    rng = np.random.default_rng(int(radius))
    m = cells_h * cells_w
    relative = rng.uniform(size=(m, 2)).astype(np.float32)
    rows, cols = np.divmod(np.arange(m), cells_w)
    keypoints = (np.stack([cols, rows], axis=1) + relative) * cell - 0.5
    scores = rng.uniform(size=m).astype(np.float32)
    valid = rng.uniform(size=m) < 0.9
    keep = np.asarray(nms.radius_nms(keypoints, scores, valid, cells_h, cells_w, radius, cell))
    candidates = np.flatnonzero(valid)
    expected = candidates[nms.radius_nms_host(keypoints[candidates], scores[candidates], radius)]
    assert 0 < len(expected) < len(candidates)  # the test exercises suppression
    np.testing.assert_array_equal(np.flatnonzero(keep), np.sort(expected))


def test_detector_nms_keeps_points_apart_like_evaluation(detector, variables, image):
    radius = 10.0
    candidates = detector.detect(image[:37, :53])
    kept = Detector(variables, SMALL_MODEL, nms_radius=radius).detect(image[:37, :53])
    distances = np.linalg.norm(kept.keypoints[:, None] - kept.keypoints[None], axis=-1)
    assert np.all(distances[~np.eye(len(distances), dtype=bool)] > radius)
    expected = nms.radius_nms_host(candidates.keypoints, candidates.scores, radius)
    assert len(expected) < len(candidates.scores)
    assert_same_features(kept, select(candidates, expected))


def test_upsample_equals_the_network_on_an_opencv_enlarged_image_mapped_back(variables, photo):
    # Multiples of 16 make OpenCV's fixed-point bilinear 2x enlargement exact in uint8 (weights
    # 9/16, 3/16, 1/16), so both paths feed the network the same pixels: what is left to agree
    # on is the resampling grid (pixel centres aligned, edges replicated) and the mapping back.
    image = (photo[100:164, 100:196] // 16 * 16).astype(np.uint8)
    height, width = image.shape[:2]
    enlarged = cv2.resize(image, (2 * width, 2 * height), interpolation=cv2.INTER_LINEAR)
    on_enlarged = Detector(variables, SMALL_MODEL).detect(enlarged)
    upsampled = Detector(variables, SMALL_MODEL, upsample=2).detect(image)
    assert len(upsampled.scores) == (height // 4) * (width // 4)
    mapped = (on_enlarged.keypoints + 0.5) / 2 - 0.5
    assert_same_features(upsampled, on_enlarged._replace(keypoints=mapped), atol=1e-4)
    assert np.all(inside(upsampled.keypoints, height, width))


def test_upsample_with_nms_and_padding_keeps_points_inside_and_apart(variables, image):
    odd = image[:37, :53]
    candidates = Detector(variables, SMALL_MODEL, upsample=2).detect(odd)
    assert np.all(inside(candidates.keypoints, 37, 53))
    kept = Detector(variables, SMALL_MODEL, upsample=2, nms_radius=4).detect(odd)
    expected = nms.radius_nms_host(candidates.keypoints, candidates.scores, 4.0)
    assert len(expected) < len(candidates.scores)
    assert_same_features(kept, select(candidates, expected))


@pytest.mark.parametrize("upsample", [0, -2, 1.5, True])
def test_upsample_must_be_a_positive_integer(variables, upsample):
    with pytest.raises(ValueError, match="upsample must be a positive integer"):
        Detector(variables, SMALL_MODEL, upsample=upsample)


def test_border_drops_points_near_the_edges(detector, variables, image):
    everything = detector.detect(image[:37, :53])
    kept = Detector(variables, SMALL_MODEL, border=6).detect(image[:37, :53])
    expected = inside(everything.keypoints, 37, 53, border=6)
    assert 0 < expected.sum() < len(expected)
    assert_same_features(kept, select(everything, expected))


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((37, 53, 3), np.float32),
        np.zeros((37, 53, 4), np.uint8),
        np.zeros((7, 53, 3), np.uint8),
        np.zeros((53,), np.uint8),
    ],
)
def test_bad_images_raise_one_line_value_error_naming_the_shape(detector, bad):
    with pytest.raises(ValueError, match=r"\(" + ", ".join(map(str, bad.shape))) as error:
        detector.detect(bad)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("any_scale", [False, True])
@pytest.mark.parametrize("interpolate", [True, False])
def test_a_top_n_detector_computes_its_points_descriptors_alone_and_the_same(
    variables, photo, any_scale, interpolate, monkeypatch
):
    """Few points kept: only theirs are computed (``model.describe``), equal to the whole
    descriptor map's that every point gets; also where descriptors are not interpolated."""
    calls = []
    describe = detector_lib.describe_points
    monkeypatch.setattr(
        detector_lib, "describe_points", lambda *a, **k: calls.append(1) or describe(*a, **k)
    )
    config = dataclasses.replace(SMALL_MODEL, interpolate_descriptors=interpolate)
    image = np.ascontiguousarray(photo[100:231, 150:313])  # 17 x 21 cells, 3 levels
    detector = Detector(variables, config, any_scale=any_scale)
    every = detector.detect(image)
    assert not calls  # all points: the whole map, no sparse path
    top = detector.detect(image, top_n=20)
    assert calls  # 20 of 357 cells: their descriptors alone
    np.testing.assert_array_equal(top.keypoints, every.keypoints[:20])
    np.testing.assert_array_equal(top.scores, every.scores[:20])
    np.testing.assert_allclose(top.descriptors, every.descriptors[:20], atol=1e-5)
    assert inference.points.describes_sparsely(20, 357)
    assert not inference.points.describes_sparsely(None, 357)
    assert not inference.points.describes_sparsely(100, 357)


def test_images_that_pad_to_one_shape_compile_once(variables, image, monkeypatch):
    traces = []
    select = detector_lib._select_points

    def counting(*args, **kwargs):
        traces.append(1)
        return select(*args, **kwargs)

    monkeypatch.setattr(detector_lib, "_select_points", counting)
    fresh = Detector(variables, SMALL_MODEL)
    fresh.detect(image[:37, :53])
    fresh.detect(image[:38, :54])
    fresh.detect(image)
    assert len(traces) == 1
    fresh.detect(image, top_n=3)
    assert len(traces) == 2


def test_detect_batch_equals_per_image_results(detector, image, photo):
    stack = np.stack([image[:37, :53], image[3:, 3:]])
    for batched, single in zip(detector.detect_batch(stack), stack):
        assert_same_features(batched, detector.detect(single))
    mixed = [image[:37, :53], cv2.cvtColor(photo[:48, :64], cv2.COLOR_RGB2GRAY), image[2:, 2:]]
    for batched, single in zip(detector.detect_batch(mixed), mixed):
        assert_same_features(batched, detector.detect(single))


def test_weights_round_trip_in_float16(variables, tmp_path):
    path = tmp_path / "weights.npz"
    inference.save_weights(path, variables, SMALL_MODEL)
    config, loaded = inference.load_weights(path)
    assert config == SMALL_MODEL
    flat = jax.tree_util.tree_leaves_with_path(variables)
    assert [p for p, _ in flat] == [p for p, _ in jax.tree_util.tree_leaves_with_path(loaded)]
    for (_, original), restored in zip(flat, jax.tree.leaves(loaded)):
        assert restored.dtype == np.float32
        np.testing.assert_allclose(restored, original, rtol=1e-3, atol=1e-4)


def test_corrupt_or_truncated_weights_files_are_a_clear_error(variables, tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not an npz")
    good = tmp_path / "good.npz"
    inference.save_weights(good, variables, SMALL_MODEL)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for path in (junk, truncated):
        with pytest.raises(ValueError, match="is not a readable .npz weights file"):
            inference.load_weights(path)
    array = tmp_path / "array.npy"
    np.save(array, np.zeros(3))
    with pytest.raises(ValueError, match="single .npy array"):
        inference.load_weights(array)


def test_save_weights_refuses_values_float16_cannot_hold(variables, tmp_path):
    huge = {
        "params": variables["params"],
        "batch_stats": jax.tree.map(lambda x: np.full_like(x, 1e6), variables["batch_stats"]),
    }
    with pytest.raises(ValueError, match="float16"):
        inference.save_weights(tmp_path / "w.npz", huge, SMALL_MODEL)


def test_pretrained_loads_shipped_weights_by_name_or_says_how_to_train(
    variables, fast_variables, image, tmp_path, monkeypatch
):
    monkeypatch.setattr(weights_lib, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setattr(weights_lib, "PRETRAINED", {"paper": "paper.npz", "fast": "fast.npz"})
    with pytest.raises(FileNotFoundError, match="usp-jax train"):
        Detector.pretrained()
    inference.save_weights(tmp_path / "paper.npz", variables, SMALL_MODEL)
    inference.save_weights(tmp_path / "fast.npz", fast_variables, SMALL_FAST)
    pretrained = Detector.pretrained(top_n=4)
    assert pretrained.model_config == SMALL_MODEL  # the default is the paper network's
    assert len(pretrained.detect(image).scores) == 4
    assert Detector.pretrained("paper").model_config == SMALL_MODEL
    assert Detector.pretrained("fast").model_config == SMALL_FAST
    monkeypatch.setattr(weights_lib, "DEFAULT_PRETRAINED", "fast")
    assert Detector.pretrained().model_config == SMALL_FAST
    with pytest.raises(ValueError, match="unknown weights 'vgg16'.*paper, fast"):
        Detector.pretrained("vgg16")


def test_every_named_weights_file_ships_with_the_package():
    assert "paper" in inference.PRETRAINED
    for name, file in inference.PRETRAINED.items():
        assert (inference.WEIGHTS_DIR / file).is_file(), name
    assert inference.DEFAULT_PRETRAINED in inference.PRETRAINED


def test_load_takes_a_weights_file_a_training_workdir_or_nothing_for_the_shipped_weights(
    variables, detector, image, tmp_path, monkeypatch
):
    weights = tmp_path / "paper.npz"
    inference.save_weights(weights, variables, SMALL_MODEL)
    monkeypatch.setattr(weights_lib, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setattr(weights_lib, "DEFAULT_PRETRAINED", "paper")
    from_file = Detector.load(weights, top_n=5)
    assert from_file.model_config == SMALL_MODEL and from_file.top_n == 5
    _, stored = inference.load_weights(weights)
    assert_same_features(
        from_file.detect(image), Detector(stored, SMALL_MODEL).detect(image, top_n=5)
    )
    np.testing.assert_array_equal(
        Detector.load().detect(image, top_n=5).keypoints, from_file.detect(image).keypoints
    )
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        Detector.load(tmp_path / "absent.npz")
    with pytest.raises(FileNotFoundError):
        Detector.load(tmp_path / "no-workdir")


def test_from_checkpoint_restores_the_trained_variables(variables, detector, image, tmp_path):
    state = {
        "params": variables["params"],
        "batch_stats": variables["batch_stats"],
        "opt_state": optax.adam(1e-3).init(variables["params"]),
        "step": np.int32(7),
        "key": jax.random.PRNGKey(1),
    }
    mngr = checkpoint.manager(tmp_path / "checkpoints")
    checkpoint.save(mngr, 7, state, Config(model=SMALL_MODEL))
    mngr.wait_until_finished()
    restored = Detector.from_checkpoint(tmp_path)
    assert restored.model_config == SMALL_MODEL
    assert_same_features(restored.detect(image), detector.detect(image))


def test_a_checkpoint_holding_nan_is_refused_naming_step_and_array(variables, tmp_path):
    params = flax.traverse_util.flatten_dict(variables["params"], sep="/")
    key = sorted(params)[0]
    params[key] = np.asarray(params[key]).copy()
    params[key].flat[0] = np.nan
    state = {
        "params": flax.traverse_util.unflatten_dict(params, sep="/"),
        "batch_stats": variables["batch_stats"],
        "step": np.int32(3),
    }
    mngr = checkpoint.manager(tmp_path / "checkpoints")
    checkpoint.save(mngr, 3, state, Config(model=SMALL_MODEL))
    mngr.wait_until_finished()
    with pytest.raises(ValueError, match=f"checkpoint step 3 .*params/{key} holds NaN"):
        Detector.from_checkpoint(tmp_path)


@pytest.mark.parametrize("network, upsample", [("paper", 1), ("paper", 2), ("fast", 1)])
def test_exported_detector_runs_without_the_model(
    variables, fast_variables, image, tmp_path, network, upsample
):
    path = tmp_path / "detector.jax"
    weights, config = {"paper": (variables, SMALL_MODEL), "fast": (fast_variables, SMALL_FAST)}[
        network
    ]
    source = Detector(weights, config, top_n=6, nms_radius=10, upsample=upsample)
    inference.export(source, path, 37, 53)
    run = inference.load_exported(path)
    stack = np.stack([image[:37, :53], image[3:, 3:]])
    expected = source.detect_batch(stack)
    for exported, features in zip(run(stack), expected):
        assert_same_features(exported, features)
    (single,) = run(stack[:1])  # the batch dimension is symbolic
    assert_same_features(single, expected[0])


def test_as_method_returns_every_candidate_for_uniform_evaluation(variables, image):
    method = evaluation.as_method(
        Detector(variables, SMALL_MODEL, top_n=3, nms_radius=10, border=4)
    )
    features = method.detect(image)
    assert method.name == "UnsuperPoint" and method.norm == cv2.NORM_L2
    assert len(features.scores) == (40 // 8) * (56 // 8)
    upsampled = evaluation.as_method(Detector(variables, SMALL_MODEL, top_n=3, upsample=2))
    assert len(upsampled.detect(image).scores) == (40 // 4) * (56 // 4)


def test_to_cv2_points_match_and_give_a_homography(detector, photo):
    # A shift by whole cells moves the (translation-equivariant) network's cells onto each
    # other, so even random weights match points further from the border than the network's
    # receptive field (about 90 px), hence an image this large.
    height, width = 160, 224
    image = cv2.resize(photo, (width, height), interpolation=cv2.INTER_AREA)
    shift = np.array([[1, 0, 16], [0, 1, 8], [0, 0, 1]], np.float64)
    warped = cv2.warpPerspective(image, shift, (width, height))
    keypoints1, descriptors1 = inference.to_cv2(detector.detect(image))
    keypoints2, descriptors2 = inference.to_cv2(detector.detect(warped))
    assert all(isinstance(k, cv2.KeyPoint) for k in keypoints1)
    assert descriptors1.dtype == np.float32 and descriptors1.shape == (len(keypoints1), 16)
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(descriptors1, descriptors2)
    p1 = np.float32([keypoints1[m.queryIdx].pt for m in matches])
    p2 = np.float32([keypoints2[m.trainIdx].pt for m in matches])
    correct = np.linalg.norm(p1 + shift[:2, 2] - p2, axis=1) < 1
    assert correct.sum() >= 50 and correct.mean() > 0.5
    homography, _ = cv2.findHomography(p1, p2, cv2.RANSAC, 1.0)
    corners = np.array([[0, 0], [0, height - 1], [width - 1, 0], [width - 1, height - 1]])
    error = evaluation.project_points(corners, homography) - evaluation.project_points(
        corners, shift
    )
    assert np.linalg.norm(error, axis=1).mean() < 2


class _CornerDetector(Detector):
    """A Detector whose network finds one keypoint on the first and one on the last pixel centre
    of whatever image it is given, and records that image's shape."""

    def __init__(self, max_side):
        self.max_side = max_side

    def _call(self, padded, sizes, top_n):
        self.shape = tuple(sizes[0])
        height, width = sizes[0]
        keypoints = np.array([[0, 0], [width - 1, height - 1]], np.float32)
        return [Features(keypoints, np.ones(2, np.float32), np.zeros((2, 4), np.float32))]


@pytest.mark.parametrize(
    "max_side, detected_shape", [(0, (600, 800)), (1000, (600, 800)), (400, (300, 400))]
)
def test_detection_on_a_smaller_copy_returns_keypoints_in_the_originals_pixels(
    max_side, detected_shape
):
    detector = _CornerDetector(max_side)
    features = detector.detect(np.zeros((600, 800, 3), np.uint8))
    assert detector.shape[:2] == detected_shape
    # Halved by area averaging, the first pixel of the copy covers pixels 0-1 of the original
    # (centre 0.5) and the last one pixels 798-799 (centre 798.5).
    expected = (
        [[0, 0], [799, 599]] if detected_shape == (600, 800) else [[0.5, 0.5], [798.5, 598.5]]
    )
    np.testing.assert_allclose(features.keypoints, expected)


#: In-plane turns (degrees) each shipped network must register the photo across. The upright
#: ones were trained on small turns only; the fast one already misses 3 px at 20 degrees.
SHIPPED_TURNS = {
    "paper": (20,),
    "parallax": (20,),
    "fast": (10,),
    "distilled": (10,),
    "rotation": (20, 120, -150),
}


@pytest.mark.parametrize(
    "name, turn", [(n, t) for n in sorted(weights_lib.PRETRAINED) for t in SHIPPED_TURNS[n]]
)
def test_each_shipped_weights_file_recovers_a_known_homography(name, turn, photo):
    detector = Detector.pretrained(name, top_n=500)
    truth = np.vstack([cv2.getRotationMatrix2D((255.5, 255.5), turn, 0.9), [0, 0, 1]])
    warped = cv2.warpPerspective(photo, truth, (512, 512))
    found = inference.match_and_estimate(detector.detect(photo), detector.detect(warped))
    assert found.homography is not None
    assert evaluation.corner_error(truth, found.homography, (512, 512)) < 3


def test_replace_changes_only_the_options_it_is_given(variables):
    original = Detector(variables, SMALL_MODEL, top_n=9, nms_radius=2, border=1, max_side=64)
    copy = original.replace(upsample=2, refine=False)
    options = ("top_n", "nms_radius", "border", "max_side", "any_scale")
    assert [getattr(copy, o) for o in options] == [getattr(original, o) for o in options]
    assert (copy.upsample, copy.refine, copy.refiner) == (2, False, None)
    assert copy.model_config == original.model_config
