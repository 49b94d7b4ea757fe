"""Hostile inputs and faults: one line on stderr and exit status 2, nothing half-made on disk,
and a workdir whose checkpoints, metrics and config stay consistent (issue: "one clear line,
nothing lost, every time")."""

import errno
import json
import math
import os
import subprocess
import sys
import types

import jax
import numpy as np
import pytest
from conftest import SMALL_MODEL, TINY_RUN, USP_JAX, child_env, tiny_config, train_args

from usp_jax import config as config_lib
from usp_jax import inference
from usp_jax.cli import main
from usp_jax.inference import nms
from usp_jax.training import checkpoint, train
from usp_jax.training import metrics as metrics_lib
from usp_jax.training import step as step_lib
from usp_jax.training import workdir as workdir_lib


def one_error_line(capsys, command: str) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if "libpng warning" not in line]
    assert len(err) == 1, err
    assert err[0].startswith(f"usp-jax {command}: error: ")
    return err[0]


# ---------------------------------------------------------------------------------------------
# Values: range-checked where they are parsed, before anything is written


@pytest.mark.parametrize(
    "override, message",
    [
        ("data.height=7", "data.height=7 must be >= 8"),
        ("data.width=100", "multiple of 8"),
        ("checkpoint_every=0", "checkpoint_every=0 must be >= 1"),
        ("log_every=0", "log_every=0 must be >= 1"),
        ("num_steps=-1", "num_steps=-1 must be >= 1"),
        ("batch_size=0", "batch_size=0"),
        ("optim.learning_rate=nan", "not a finite number"),
        ("loss.alpha_usp=inf", "not a finite number"),
        ("loss.alpha_desc=-1", "must be >= 0"),
        ("model=3", "'model' is a section"),
        ("model.descriptor_dim=0", "model.descriptor_dim=0"),
        ("model.dtype=int8", "float32, bfloat16, float16"),
        ("data.shuffle_seed='x'", "is not of type int or None"),
    ],
)
def test_a_bad_config_value_is_one_line_and_leaves_no_workdir(override, message, tmp_path, capsys):
    workdir = tmp_path / "w"
    assert main(["train", "--data", "sample", "--workdir", str(workdir), *TINY_RUN, override]) == 2
    assert message in one_error_line(capsys, "train")
    assert not workdir.exists()


def test_steps_and_num_steps_must_agree_and_negatives_are_refused(tmp_path, capsys):
    workdir = str(tmp_path / "w")
    assert main(["train", "--workdir", workdir, "--steps", "2", "num_steps=-1", *TINY_RUN]) == 2
    assert "num_steps=-1 must be >= 1" in one_error_line(capsys, "train")
    assert main(["train", "--workdir", workdir, "--steps", "2", "num_steps=3", *TINY_RUN]) == 2
    assert "--steps 2 and num_steps=3 disagree" in one_error_line(capsys, "train")
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize(
    "source, message",
    [
        ("def get_config(:\n", "syntax error at line 1"),
        ("import no_such_module_of_usp_jax\n", "failed to run: ModuleNotFoundError"),
        ("def get_config():\n    return 3\n", "get_config() returned int, not a"),
        (
            "def get_config():\n    raise RuntimeError('boom')\n",
            "get_config() failed: RuntimeError: boom",
        ),
        (
            "from usp_jax import config\ndef get_config():\n"
            "    return config.Config(log_every=0)\n",
            "log_every=0 must be >= 1",
        ),
    ],
)
def test_a_broken_config_file_is_one_line(source, message, tmp_path, capsys):
    path = tmp_path / "recipe.py"
    path.write_text(source)
    assert main(["train", "--workdir", str(tmp_path / "w"), "--config", str(path)]) == 2
    line = one_error_line(capsys, "train")
    assert message in line and str(path) in line
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["detect", "a.png", "--nms", "nan"], "'nan' is not a radius"),
        (["detect", "a.png", "--nms", "inf"], "'inf' is not a radius"),
        (["detect", "a.png", "--nms", "-1"], "'-1' is not a radius"),
        (["match", "a.png", "b.png", "--nms=-inf"], "'-inf' is not a radius"),
        (["export", "--save-weights", "w.npz", "--nms", "nan"], "'nan' is not a radius"),
        (["detect", "a.png", "--upsample", "100"], "'100' is above 8"),
        (["evaluate", "--hpatches", "x", "--res", "100000x8"], "exceeds"),
        (["train", "--workdir", "w", "--steps", "0"], "'0' is not a positive integer"),
    ],
)
def test_a_bad_option_is_one_parser_line_with_status_2(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith("usp-jax")


def test_the_api_rejects_non_finite_radii():
    variables = step_lib.init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    for bad in (math.nan, math.inf, -1.0):
        with pytest.raises(ValueError, match="nms_radius and border must be finite"):
            inference.Detector(variables, SMALL_MODEL, nms_radius=bad)
        with pytest.raises(ValueError, match="finite number >= 0"):
            nms.radius_nms(np.zeros((4, 2)), np.zeros(4), np.ones(4, bool), 2, 2, bad)


# ---------------------------------------------------------------------------------------------
# Paths: unwritable outputs and workdirs


def test_unwritable_outputs_are_one_line_before_any_work(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (["export", "--save-weights", str(tmp_path / "no" / "w.npz")], "export", "does not exist"),
        (["export", "--artifact", str(tmp_path)], "export", "is a folder, not a file"),
        (["detect", "a.png", "--out", str(tmp_path / "no" / "k.png")], "detect", "no"),
        (["detect", "a.png", "--json", str(afile / "k.json")], "detect", "afile"),
        (["demo", "--out", str(afile)], "demo", "is not a folder"),
        (["make-pairs", "--images", "x", "--out", str(afile / "p")], "make-pairs", "afile"),
        (
            ["train", "--data", "sample", "--workdir", str(afile), *TINY_RUN],
            "train",
            "exists and is not a folder",
        ),
    ]
    for argv, command, message in cases:
        assert main(argv) == 2, argv
        assert message in one_error_line(capsys, command)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_a_workdir_in_a_read_only_folder_is_one_line(tmp_path, capsys, monkeypatch):
    # Root ignores permission bits, so the check itself is made to answer "not writable".
    monkeypatch.setattr(workdir_lib.os, "access", lambda path, mode: False)
    assert main(["train", "--data", "sample", "--workdir", str(tmp_path / "w"), *TINY_RUN]) == 2
    assert "is not writable" in one_error_line(capsys, "train")
    assert not (tmp_path / "w").exists()


# ---------------------------------------------------------------------------------------------
# Weights files: shapes against their config, every value finite


def _rewrite(source, target, change):
    arrays = dict(np.load(source))
    change(arrays)
    np.savez(target, **arrays)
    return target


@pytest.mark.parametrize(
    "case, message",
    [
        ("nan", "holds NaN or infinite values"),
        ("inf", "holds NaN or infinite values"),
        ("shape", "has shape (3, 3)"),
        ("missing", "is missing"),
        ("extra", "params/Extra/kernel is not part of"),
        ("config", "model_config entry is not a valid model config"),
        ("strings", "not floating-point weights"),
    ],
)
def test_a_bad_weights_file_is_one_line_naming_the_file_and_the_array(
    case, message, small_weights, tmp_path, capsys
):
    key = "params/descriptor/kernel"

    def change(arrays):
        if case in ("nan", "inf"):
            arrays[key] = arrays[key].copy()
            arrays[key].flat[3] = np.nan if case == "nan" else np.inf
        elif case == "shape":
            arrays[key] = np.zeros((3, 3), np.float16)
        elif case == "missing":
            del arrays[key]
        elif case == "extra":
            arrays["params/Extra/kernel"] = np.zeros(3, np.float16)
        elif case == "config":
            arrays["model_config"] = np.array(json.dumps({"descriptor_dim": -4}))
        else:
            arrays[key] = np.array(["a", "b"])

    bad = _rewrite(small_weights, tmp_path / f"{case}.npz", change)
    with pytest.raises(ValueError) as info:
        inference.load_weights(bad)
    assert str(bad) in str(info.value) and message in str(info.value)
    if case in ("nan", "shape"):
        assert key in str(info.value)
    assert main(["detect", str(tmp_path / "a.png"), "--checkpoint", str(bad)]) == 2
    assert message in one_error_line(capsys, "detect")


def test_good_weights_still_load(small_weights):
    model_config, variables = inference.load_weights(small_weights)
    assert model_config == SMALL_MODEL and "batch_stats" in variables


# ---------------------------------------------------------------------------------------------
# Radius NMS at any radius: exact, memory bounded


@pytest.mark.parametrize(
    "radius, cell, grid",
    [
        (30.0, 8.0, (6, 7)),
        (100.0, 8.0, (6, 7)),
        (1e9, 8.0, (6, 7)),
        (40.0, 8.0, (20, 30)),
        (33.0, 4.0, (20, 30)),
        (4.0, 8.0, (1, 1)),
        (1e9, 8.0, (1, 5)),
    ],
)
def test_radius_nms_at_large_radii_matches_evaluation_nms_radius(radius, cell, grid):
    cells_h, cells_w = grid
    rng = np.random.default_rng(7)
    m = cells_h * cells_w
    rows, cols = np.divmod(np.arange(m), cells_w)
    keypoints = ((np.stack([cols, rows], axis=1) + rng.uniform(size=(m, 2))) * cell - 0.5).astype(
        np.float32
    )
    scores = rng.uniform(size=m).astype(np.float32)
    scores[: m // 4] = scores[0]  # ties: the lower index goes first in both
    valid = rng.uniform(size=m) < 0.9
    valid[0] = True
    keep = np.asarray(nms.radius_nms(keypoints, scores, valid, cells_h, cells_w, radius, cell))
    candidates = np.flatnonzero(valid)
    expected = candidates[nms.radius_nms_host(keypoints[candidates], scores[candidates], radius)]
    np.testing.assert_array_equal(np.flatnonzero(keep), np.sort(expected))
    # limit: the strongest `limit` points of the same result.
    limited = np.asarray(
        nms.radius_nms(keypoints, scores, valid, cells_h, cells_w, radius, cell, limit=2)
    )
    np.testing.assert_array_equal(np.flatnonzero(limited), np.sort(expected[:2]))


def test_a_huge_nms_radius_keeps_one_point_per_image(small_weights, photo):
    detector = inference.Detector.from_weights(small_weights, nms_radius=1e9, top_n=50)
    assert len(detector.detect(photo[:96, :128]).keypoints) == 1


# ---------------------------------------------------------------------------------------------
# Resuming: refuse a changed config unless asked, never rewrite a record of a run that did not
# start, refuse an incompatible network in one line


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("trained") / "run"
    train.fit(tiny_config(), workdir, progress=False)
    return workdir


def _snapshot(workdir):
    return {
        p.relative_to(workdir): p.read_bytes() for p in sorted(workdir.rglob("*")) if p.is_file()
    }


def test_resuming_with_other_settings_is_refused_naming_the_keys(trained):
    before = _snapshot(trained)
    changed = tiny_config(seed=7, **{"optim.learning_rate": 0.5})
    with pytest.raises(workdir_lib.ConfigChanged) as info:
        train.fit(changed, trained, progress=False, num_steps=4)
    assert "optim.learning_rate: 0.001 -> 0.5" in str(info.value)
    assert "seed: 0 -> 7" in str(info.value) and "--allow-config-change" in str(info.value)
    assert _snapshot(trained) == before


@pytest.mark.slow
def test_an_incompatible_network_is_refused_even_when_changes_are_allowed(trained, capsys):
    before = _snapshot(trained)
    bigger = tiny_config(**{"model.descriptor_dim": 128})
    with pytest.raises(workdir_lib.ConfigChanged, match="do not fit .*descriptor"):
        train.fit(bigger, trained, progress=False, num_steps=4, allow_config_change=True)
    with pytest.raises(workdir_lib.ConfigChanged, match="do not fit"):
        train.fit(
            tiny_config(**{"optim.clip_norm": 1.0}),
            trained,
            progress=False,
            num_steps=4,
            allow_config_change=True,
        )
    assert _snapshot(trained) == before
    assert (
        main(
            [
                "train",
                "--workdir",
                str(trained),
                "--data",
                "sample",
                "--no-progress",
                "--steps",
                "4",
                "--allow-config-change",
                "model.descriptor_dim=128",
            ]
        )
        == 2
    )
    line = one_error_line(capsys, "train")
    assert "model.descriptor_dim: 16 -> 128" in line
    assert _snapshot(trained) == before


@pytest.mark.slow
def test_allowed_changes_resume_and_are_recorded(tmp_path):
    workdir = tmp_path / "run"
    train.fit(tiny_config(), workdir, progress=False)
    # The step count, intervals and data loading may change without the flag.
    train.fit(
        tiny_config(num_steps=3, log_every=3, **{"data.num_workers": 1}), workdir, progress=False
    )
    assert config_lib.read(workdir / "config.json").num_steps == 3
    assert not (workdir / workdir_lib.CONFIG_CHANGES_FILE).exists()
    state = train.fit(
        tiny_config(num_steps=4, **{"optim.learning_rate": 0.002}),
        workdir,
        progress=False,
        allow_config_change=True,
    )
    assert int(state.step) == 4
    assert config_lib.read(workdir / "config.json").optim.learning_rate == 0.002
    changes = [
        json.loads(line)
        for line in (workdir / workdir_lib.CONFIG_CHANGES_FILE).read_text().splitlines()
    ]
    assert changes == [{"step": 3, "changes": {"optim.learning_rate": [0.001, 0.002]}}]
    assert not (workdir / workdir_lib.LOCK_FILE).exists()


def test_a_damaged_config_record_is_one_line(tmp_path, capsys):
    workdir = tmp_path / "run"
    workdir.mkdir()
    (workdir / "config.json").write_text("{not json")
    assert main(["train", "--data", "sample", "--workdir", str(workdir), *TINY_RUN]) == 2
    assert "config.json is not a readable usp-jax config" in one_error_line(capsys, "train")
    assert (workdir / "config.json").read_text() == "{not json"


# ---------------------------------------------------------------------------------------------
# One run per workdir


@pytest.mark.slow
def test_a_second_train_on_a_locked_workdir_is_told_who_holds_it(tmp_path):
    """The second run is a real process: the lock is the kernel's, per open file."""
    workdir = tmp_path / "run"
    workdir.mkdir()
    lock = workdir_lib.WorkdirLock(workdir)
    try:
        result = subprocess.run(
            [*USP_JAX, *train_args(workdir, 2, *TINY_RUN)],
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        lock.release()
    err = [line for line in result.stderr.splitlines() if "libpng" not in line]
    assert result.returncode == 2 and len(err) == 1, result.stderr
    assert f"is in use by pid {os.getpid()} on host" in err[0]
    assert sorted(p.name for p in workdir.iterdir()) == []


def test_a_lock_left_by_a_dead_process_does_not_block(tmp_path):
    workdir = tmp_path / "run"
    workdir.mkdir()
    # What a killed run leaves: the file, but no process holding its lock.
    (workdir / workdir_lib.LOCK_FILE).write_text("pid 1 on host gone\n")
    lock = workdir_lib.WorkdirLock(workdir)
    assert f"pid {os.getpid()}" in (workdir / workdir_lib.LOCK_FILE).read_text()
    with pytest.raises(workdir_lib.WorkdirError, match=f"in use by pid {os.getpid()}"):
        workdir_lib.WorkdirLock(workdir)
    lock.release()
    assert not (workdir / workdir_lib.LOCK_FILE).exists()


# ---------------------------------------------------------------------------------------------
# A full disk


def _full_disk_after(step):
    original = metrics_lib.MetricsWriter.write

    def write(self, done, metrics):
        if done > step:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "metrics.jsonl")
        original(self, done, metrics)

    return write


def test_a_full_disk_stops_the_run_in_one_error_and_the_workdir_resumes(tmp_path, monkeypatch):
    workdir = tmp_path / "run"
    monkeypatch.setattr(metrics_lib.MetricsWriter, "write", _full_disk_after(2))
    with pytest.raises(
        workdir_lib.WorkdirError, match="No space left on device.*checkpoint is step 2"
    ):
        train.fit(tiny_config(num_steps=4), workdir, progress=False)
    monkeypatch.undo()
    assert checkpoint.manager(workdir / "checkpoints").latest_step() == 2
    assert config_lib.read(workdir / "config.json") == tiny_config(num_steps=4)
    assert not (workdir / workdir_lib.LOCK_FILE).exists()
    # A row cut short by the full disk is dropped, and the run resumes.
    with open(workdir / "metrics.jsonl", "a") as file:
        file.write('{"step": 3, "lo')
    assert [r["step"] for r in metrics_lib.read_metrics(workdir)] == [1, 2]
    state = train.fit(tiny_config(num_steps=4), workdir, progress=False)
    assert int(state.step) == 4
    assert [r["step"] for r in metrics_lib.read_metrics(workdir)] == [1, 2, 3, 4]


def test_orbax_write_errors_are_recognised_as_a_full_disk():
    error = ValueError(
        'RESOURCE_EXHAUSTED: Error writing local file "/x/checkpoints/4.orbax-'
        "checkpoint-tmp/_sharding\": No space left on device [os_error_code='28']"
    )
    assert train._os_error_in(RuntimeError("no system error behind this")) is None
    try:
        raise RuntimeError("save failed") from error
    except RuntimeError as wrapped:
        found = train._os_error_in(wrapped)
    assert found.errno == errno.ENOSPC and found.filename.endswith("_sharding")


FULL_DISK_SCRIPT = """
import errno, os, sys
from usp_jax.training import metrics
from usp_jax.cli import main
original = metrics.MetricsWriter.write
def write(self, done, values):
    if done > 2:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self._jsonl.name)
    original(self, done, values)
metrics.MetricsWriter.write = write
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_a_full_disk_is_one_line_from_the_command(tmp_path):
    workdir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-c", FULL_DISK_SCRIPT, *train_args(workdir, 4, *TINY_RUN)],
        capture_output=True,
        text=True,
        timeout=300,
        env=child_env(),
    )
    err = [line for line in result.stderr.splitlines() if "libpng" not in line]
    assert result.returncode == 2 and len(err) == 1, result.stderr
    assert "No space left on device" in err[0] and "checkpoint is step 2" in err[0]
    assert "metrics.jsonl" in err[0]


@pytest.mark.skipif(
    os.geteuid() != 0 or not sys.platform.startswith("linux"),
    reason="mounting a small tmpfs needs root on Linux",
)
@pytest.mark.slow
def test_a_really_full_tmpfs_is_one_line(tmp_path):
    mount = tmp_path / "small"
    mount.mkdir()
    if subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)], capture_output=True
    ).returncode:
        pytest.skip("this container may not mount a tmpfs")
    try:
        result = subprocess.run(
            [*USP_JAX, *train_args(mount / "run", 2, *TINY_RUN)],
            capture_output=True,
            text=True,
            timeout=300,
            env=child_env(),
        )
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)
    # Exactly one line: the failed save's native threads, which call back into orbax's closed
    # asyncio loop, print nothing (they used to print hundreds of tracebacks around it).
    err = [line for line in result.stderr.splitlines() if "libpng" not in line]
    assert result.returncode == 2 and len(err) == 1, result.stderr
    assert err[0].startswith("usp-jax train: error: writing step 2 failed: ")
    assert err[0].endswith("No space left on device")


def test_only_callbacks_into_a_closed_loop_are_kept_quiet():
    from usp_jax.cli.errors import without_closed_loop_callbacks

    seen = []
    hook = without_closed_loop_callbacks(seen.append)
    kept = [RuntimeError("Event loop is still running"), ValueError("Event loop is closed")]
    for error in [RuntimeError("Event loop is closed"), *kept]:
        hook(types.SimpleNamespace(exc_value=error))
    assert [unraisable.exc_value for unraisable in seen] == kept
