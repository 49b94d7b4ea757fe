"""The second hostile probe's defect classes and a new user's stumbles, rerun as tests: each case
ends in one clear line and exit status 2 (or does what the docs promise), writes nothing
half-made and overwrites nothing of the user's."""

import json
import logging
import os
import shutil

import numpy as np
import pytest
from conftest import TINY_RUN, one_error_line, snapshot

from usp_jax import inference
from usp_jax.cli import main
from usp_jax.core.model import ModelConfig, fast_config
from usp_jax.evaluation import pairs as pairs_lib
from usp_jax.inference import memory, video, weights
from usp_jax.training import config as config_lib
from usp_jax.training import metrics as metrics_lib
from usp_jax.training import workdir as workdir_lib


@pytest.fixture
def image(tmp_path, photo):
    import cv2

    path = tmp_path / "photo.png"
    assert cv2.imwrite(str(path), np.ascontiguousarray(photo[100:196, 100:228, ::-1]))
    return path


# ---------------------------------------------------------------------------------------------
# 1. A photo too large for the convolutions' packing: refused naming --max-side, not an abort


def test_packing_reserves_four_bytes_per_tap_of_the_widest_convolution():
    # The paper network: the second full-resolution conv, 9 taps x 32 inputs, float32.
    assert memory.packing_bytes(ModelConfig(), 1, 4000, 6000) == 4 * 9 * 32 * 4000 * 6000
    # The fast network: its widest packing is the 1/4-resolution residual conv's, 9 x 24 / 16,
    # or the first conv's 9 x 3, whichever is larger.
    fast = fast_config()
    per_pixel = max(27, 9 * fast.backbone_channels[1] / 16, 9 * fast.backbone_channels[2] / 16)
    assert memory.packing_bytes(fast, 2, 80, 80) == int(4 * per_pixel * 2 * 80 * 80)


def test_a_photo_whose_packing_outgrows_the_system_is_refused_naming_a_side_that_fits(
    image, monkeypatch, capsys
):
    memory._FITTED.clear()
    # The system grants 10 MB at once: the 96x128 photo's packing (14 MB) is refused although
    # plenty is free, as the kernel refused a 6000x4000 photo's 28 GB on a 24 GB machine.
    monkeypatch.setattr(memory, "reservable_bytes", lambda: 10 * 2**20)
    argv = ["detect", str(image), "--weights", "paper", "--max-side", "0", "--no-refine"]
    assert main(argv) == 2
    line = one_error_line(capsys, "detect")
    assert "to reserve for its convolutions" in line
    side = int(line.split("--max-side ")[1].split()[0])
    assert memory.packing_bytes(ModelConfig(), 1, side * 3 // 4, side) <= 10 * 2**20
    memory._FITTED.clear()


def test_reservable_memory_follows_the_overcommit_policy():
    limit = memory.reservable_bytes()
    assert limit is None or limit > 2**28  # RAM and swap, or the commit limit left


# ---------------------------------------------------------------------------------------------
# 2. Paths in a run's settings are the folders they name


def test_one_folder_typed_two_ways_is_one_setting_and_two_folders_of_one_name_are_two(
    tmp_path, monkeypatch
):
    for place in ("a", "b"):
        (tmp_path / place / "photos").mkdir(parents=True)
    base = config_lib.Config()
    monkeypatch.chdir(tmp_path / "a")
    typed = [
        config_lib.override(base, [f"data.source={source}"])
        for source in ("photos", str(tmp_path / "a" / "photos"), "../a/photos/")
    ]
    resolved = {workdir_lib.with_resolved_paths(c).data.source for c in typed}
    assert resolved == {str(tmp_path / "a" / "photos")}
    monkeypatch.chdir(tmp_path / "b")
    elsewhere = workdir_lib.with_resolved_paths(typed[0]).data.source
    assert elsewhere == str(tmp_path / "b" / "photos")
    # Names that are no path stay as typed.
    names = config_lib.override(base, ["data.source=sample", "init_weights=fast"])
    assert workdir_lib.with_resolved_paths(names) == names


@pytest.mark.slow
def test_a_resume_compares_the_folder_not_its_spelling(tmp_path, monkeypatch, capsys):
    for place, name in (("a", "coffee.png"), ("b", "chelsea.png")):
        (tmp_path / place / "photos").mkdir(parents=True)
        shutil.copy(sample_photo(name), tmp_path / place / "photos")
    workdir = str(tmp_path / "w")
    run = ["train", "--workdir", workdir, "--steps", "2", *TINY_RUN]
    monkeypatch.chdir(tmp_path / "a")
    assert main([*run, "--data", "photos"]) == 0
    recorded = json.loads((tmp_path / "w" / "config.json").read_text())["data"]["source"]
    assert recorded == str(tmp_path / "a" / "photos")
    assert main([*run, "--data", str(tmp_path / "a" / "photos")]) == 0
    monkeypatch.chdir(tmp_path / "b")
    capsys.readouterr()
    assert main([*run, "--data", "photos"]) == 2
    assert "data.source" in one_error_line(capsys, "train")


def sample_photo(name: str):
    """The bundled photo called ``name`` (scikit-image's)."""
    from usp_jax.inference.images import sample_photos

    (path,) = [path for _, path in sample_photos() if path.name == name]
    return path


# ---------------------------------------------------------------------------------------------
# 4. Sizes under one cell


@pytest.mark.parametrize(
    "argv",
    [
        ["detect", "a.png", "--max-side", "7"],
        ["match", "a.png", "b.png", "--max-side", "1"],
        ["track", "v.mp4", "--max-side", "7"],
        ["track", "v.mp4", "--network-side", "7"],
    ],
)
def test_a_side_under_one_cell_is_refused_by_the_parser(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "under 8 px" in capsys.readouterr().err


def test_the_api_refuses_a_side_under_one_cell(small_weights, tmp_path):
    model_config, variables = weights.load_weights(small_weights)
    for side in (1, 7, 2.5, -1):
        with pytest.raises(ValueError, match="max_side"):
            inference.Detector(variables, model_config, max_side=side)
    with pytest.raises(ValueError, match="max_side"):
        video.open_source(str(tmp_path), max_side=3)


# ---------------------------------------------------------------------------------------------
# 5, 6. Weights files: JSON nested too deep, integer arrays


def rewritten(source, target, **changes):
    with np.load(source) as data:
        arrays = {key: data[key] for key in data.files}
    np.savez(target, **{**arrays, **changes})
    return target


def test_a_model_config_nested_too_deep_is_one_line(small_weights, image, tmp_path, capsys):
    deep = rewritten(small_weights, tmp_path / "deep.npz", model_config=np.array("[" * 100_000))
    with pytest.raises(ValueError, match="model_config"):
        weights.load_weights(deep)
    assert main(["detect", str(image), "--checkpoint", str(deep)]) == 2
    assert "model_config entry is not a valid model config" in one_error_line(capsys, "detect")
    workdir = tmp_path / "w"
    assert (
        main(["train", "--data", "sample", "--workdir", str(workdir), "--teacher", str(deep)]) == 2
    )
    assert "model_config" in one_error_line(capsys, "train")
    assert not workdir.exists()


def test_a_config_record_nested_too_deep_is_a_damaged_record(tmp_path):
    (tmp_path / "config.json").write_text("[" * 100_000)
    with pytest.raises(workdir_lib.WorkdirError, match="not a readable usp-jax config"):
        workdir_lib.recorded_config(tmp_path)


def test_integer_weight_arrays_are_refused_naming_the_array_and_dtype(small_weights, tmp_path):
    with np.load(small_weights) as data:
        key = next(k for k in data.files if k.endswith("kernel"))
        kernel = data[key]
    path = rewritten(small_weights, tmp_path / "int8.npz", **{key: kernel.astype(np.int8)})
    with pytest.raises(ValueError, match=f"{key} holds int8"):
        weights.load_weights(path)


# ---------------------------------------------------------------------------------------------
# 7. metrics.jsonl with bad lines anywhere


def test_bad_metrics_lines_anywhere_are_skipped_and_counted(tmp_path, caplog):
    rows = [json.dumps({"step": step, "loss": 1.0 / step}) for step in (1, 2, 3)]
    lines = [rows[0], '{"step": 2, "lo', "[1, 2]", rows[1], "not json", rows[2], '{"step": 4']
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines))
    with caplog.at_level(logging.WARNING, logger="usp_jax.training.metrics"):
        read = metrics_lib.read_metrics(tmp_path)
    assert [row["step"] for row in read] == [1, 2, 3]
    assert "skipped 4 line(s)" in caplog.text and "line 2, 3, 5, 7" in caplog.text


# ---------------------------------------------------------------------------------------------
# 8. A folder given where a file is written


def test_a_folder_given_for_a_suffixed_file_is_refused_not_written_beside(
    small_weights, image, tmp_path, capsys
):
    folder = tmp_path / "out"
    folder.mkdir()
    for argv, command in (
        (["export", "--checkpoint", str(small_weights), "--save-weights", str(folder)], "export"),
        (
            ["detect", str(image), "--checkpoint", str(small_weights), "--out", str(folder)],
            "detect",
        ),
    ):
        assert main(argv) == 2, argv
        assert "is a folder, not a file" in one_error_line(capsys, command)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "photo.png"]
    model_config, variables = weights.load_weights(small_weights)
    with pytest.raises(ValueError, match="is a folder"):
        weights.save_weights(folder, variables, model_config)
    assert not (tmp_path / "out.npz").exists()


# ---------------------------------------------------------------------------------------------
# 9. An empty checkpoints/ among a user's files is no workdir


def test_user_files_beside_an_empty_checkpoints_folder_are_not_a_workdir(tmp_path, capsys):
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "thesis.tex").write_text("mine")
    before = snapshot(tmp_path)
    assert main(["train", "--data", "sample", "--workdir", str(tmp_path), *TINY_RUN]) == 2
    assert "is not a training workdir" in one_error_line(capsys, "train")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------------------------------------
# 10. make-pairs' re-run and a user's file inside a scene; skipped photos as plain lines


def test_a_rerun_refuses_a_users_file_inside_a_scene_and_keeps_it(tmp_path, photo, capsys):
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "a.png"), photo[:, :, ::-1])
    (photos / "broken.jpg").write_bytes(b"not an image")
    out = tmp_path / "pairs"
    argv = ["make-pairs", "--images", str(photos), "--out", str(out), "--size", "64x96"]
    assert main([*argv, "--views", "2", "--no-progress"]) == 0
    err = capsys.readouterr().err.splitlines()
    skipped = [line for line in err if "broken.jpg" in line]
    assert skipped == [
        f"usp-jax make-pairs: warning: skipping unreadable image {photos}/broken.jpg"
    ]
    (out / "v_a" / "notes.txt").write_text("mine")
    (out / "i_a" / "extra").mkdir()
    before = snapshot(out)
    assert main([*argv, "--views", "3", "--no-progress"]) == 2
    line = one_error_line(capsys, "make-pairs")
    assert "i_a/extra was not written by the make-pairs run" in line
    assert snapshot(out) == before


def test_make_pairs_reads_sample_as_the_bundled_photos(tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(
        pairs_lib, "make_pairs", lambda images, out, **_: seen.setdefault("i", images)
    )
    assert main(["make-pairs", "--images", "sample", "--out", str(tmp_path / "p")]) == 0
    assert len(seen["i"]) > 3 and all(path.is_file() for path in seen["i"])


# ---------------------------------------------------------------------------------------------
# 11, 12. Values of the wrong kind name their parameter or key


@pytest.mark.parametrize("top_n", [2.5, float("nan"), True, "3", 0])
def test_a_top_n_that_is_no_positive_integer_names_top_n(small_weights, top_n):
    detector = inference.Detector.load(small_weights)
    with pytest.raises(ValueError, match="top_n"):
        detector.detect(np.zeros((16, 16, 3), np.uint8), top_n=top_n)
    with pytest.raises(ValueError, match="top_n"):
        detector.replace(top_n=top_n)


@pytest.mark.parametrize(
    "override", ["data.scale_range=[[[[[[1]]]]]]", "data.scale_range=(0.5,)", "data.scale_range=7"]
)
def test_a_malformed_value_names_its_key(override, tmp_path, capsys):
    argv = ["train", "--data", "sample", "--workdir", str(tmp_path / "w"), override]
    assert main(argv) == 2
    assert "data.scale_range" in one_error_line(capsys, "train")
    assert not (tmp_path / "w").exists()


def test_a_value_nested_too_deep_to_parse_is_one_short_line(tmp_path, capsys):
    argv = ["train", "--data", "sample", "--workdir", str(tmp_path / "w")]
    assert main([*argv, "data.scale_range=" + "[" * 100_000]) == 2
    line = one_error_line(capsys, "train")
    assert "data.scale_range" in line and len(line) < 300


# ---------------------------------------------------------------------------------------------
# A new user's train, error lines and demo


def test_train_without_data_is_refused_naming_the_choices(tmp_path, capsys):
    assert main(["train", "--workdir", str(tmp_path / "w")]) == 2
    line = one_error_line(capsys, "train")
    assert "--data is required" in line and "'sample'" in line
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("command", [["detect", "a.png"], ["train", "--workdir", "w"], ["demo"]])
def test_an_unknown_option_is_the_subcommands_error_naming_its_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--bogus"])
    assert exit_info.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"usp-jax {command[0]}: error: unrecognized arguments: --bogus")
    assert line.endswith(f"(see usp-jax {command[0]} -h)")


def test_the_demo_writes_under_the_current_folder_unless_told(tmp_path, monkeypatch):
    from usp_jax import quickstart

    written = {}
    monkeypatch.setattr(quickstart, "demo", lambda out, name: written.setdefault("out", out))
    monkeypatch.chdir(tmp_path)
    assert main(["demo"]) == 0
    assert not os.path.isabs(written["out"]) and written["out"] == str(quickstart.DEFAULT_OUT)


@pytest.mark.slow
def test_train_names_the_earlier_step_of_a_damaged_checkpoint(tmp_path, capsys):
    workdir = tmp_path / "w"
    run = ["train", "--data", "sample", "--workdir", str(workdir), "--steps", "4", *TINY_RUN]
    assert main(run) == 0
    for path in (p for p in (workdir / "checkpoints" / "4").rglob("*") if p.is_file()):
        path.write_bytes(b"\xff\xfe\x00 not what orbax wrote " * 8)
    capsys.readouterr()
    run[run.index("--steps") + 1] = "6"
    assert main(run) == 2
    line = one_error_line(capsys, "train")
    assert "checkpoint step 4" in line and "is damaged" in line
    assert "the checkpoint before it is step 2" in line and "<" not in line


@pytest.mark.slow
@pytest.mark.parametrize(
    "signame, code, said", [("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "stopped by SIGTERM")]
)
def test_ctrl_c_or_sigterm_in_train_saves_a_checkpoint_and_names_the_step_it_resumes_from(
    tmp_path, signame, code, said
):
    import signal
    import subprocess
    import time

    from conftest import USP_JAX, child_env, train_args

    workdir = tmp_path / "w"
    argv = [*USP_JAX, *train_args(workdir, 10_000, *TINY_RUN, "checkpoint_every=5000")]
    # A shell starts background jobs with SIGINT ignored, and an ignored signal stays ignored
    # across exec: give the child Ctrl-C's default, as a terminal would.
    process = subprocess.Popen(
        argv,
        env=child_env(),
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 600
    while time.time() < deadline and len(metrics_lib.read_metrics(workdir)) < 3:
        time.sleep(0.5)
    process.send_signal(getattr(signal, signame))
    err = process.communicate(timeout=300)[1]
    assert process.returncode == code, err
    (line,) = [line for line in err.splitlines() if line.startswith("usp-jax train:")]
    step = int(line.split(f"{said} at step ")[1].split(";")[0])
    assert step >= 3 and (workdir / "checkpoints" / str(step)).is_dir()
    assert f"resume from step {step}" in line


# ---------------------------------------------------------------------------------------------
# 13. Compiled programs per input size are bounded


def test_a_detector_keeps_the_programs_of_its_last_sizes_only(small_weights):
    from usp_jax.inference import compiled

    detector = inference.Detector.load(small_weights, top_n=20)
    first = detector.detect(np.full((24, 32, 3), 90, np.uint8))
    for k in range(compiled.MAX_PROGRAMS + 2):
        detector.detect(np.full((32 + 8 * k, 40, 3), 90, np.uint8))
    assert detector._forward._cache_size() == compiled.MAX_PROGRAMS
    again = detector.detect(np.full((24, 32, 3), 90, np.uint8))  # compiled again: same points
    np.testing.assert_array_equal(again.keypoints, first.keypoints)
    np.testing.assert_array_equal(again.descriptors, first.descriptors)


# ---------------------------------------------------------------------------------------------
# The docs: one source per number, every weights name and command


def test_the_docs_take_speed_factors_from_the_readme():
    import pathlib
    import re

    root = pathlib.Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    factor = r"(\d+(?:\.\d+)?)x (?:the time|SIFT's time|the images/s|the compute)"
    for doc in ("docs/cli.md", "docs/api.md"):
        for value in re.findall(factor, (root / doc).read_text()):
            assert re.search(rf"\b{re.escape(value)}x\b", readme), f"{doc}: {value}x not in README"


def test_the_docs_name_every_shipped_weights_and_every_command_that_takes_them():
    import pathlib
    import re

    from usp_jax.cli.parser import build_parser
    from usp_jax.inference.weights import PRETRAINED

    root = pathlib.Path(__file__).resolve().parents[1]
    cli, api = ((root / doc).read_text() for doc in ("docs/cli.md", "docs/api.md"))
    for name in PRETRAINED:
        assert f"`{name}`" in cli and f"`{name}`" in api, name
    parser = build_parser()
    (commands,) = [a for a in parser._actions if hasattr(a, "choices") and a.choices]
    taking = {
        name
        for name, sub in commands.choices.items()
        if any("--weights" in a.option_strings for a in sub._actions)
    }
    listed = re.search(r"`--weights NAME` \(([^)]*)\)", cli)[1]
    assert taking == {name.strip() for name in listed.split(",")}
