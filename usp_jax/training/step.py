"""One training step (paper section 3): siamese branches, the loss, Adam, jitted data-parallel.

Branch A is the (photometrically augmented) image, branch B the same image warped by a random
homography T and augmented independently (``make_branches``; with ``data.context_window``, B is
rendered from a larger window around A so that T may rotate by any angle,
``make_window_branches``). Both go through one network with shared parameters;
``losses.total_loss`` compares them. The host only decodes and crops: homographies, warps and
augmentation are sampled on the device inside the jitted step, from a key derived from the step
number, so a resumed run sees exactly the randomness an uninterrupted one would.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax
import jax
import jax.numpy as jnp
import optax
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from usp_jax.core import augment, distillation, geometry, losses
from usp_jax.core.cpu_kernels import compiler_options
from usp_jax.core.model import ModelConfig, Predictions, UnsuperPoint, init_variables
from usp_jax.core.point_maps import PointMaps
from usp_jax.inference.weights import load_named
from usp_jax.training import config as config_lib


@flax.struct.dataclass
class TrainState:
    """Everything that changes during training, as one pytree (checkpointed whole)."""

    step: jax.Array  # int32 []
    params: Any
    batch_stats: Any
    opt_state: Any
    key: jax.Array  # uint32 [2], base key; step s uses fold_in(key, s)


@flax.struct.dataclass
class Teacher:
    """A frozen network whose outputs the student is trained towards (``core.distillation``).

    Not part of ``TrainState``: it never changes, and a resumed run loads it again by name."""

    variables: Any  # {"params", "batch_stats"}
    model: ModelConfig = flax.struct.field(pytree_node=False)


def load_teacher(config: config_lib.Config) -> Teacher | None:
    """The teacher ``config.distill.teacher`` names (None when it names none). Raises
    FileNotFoundError or ValueError in one line for a missing, unreadable or non-finite one."""
    if not config.distill.teacher:
        return None
    # load_named refuses NaN or infinite weights in a file and in a checkpoint alike: NaN
    # targets would otherwise surface only as a diverged run many minutes later.
    model, variables = load_named(config.distill.teacher)
    return Teacher(variables=variables, model=model)


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


def check_config(config: config_lib.Config) -> Teacher | None:
    """Raises ValueError for a field of the wrong type or out of range (``config.validate``) and
    for settings that only make sense together (each section validates itself;
    ``config.override`` applies one key at a time, so the sections cannot check each other).
    Returns the teacher it loaded to check it (None without one), for :func:`jit_train_step`."""
    config_lib.validate(config)
    try:
        teacher = load_teacher(config)
    except (OSError, ValueError) as error:
        raise ValueError(f"distill.teacher: {error}") from None
    if config.homography.rotation_range is not None and not config.data.context_window:
        raise ValueError(
            f"homography.rotation_range={config.homography.rotation_range} needs "
            "data.context_window=True: inside the crop a patch rotated that far would almost never "
            "fit (see experiments/rotation.py)"
        )
    return teacher


def create_state(config: config_lib.Config) -> TrainState:
    key = jax.random.PRNGKey(config.seed)
    init_key, train_key = jax.random.split(key)
    variables = init_variables(init_key, config.model)
    if config.init_weights:
        model_config, loaded = load_named(config.init_weights)
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


def make_pair_branches(
    key: jax.Array, batch: dict, photometric_cfg: augment.PhotometricConfig
) -> tuple[jax.Array, jax.Array, PointMaps]:
    """Section 3 for two views of a 3-D scene (a ``pairs:`` source, ``training.pairs``): the views
    are the branches, each augmented independently, and their point maps stand for T.

    batch: ``image_a``, ``image_b`` uint8 [B, H, W, 3], ``a_to_b``, ``b_to_a`` float32
    [B, H, W, 2]. Returns (images_a, images_b, ``PointMaps``).
    """
    k_a, k_b = jax.random.split(key)
    augment_all = jax.vmap(lambda k, im: augment.photometric_augment(k, im, photometric_cfg))
    images_a, images_b = (batch[k].astype(jnp.float32) / 255.0 for k in ("image_a", "image_b"))
    count = images_a.shape[0]
    return (
        augment_all(jax.random.split(k_a, count), images_a),
        augment_all(jax.random.split(k_b, count), images_b),
        PointMaps(batch["a_to_b"], batch["b_to_a"]),
    )


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


def siamese_loss(
    params: Any,
    batch_stats: Any,
    images_a: jax.Array,
    images_b: jax.Array,
    warps: jax.Array | PointMaps,
    config: config_lib.Config,
    teacher_pred: Predictions | None = None,
) -> tuple[jax.Array, tuple[dict, Any]]:
    """Eq. 4 of a batch of branch pairs, both branches through one network in training mode.

    images_a, images_b: [B, H, W, 3] float in [0, 1]; warps: T mapping A's pixels to B's,
    homographies [B, 3, 3] (as ``make_branches`` returns them) or ``PointMaps``. With ``teacher_pred`` (a frozen teacher's
    predictions of ``images_a`` then ``images_b``, [2B, ...]) the loss is ``distill.alpha_self``
    times eq. 4 plus ``distillation.distillation_loss``. Returns (loss, (metrics, new
    batch_stats)), the metrics ``losses.total_loss``'s (and ``distill/``'s) and the ``pred/``
    statistics of both branches' predictions; differentiable in ``params``.
    """
    batch, height, width, _ = images_a.shape
    # One forward over both branches: the siamese weights are shared, and BatchNorm sees both
    # views of every image.
    pred, updates = UnsuperPoint(config.model).apply(
        {"params": params, "batch_stats": batch_stats},
        jnp.concatenate([images_a, images_b]),
        train=True,
        mutable=["batch_stats"],
    )
    pred_a = jax.tree.map(lambda x: x[:batch], pred)
    pred_b = jax.tree.map(lambda x: x[batch:], pred)
    loss, metrics = losses.total_loss(pred_a, pred_b, warps, height, width, config.loss)
    if teacher_pred is not None:
        teacher_a = jax.tree.map(lambda x: x[:batch], teacher_pred)
        teacher_b = jax.tree.map(lambda x: x[batch:], teacher_pred)
        distilled, distill_metrics = distillation.distillation_loss(
            pred_a, pred_b, teacher_a, teacher_b, config.distill
        )
        loss = config.distill.alpha_self * loss + distilled
        # "loss" stays what is minimised; eq. 4 alone goes on under its own name.
        metrics.update(distill_metrics, **{"loss/self": metrics["loss"], "loss": loss})
    metrics.update({f"pred/{k}": v for k, v in _prediction_stats(pred).items()})
    return loss, (metrics, updates["batch_stats"])


def train_step(
    state: TrainState,
    images: jax.Array | dict,
    config: config_lib.Config,
    teacher: Teacher | None = None,
) -> tuple[TrainState, dict]:
    """One optimisation step on a uint8 batch [B, H, W, 3] (with ``config.data.context_window``,
    context windows [B, S, S, 4], see ``make_window_branches``; from a ``pairs:`` source, a dict
    of two views and their point maps, see ``make_pair_branches``); a pure function of its inputs.
    A ``teacher`` sees both branches in inference mode, without gradient, and its predictions
    are the distillation targets (``siamese_loss``).

    Returns the new state and a metrics dict (every loss term, K, mean d_k, score and position
    statistics, ``finite``). A step whose loss, gradients or new parameters are not finite leaves
    the state unchanged and reports ``finite = 0`` so the loop can stop on the last good state.
    """
    optimizer = make_optimizer(config.optim)
    step_key = jax.random.fold_in(state.key, state.step)
    branch_stats = {}
    if isinstance(images, dict):
        images_a, images_b, warps = make_pair_branches(step_key, images, config.photometric)
        branch_stats["data/seen_in_b"] = jnp.mean(jnp.isfinite(images["a_to_b"][..., 0]))
    elif config.data.context_window:
        images = images.astype(jnp.float32) / 255.0
        images_a, images_b, warps, valid_b = make_window_branches(
            step_key,
            images,
            config.data.height,
            config.data.width,
            config.homography,
            config.photometric,
        )
        branch_stats["data/valid_b"] = jnp.mean(valid_b)
    else:
        images_a, images_b, warps = make_branches(
            step_key, images.astype(jnp.float32) / 255.0, config.homography, config.photometric
        )

    teacher_pred = None
    if teacher is not None:
        teacher_pred = jax.lax.stop_gradient(
            UnsuperPoint(teacher.model).apply(
                teacher.variables, jnp.concatenate([images_a, images_b]), train=False
            )
        )

    def loss_fn(params):
        return siamese_loss(
            params, state.batch_stats, images_a, images_b, warps, config, teacher_pred
        )

    (loss, (metrics, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
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
    return jax.make_mesh((jax.device_count(),), ("data",), axis_types=(jax.sharding.AxisType.Auto,))


def jit_train_step(
    config: config_lib.Config, mesh: jax.sharding.Mesh, teacher: Teacher | None = None
) -> Callable:
    """``train_step`` jitted data-parallel: batch sharded over ``mesh``, state replicated.

    Under plain jit with sharded inputs XLA inserts the gradient all-reduce itself, and the
    BatchNorm statistics are global across devices, so N devices compute what one would. The
    teacher ``config.distill`` names, if any, is compiled into the step: ``teacher`` when the
    caller has loaded it already (:func:`check_config` returns it), else loaded here.
    """
    replicated = NamedSharding(mesh, P())
    if teacher is None:
        teacher = load_teacher(config)
    if teacher is not None:
        teacher = jax.device_put(teacher, replicated)
    return jax.jit(
        lambda state, images: train_step(state, images, config, teacher),
        in_shardings=(replicated, NamedSharding(mesh, P("data"))),
        out_shardings=(replicated, replicated),
        donate_argnums=0,
        compiler_options=compiler_options(),
    )
