"""Training on two views of a 3-D scene (``pairs:FOLDER``): the folder layout, examples, bad
pairs, and a run end to end."""

import json

import cv2
import numpy as np
import pytest
from test_train import tiny_config

from usp_jax.training import data, pairs, train, workdir
from usp_jax.training import metrics as metrics_lib

FOCAL, WALL, BASELINE = 100.0, 4.0, 0.2  # a wall 4 m away seen from two places 0.2 m apart


def write_pair(folder, height=48, width=64, seed=0):
    """Views of a textured wall from cameras 0.2 m apart sideways: view 2 is view 1 moved
    FOCAL * BASELINE / WALL px left (scaled with the image's width)."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (height, width + 40, 3), np.uint8), (3, 3), 0)
    focal = FOCAL * width / 64
    shift = round(focal * BASELINE / WALL)
    K = [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]]
    for index, start in ((1, 0), (2, shift)):
        view = np.ascontiguousarray(texture[:, start : start + width])
        cv2.imwrite(str(folder / f"{index}.png"), cv2.cvtColor(view, cv2.COLOR_RGB2BGR))
        np.save(folder / f"depth{index}.npy", np.full((height, width), WALL, np.float32))
    pose = {"K1": K, "K2": K, "R": np.eye(3).tolist(), "t": [-BASELINE, 0, 0]}
    (folder / "pose.json").write_text(json.dumps(pose))
    return folder


def test_a_pair_folder_gives_both_views_and_their_point_maps(tmp_path):
    for i in range(3):
        write_pair(tmp_path / f"p{i}", seed=i)
    pipeline = data.make_dataset(
        data.DataConfig(source=f"pairs:{tmp_path}", height=48, width=64), 2, seed=0
    )
    batch = pipeline[0]
    assert {k: (v.shape, v.dtype) for k, v in batch.items()} == {
        "image_a": ((2, 48, 64, 3), np.uint8),
        "image_b": ((2, 48, 64, 3), np.uint8),
        "a_to_b": ((2, 48, 64, 2), np.float32),
        "b_to_a": ((2, 48, 64, 2), np.float32),
    }
    # Either way round, A's pixel x lies at x -+ 5 in B (the same shift, the other direction).
    seen = np.isfinite(batch["a_to_b"][..., 0])
    shifts = np.unique(np.round(batch["a_to_b"][..., 0] - np.arange(64), 3)[seen])
    assert set(shifts) <= {-5.0, 5.0} and 0.85 < seen.mean() < 0.95


def test_a_pair_larger_than_the_crop_is_resized_with_its_intrinsics(tmp_path):
    pair = pairs.read_pair(write_pair(tmp_path / "p", height=96, width=128))
    example = pairs.example(pair, 48, 64, np.random.default_rng(0))
    a_to_b = example["a_to_b"]
    seen = np.isfinite(a_to_b[..., 0])
    shift = np.abs(a_to_b[..., 0] - np.arange(64))[seen]
    np.testing.assert_allclose(shift, 5.0, atol=1e-3)  # 10 px at 128 wide is 5 px at 64


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda f: (f / "depth2.npy").unlink(), "depth2.npy is missing"),
        (lambda f: np.save(f / "depth1.npy", np.ones((10, 10))), "depth1.npy is (10, 10)"),
        (lambda f: (f / "pose.json").write_text('{"K1": 1}'), "pose.json"),
        (lambda f: (f / "1.png").write_bytes(b"not a png"), "1.png"),
    ],
)
def test_a_broken_pair_is_skipped_naming_why_and_the_next_one_is_used(tmp_path, damage, reason):
    damage(write_pair(tmp_path / "a"))
    write_pair(tmp_path / "b", seed=1)
    pipeline = data.make_dataset(
        data.DataConfig(source=f"pairs:{tmp_path}", height=48, width=64, shuffle_seed=0), 2, seed=0
    )
    assert pipeline[0]["image_a"].shape == (2, 48, 64, 3)
    (line,) = pipeline.skipped.reasons()
    assert "unreadable pair" in line and reason in line


def test_a_folder_without_usable_pairs_stops_at_once_naming_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        data.make_dataset(data.DataConfig(source=f"pairs:{tmp_path / 'none'}"), 2, seed=0)
    with pytest.raises(ValueError, match="holds no NAME/pose.json"):
        data.make_dataset(data.DataConfig(source=f"pairs:{tmp_path}"), 2, seed=0)
    (write_pair(tmp_path / "a") / "depth1.npy").unlink()
    with pytest.raises(ValueError, match="none of its 1 images is usable"):
        data.make_dataset(data.DataConfig(source=f"pairs:{tmp_path}"), 2, seed=0)


def test_context_windows_and_pairs_are_refused_together():
    with pytest.raises(ValueError, match="pairs: source brings its own geometry"):
        data.DataConfig(source="pairs:x", context_window=True)


def test_a_pairs_source_is_stored_with_its_folder_resolved(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = tiny_config(**{"data.source": "pairs:rel"})
    assert workdir.with_resolved_paths(config).data.source == f"pairs:{tmp_path / 'rel'}"


def test_a_run_on_view_pairs_trains_and_logs_how_much_of_a_b_sees(tmp_path):
    for i in range(2):
        write_pair(tmp_path / "pairs" / f"p{i}", seed=i)
    cfg = tiny_config(num_steps=2, **{"data.source": f"pairs:{tmp_path / 'pairs'}"})
    train.fit(cfg, tmp_path / "run", progress=False)
    rows = metrics_lib.read_metrics(tmp_path / "run")
    assert [r["step"] for r in rows] == [1, 2]
    assert all(np.isfinite(r["loss"]) and 0.85 < r["data/seen_in_b"] < 0.95 for r in rows)
    assert all(r["usp/K"] > 0 for r in rows)
