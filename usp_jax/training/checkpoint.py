"""Orbax checkpoints of a training run: the whole ``TrainState`` plus the resolved config.

Reading a checkpoint's network alone, for inference, is ``inference.weights.read_checkpoint``.
Orbax writes each step into a temporary folder and renames it only once complete, so a run
killed while saving leaves no half checkpoint behind: ``latest_step`` only sees complete ones.
"""

from __future__ import annotations

import pathlib
from typing import Any

import jax
import orbax.checkpoint as ocp

from usp_jax.inference.weights import resolve_checkpoint
from usp_jax.training import config as config_lib


def manager(directory: pathlib.Path | str, keep: int = 3, create: bool = True):
    """A CheckpointManager over ``directory`` (made absolute: orbax requires it)."""
    directory = pathlib.Path(directory).expanduser().absolute()
    if not create and not directory.is_dir():
        raise FileNotFoundError(f"checkpoint folder {directory} does not exist")
    return ocp.CheckpointManager(
        directory,
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=create),
    )


def save(mngr, step: int, state: Any, config: config_lib.Config) -> None:
    """Asynchronous save; call ``mngr.wait_until_finished()`` before exiting."""
    mngr.save(
        step,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state),
            config=ocp.args.JsonSave(config_lib.to_dict(config)),
        ),
    )


def restore_state(mngr, like: Any, step: int | None = None) -> Any:
    """Restores the state saved at ``step`` (default: latest), shaped and sharded like ``like``."""
    step = mngr.latest_step() if step is None else step
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
    return mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))[
        "state"
    ]


def load_config(path: pathlib.Path | str) -> config_lib.Config:
    """The config saved with the latest checkpoint under ``path`` (a workdir, its
    ``checkpoints/`` or one step; ``inference.weights.resolve_checkpoint``)."""
    directory, step = resolve_checkpoint(path)
    with ocp.CheckpointManager(directory) as mngr:
        saved = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    return config_lib.from_dict(saved["config"], config_lib.Config)
