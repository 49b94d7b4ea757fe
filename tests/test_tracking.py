"""The video tracker (``inference.tracking``), its sources and outputs (``inference.video``) and
``usp-jax track``: tracks on a sequence of known motion follow that motion, the keyframe rule
and track ids on controlled matches, and every bad input ends in one line and no output."""

import json

import cv2
import jax
import numpy as np
import pytest

from usp_jax.cli import main
from usp_jax.inference import tracking
from usp_jax.inference.detector import Detector
from usp_jax.inference.features import Features
from usp_jax.inference.images import grey
from usp_jax.inference.methods import opencv_method

SIZE = (96, 128)  # (height, width) of the test frames
STEPS = 6
# Per frame: a pan of (2.5, -1.5) px and a turn of 3 degrees about the frame's centre (4 px at
# the corners; 15 degrees, 21 px, over the sequence).
SHIFT, TURN = np.array([2.5, -1.5]), 3.0


def motion(k: float) -> np.ndarray:
    """float64 [2, 3]: the affine map from frame 0's pixels to frame k's."""
    height, width = SIZE
    turn = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), TURN * k, 1.0)
    turn[:, 2] += SHIFT * k
    return turn


@pytest.fixture(scope="module")
def frames(photo):
    """STEPS frames of a real photo moved by ``motion``: frame k shows the photo's centre
    crop warped by ``motion(k)`` (the photo's rest fills the border, so nothing turns black)."""
    height, width = SIZE
    small = cv2.resize(photo, (2 * width, 2 * height), interpolation=cv2.INTER_AREA)
    # Frame 0's pixel (x, y) is the small photo's (x + width / 2, y + height / 2).
    out = []
    for k in range(STEPS):
        to_frame = motion(k) @ np.array([[1, 0, -width / 2], [0, 1, -height / 2], [0, 0, 1]])
        out.append(cv2.warpAffine(small, to_frame, (width, height), flags=cv2.INTER_LINEAR))
    return out


def _apply(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ affine[:, :2].T + affine[:, 2]


def _step_errors(results) -> np.ndarray:
    """Distances (px) of every point continued from the previous frame to where the known
    motion takes that point's previous position."""
    errors = []
    for before, after in zip(results[:-1], results[1:]):
        step = motion(after.index) @ np.vstack(
            [cv2.invertAffineTransform(motion(before.index)), [0, 0, 1]]
        )
        common, i, j = np.intersect1d(before.track_ids, after.track_ids, return_indices=True)
        errors.append(np.linalg.norm(_apply(step, before.points[i]) - after.points[j], axis=1))
    return np.concatenate(errors)


# Tolerances (px) per detector: the median step error, the share within RANSAC's 3 px, and the
# median error over the whole sequence. The network's cells localise to about 1 px on frames this
# small (0.7 px on the held-out pairs); SIFT refines its positions to a tenth of a pixel.
TOLERANCES = {"network": (1.2, 0.85, 2.0), "sift": (0.3, 0.95, 0.5)}


@pytest.mark.parametrize("which", ["network", "sift"])
def test_tracks_follow_a_known_pan_and_turn(frames, which):
    detector = (
        Detector.pretrained(top_n=200, nms_radius=4)
        if which == "network"
        else opencv_method("SIFT", 200)
    )
    results = list(tracking.track(frames, detector))
    assert [r.index for r in results] == list(range(STEPS))
    errors = _step_errors(results)
    median, share, whole_median = TOLERANCES[which]
    # Most points are carried on, and they move as the frames do.
    assert len(errors) > 0.5 * sum(len(r.points) for r in results[1:])
    assert np.median(errors) < median and np.mean(errors < 3.0) > share
    # A track through every frame ends where the whole motion takes its start.
    first, last = results[0], results[-1]
    common, i, j = np.intersect1d(first.track_ids, last.track_ids, return_indices=True)
    assert len(common) >= 10
    whole = np.linalg.norm(_apply(motion(STEPS - 1), first.points[i]) - last.points[j], axis=1)
    assert np.median(whole) < whole_median


def test_every_n_tracks_every_nth_frame_and_the_motion_still_matches(frames):
    results = list(
        tracking.track(frames, opencv_method("SIFT", 200), tracking.TrackingConfig(every=2))
    )
    assert [r.index for r in results] == list(range(0, STEPS, 2))
    assert np.median(_step_errors(results)) < 1.0


def test_planar_verification_finds_the_same_motion(frames):
    config = tracking.TrackingConfig(planar=True)
    results = list(tracking.track(frames[:3], opencv_method("SIFT", 200), config))
    assert all(r.inliers.sum() > 20 for r in results[1:])
    assert np.median(_step_errors(results)) < 1.0


@pytest.mark.parametrize("refine", [False, True])
def test_refined_matches_reach_verification_only_when_asked(frames, monkeypatch, refine):
    # Points of frame 0 on a grid, frame 1's where the known motion takes them plus 1 px.
    xs, ys = np.meshgrid(np.arange(16.0, 112.0, 8.0), np.arange(16.0, 80.0, 8.0))
    points0 = np.stack([xs, ys], axis=-1).reshape(-1, 2)
    truth = _apply(motion(1), points0)
    points1 = truth + np.where(np.arange(len(truth))[:, None] % 2, 1.0, -1.0) * [1.0, 0.0]
    descriptors = np.eye(len(points0), dtype=np.float32)  # match i to i
    features = [
        Features(p.astype(np.float32), np.ones(len(p)), descriptors) for p in (points0, points1)
    ]
    seen = {}

    def verify(points1, points2, config):
        seen["p2"] = points2
        return np.ones(len(points2), bool)

    monkeypatch.setattr(tracking, "verify", verify)
    config = tracking.TrackingConfig(refine_matches=refine)
    greys = tuple(grey(frame).astype(np.float32) for frame in frames[:2])
    matches, _ = tracking.match_frames(*features, cv2.NORM_L2, config, greys)
    error = np.linalg.norm(seen["p2"] - truth[matches[:, 1]], axis=1)
    if refine:  # closer; the turn of 3 degrees and the frames' resampling bias plain NCC
        assert np.median(error) < 0.4
    else:
        np.testing.assert_allclose(error, 1.0, atol=1e-5)


def test_a_frame_costs_one_refinement_its_match_to_the_previous_frame(frames, monkeypatch):
    """The match to the keyframe is verified as matched: refining it too changed nothing
    measurable on footage (RESULTS.md "Video") and cost a second refinement per frame."""
    calls = []

    def counting(*args, **kwargs):
        calls.append(kwargs["affine_steps"])
        return refine_matches(*args, **kwargs)

    refine_matches = tracking.refine_matches
    monkeypatch.setattr(tracking, "refine_matches", counting)
    monkeypatch.setattr(tracking, "THREADS", 1)  # one call per refinement, not a share per thread
    results = list(tracking.track(frames[:4], opencv_method("SIFT", 200)))
    assert any(r.keyframe != r.index - 1 for r in results[2:])  # a keyframe match was made
    assert calls == [tracking.AFFINE_STEPS] * 3
    calls.clear()
    list(
        tracking.track(
            frames[:3], opencv_method("SIFT", 200), tracking.TrackingConfig(refine_matches=False)
        )
    )
    assert calls == []


def test_the_refinement_split_over_threads_tracks_as_on_one(frames, monkeypatch):
    def run(threads):
        monkeypatch.setattr(tracking, "THREADS", threads)
        return list(tracking.track(frames[:4], opencv_method("SIFT", 200)))

    one, three = run(1), run(3)
    assert sum(int(r.inliers.sum()) for r in one) > 0
    for a, b in zip(one, three, strict=True):
        np.testing.assert_array_equal(a.matches, b.matches)
        np.testing.assert_array_equal(a.inliers, b.inliers)
        np.testing.assert_array_equal(a.track_ids, b.track_ids)


@pytest.mark.parametrize(
    "options, refined",
    [(["--method", "orb"], False), (["--method", "orb", "--refine-matches"], True), ([], True)],
)
def test_cli_refines_the_networks_matches_by_default_and_a_peers_when_asked(
    frames, tmp_path, monkeypatch, options, refined
):
    configs = []
    track = tracking.track

    def recording(frames, detector, config):
        configs.append(config)
        return track(frames, detector, config)

    monkeypatch.setattr(tracking, "track", recording)
    _write_video(source := tmp_path / "tiny.avi", frames[:2])
    assert main(["track", str(source), "--no-progress", "--top", "50", *options]) == 0
    assert [c.refine_matches for c in configs] == [refined]


def test_track_ids_continue_previous_then_bridge_from_the_keyframe_then_start_new():
    ids, next_id = tracking.assign_track_ids(
        5,
        np.array([10, 11, 12]),
        (np.array([[0, 1], [2, 0], [1, 4]]), np.array([True, False, True])),
        np.array([7, 8, 11]),
        # Keyframe point 0 (track 7) bridges to point 2; point 3's keyframe track 11 is point
        # 4's already; the outlier to point 0 does not count.
        (np.array([[0, 2], [2, 3], [1, 0]]), np.array([True, True, False])),
        next_id=20,
    )
    assert ids.tolist() == [20, 10, 7, 21, 11] and next_id == 22


class _Scripted:
    """A detector that returns prepared features: frame k (its first pixel says k) gets
    ``features[k]``."""

    def __init__(self, features):
        self.features = features

    def detect(self, frame):
        return self.features[int(frame[0, 0, 0])]


def test_keyframe_rule_new_keyframe_when_its_inliers_fall_under_half_the_previous_ones():
    # A window of 200 points slides along a stream by 40 per frame (each point keeps its place
    # and descriptor): a frame shares 200 - 40 g points with the frame g back. 160 with the
    # previous frame, so the keyframe changes when 200 - 40 g < 80: at g = 4, not at 3 (80).
    rng = np.random.default_rng(0)
    width, step, count = 200, 40, 9
    points = rng.uniform(0, 500, (width + step * count, 2)).astype(np.float32)
    descriptors = rng.normal(size=(width + step * count, 32)).astype(np.float32)
    window = [slice(k * step, k * step + width) for k in range(count)]
    scripted = [Features(points[w], np.ones(width, np.float32), descriptors[w]) for w in window]
    frames = [np.full((8, 8, 3), k, np.uint8) for k in range(count)]
    config = tracking.TrackingConfig(planar=True)
    results = list(tracking.track(frames, _Scripted(scripted), config))
    assert [r.index for r in results if r.is_keyframe] == [0, 4, 8]
    assert [r.keyframe for r in results] == [0, 0, 0, 0, 0, 4, 4, 4, 4]
    assert [r.keyframe_inliers for r in results[1:]] == [160, 120, 80, 40, 160, 120, 80, 40]
    assert all(r.inliers.sum() == 160 for r in results[1:])
    # Points carried from frame 0 to 4 through every frame keep their ids.
    assert len(np.intersect1d(results[0].track_ids, results[4].track_ids)) == 40


def test_frames_of_changing_size_are_refused_naming_the_frame():
    frames = [np.zeros((64, 64, 3), np.uint8)] * 2 + [np.zeros((64, 72, 3), np.uint8)]
    with pytest.raises(ValueError, match="frame 2 has shape"):
        list(tracking.track(frames, opencv_method("ORB", 50)))


def _write_video(path, frames, fourcc="MJPG"):
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (width, height))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()


@pytest.mark.parametrize("method", ["usp", "sift"])
def test_cli_tracks_a_tiny_video_into_json_tracks_and_an_annotated_video(
    frames, tmp_path, capsys, method
):
    _write_video(source := tmp_path / "tiny.avi", frames)
    out, record, tracks = tmp_path / "out.avi", tmp_path / "t.json", tmp_path / "tracks.csv"
    argv = ["track", str(source), "--method", method, "--no-progress", "--top", "200"]
    assert main([*argv, "--out", str(out), "--json", str(record), "--tracks", str(tracks)]) == 0
    assert f"{STEPS} frames tracked with {method}" in capsys.readouterr().out
    document = json.loads(record.read_text())
    assert [f["index"] for f in document["frames"]] == list(range(STEPS))
    assert all(sum(f["inliers"]) > 20 for f in document["frames"][1:])
    rows = tracks.read_text().splitlines()
    assert rows[0] == "track,frame,x,y" and len(rows) > 100
    capture = cv2.VideoCapture(str(out))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == STEPS
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["tiny.avi", "out.avi", "t.json", "t.npz", "tracks.csv"]
    )
    # Beside the JSON, every frame's points again with their scores and descriptors.
    saved = tracking.load_features(tmp_path / "t.npz")
    assert document["features"] == "t.npz" and len(saved) == STEPS
    for frame, record in zip(saved, document["frames"], strict=True):
        assert np.allclose(frame["points"], record["points"], atol=0.005)
        assert frame["track_ids"].tolist() == record["track_ids"]
        assert len(frame["scores"]) == len(frame["descriptors"]) == len(record["points"])


@pytest.mark.parametrize("method", ["SIFT", "ORB"])
def test_features_file_round_trip_keeps_points_scores_ids_and_descriptors(frames, tmp_path, method):
    results = list(tracking.track(frames[:3], opencv_method(method, 100)))
    tracking.save_features(tmp_path / "f.npz", results)
    loaded = tracking.load_features(tmp_path / "f.npz")
    assert [f["index"] for f in loaded] == [r.index for r in results]
    for frame, result in zip(loaded, results, strict=True):
        assert np.array_equal(frame["points"], result.points)
        assert np.array_equal(frame["scores"], result.scores)
        assert np.array_equal(frame["track_ids"], result.track_ids)
        if method == "ORB":  # binary descriptors: their bytes, exactly
            assert np.array_equal(frame["descriptors"], result.descriptors)
        else:  # float descriptors as float16
            assert frame["descriptors"].dtype == np.float16
            assert np.allclose(frame["descriptors"], result.descriptors, rtol=1e-3, atol=1e-3)


def test_camera_motion_is_the_median_inlier_step_and_zero_for_a_still_camera(frames):
    moving = list(tracking.track(frames[:4], opencv_method("SIFT", 200)))
    still = list(tracking.track([frames[0]] * 4, opencv_method("SIFT", 200)))
    # Per frame: the pan's 2.9 px plus up to 4 px of the turn at the corners.
    assert 2.5 < tracking.camera_motion(moving) < 5.0
    assert tracking.camera_motion(still) < 0.01 < tracking.STATIC_MOTION
    assert tracking.camera_motion(moving[:1]) is None


@pytest.mark.parametrize("still", [True, False])
def test_cli_warns_when_the_camera_does_not_move(frames, tmp_path, capsys, still):
    _write_video(source := tmp_path / "tiny.avi", [frames[0]] * 4 if still else frames[:4])
    assert main(["track", str(source), "--method", "sift", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert ("warning: the camera does not move" in err) == still


def test_cli_progress_bar_names_the_source_and_method(frames, tmp_path, capsys):
    _write_video(source := tmp_path / "tiny.avi", frames[:3])
    assert main(["track", str(source), "--method", "orb"]) == 0
    assert "tracking tiny.avi (orb)" in capsys.readouterr().err


@pytest.mark.parametrize(
    "options, expected",
    [
        ([], ("distilled", tracking.VIDEO_SIDE, False)),
        (["--weights", "paper", "--network-side", "0"], ("paper", 0, False)),
    ],
)
def test_cli_network_defaults_to_the_distilled_weights_at_the_video_side(
    frames, tmp_path, monkeypatch, options, expected
):
    """``track``'s own default is the real-time one (``tracking.default_detector``), not the
    package's ``paper``; ``--weights`` and ``--network-side`` override it."""
    loaded = []
    pretrained = Detector.pretrained.__func__

    def recording(cls, name=None, **kwargs):
        loaded.append((name, kwargs["max_side"], kwargs["refine"]))
        return pretrained(cls, name, **kwargs)

    monkeypatch.setattr(Detector, "pretrained", classmethod(recording))
    _write_video(source := tmp_path / "tiny.avi", frames[:2])
    assert main(["track", str(source), "--no-progress", "--top", "50", *options]) == 0
    assert loaded == [expected]
    monkeypatch.undo()
    default = tracking.default_detector()
    assert (default.max_side, default.top_n) == (tracking.VIDEO_SIDE, tracking.TOP_N)
    assert default.refiner is None
    distilled = Detector.pretrained("distilled").variables
    assert all(
        np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(default.variables), jax.tree.leaves(distilled))
    )


def test_cli_png_strip_and_every(frames, tmp_path, capsys):
    for k, frame in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{k:03d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    strip = tmp_path / "strip.png"
    argv = ["track", str(tmp_path), "--method", "orb", "--every", "2", "--no-progress"]
    assert main([*argv, "--out", str(strip)]) == 0
    assert "3 frames tracked" in capsys.readouterr().out
    assert cv2.imread(str(strip)).shape == (SIZE[0], 3 * SIZE[1], 3)


def _bad_inputs(tmp_path, frames):
    (tmp_path / "empty.avi").write_bytes(b"")
    (tmp_path / "garbage.avi").write_bytes(np.random.default_rng(0).bytes(4000))
    (no_frames := tmp_path / "no_frames").mkdir()
    (no_frames / "notes.txt").write_text("no images here")
    _write_video(tmp_path / "one.avi", frames[:1])
    (sizes := tmp_path / "sizes").mkdir()
    for k, frame in enumerate([frames[0], frames[1], frames[2][:, :-8]]):
        cv2.imwrite(str(sizes / f"{k}.png"), frame)
    return {
        "an empty video": ([str(tmp_path / "empty.avi")], "no frame can be read"),
        "an unreadable video": ([str(tmp_path / "garbage.avi")], "no frame can be read"),
        "a missing video": ([str(tmp_path / "missing.avi")], "does not exist"),
        "a video with one frame": ([str(tmp_path / "one.avi")], "1 frame tracked"),
        "a missing camera": (["9"], "camera 9 cannot be opened"),
        "a folder with no frames": ([str(no_frames)], "folder has no frames"),
        "frames of changing size": ([str(sizes)], "frame 2 has shape"),
        "an unwritable --out": (
            [str(sizes), "--out", str(tmp_path / "nowhere" / "o.avi")],
            "does not exist",
        ),
        "an --out of no known kind": ([str(sizes), "--out", str(tmp_path / "o.gif")], "'.gif'"),
        "--weights with an OpenCV method": ([str(sizes), "--weights", "fast"], "only apply"),
        "--network-side with an OpenCV method": (
            [str(sizes), "--network-side", "320"],
            "--network-side only apply",
        ),
    }


@pytest.mark.parametrize(
    "case",
    [
        "an empty video",
        "an unreadable video",
        "a missing video",
        "a video with one frame",
        "a missing camera",
        "a folder with no frames",
        "frames of changing size",
        "an unwritable --out",
        "an --out of no known kind",
        "--weights with an OpenCV method",
        "--network-side with an OpenCV method",
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(frames, tmp_path, capsys, case):
    argv, message = _bad_inputs(tmp_path, frames)[case]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    outputs = tmp_path / "out"
    outputs.mkdir()
    written = ["--json", str(outputs / "t.json"), "--tracks", str(outputs / "t.csv")]
    if "--out" not in argv:
        written += ["--out", str(outputs / "o.avi")]
    code = main(["track", *argv, "--method", "orb", "--no-progress", *written])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert err[0].startswith("usp-jax track: error: ")
    assert list(outputs.iterdir()) == []  # not even a partial file
    assert sorted(p.name for p in tmp_path.rglob("*") if p != outputs) == before


def test_a_json_named_npz_is_refused_before_tracking(frames, tmp_path, capsys):
    _write_video(source := tmp_path / "tiny.avi", frames[:2])
    code = main(["track", str(source), "--method", "orb", "--json", str(tmp_path / "t.npz")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "name the JSON file .json" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.avi"]
