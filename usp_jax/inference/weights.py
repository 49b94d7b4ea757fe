"""Where a detector's weights come from: the float16 ``.npz`` files (the ones that ship inside
the package, by name, and those ``usp-jax export --save-weights`` writes) and the network inside
a training checkpoint.

A weights file holds ``{"params", "batch_stats"}`` flattened to ``"params/..."`` keys, float16,
and the ModelConfig as JSON under ``model_config``. Reading one checks it completely before
anything is returned. Orbax is imported only to read a checkpoint, never for a weights file.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import json
import pathlib
import re
import zipfile

import flax
import jax
import numpy as np

from usp_jax.core import settings
from usp_jax.core.model import ModelConfig, init_variables

#: Folder of the weights that ship inside the package (experiments/RESULTS.md says how each
#: was trained).
WEIGHTS_DIR = importlib.resources.files("usp_jax") / "weights"
#: Shipped weights by name -> their file in WEIGHTS_DIR. "paper": the paper's VGG network;
#: "fast": ``core.model.fast_config()`` trained by experiments/fast.py, 4.3-5.3x the images/s but below
#: the paper network on the held-out pairs (HA@3 0.66 vs 0.91, MS 0.57 vs 0.65; RESULTS).
#: "rotation": the fast network trained on full-circle rotations by experiments/rotation.py,
#: for imagery that turns in-plane (its matching score no longer falls with the angle); on
#: upright pairs the upright weights are better.
#: "distilled": the fast network distilled from "paper" by experiments/distill.py, 20,000 steps:
#: the fast network's speed, above "fast" on HA@3 and MS (0.81 and 0.64) but below "paper".
PRETRAINED = {
    "paper": "paper.npz",
    "fast": "fast.npz",
    "rotation": "rotation.npz",
    "distilled": "distilled.npz",
    # ``paper`` fine-tuned on two views of rendered 3-D rooms (experiments/parallax_pairs.py):
    # more matches across parallax (leuven, aloe), the same elsewhere (RESULTS.md, real pairs).
    "parallax": "parallax.npz",
}
#: What ``Detector.pretrained()`` loads: the best of the named weights on the held-out pairs.
DEFAULT_PRETRAINED = "paper"

# Key of the JSON ModelConfig inside a weights file; parameter keys are "params/..." paths.
_CONFIG_KEY = "model_config"
_SEPARATOR = "/"


def weights_file(path: str | pathlib.Path) -> pathlib.Path:
    """The file :func:`save_weights` writes for ``path``: ``.npz`` is added to a name without
    it, as numpy does, and a weights file is told from a training workdir by that suffix."""
    path = pathlib.Path(path)
    return path if path.name.endswith(".npz") else path.with_name(path.name + ".npz")


def save_weights(
    path: str | pathlib.Path, variables: dict, model_config: ModelConfig
) -> pathlib.Path:
    """Write ``{"params", "batch_stats"}`` as one float16 ``.npz`` plus the ModelConfig as JSON;
    returns the file written (:func:`weights_file`).

    Float16 halves the file; inference casts back to float32. Raises ValueError instead of
    writing a value that float16 cannot hold (|x| > 65504), so no weight is silently lost, and
    for a ``path`` that is a folder (rather than writing ``FOLDER.npz`` beside it).
    """
    if pathlib.Path(path).is_dir():
        raise ValueError(f"weights file {path} is a folder, not a file")
    flat = flax.traverse_util.flatten_dict(
        {"params": variables["params"], "batch_stats": variables["batch_stats"]},
        sep=_SEPARATOR,
    )
    largest = np.finfo(np.float16).max
    for key, value in flat.items():
        if np.any(np.abs(np.asarray(value)) > largest):
            raise ValueError(f"weight {key} does not fit in float16 (|x| > {largest:g})")
    arrays = {key: np.asarray(value, dtype=np.float16) for key, value in flat.items()}
    config_json = json.dumps(dataclasses.asdict(model_config))
    path = weights_file(path)
    np.savez_compressed(path, **arrays, **{_CONFIG_KEY: np.array(config_json)})
    return path


def load_weights(path: str | pathlib.Path) -> tuple[ModelConfig, dict]:
    """Inverse of :func:`save_weights`: ``(ModelConfig, {"params", "batch_stats"})`` in float32.

    Checks the file before returning anything: its model config is valid, it holds exactly the
    arrays that config's network has, with their shapes (``jax.eval_shape`` of
    ``model.init_variables``), and every value is finite. Raises ValueError naming the file and
    the first bad array.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file {path} does not exist")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        # numpy's own message for a non-zip file talks about pickles, which misleads.
        raise ValueError(f"{path} is not a readable .npz weights file ({type(error).__name__})")
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"{path} is a single .npy array, not a usp-jax .npz weights file")
    with data:
        if _CONFIG_KEY not in data:
            raise ValueError(f"{path} is not a usp-jax weights file (no {_CONFIG_KEY} entry)")
        try:
            model_config = settings.from_dict(json.loads(str(data[_CONFIG_KEY])), ModelConfig)
            settings.check_fields(model_config, "model.")
        except (ValueError, TypeError, AttributeError, RecursionError) as error:
            raise ValueError(
                f"{path}: its {_CONFIG_KEY} entry is not a valid model config"
                f" ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''})"
            ) from None
        flat = {}
        for key in data.files:
            if key == _CONFIG_KEY:
                continue
            try:
                array = data[key]
            except (OSError, ValueError, zipfile.BadZipFile) as error:
                raise ValueError(f"{path}: array {key} is not readable ({type(error).__name__})")
            if array.dtype.kind != "f":  # integers would run, but no training writes them
                raise ValueError(
                    f"{path}: array {key} holds {array.dtype}, not floating-point weights"
                )
            flat[key] = array.astype(np.float32)
    _check_arrays(path, model_config, flat)
    return model_config, flax.traverse_util.unflatten_dict(flat, sep=_SEPARATOR)


def _check_arrays(path: pathlib.Path, model_config: ModelConfig, flat: dict) -> None:
    """Raises ValueError for the first array missing, extra, of the wrong shape or not finite."""
    abstract = jax.eval_shape(
        functools.partial(init_variables, config=model_config), jax.random.PRNGKey(0)
    )
    expected = flax.traverse_util.flatten_dict(
        {"params": abstract["params"], "batch_stats": abstract.get("batch_stats", {})},
        sep=_SEPARATOR,
    )
    network = (
        f"its {model_config.backbone} network (descriptor_dim"
        f" {model_config.descriptor_dim}, head_channels {model_config.head_channels})"
    )
    for key, like in expected.items():
        if key not in flat:
            raise ValueError(f"{path}: array {key} of {network} is missing")
        if flat[key].shape != like.shape:
            raise ValueError(
                f"{path}: array {key} has shape {flat[key].shape}, {network} needs {like.shape}"
            )
    for key, array in flat.items():
        if key not in expected:
            raise ValueError(f"{path}: array {key} is not part of {network}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{path}: array {key} holds NaN or infinite values")


def resolve_checkpoint(path: str | pathlib.Path) -> tuple[pathlib.Path, int]:
    """(checkpoints folder, step) for a training workdir, its ``checkpoints/`` folder, or one
    step folder; the latest complete step unless a step folder is named."""
    import orbax.checkpoint as ocp

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


def read_checkpoint(path: str | pathlib.Path) -> tuple[dict, dict]:
    """(the run's config as a dict, ``{"params", "batch_stats"}``) of the checkpoint under
    ``path`` (:func:`resolve_checkpoint`), on this process's first device, whatever devices the
    run that saved it trained on. Reads only what inference needs."""
    directory, step = resolve_checkpoint(path)
    if not (directory / str(step) / "state").is_dir():
        raise ValueError(damaged_checkpoint(directory, step, "it has no state/ folder"))
    try:
        return _read_step(directory, step)
    except Exception as error:  # damaged files: orbax's errors name neither file nor step
        raise ValueError(damaged_checkpoint(directory, step, error)) from error


def damaged_checkpoint(
    directory: pathlib.Path, step: int, problem: str | BaseException, resuming: bool = False
) -> str:
    """The one line for an unreadable checkpoint (loaded, or ``resuming`` a run): its folder,
    what is wrong (an error's type and first line, cut short and without the object reprs of
    the libraries underneath), and the step before it to use instead."""
    if isinstance(problem, BaseException):
        lines = str(problem).strip().splitlines()
        text = re.sub(r"\s*<[^<>]*>", "", lines[0]) if lines else ""
        text = text if len(text) <= 120 else text[:117] + "..."
        problem = f"{type(problem).__name__}: {text}" if text else type(problem).__name__
    earlier = [int(p.name) for p in directory.iterdir() if p.name.isdigit() and int(p.name) < step]
    damaged = directory / str(step)
    if not earlier:
        instead = "; there is no earlier checkpoint"
    elif resuming:
        instead = (
            f"; the checkpoint before it is step {max(earlier)}: move {damaged} away to resume"
            " from that one, or use a new --workdir"
        )
    else:
        instead = f"; the checkpoint before it is {directory / str(max(earlier))}, load that one"
    return f"checkpoint step {step} ({damaged}) is damaged: {problem}{instead}"


def _read_step(directory: pathlib.Path, step: int) -> tuple[dict, dict]:
    import orbax.checkpoint as ocp

    mngr = ocp.CheckpointManager(
        directory,
        item_handlers={
            "state": ocp.StandardCheckpointHandler(),
            "config": ocp.JsonCheckpointHandler(),
        },
    )
    config = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
    # Onto this process's first device: a run on several devices or hosts saved its arrays
    # with shardings over those, which orbax refuses to recreate on other devices.
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    abstract = jax.tree.map(
        lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=device),
        mngr.item_metadata(step)["state"],
    )
    restored = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
    state = restored["state"]
    return config, {"params": state["params"], "batch_stats": state["batch_stats"]}


def load_checkpoint(path: str | pathlib.Path) -> tuple[ModelConfig, dict]:
    """:func:`load_weights` for a training checkpoint: ``(ModelConfig, {"params",
    "batch_stats"})`` of the run in ``path`` (a workdir, its ``checkpoints/`` or one step).
    Raises ValueError naming the step and the array for a NaN or infinite value, as for a
    weights file: a detector of such weights finds nothing, silently."""
    config, variables = read_checkpoint(path)
    flat = flax.traverse_util.flatten_dict(variables, sep=_SEPARATOR)
    for key, array in flat.items():
        if not np.all(np.isfinite(np.asarray(array))):
            directory, step = resolve_checkpoint(path)
            raise ValueError(
                f"checkpoint step {step} ({directory / str(step)}): array {key} holds NaN or"
                " infinite values"
            )
    return settings.from_dict(config["model"], ModelConfig), variables


def load_named(spec: str | pathlib.Path) -> tuple[ModelConfig, dict]:
    """Weights by what a user types: a shipped name (``PRETRAINED``), a ``.npz`` weights file, or
    a training workdir (its ``checkpoints/`` or one step). Raises FileNotFoundError or ValueError
    in one line, as :func:`load_weights` and :func:`load_checkpoint` do."""
    if str(spec) in PRETRAINED:
        return load_weights(pretrained_path(str(spec)))
    if pathlib.Path(spec).suffix == ".npz":
        return load_weights(spec)
    if not pathlib.Path(spec).exists():
        raise FileNotFoundError(
            f"{spec} is neither shipped weights ({', '.join(PRETRAINED)}), a .npz weights file"
            " nor a training workdir"
        )
    return load_checkpoint(spec)


def pretrained_path(name: str):
    """The file of the shipped weights called ``name`` (``PRETRAINED``), as an
    ``importlib.resources`` traversable. Raises ValueError listing the names for an unknown one."""
    if name not in PRETRAINED:
        raise ValueError(
            f"unknown weights {name!r}; the shipped weights are {', '.join(PRETRAINED)}"
        )
    return WEIGHTS_DIR / PRETRAINED[name]
