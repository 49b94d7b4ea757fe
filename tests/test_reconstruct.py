"""``usp-jax reconstruct``: its bad input (one line, exit 2, nothing half-written) on a small
random network, and a rendered camera path that reconstructs with its true relative rotations."""

import json
import re
import sys

import cv2
import numpy as np
import pytest

from usp_jax.cli import main


def _write(folder, images):
    folder.mkdir(exist_ok=True)
    for name, image in images.items():
        cv2.imwrite(str(folder / name), image)
    return folder


def _noise(seed, shape=(64, 80)):
    return np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)


def _argv(images, out, weights):
    return ["reconstruct", str(images), "--out", str(out), "--checkpoint", str(weights)] + [
        "--top",
        "50",
        "--no-progress",
    ]


@pytest.mark.parametrize(
    "images, message",
    [
        ({}, "two images or more, found 0"),
        ({"a.png": _noise(0)}, "two images or more, found 1"),
        ({"a.png": _noise(0), "b.png": _noise(1, (64, 96))}, "b.png is 96x64.*one COLMAP camera"),
    ],
    ids=["empty", "one-image", "mixed-sizes"],
)
def test_too_few_or_mixed_images_are_one_line_exit_2_and_write_nothing(
    images, message, small_weights, tmp_path, capsys
):
    folder = _write(tmp_path / "images", images)
    assert main(_argv(folder, tmp_path / "out", small_weights)) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and re.search(message, error)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]


def test_a_folder_holding_something_else_is_refused(small_weights, tmp_path, capsys):
    folder = _write(tmp_path / "images", {"a.png": _noise(0), "b.png": _noise(1)})
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(_argv(folder, out, small_weights)) == 2
    assert "not a reconstruct output" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize(
    "options, message",
    [
        (["--camera-model", "PINHOL"], "camera model 'PINHOL' is not COLMAP's; one of"),
        (["--camera-params", "500,320,240"], "SIMPLE_RADIAL takes 4 finite parameters"),
        (["--camera-params", "500,x"], "expected numbers separated by commas, got '500,x'"),
        (["--no-refine-intrinsics"], "--no-refine-intrinsics needs the camera"),
    ],
    ids=["unknown-model", "wrong-count", "not-numbers", "fixed-without-camera"],
)
def test_a_camera_colmap_cannot_use_is_one_line_exit_2_and_writes_nothing(
    options, message, small_weights, tmp_path, capsys
):
    folder = _write(tmp_path / "images", {"a.png": _noise(0), "b.png": _noise(1)})
    try:
        status = main([*_argv(folder, tmp_path / "out", small_weights), *options])
    except SystemExit as stop:  # argparse's own check of the option's type
        status = stop.code
    assert status == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and message in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]


def test_without_pycolmap_the_error_names_the_install_command(
    small_weights, tmp_path, capsys, monkeypatch
):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap raises ImportError
    folder = _write(tmp_path / "images", {"a.png": _noise(0), "b.png": _noise(1)})
    assert main(_argv(folder, tmp_path / "out", small_weights)) == 2
    assert "pip install 'usp-jax[sfm]'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_no_model_still_writes_the_summary_and_unreadable_images_are_skipped(
    small_weights, tmp_path, capsys
):
    folder = _write(tmp_path / "images", {f"{i}.png": _noise(i) for i in range(3)})
    (folder / "broken.png").write_bytes(b"not an image")
    out = tmp_path / "out"
    assert main(_argv(folder, out, small_weights)) == 2
    error = capsys.readouterr().err
    assert "no model found" in error.splitlines()[-1]
    assert "WARNING" in error and "skipping" in error and "broken.png" in error
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == 3 and summary["models"] == [] and len(summary["skipped"]) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "out"]  # no partial folder
    # Its own earlier output is replaced, not refused.
    assert main(_argv(folder, out, small_weights)) == 2
    assert "no model found" in capsys.readouterr().err


#: Six views of a rendered room's far wall from a camera sliding 1 m sideways (true poses
#: known), 240x320: at that size the bundled photos on the walls are about as sharp as a view.
VIEWS, HEIGHT, WIDTH, TOP = 6, 240, 320, 500


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """(images folder, true poses by name, reconstruct output) of a rendered camera path."""
    from usp_jax.evaluation import scenes
    from usp_jax.inference.images import read_image, sample_photos

    photos = [
        read_image(path)
        for _, path in sample_photos()
        if not any(word in path.name for word in scenes.RESERVED)
    ]
    scene = scenes.room(photos, seed=0)
    middle = (scene.low[1] + scene.high[1]) / 2
    target = [scene.high[0] + scenes.CLEARANCE, middle, 1.4]
    root = tmp_path_factory.mktemp("rendered")
    images, poses = root / "images", {}
    images.mkdir()
    for index, side in enumerate(np.linspace(-0.5, 0.5, VIEWS)):
        pose = scenes.look_at([scene.low[0], middle + side, 1.5], target)
        camera = scenes.Camera(scenes.intrinsics(HEIGHT, WIDTH), *pose, HEIGHT, WIDTH)
        image = scenes.render(scene, camera)[0]
        cv2.imwrite(str(images / f"{index}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        poses[f"{index}.png"] = (camera.R, camera.centre)
    out = root / "out"
    argv = ["reconstruct", str(images), "--out", str(out), "--top", str(TOP), "--no-progress"]
    assert main([*argv, "--export-features"]) == 0
    return images, poses, out


@pytest.mark.slow
def test_a_rendered_path_reconstructs_with_its_true_relative_rotations(rendered):
    import pycolmap

    from usp_jax import sfm

    _, poses, out = rendered
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))  # COLMAP's own reader opens it
    assert model.num_reg_images() == VIEWS
    errors = sfm.pose_errors(model, poses)
    # Measured 0.08-0.35 degrees (rotation) and 0.44-0.80 (translation direction) over three
    # runs; 0.67 and 0.59 before the epipolar filter and the keypoint refinement.
    assert errors["pairs"] == VIEWS * (VIEWS - 1) // 2
    assert errors["median_rotation_error"] < 1.0
    assert errors["median_translation_error"] < 5.0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["registered_images"] == VIEWS and summary["points"] == model.num_points3D()
    assert {"points.ply", "cameras.png", "database.db", "features.npz"} <= {
        p.name for p in out.iterdir()
    }


@pytest.mark.slow
def test_a_known_camera_is_held_fixed_and_the_path_still_reconstructs(rendered, tmp_path):
    import pycolmap

    from usp_jax import sfm
    from usp_jax.evaluation import scenes

    images, poses, _ = rendered
    (fx, _, cx), (_, fy, cy) = scenes.intrinsics(HEIGHT, WIDTH)[:2]
    known = [fx, fy, cx + 0.5, cy + 0.5]  # COLMAP's principal point is OpenCV's plus 0.5
    out = tmp_path / "known"
    argv = ["reconstruct", str(images), "--out", str(out), "--top", str(TOP), "--no-progress"]
    assert (
        main([*argv, "--camera-model", "PINHOLE", "--camera-params", ",".join(map(str, known))])
        == 0
    )
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    (camera,) = model.cameras.values()
    assert camera.model_name == "PINHOLE"
    np.testing.assert_allclose(camera.params, known)  # bundle adjustment left it as given
    summary = json.loads((out / "summary.json").read_text())
    assert summary["camera"] == {
        "model": "PINHOLE",
        "params": known,
        "refined": False,
        "found": list(camera.params),
    }
    assert model.num_reg_images() == VIEWS
    assert sfm.pose_errors(model, poses)["median_rotation_error"] < 1.0


@pytest.mark.slow
def test_the_database_holds_what_the_detector_and_matcher_produced(rendered):
    import pycolmap

    from usp_jax.cli.reconstruct import WEIGHTS
    from usp_jax.inference.detector import MAX_SIDE, Detector
    from usp_jax.inference.images import read_image
    from usp_jax.inference.matching import mutual_nearest_neighbours

    images, _, out = rendered
    detector = Detector.pretrained(WEIGHTS, top_n=TOP, max_side=MAX_SIDE, refine=True)
    names = [f"{index}.png" for index in range(VIEWS)]
    features = [detector.detect(read_image(images / name)) for name in names]
    summary = json.loads((out / "summary.json").read_text())
    exported = np.load(out / "features.npz")
    differing = 0
    with pycolmap.Database.open(str(out / "database.db")) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        for name, found in zip(names, features):
            # The detector's keypoints, each moved at most the refinement's reach or not at all.
            moved = np.linalg.norm(
                db.read_keypoints(ids[name])[:, :2] - found.keypoints - 0.5, axis=1
            )
            assert len(moved) == len(found.keypoints) and moved.max() < 5.0
            differing += int((moved > 1e-3).sum())
        for i, j in [(0, 1), (2, 5)]:
            expected = mutual_nearest_neighbours(features[i].descriptors, features[j].descriptors)
            pair = f"{names[i]}//{names[j]}"
            np.testing.assert_array_equal(exported[f"{pair}/matches"], expected)
            # COLMAP gets the mutual nearest neighbours that pass the epipolar filter and settle.
            matches = db.read_matches(ids[names[i]], ids[names[j]])
            np.testing.assert_array_equal(exported[f"{pair}/kept"], matches)
            assert set(map(tuple, matches)) <= set(map(tuple, expected)) and len(matches) > 20
        counts = summary["refinement"]
        assert db.num_matches() == counts["kept_matches"] <= summary["epipolar_matches"]
        assert summary["epipolar_matches"] == counts["matches"] <= summary["matches"]
    assert 0 < differing <= counts["moved"]


def test_refine_keypoints_writes_the_refined_keypoints_to_the_database_and_counts_them(
    small_weights, tmp_path, capsys
):
    import pycolmap

    # Shifted copies of one smooth texture: the random network's matches join some keypoints
    # into tracks, whatever registers.
    texture = cv2.GaussianBlur(_noise(0, (96, 128)), (0, 0), 1.5)
    views = {f"{i}.png": np.roll(texture, (2 * i, 3 * i), axis=(0, 1)) for i in range(3)}
    folder = _write(tmp_path / "images", views)
    out = tmp_path / "out"
    main([*_argv(folder, out, small_weights), "--export-features"])  # refinement is the default
    summary = json.loads((out / "summary.json").read_text())
    assert summary["refine_keypoints"] is True and "refine" in summary["seconds"]
    counts = summary["refinement"]
    assert counts["tracks"] > 0 and counts["observations"] >= counts["moved"]
    assert counts["settled_matches"] <= counts["kept_matches"] <= counts["matches"]
    assert counts["matches"] == summary["epipolar_matches"]
    exported = np.load(out / "features.npz")
    with pycolmap.Database.open(str(out / "database.db")) as db:
        for image in db.read_all_images():
            np.testing.assert_array_equal(
                db.read_keypoints(image.image_id)[:, :2], exported[f"{image.name}/keypoints"]
            )
        assert db.num_matches() == counts["kept_matches"]
