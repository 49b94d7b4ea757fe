"""benchmarks/bench_video.py's method specs: what each --networks and --baselines entry runs."""

import pathlib

import cv2
import numpy as np
import pytest

from usp_jax.inference.methods import opencv_method

BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def bench_video(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the script imports its sibling `common`
    import bench_video

    return bench_video


@pytest.mark.parametrize(
    "spec, expected",
    [
        ("paper", ("paper", 0, None, "UnsuperPoint paper")),
        ("fast:480", ("fast", 480, None, "UnsuperPoint fast at 480 px")),
        ("fast:480+refine", ("fast", 480, True, "UnsuperPoint fast at 480 px +refine")),
        ("paper-refine", ("paper", 0, False, "UnsuperPoint paper -refine")),
    ],
)
def test_network_spec_reads_name_side_and_refinement(bench_video, spec, expected):
    assert bench_video.network_spec(spec) == expected


def test_network_spec_refuses_a_side_that_is_no_whole_number(bench_video):
    with pytest.raises(ValueError, match="whole number"):
        bench_video.network_spec("fast:abc")


def test_a_shrunk_peer_detects_on_the_resized_frame_in_the_frames_pixels(bench_video, photo):
    """``SIFT:SIDE``: SIFT on the frame resized by OpenCV, its points scaled back about pixel
    corners, so that every method is matched in the frame's pixels."""
    frame = np.ascontiguousarray(photo[:300, :400])
    sift = opencv_method("SIFT", 300)
    small = cv2.resize(frame, (200, 150), interpolation=cv2.INTER_AREA)
    expected = sift.detect(small)
    found = bench_video.Shrunk(sift, 200).detect(frame)
    np.testing.assert_allclose(found.keypoints, (expected.keypoints + 0.5) * 2 - 0.5, atol=1e-4)
    np.testing.assert_array_equal(found.descriptors, expected.descriptors)
    assert bench_video.sided("SIFT:200") == ("SIFT", 200)


@pytest.mark.parametrize(
    "options, message",
    [
        (["--networks", "papr"], "unknown weights 'papr'"),
        (["--baselines", "SIFT:big"], "whole number"),
    ],
)
def test_a_bad_method_is_one_line_before_the_video_is_read(
    bench_video, monkeypatch, capsys, tmp_path, options, message
):
    # The video does not exist: an error about it would mean the specs were read too late.
    monkeypatch.setattr("sys.argv", ["bench_video.py", str(tmp_path / "none.mp4"), *options])
    with pytest.raises(SystemExit) as exit_info:
        bench_video.main()
    error = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and message in error[-1], error


def test_pose_accuracy_of_exact_matches_along_a_camera_path_is_one(bench_video):
    from usp_jax.evaluation import scenes
    from usp_jax.inference.features import Features

    room = scenes.Scene((), np.array([1.0, 1, 1]), np.array([3.0, 3, 1.5]), np.zeros((0, 2, 2)))
    cameras = scenes.camera_path(room, 6, height=120, width=160, seed=0)
    points = np.random.default_rng(0).uniform((-5, -5, 0), (9, 9, 3), (400, 3))

    class Recording:
        norm = cv2.NORM_L2
        features = {}

    for index, camera in enumerate(cameras):
        pixels, depth = scenes.project(points, camera)
        # Points behind the camera get no descriptor match: a unique code per point and side.
        codes = np.eye(800, dtype=np.float32)[np.arange(400) + 400 * (depth < 0)]
        Recording.features[index] = Features(pixels.astype(np.float32), np.ones(400), codes)
    accuracy = bench_video.pose_accuracy(Recording, [(0, 5), (1, 3)], cameras)
    assert accuracy == {
        "5": pytest.approx(1, abs=1e-3),
        "10": pytest.approx(1, abs=1e-3),
        "20": pytest.approx(1, abs=1e-3),
    }


def test_ncc_refines_a_methods_matches_in_the_tracker_and_its_absence_does_not(bench_video):
    from usp_jax.inference import tracking

    assert bench_video.refinement("distilled:560-refine/ncc") == (
        "distilled:560-refine",
        tracking.TrackingConfig(),
        f" +ncc {tracking.AFFINE_STEPS}",
    )
    assert bench_video.refinement("SIFT/ncc=2")[1:] == (
        tracking.TrackingConfig(affine_steps=2),
        " +ncc 2",
    )
    assert not bench_video.refinement("SIFT")[1].refine_matches
    with pytest.raises(ValueError, match="ncc or ncc=STEPS"):
        bench_video.refinement("SIFT/nms2")
