"""The hostile-input probe's nine defect classes, rerun as tests: each case ends in one clear
line and exit status 2 (or, for a meaningless result, says so), writes nothing half-made and
overwrites nothing of the user's."""

import argparse
import errno
import json
import os
import re
import shutil

import cv2
import numpy as np
import pytest
from conftest import SMALL_MODEL, TINY_RUN, one_error_line, snapshot, tiny_config

from usp_jax import inference
from usp_jax.cli import main
from usp_jax.cli.parser import build_parser
from usp_jax.evaluation import pairs as pairs_lib
from usp_jax.evaluation import pairs_folder, sequences
from usp_jax.inference import matching as matching_lib
from usp_jax.inference import memory
from usp_jax.training import checkpoint, train
from usp_jax.training import workdir as workdir_lib


def write_rgb(path, image):
    assert cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return path


@pytest.fixture
def image(tmp_path, photo):
    return write_rgb(tmp_path / "photo.png", np.ascontiguousarray(photo[100:196, 100:228]))


def tiny_pairs(folder, homography=np.eye(3)):
    """One HPatches scene (v_a: two 64x96 views and H_1_2) under ``folder``."""
    scene = folder / "v_a"
    scene.mkdir(parents=True)
    rng = np.random.default_rng(0)
    view = rng.integers(0, 255, (64, 96, 3), dtype=np.uint8)
    write_rgb(scene / "1.ppm", view)
    write_rgb(scene / "2.ppm", view)
    np.savetxt(scene / "H_1_2", homography)
    return folder


# ---------------------------------------------------------------------------------------------
# 1. A damaged checkpoint, in every command that reads one


@pytest.fixture(scope="module")
def two_checkpoints(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("two") / "run"
    train.fit(tiny_config(SMALL_MODEL, (32, 48), 4), workdir, progress=False)
    assert sorted(p.name for p in (workdir / "checkpoints").iterdir()) == ["2", "4"]
    return workdir


@pytest.mark.parametrize("damage", ["no state folder", "corrupt bytes"])
def test_a_damaged_checkpoint_is_one_line_naming_its_step_and_the_one_before(
    damage, two_checkpoints, image, tmp_path, capsys
):
    workdir = tmp_path / "run"
    shutil.copytree(two_checkpoints, workdir)
    state = workdir / "checkpoints" / "4" / "state"
    if damage == "no state folder":
        shutil.rmtree(state)
    else:
        for path in (p for p in state.rglob("*") if p.is_file()):
            path.write_bytes(b"\xff\xfe\x00 not what orbax wrote " * 8)
    earlier = str(workdir / "checkpoints" / "2")
    with pytest.raises(ValueError) as info:
        inference.Detector.from_checkpoint(workdir)
    assert "checkpoint step 4" in str(info.value) and earlier in str(info.value)
    if damage == "no state folder":
        assert "no state/ folder" in str(info.value)
    pairs = tiny_pairs(tmp_path / "pairs")
    for argv in (
        ["detect", str(image), "--checkpoint", str(workdir)],
        ["evaluate", "--hpatches", str(pairs), "--checkpoint", str(workdir), "--no-progress"],
        ["export", "--checkpoint", str(workdir), "--save-weights", str(tmp_path / "w.npz")],
    ):
        assert main(argv) == 2, argv
        line = one_error_line(capsys, argv[0])
        assert "checkpoint step 4" in line and "is damaged" in line and earlier in line
    assert not (tmp_path / "w.npz").exists()
    # The checkpoint the message names loads.
    assert inference.Detector.from_checkpoint(earlier).model_config.descriptor_dim == 16


# ---------------------------------------------------------------------------------------------
# 2. The path printed is the path written


def test_every_path_a_command_prints_is_the_file_it_wrote(small_weights, image, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    pairs = tiny_pairs(tmp_path / "pairs")
    weights = str(small_weights)
    for argv in (
        ["export", "--checkpoint", weights, "--save-weights", str(out / "w")],
        ["export", "--checkpoint", weights, "--artifact", str(out / "a"), "--res", "32x48"],
        ["detect", str(image), "--checkpoint", weights, "--out", str(out / "k")],
        ["detect", str(image), "--checkpoint", weights, "--json", str(out / "k.json")],
        ["match", str(image), str(image), "--checkpoint", weights, "--out", str(out / "m")],
        ["match", str(image), str(image), "--checkpoint", weights, "--json", str(out / "m.json")],
        [
            "evaluate",
            *("--hpatches", str(pairs), "--checkpoint", weights, "--baselines", "orb"),
            *("--res", "64x96", "--no-progress", "--json", str(out / "e.json")),
            *("--plots", str(out / "plots")),
        ],
    ):
        assert main(argv) == 0, argv
    printed = re.findall(r"^wrote (\S+)", capsys.readouterr().out, re.MULTILINE)
    written = [str(p) for p in sorted(out.rglob("*")) if p.is_file()]
    assert sorted(printed) == written
    assert str(out / "w.npz") in printed and str(out / "k.png") in printed
    assert inference.Detector.load(out / "w.npz").model_config == SMALL_MODEL


def test_a_figure_suffix_matplotlib_cannot_write_is_refused_before_any_work(image, capsys):
    assert main(["detect", str(image), "--out", str(image.with_suffix(".xyz"))]) == 2
    assert "cannot be written as .xyz" in one_error_line(capsys, "detect")


# ---------------------------------------------------------------------------------------------
# 3. Never overwrite or mix into existing data


def test_make_pairs_writes_only_into_a_new_or_empty_folder_or_over_its_own_output(
    tmp_path, photo, capsys
):
    photos = tmp_path / "photos"
    photos.mkdir()
    write_rgb(photos / "a.png", np.ascontiguousarray(photo[::2, ::2]))
    make = ["make-pairs", "--images", str(photos), "--size", "64x96", "--views", "2"]
    make += ["--no-progress", "--out"]
    hpatches = tiny_pairs(tmp_path / "hpatches")
    for folder in (photos, hpatches):  # the user's photos; pairs not made by make-pairs
        before = snapshot(folder)
        assert main([*make, str(folder)]) == 2
        assert f"no {pairs_folder.MANIFEST}" in one_error_line(capsys, "make-pairs")
        assert snapshot(folder) == before
    out = tmp_path / "out"
    assert main([*make, str(out)]) == 0
    manifest = json.loads((out / pairs_folder.MANIFEST).read_text())
    assert manifest["complete"] and manifest["scenes"] == ["i_a", "v_a"]
    first = snapshot(out)
    assert main([*make, str(out)]) == 0  # a re-run replaces its own output, identically
    assert snapshot(out) == first
    (out / "notes.txt").write_text("mine")
    assert main([*make, str(out), "--seed", "3"]) == 2
    assert "notes.txt was not written by the make-pairs run" in one_error_line(capsys, "make-pairs")
    assert snapshot(out) == {**first, (out / "notes.txt").relative_to(out): b"mine"}


def test_train_refuses_a_folder_that_is_not_a_workdir_before_writing(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"not touched")
    assert main(["train", "--data", "sample", "--workdir", str(photos), *TINY_RUN]) == 2
    assert "is not a training workdir" in one_error_line(capsys, "train")
    assert sorted(p.name for p in photos.iterdir()) == ["a.jpg"]


# ---------------------------------------------------------------------------------------------
# 4. Memory: an image too large for native size is refused before compiling


def test_an_image_too_large_for_the_free_memory_is_one_line_naming_max_side(
    small_weights, image, monkeypatch, capsys
):
    free = 200_000  # bytes: what a 96x128 photo at native size outgrows with SMALL_MODEL
    monkeypatch.setattr(memory, "available_bytes", lambda: free)
    monkeypatch.setattr(memory, "_FITTED", set())  # shapes other tests ran on fitted then
    argv = ["detect", str(image), "--checkpoint", str(small_weights), "--max-side", "0"]
    assert main(argv) == 2
    line = one_error_line(capsys, "detect")
    side = int(re.search(r"--max-side (\d+) or less", line).group(1))
    assert 8 <= side < 128 and side % 8 == 0
    # The side it names fits, and detection there runs.
    height = side * 96 // 128
    assert memory.activation_bytes(SMALL_MODEL, 1, height, side) <= free
    assert main([*argv[:-1], str(side)]) == 0
    with pytest.raises(memory.ImageTooLarge, match="max_side="):
        inference.Detector.from_weights(small_weights).detect(np.zeros((96, 128, 3), np.uint8))


@pytest.mark.parametrize("upsample", [1, 2])
def test_a_tight_fit_is_decided_by_xlas_own_figure(small_weights, monkeypatch, upsample):
    detector = inference.Detector.from_weights(small_weights, upsample=upsample, top_n=50)
    side = memory.REFERENCE_SIDE
    images, sizes = np.zeros((1, side, side, 3), np.uint8), np.array([[side, side]], np.int32)
    compiled = detector._forward.lower(detector.variables, images, sizes, top_n=50).compile()
    analysis = compiled.memory_analysis()
    need = analysis.temp_size_in_bytes + analysis.output_size_in_bytes  # of a 128x128 image
    assert detector._bytes_per_pixel() * side**2 == pytest.approx(need)
    monkeypatch.setattr(memory, "_FITTED", set())
    shape = (1, side, side, 3)
    monkeypatch.setattr(memory, "available_bytes", lambda: int(0.9 * need))
    with pytest.raises(memory.ImageTooLarge):
        memory.check_fits(SMALL_MODEL, shape, upsample, detector._bytes_per_pixel)
    monkeypatch.setattr(memory, "available_bytes", lambda: int(1.5 * need))
    memory.check_fits(SMALL_MODEL, shape, upsample, detector._bytes_per_pixel)


def test_available_memory_is_read_from_the_system():
    free = memory.available_bytes()
    assert free is not None and 0 < free <= os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


# ---------------------------------------------------------------------------------------------
# 5. Every option checked before anything is written; scenes written whole or not at all


def test_a_bad_seed_is_refused_before_anything_is_written(tmp_path, photo, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    write_rgb(photos / "a.png", np.ascontiguousarray(photo[::4, ::4]))
    for seed in ("-1", str(2**32)):
        with pytest.raises(SystemExit) as exit_info:
            main(
                [
                    "make-pairs",
                    "--images",
                    str(photos),
                    "--out",
                    str(tmp_path / "o"),
                    "--seed",
                    seed,
                ]
            )
        assert exit_info.value.code == 2
        assert "--seed" in capsys.readouterr().err
    with pytest.raises(ValueError, match="seed must be an integer from 0"):
        pairs_lib.make_pairs(photos, tmp_path / "o", seed=-1)
    assert not (tmp_path / "o").exists()


def test_a_scene_that_fails_midway_leaves_nothing_half_made(tmp_path, photo, monkeypatch):
    photos = tmp_path / "photos"
    photos.mkdir()
    write_rgb(photos / "a.png", np.ascontiguousarray(photo[::4, ::4]))
    written = []

    def imwrite(path, image):  # the disk fills up at the scene's second image
        written.append(path)
        return len(written) < 2 and cv2.imwrite(path, image)

    monkeypatch.setattr(pairs_lib.cv2, "imwrite", imwrite)
    with pytest.raises(OSError, match="could not write"):
        pairs_lib.make_pairs(photos, tmp_path / "o", size=(64, 96), num_views=2)
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [pairs_folder.MANIFEST]
    assert not json.loads((tmp_path / "o" / pairs_folder.MANIFEST).read_text())["complete"]


# ---------------------------------------------------------------------------------------------
# 6. Pair files checked up front, each named


@pytest.mark.parametrize(
    "homography, message",
    [
        (np.zeros((3, 3)), "singular (rank 0)"),
        (np.array([[1.0, 2, 3], [2, 4, 6], [0, 0, 1]]), "singular (rank 2)"),
        (np.array([[1.0, 0, np.nan], [0, 1, 0], [0, 0, 1]]), "NaN or infinite"),
    ],
)
def test_a_bad_homography_file_is_named_before_any_work(
    homography, message, tmp_path, capsys, monkeypatch
):
    pairs = tiny_pairs(tmp_path / "pairs", homography)
    path = str(pairs / "v_a" / "H_1_2")
    with pytest.raises(ValueError, match=re.escape(message)) as info:
        sequences.scan_sequences(pairs)
    assert path in str(info.value)

    def no_work(*args, **kwargs):
        raise AssertionError("a pair was evaluated before the pair files were checked")

    monkeypatch.setattr("usp_jax.evaluation.protocol.evaluate_pair", no_work)
    assert main(["evaluate", "--hpatches", str(pairs), "--no-progress"]) == 2
    line = one_error_line(capsys, "evaluate")
    assert path in line and message in line


# ---------------------------------------------------------------------------------------------
# 7. A homography from too few inliers is reported as none


def _matching(inliers: int) -> matching_lib.Matching:
    mask = np.arange(40) < inliers
    return matching_lib.Matching(np.zeros((40, 2), np.int64), mask, np.eye(3))


def test_a_homography_needs_min_inliers_to_count():
    assert not _matching(4).reliable and not _matching(matching_lib.MIN_INLIERS - 1).reliable
    assert _matching(matching_lib.MIN_INLIERS).reliable
    assert not matching_lib.Matching(np.zeros((0, 2)), np.zeros(0, bool), None).reliable


def test_match_says_a_chance_homography_means_nothing(image, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(matching_lib, "match_and_estimate", lambda f1, f2: _matching(5))
    black = write_rgb(tmp_path / "black.png", np.zeros((96, 128, 3), np.uint8))
    out = tmp_path / "m.json"
    argv = ["match", str(image), str(black), "--weights", "fast", "--json", str(out)]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "no reliable homography: 5 RANSAC inliers" in captured.out
    assert "homography image1 -> image2" not in captured.out
    assert "usp-jax match: warning: no reliable homography" in captured.err
    result = json.loads(out.read_text())
    assert result["homography"] is None and result["reliable"] is False
    assert result["ransac_estimate"] == np.eye(3).tolist()


def test_a_photo_against_a_black_image_gives_no_homography(image, tmp_path, capsys):
    black = write_rgb(tmp_path / "black.png", np.zeros((96, 128, 3), np.uint8))
    assert main(["match", str(image), str(black), "--weights", "fast"]) == 0
    out = capsys.readouterr().out
    assert "no reliable homography" in out or "no homography" in out
    assert "homography image1 -> image2" not in out


# ---------------------------------------------------------------------------------------------
# 8. A full disk names the step being written and the last complete checkpoint


def test_a_failed_background_save_names_its_own_step_and_the_last_complete_one(
    tmp_path, monkeypatch
):
    workdir = tmp_path / "run"
    original = checkpoint.save

    def save(mngr, step, state, config):
        if step == 2:
            original(mngr, step, state, config)
        elif step == 6:  # step 4's background write failed; this save reports it
            raise ValueError(
                f'RESOURCE_EXHAUSTED: Error writing local file "{workdir}/checkpoints/4.orbax-'
                "checkpoint-tmp-17/state/_sharding\": No space left on device [os_error_code='28']"
            )

    monkeypatch.setattr(checkpoint, "save", save)
    with pytest.raises(workdir_lib.WorkdirError) as info:
        train.fit(tiny_config(SMALL_MODEL, (32, 48), 6), workdir, progress=False)
    message = str(info.value)
    assert message.startswith("writing step 4 failed: ") and "4.orbax-checkpoint-tmp" in message
    assert message.endswith("No space left on device; the last complete checkpoint is step 2")


def test_the_last_complete_checkpoint_is_read_from_disk(tmp_path):
    folder = tmp_path / "checkpoints"
    for name in ("2", "4", "6.orbax-checkpoint-tmp-3"):
        (folder / name).mkdir(parents=True)
    assert train._last_complete_step(folder) == 4
    assert train._last_complete_step(tmp_path / "none") is None
    error = OSError(errno.ENOSPC, "full", f"{folder}/6.orbax-checkpoint-tmp-3/state/x")
    assert train._failed_step(error, 10) == 6
    assert train._failed_step(OSError(errno.ENOSPC, "full", "metrics.jsonl"), 10) == 10


# ---------------------------------------------------------------------------------------------
# 9. Every numeric option has a range, checked by the parser


def _numeric_options():
    parser = build_parser()
    commands = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)][0]
    for command, subparser in commands.choices.items():
        required = []
        for action in subparser._actions:
            if not action.option_strings and action.nargs not in ("*", "?"):
                required.append("x")
            elif action.option_strings and action.required:
                required += [action.option_strings[0], "x"]
        for action in subparser._actions:
            if action.option_strings and action.type is not None:
                yield command, required, action.option_strings[-1]


@pytest.mark.parametrize("value", ["99999999999999999999", "-99999999999999999999", "nan", "1e400"])
def test_every_numeric_option_refuses_absurd_values_in_one_line(value, capsys):
    options = list(_numeric_options())
    assert len(options) > 20
    for command, required, flag in options:
        try:  # the parser refuses it, or the command before anything runs (make-pairs' angles)
            code = main([command, *required, f"{flag}={value}"])
        except SystemExit as exit_info:
            code = exit_info.code
        assert code == 2, (command, flag)
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith(f"usp-jax {command}"), (command, flag, err)
