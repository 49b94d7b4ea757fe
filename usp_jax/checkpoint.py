"""Orbax checkpoints of a training run: the whole ``TrainState`` plus the resolved config.

Orbax writes each step into a temporary folder and renames it only once complete, so a run
killed while saving leaves no half checkpoint behind: ``latest_step`` only sees complete ones.
"""

from __future__ import annotations

import pathlib
from typing import Any

import jax
import orbax.checkpoint as ocp

from usp_jax import config as config_lib


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


def resolve(path: pathlib.Path | str) -> tuple[pathlib.Path, int]:
    """(checkpoints folder, step) for a workdir, its ``checkpoints/`` folder, or one step folder."""
    path = pathlib.Path(path).expanduser().absolute()
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    if (path / "checkpoints").is_dir():
        path = path / "checkpoints"
    if path.name.isdigit() and (path / "state").is_dir():
        return path.parent, int(path.name)
    step = ocp.CheckpointManager(path).latest_step()
    if step is None:
        raise FileNotFoundError(f"no complete checkpoint under {path}")
    return path, step


def load_config(path: pathlib.Path | str) -> config_lib.Config:
    """The config saved with the latest checkpoint under ``path`` (see :func:`resolve`)."""
    directory, step = resolve(path)
    with ocp.CheckpointManager(directory) as mngr:
        saved = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    return config_lib.from_dict(saved["config"])


def load_variables(path: pathlib.Path | str) -> tuple[config_lib.Config, dict]:
    """For inference: (config, {"params", "batch_stats"}) of the latest checkpoint under ``path``,
    on this process's first device, whatever devices the run that saved it trained on."""
    directory, step = resolve(path)
    mngr = ocp.CheckpointManager(directory, item_handlers={
        "state": ocp.StandardCheckpointHandler(), "config": ocp.JsonCheckpointHandler()})
    cfg = config_lib.from_dict(
        mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
    )
    # Onto this process's first device: a run on several devices or hosts saved its arrays
    # with shardings over those, which orbax refuses to recreate on other devices.
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    abstract = jax.tree.map(
        lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=device),
        mngr.item_metadata(step)["state"],
    )
    restored = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
    state = restored["state"]
    return cfg, {"params": state["params"], "batch_stats": state["batch_stats"]}
