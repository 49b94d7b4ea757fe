"""Self-supervised training (paper section 3): siamese branches, a jit data-parallel step, the loop.

Branch A is the (photometrically augmented) image, branch B the same image warped by a random
homography T and augmented independently (``make_branches``; with ``data.context_window``, B is
rendered from a larger window around A so that T may rotate by any angle,
``make_window_branches``). Both go through one network with shared parameters;
``losses.total_loss`` compares them. The host only decodes and crops: homographies, warps and
augmentation are sampled on the device inside the jitted step, from a key derived from the step
number, so a resumed run sees exactly the randomness an uninterrupted one would.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pathlib
import shutil
import socket
import time
from typing import Any, Callable, Iterator

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec as P

from usp_jax import augment, geometry, losses, paths
from usp_jax import config as config_lib
from usp_jax import distributed as multihost
from usp_jax.model import Predictions, UnsuperPoint, compiler_options, init_variables

log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """The loss or the gradients became NaN or inf."""


class ConfigChanged(ValueError):
    """A workdir is resumed with settings other than those it was trained with."""


class WorkdirError(RuntimeError):
    """The workdir cannot be used: not a folder, not writable, in use by another run, or a
    write failed (a full disk) partway."""


#: Settings a resumed run may change without ``allow_config_change``: where it stops, how
#: often it logs and saves, how many checkpoints it keeps and how it reads its photos. None of
#: them changes what a training step computes.
RESUMABLE_KEYS = frozenset({
    "num_steps", "checkpoint_every", "keep_checkpoints", "log_every",
    "data.num_workers", "data.prefetch", "data.tfds_data_dir",
})
#: Held by a running ``fit`` inside its workdir; names the holder's pid and host.
LOCK_FILE = "train.lock"
#: One JSON line per resume that changed settings with ``allow_config_change``.
CONFIG_CHANGES_FILE = "config_changes.jsonl"


@flax.struct.dataclass
class TrainState:
    """Everything that changes during training, as one pytree (checkpointed whole)."""

    step: jax.Array  # int32 []
    params: Any
    batch_stats: Any
    opt_state: Any
    key: jax.Array  # uint32 [2], base key; step s uses fold_in(key, s)


def learning_rate(cfg: config_lib.OptimConfig) -> optax.Schedule:
    """Step -> rate: linear warm-up from 0 (if any), then constant or cosine decay to 0."""
    peak = optax.constant_schedule(cfg.learning_rate)
    if cfg.decay_steps:
        peak = optax.cosine_decay_schedule(cfg.learning_rate, cfg.decay_steps)
    if not cfg.warmup_steps:
        return peak
    warmup = optax.linear_schedule(0.0, cfg.learning_rate, cfg.warmup_steps)
    return optax.join_schedules([warmup, peak], [cfg.warmup_steps])


def make_optimizer(cfg: config_lib.OptimConfig) -> optax.GradientTransformation:
    adam = optax.adam(learning_rate(cfg))
    return optax.chain(optax.clip_by_global_norm(cfg.clip_norm), adam) if cfg.clip_norm else adam


def check_config(config: config_lib.Config) -> None:
    """Raises ValueError for a field of the wrong type or out of range (``config.validate``) and
    for settings that only make sense together (each section validates itself;
    ``config.override`` applies one key at a time, so the sections cannot check each other)."""
    config_lib.validate(config)
    if config.homography.rotation_range is not None and not config.data.context_window:
        raise ValueError(
            f"homography.rotation_range={config.homography.rotation_range} needs "
            "data.context_window=True: inside the crop a patch rotated that far would almost never "
            "fit (see experiments/rotation.py)"
        )


def create_state(config: config_lib.Config) -> TrainState:
    key = jax.random.PRNGKey(config.seed)
    init_key, train_key = jax.random.split(key)
    variables = init_variables(init_key, config.model)
    if config.init_weights:
        from usp_jax import inference  # inference imports the evaluation stack; train need not

        model_config, loaded = inference.load_weights(config.init_weights)
        # Compare weight shapes, not configs: dtype, BatchNorm momentum or the heads' init scale
        # may differ between the exporting and the continuing run (export on a CPU writes
        # float32, a TPU run computes in bfloat16) without changing a single weight.
        if jax.tree.map(jnp.shape, loaded) != jax.tree.map(jnp.shape, variables):
            raise ValueError(
                f"{config.init_weights} holds a {model_config} network, whose weights do not fit "
                f"the run's {config.model}"
            )
        variables = loaded
    optimizer = make_optimizer(config.optim)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=variables["params"],
        batch_stats=variables["batch_stats"],
        opt_state=optimizer.init(variables["params"]),
        key=train_key,
    )


def make_branches(
    key: jax.Array,
    images: jax.Array,
    homography_cfg: geometry.HomographyConfig,
    photometric_cfg: augment.PhotometricConfig,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Section 3: branch A = aug(image), branch B = aug(T(image)) with independent augmentations.

    images: [B, H, W, 3] float in [0, 1]. Returns (images_a, images_b, T [B, 3, 3]).
    """
    batch, height, width, _ = images.shape
    k_h, k_a, k_b = jax.random.split(key, 3)
    homographies = jax.vmap(lambda k: geometry.sample_homography(k, height, width, homography_cfg))(
        jax.random.split(k_h, batch)
    )
    warped, _ = jax.vmap(lambda im, h: geometry.warp_image(im, h, (height, width)))(
        images, homographies
    )
    augment_all = jax.vmap(lambda k, im: augment.photometric_augment(k, im, photometric_cfg))
    images_a = augment_all(jax.random.split(k_a, batch), images)
    images_b = augment_all(jax.random.split(k_b, batch), warped)
    return images_a, images_b, homographies


# Bilinear weights of a pixel whose neighbours all show the photo sum to 1 up to rounding.
_VALID_ALPHA = 1.0 - 1e-3


def make_window_branches(
    key: jax.Array,
    windows: jax.Array,
    height: int,
    width: int,
    homography_cfg: geometry.HomographyConfig,
    photometric_cfg: augment.PhotometricConfig,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Section 3 with B rendered from a context window around A, so that T may rotate by any angle.

    Branch A = aug(the [height, width] crop at the centre of each window); branch B = aug(T(the
    whole window)), with T from ``geometry.sample_window_homography``, so B shows real photo content
    at any rotation. B's pixels whose source lies outside the window or on its padding are 0 and
    False in ``valid_b``; their points have no partner inside A, which the losses already mask.

    Args:
      key: PRNG key.
      windows: [B, S_h, S_w, 4] float in [0, 1], RGB and validity (1 = photo, 0 = padding), as
        ``data.random_context_crop`` delivers them (divided by 255); the centre crops lie inside
        the photo.
      height, width: the crop's (and B's) size in pixels (static).
      homography_cfg, photometric_cfg: static.
    Returns:
      images_a [B, height, width, 3], images_b [B, height, width, 3], T [B, 3, 3] mapping A's pixels
      to B's (as ``make_branches``), and valid_b bool [B, height, width].
    """
    batch, window_height, window_width, _ = windows.shape
    window = (window_height, window_width)
    origin_x, origin_y = geometry.window_origin(height, width, window)
    k_h, k_a, k_b = jax.random.split(key, 3)
    homographies = jax.vmap(
        lambda k: geometry.sample_window_homography(k, height, width, window, homography_cfg)
    )(jax.random.split(k_h, batch))
    # Window pixels are A's shifted by the origin: undo the shift, then apply T.
    from_window = geometry.compose_homographies(
        homographies, geometry.translation(-origin_x, -origin_y)
    )
    warped, inside = jax.vmap(lambda im, h: geometry.warp_image(im, h, (height, width)))(
        windows, from_window
    )
    valid_b = inside & (warped[..., 3] >= _VALID_ALPHA)
    crops = windows[:, origin_y : origin_y + height, origin_x : origin_x + width, :3]
    augment_all = jax.vmap(lambda k, im: augment.photometric_augment(k, im, photometric_cfg))
    images_a = augment_all(jax.random.split(k_a, batch), crops)
    # Zeroed after augmenting too: brightness, contrast and noise would otherwise paint the
    # missing pixels grey or speckled, i.e. texture the network could learn to find points on.
    images_b = augment_all(jax.random.split(k_b, batch), warped[..., :3]) * valid_b[..., None]
    return images_a, images_b, homographies, valid_b


def score_position_r2(scores: jax.Array, keypoints: jax.Array) -> jax.Array:
    """How much of the score variation is a linear ramp across the image, mean over the batch.

    scores [B, M], keypoints [B, M, 2] -> scalar in [0, 1]: per image corr(s, x)^2 + corr(s, y)^2
    (x and y of the cell grid are uncorrelated, so this is the R^2 of a plane fit). Near 1, the
    network scores where a point is rather than what it looks like: it has read its position off
    the zero padding (see losses.pair_loss).
    """

    def r2(values, coordinate):
        a = values - jnp.mean(values, axis=-1, keepdims=True)
        b = coordinate - jnp.mean(coordinate, axis=-1, keepdims=True)
        cov = jnp.sum(a * b, axis=-1)
        return cov**2 / jnp.maximum(jnp.sum(a * a, axis=-1) * jnp.sum(b * b, axis=-1), 1e-20)

    return jnp.mean(r2(scores, keypoints[..., 0]) + r2(scores, keypoints[..., 1]))


def _prediction_stats(pred: Predictions) -> dict:
    return {
        "score_mean": jnp.mean(pred.scores),
        "score_std": jnp.std(pred.scores),
        "score_position_r2": score_position_r2(pred.scores, pred.keypoints),
        "relative_std": jnp.std(pred.relative),
        # Share of points in the outer 10% of their cell: the border pile-up peers reported.
        "relative_at_edge": jnp.mean((pred.relative < 0.05) | (pred.relative > 0.95)),
    }


def train_step(
    state: TrainState, images: jax.Array, config: config_lib.Config
) -> tuple[TrainState, dict]:
    """One optimisation step on a uint8 batch [B, H, W, 3] (with ``config.data.context_window``,
    context windows [B, S, S, 4], see ``make_window_branches``); a pure function of its inputs.

    Returns the new state and a metrics dict (every loss term, K, mean d_k, score and position
    statistics, ``finite``). A step whose loss, gradients or new parameters are not finite leaves
    the state unchanged and reports ``finite = 0`` so the loop can stop on the last good state.
    """
    model = UnsuperPoint(config.model)
    optimizer = make_optimizer(config.optim)
    batch, height, width, _ = images.shape
    images = images.astype(jnp.float32) / 255.0
    step_key = jax.random.fold_in(state.key, state.step)
    branch_stats = {}
    if config.data.context_window:
        height, width = config.data.height, config.data.width
        images_a, images_b, homographies, valid_b = make_window_branches(
            step_key, images, height, width, config.homography, config.photometric
        )
        branch_stats["data/valid_b"] = jnp.mean(valid_b)
    else:
        images_a, images_b, homographies = make_branches(
            step_key, images, config.homography, config.photometric
        )

    def loss_fn(params):
        # One forward over both branches: the siamese weights are shared, and BatchNorm sees both
        # views of every image.
        pred, updates = model.apply(
            {"params": params, "batch_stats": state.batch_stats},
            jnp.concatenate([images_a, images_b]),
            train=True,
            mutable=["batch_stats"],
        )
        pred_a = jax.tree.map(lambda x: x[:batch], pred)
        pred_b = jax.tree.map(lambda x: x[batch:], pred)
        loss, metrics = losses.total_loss(
            pred_a, pred_b, homographies, height, width, config.loss
        )
        metrics.update({f"pred/{k}": v for k, v in _prediction_stats(pred).items()})
        return loss, (metrics, updates["batch_stats"])

    (loss, (metrics, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
        state.params
    )
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    grad_norm = optax.tree.norm(grads)
    finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm) & jnp.isfinite(optax.tree.norm(params))
    new_state = TrainState(state.step + 1, params, batch_stats, opt_state, state.key)
    new_state = jax.tree.map(lambda new, old: jnp.where(finite, new, old), new_state, state)
    metrics.update({"grad_norm": grad_norm, "finite": finite.astype(jnp.float32), **branch_stats})
    return new_state, metrics


def data_mesh() -> jax.sharding.Mesh:
    """A 1-D mesh over every device (all hosts): the batch is split along it.

    Auto axes let XLA propagate the batch sharding through the vmapped per-image code.
    """
    return jax.make_mesh(
        (jax.device_count(),), ("data",), axis_types=(jax.sharding.AxisType.Auto,)
    )


def jit_train_step(config: config_lib.Config, mesh: jax.sharding.Mesh) -> Callable:
    """``train_step`` jitted data-parallel: batch sharded over ``mesh``, state replicated.

    Under plain jit with sharded inputs XLA inserts the gradient all-reduce itself, and the
    BatchNorm statistics are global across devices, so N devices compute what one would.
    """
    replicated = NamedSharding(mesh, P())
    return jax.jit(
        lambda state, images: train_step(state, images, config),
        in_shardings=(replicated, NamedSharding(mesh, P("data"))),
        out_shardings=(replicated, replicated),
        donate_argnums=0,
        compiler_options=compiler_options(),
    )


class MetricsWriter:
    """Appends metrics to ``metrics.jsonl`` and TensorBoard event files (first process only)."""

    def __init__(self, workdir: pathlib.Path, enabled: bool = True):
        self.enabled = enabled
        if not enabled:
            return
        from tensorboardX import SummaryWriter

        path = workdir / "metrics.jsonl"
        _drop_torn_line(path)
        self._jsonl = open(path, "a")
        self._tb = SummaryWriter(str(workdir / "tensorboard"))

    def write(self, step: int, metrics: dict[str, float]) -> None:
        if not self.enabled:
            return
        self._jsonl.write(json.dumps({"step": step, **metrics}) + "\n")
        self._jsonl.flush()
        for name, value in metrics.items():
            self._tb.add_scalar(name, value, step)

    def close(self) -> None:
        if self.enabled:
            self._jsonl.close()
            self._tb.close()


def _drop_torn_line(path: pathlib.Path) -> None:
    """Cuts a last line that a kill or a full disk left without its newline."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    text = path.read_bytes()
    if not text.endswith(b"\n"):
        with open(path, "r+b") as file:
            file.truncate(text.rfind(b"\n") + 1)


def read_metrics(workdir: str | pathlib.Path) -> list[dict]:
    """The rows :class:`MetricsWriter` appended to ``WORKDIR/metrics.jsonl``, in the order written
    (``[]`` before the first log). A run resumed after a kill logs the steps after its last
    checkpoint a second time; the later row of a step is the one its kept weights went through.
    A last line cut short by a kill or a full disk is skipped."""
    path = pathlib.Path(workdir) / "metrics.jsonl"
    if not path.is_file():
        return []
    complete = path.read_text().split("\n")[:-1]  # text after the last newline is unfinished
    return [json.loads(line) for line in complete if line.strip()]


def _progress_postfix(metrics: dict[str, float], steps_per_s: float, batch_size: int) -> dict:
    return {
        "steps/s": f"{steps_per_s:.2f}",
        "img/s": f"{2 * batch_size * steps_per_s:.1f}",
        "loss": f"{metrics['loss']:.4g}",
        "usp": f"{metrics['loss/usp']:.4g}",
        "uni": f"{metrics['loss/uni_xy']:.3g}",
        "desc": f"{metrics['loss/desc']:.4g}",
        "K": f"{metrics['usp/K']:.0f}",
        "d": f"{metrics['usp/mean_d']:.2f}",
    }


def collapse_warnings(metrics: dict[str, float]) -> dict[str, str]:
    """The collapses peers reported, and the score ramp, read off one metrics row: {what: message}."""
    warnings = {}
    # Saturated and constant. A constant near 1/2 is the normal start under the mean anchor: the
    # scores spread once positions become repeatable (~2,000 steps in experiments/cpu_photos.py).
    saturated = abs(metrics.get("pred/score_mean", 0.5) - 0.5) > 0.4
    if metrics.get("pred/score_std", 1.0) < 0.02 and saturated:
        warnings["scores"] = (
            f"scores have collapsed to a constant (std {metrics['pred/score_std']:.3g}, mean "
            f"{metrics['pred/score_mean']:.3g}); loss.alpha_score_mean > 0 anchors their mean"
        )
    if metrics.get("pred/score_position_r2", 0.0) > 0.5:
        warnings["score ramp"] = (
            f"scores follow the position in the image, not its content (R^2 of a plane fit "
            f"{metrics['pred/score_position_r2']:.2f}); loss.alpha_uni_score > 0 rewards such a "
            f"ramp, loss.alpha_score_mean alone does not"
        )
    if metrics.get("desc/sim_negative", 0.0) > 0.9:
        warnings["descriptors"] = (
            f"descriptors have collapsed onto one vector (mean similarity of non-matching pairs "
            f"{metrics['desc/sim_negative']:.2f}): the hinge's positives outweigh its negatives; "
            f"lower loss.lambda_d in proportion to the cell count (250 suits 240x320)"
        )
    return warnings


def _check_finite(metrics: dict | None, step: int, mngr) -> None:
    if metrics is not None and not float(metrics["finite"]):
        raise TrainingDiverged(
            f"loss became non-finite at step {step} (loss={float(metrics['loss'])}); stopped, "
            f"last good checkpoint: step {mngr.latest_step()} in {mngr.directory}"
        )


# ---------------------------------------------------------------------------------------------
# The workdir: checks before anything is written, the lock, the record of the config


def _check_workdir_path(workdir: pathlib.Path) -> None:
    """Raises WorkdirError unless ``workdir`` is, or can be made as, a writable folder."""
    problem = paths.folder_problem(workdir)
    if problem:
        raise WorkdirError(f"workdir {workdir}{problem}")
    for name in ("config.json", "checkpoints", "metrics.jsonl", "tensorboard"):
        path = workdir / name
        if path.exists() and not os.access(path, os.W_OK):
            raise WorkdirError(f"workdir {workdir}: {path} is not writable")


class _WorkdirLock:
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
        os.write(fd, f"pid {os.getpid()} on host {socket.gethostname()} (since {started})\n".encode())

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
        except (ValueError, TypeError) as error:  # JSONDecodeError is a ValueError
            raise WorkdirError(
                f"{path} is not a readable usp-jax config ({type(error).__name__}); the run's"
                " record is damaged"
            ) from None
    if (workdir / "checkpoints").is_dir():
        from usp_jax import checkpoint

        try:
            return checkpoint.load_config(workdir)
        except FileNotFoundError:
            return None
    return None


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


def _check_resume(
    workdir: pathlib.Path, previous: config_lib.Config, config: config_lib.Config,
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


def _first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def _write_failed(error: OSError, what: str, workdir: pathlib.Path, mngr) -> WorkdirError:
    latest = mngr.latest_step() if mngr is not None else None
    where = error.filename or workdir
    kept = f"; the last complete checkpoint is step {latest}" if latest is not None else ""
    return WorkdirError(f"{what}: {where}: {error.strerror or _first_line(error)}{kept}")


def _os_error_in(error: BaseException) -> OSError | None:
    """The OSError behind ``error``, or None. Orbax's writes (TensorStore) fail with a
    ValueError that carries the system's error code in its text: ``[os_error_code='28']``."""
    import re

    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno is not None:
            return error
        code = re.search(r"os_error_code='(\d+)'", str(error))
        if code:
            path = re.search(r'(?:file|Failed writing:) "([^"]+)"', str(error))
            number = int(code.group(1))
            return OSError(number, os.strerror(number), path.group(1) if path else None)
        error = error.__cause__ or error.__context__
    return None


def fit(
    config: config_lib.Config,
    workdir: str | pathlib.Path,
    *,
    progress: bool = True,
    distributed: bool | multihost.Launch = False,
    num_steps: int | None = None,
    allow_config_change: bool = False,
) -> TrainState:
    """Trains (or resumes) the run in ``workdir`` up to ``num_steps`` (default config.num_steps).

    Re-running with the same workdir resumes from its latest complete checkpoint. A workdir
    trained with other settings is refused (``ConfigChanged``, naming the keys) unless
    ``allow_config_change``; the keys of ``RESUMABLE_KEYS`` (the step count, logging and
    checkpoint intervals, data loading) may always change, and a network or optimizer whose
    arrays do not fit the checkpoints never continues. Everything is checked before the
    workdir is created or changed; ``config.json`` is (re)written only once the run starts.
    A lock on ``WORKDIR/train.lock`` keeps a second run out (``WorkdirError`` naming the holder).

    Writes ``config.json``, ``checkpoints/``, ``metrics.jsonl`` and ``tensorboard/`` into workdir.
    Raises ``TrainingDiverged`` on a non-finite loss, keeping the last good checkpoint, and
    ``WorkdirError`` when a write fails (a full disk), naming the last complete checkpoint.
    ``distributed`` (True, or a ``distributed.Launch`` with explicit coordinator, process count
    and id) joins a multi-process run first unless this process has joined one already
    (``distributed.initialize``). Every process then runs ``fit`` with the same arguments and
    loads only its share of each global batch; only process 0 writes the config, metrics and
    TensorBoard files, all of them take part in every checkpoint save and restore (the workdir
    must be on storage they share). When one of them gets SIGTERM, which JAX's runtime catches
    there, all save a checkpoint at the same step and return early (``state.step < num_steps``).
    After a failure in a multi-process run the process must
    exit (the CLI does, ``distributed.leave_after_failure``): its checkpoint manager is left
    as it is, because closing it waits on processes that are gone.
    """
    from tqdm.auto import tqdm

    from usp_jax import checkpoint, data

    workdir = pathlib.Path(workdir).expanduser().absolute()
    num_steps = config.num_steps if num_steps is None else num_steps
    check_config(config)
    if isinstance(num_steps, bool) or not isinstance(num_steps, (int, np.integer)) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
    if distributed and not jax.distributed.is_initialized():
        launch = distributed if isinstance(distributed, multihost.Launch) else multihost.Launch()
        multihost.check_launch(launch, config.batch_size)
        multihost.initialize(launch)
    multihost.check_batch(config.batch_size, jax.process_count())
    if config.batch_size % jax.device_count():
        raise ValueError(
            f"batch_size {config.batch_size} is not divisible by the {jax.device_count()} devices"
        )
    is_main = jax.process_index() == 0
    single = jax.process_count() == 1
    _check_workdir_path(workdir)
    # What can reject the inputs (the --init weights, the data path) runs before the workdir is
    # written, so a bad argument leaves no half-made run behind to be resumed later.
    initial = create_state(config)
    dataset = data.make_dataset(
        config.data,
        config.batch_size // jax.process_count(),
        seed=config.seed,
        process_index=jax.process_index(),
        process_count=jax.process_count(),
    )
    created = not workdir.exists()
    lock = mngr = None
    try:
        try:
            workdir.mkdir(parents=True, exist_ok=True)
            lock = _WorkdirLock(workdir) if is_main else None
        except OSError as error:
            raise WorkdirError(
                f"workdir {workdir}: {error.strerror or _first_line(error)}"
            ) from None
        previous = recorded_config(workdir)
        changes = {}
        if previous is not None:
            changes = _check_resume(workdir, previous, config, allow_config_change)
        # Every process has read the record before process 0 rewrites it below.
        _sync_processes("usp_jax: workdir checked")
        mesh = data_mesh()
        replicated = NamedSharding(mesh, P())
        batch_sharding = NamedSharding(mesh, P("data"))
        state = jax.device_put(initial, replicated)
        mngr = checkpoint.manager(workdir / "checkpoints", keep=config.keep_checkpoints)
        if mngr.latest_step() is not None:
            latest = mngr.latest_step()
            try:
                state = checkpoint.restore_state(mngr, state)
            except Exception as error:  # a damaged checkpoint: one line, the cause chained
                raise WorkdirError(
                    f"cannot restore checkpoint step {latest} of {workdir}:"
                    f" {_first_line(error)}"
                ) from error
            log.info("resumed from step %d", int(state.step))
        start = int(state.step)
        if is_main:  # the run starts: only now is its record (re)written
            if previous is None or previous != config:
                config_lib.save(config, workdir / "config.json")
            if changes:
                with open(workdir / CONFIG_CHANGES_FILE, "a") as file:
                    file.write(json.dumps({"step": start, "changes": {
                        k: [old, new] for k, (old, new) in changes.items()}}) + "\n")
        writer = MetricsWriter(workdir, enabled=is_main)
    except BaseException as error:
        if mngr is not None:
            mngr.close()
        if lock is not None:
            lock.release()
        # Made by this call for a run that never started. Process 0's to remove: another
        # process may have found it already made.
        if created and is_main and workdir.is_dir():
            shutil.rmtree(workdir, ignore_errors=True)
        cause = _os_error_in(error)
        if cause is not None and not isinstance(error, (WorkdirError, ConfigChanged)):
            raise _write_failed(cause, "cannot start the run", workdir, None) from error
        raise
    step_fn = jit_train_step(config, mesh)
    bar = tqdm(
        total=num_steps, initial=start, disable=not (progress and is_main), unit="step",
        dynamic_ncols=True,
    )
    batches: Iterator[np.ndarray] = data.iterate(dataset, start)
    last_log_time, last_log_step = time.perf_counter(), start
    previous_metrics = None
    warned: set[str] = set()
    done = start
    finished = False
    try:
        try:
            for step in range(start, num_steps):
                local = next(batches)
                images = jax.make_array_from_process_local_data(batch_sharding, local)
                state, metrics = step_fn(state, images)
                done = step + 1
                # Checking the previous step while this one runs keeps the device busy.
                _check_finite(previous_metrics, done - 1, mngr)
                previous_metrics = metrics
                stop = multihost.preempted(done)
                last = stop or done == num_steps
                if done % config.log_every and done % config.checkpoint_every and not last:
                    bar.update(1)
                    continue
                metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                _check_finite(metrics, done, mngr)
                now = time.perf_counter()
                steps_per_s = (done - last_log_step) / max(now - last_log_time, 1e-9)
                last_log_time, last_log_step = now, done
                metrics.update({"steps_per_s": steps_per_s, **data.stats(dataset)})
                # Warn once per kind, after the first steps have had a chance to move away from init.
                for what, message in (collapse_warnings(metrics) if done >= 100 else {}).items():
                    if what not in warned:
                        warned.add(what)
                        log.warning("step %d: %s", done, message)
                writer.write(done, metrics)
                bar.set_postfix(_progress_postfix(metrics, steps_per_s, config.batch_size))
                bar.update(1)
                if done % config.checkpoint_every == 0 or last:
                    checkpoint.save(mngr, done, state, config)
                if stop:
                    log.warning("stopping at step %d: a process got SIGTERM (its job is ending or"
                                " being preempted); rerun to resume", done)
                    break
            mngr.wait_until_finished()
            finished = True
        except (TrainingDiverged, KeyboardInterrupt):
            raise
        except Exception as error:
            cause = _os_error_in(error)
            if cause is None:
                raise
            if single:
                _settle(mngr)
            raise _write_failed(cause, f"writing step {done} failed", workdir, mngr) from error
    finally:
        # A failed multi-process run leaves its pending save: finishing it would wait for
        # processes that have stopped, and this one is about to exit.
        if finished or single:
            _settle(mngr)
            mngr.close()
        bar.close()
        _close_quietly(writer)
        if lock is not None:
            lock.release()
    return state


def _sync_processes(name: str) -> None:
    """Waits until every process of a multi-process run gets here (a no-op for one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def _settle(mngr) -> None:
    """Waits for a pending save; a failed one leaves only orbax's temporary folder, which
    ``latest_step`` never reports."""
    try:
        mngr.wait_until_finished()
    except Exception as error:  # reported by the caller's own error, or already raised
        log.debug("pending checkpoint save failed: %s", _first_line(error))


def _close_quietly(writer: MetricsWriter) -> None:
    try:
        writer.close()
    except OSError as error:  # a full disk fails the final flush too
        log.debug("closing the metrics writer failed: %s", _first_line(error))
