"""A training run's folder: checks made before anything is written (also for the CLI's output
folders), the lock that keeps a second run out, the record of the config it was started with,
and the rule for resuming it with other settings (README, "Resuming").
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pathlib
import socket
import time
from typing import Any

import jax

from usp_jax.training import config as config_lib
from usp_jax.training.step import create_state

log = logging.getLogger(__name__)


class ConfigChanged(ValueError):
    """A workdir is resumed with settings other than those it was trained with."""


class WorkdirError(RuntimeError):
    """The workdir cannot be used: not a folder, not writable, in use by another run, or a
    write failed (a full disk) partway."""


#: Settings a resumed run may change without ``allow_config_change``: where it stops, how
#: often it logs and saves, how many checkpoints it keeps and how it reads its photos. None of


#: them changes what a training step computes.
RESUMABLE_KEYS = frozenset(
    {
        "num_steps",
        "checkpoint_every",
        "keep_checkpoints",
        "log_every",
        "data.num_workers",
        "data.prefetch",
        "data.tfds_data_dir",
    }
)
#: Held by a running ``fit`` inside its workdir; names the holder's pid and host.
LOCK_FILE = "train.lock"
#: One JSON line per resume that changed settings with ``allow_config_change``.
CONFIG_CHANGES_FILE = "config_changes.jsonl"


def folder_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be used, or be made, as a writable folder; None when it can.

    The text continues a sentence that names the path, e.g. ``f"--out {path}{problem}"``: the
    path exists as a file, or the nearest existing ancestor is a file or not writable.
    """
    target = pathlib.Path(path).expanduser().absolute()
    if target.exists() and not target.is_dir():
        return " exists and is not a folder"
    existing = target
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f": {existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f": {existing} is not writable"
    return None


#: What a run writes into its workdir: a folder holding any of them is a workdir (to resume).
WORKDIR_ENTRIES = frozenset(
    {"config.json", "checkpoints", "metrics.jsonl", "tensorboard", LOCK_FILE, CONFIG_CHANGES_FILE}
)


def check_workdir_path(workdir: pathlib.Path) -> None:
    """Raises WorkdirError unless ``workdir`` is, or can be made as, a writable folder, and is
    new, empty or a workdir already (``WORKDIR_ENTRIES``): a run never mixes its files into a
    folder of other data, such as the photos it trains on."""
    problem = folder_problem(workdir)
    if problem:
        raise WorkdirError(f"workdir {workdir}{problem}")
    entries = sorted(p.name for p in workdir.iterdir()) if workdir.is_dir() else []
    others = [name for name in entries if name not in WORKDIR_ENTRIES]
    if others and not _holds_a_run(workdir):
        raise WorkdirError(
            f"workdir {workdir} holds {len(others)} other entries (e.g. {others[0]}) and is not"
            " a training workdir (no config.json, no checkpoint in checkpoints/); give a new or"
            " empty folder"
        )
    for name in ("config.json", "checkpoints", "metrics.jsonl", "tensorboard"):
        path = workdir / name
        if path.exists() and not os.access(path, os.W_OK):
            raise WorkdirError(f"workdir {workdir}: {path} is not writable")


def _holds_a_run(workdir: pathlib.Path) -> bool:
    """Whether a run has written ``workdir``: its config record, or a checkpoint (an empty
    ``checkpoints/`` beside other files may be anyone's)."""
    checkpoints = workdir / "checkpoints"
    return (workdir / "config.json").is_file() or (
        checkpoints.is_dir() and any(checkpoints.iterdir())
    )


class WorkdirLock:
    """An exclusive ``flock`` on ``WORKDIR/train.lock``, which names its holder (pid, host,
    start time). The kernel drops it when the process dies, so a killed run leaves no stale
    lock; a clean exit removes the file."""

    def __init__(self, workdir: pathlib.Path):
        import fcntl

        self.path = workdir / LOCK_FILE
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode(errors="replace").strip() or "another process"
                os.close(fd)
                raise WorkdirError(
                    f"workdir {workdir} is in use by {holder}; wait for that run to end or stop it"
                ) from None
            except OSError:
                os.close(fd)
                raise
            # The previous holder may have removed the file between our open and our lock.
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self.fd = fd
        started = time.strftime("%Y-%m-%d %H:%M:%S")
        os.ftruncate(fd, 0)
        os.write(
            fd, f"pid {os.getpid()} on host {socket.gethostname()} (since {started})\n".encode()
        )

    def release(self) -> None:
        if self.fd is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self.fd)
        self.fd = None


def recorded_config(workdir: pathlib.Path) -> config_lib.Config | None:
    """The config a workdir's run was started with: ``config.json``, or the latest checkpoint's
    when that file is missing; None for a workdir no run has written."""
    path = workdir / "config.json"
    if path.is_file():
        try:
            return config_lib.read(path)
        # JSONDecodeError is a ValueError; JSON nested too deep a RecursionError.
        except (ValueError, TypeError, AttributeError, RecursionError) as error:
            raise WorkdirError(
                f"{path} is not a readable usp-jax config ({type(error).__name__}); the run's"
                " record is damaged"
            ) from None
    if (workdir / "checkpoints").is_dir():
        from usp_jax.training import checkpoint

        try:
            return checkpoint.load_config(workdir)
        except FileNotFoundError:
            return None
    return None


def _resolved(spec: str) -> str:
    """A path setting as the folder or file it names from here (``~`` and ``..`` resolved), so
    that one folder compares equal however it is typed, and two folders of one relative name
    from different directories do not; names that are no path (shipped weights, ``sample``,
    ``tfds:``) and "" stay as they are."""
    from usp_jax.inference.weights import PRETRAINED

    if not spec or spec == "sample" or spec.startswith("tfds:") or spec in PRETRAINED:
        return spec
    if spec.startswith("pairs:"):
        return "pairs:" + _resolved(spec.removeprefix("pairs:"))
    return str(pathlib.Path(spec).expanduser().resolve())


def with_resolved_paths(config: config_lib.Config) -> config_lib.Config:
    """``config`` with its paths (``data.source``, ``init_weights``, ``distill.teacher``)
    resolved (:func:`_resolved`). A workdir's record is stored so; an older record's relative
    paths are read from the current directory, as that run read them from its own."""
    return dataclasses.replace(
        config,
        data=dataclasses.replace(config.data, source=_resolved(config.data.source)),
        init_weights=_resolved(config.init_weights),
        distill=dataclasses.replace(config.distill, teacher=_resolved(config.distill.teacher)),
    )


def _state_layout(config: config_lib.Config) -> Any:
    """Shapes and dtypes of the TrainState ``config`` trains (nothing is computed)."""
    blank = dataclasses.replace(config, init_weights="")
    return jax.eval_shape(lambda: create_state(blank))


def _layout_mismatch(old: config_lib.Config, new: config_lib.Config) -> str | None:
    """Where the state ``new`` trains differs from the one ``old`` saved, or None."""
    old_leaves, old_tree = jax.tree_util.tree_flatten_with_path(_state_layout(old))
    new_leaves, new_tree = jax.tree_util.tree_flatten_with_path(_state_layout(new))
    if old_tree != new_tree:
        return "the state holds other arrays (model or optimizer structure)"
    for (path, a), (_, b) in zip(old_leaves, new_leaves):
        if a.shape != b.shape or a.dtype != b.dtype:
            return f"{jax.tree_util.keystr(path)} is {a.shape} in the checkpoints, {b.shape} here"
    return None


def _describe(changes: dict) -> str:
    return ", ".join(f"{key}: {old!r} -> {new!r}" for key, (old, new) in changes.items())


def check_resume(
    workdir: pathlib.Path,
    previous: config_lib.Config,
    config: config_lib.Config,
    allow_config_change: bool,
) -> dict:
    """The rule for resuming (README, "Resuming"): returns the changed keys, or raises."""
    changes = config_lib.differences(previous, config)
    material = {k: v for k, v in changes.items() if k not in RESUMABLE_KEYS}
    if material and not allow_config_change:
        raise ConfigChanged(
            f"workdir {workdir} was trained with other settings ({_describe(material)}); rerun"
            " with those, use a new --workdir, or pass --allow-config-change to continue it with"
            " these"
        )
    mismatch = _layout_mismatch(previous, config) if material else None
    if mismatch:
        raise ConfigChanged(
            f"workdir {workdir} cannot continue with {_describe(material)}: its checkpoints do"
            f" not fit this network or optimizer ({mismatch}); use a new --workdir (and"
            " --init WEIGHTS.npz to start from its weights)"
        )
    if material:
        log.warning("continuing %s with changed settings: %s", workdir, _describe(material))
    elif changes:
        log.info("resuming %s with %s", workdir, _describe(changes))
    return material
