"""Running a trained UnsuperPoint: images of any size in, sorted keypoints and descriptors out.

One jitted function per detector does everything on the device: uint8 -> float, an optional
enlargement (``upsample``), the network, dropping points in the padding and the border, radius
NMS, top-N selection and the gather of the selected descriptors (interpolated inside the model,
paper section 2.4). The host only pads images to whole 8x8 cells and slices the fixed-size
results. Coordinates follow the project's convention (``usp_jax.model`` docstring): (x, y),
pixel centres at integers, as in OpenCV.

Padding: images are padded at the bottom and right by *edge replication* to a multiple of 8.
Zero padding would put an artificial black step right after the last row/column, which the
network scores like any strong edge; replication adds no new gradient, so points near the
bottom/right border behave like points elsewhere. Points that land in the padding are dropped.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import json
import math
import pathlib
import zipfile
from collections.abc import Sequence
from typing import Any

import cv2
import flax
import jax
import jax.numpy as jnp
import numpy as np

from usp_jax import checkpoint
from usp_jax import config as config_lib
from usp_jax.evaluation import Features, Method
from usp_jax.model import CELL, ModelConfig, UnsuperPoint, compiler_options, init_variables

#: Folder of the weights that ship inside the package (experiments/RESULTS.md says how each
#: was trained).
WEIGHTS_DIR = importlib.resources.files("usp_jax") / "weights"
#: Shipped weights by name -> their file in WEIGHTS_DIR. "paper": the paper's VGG network;
#: "fast": ``model.fast_config()`` trained by experiments/fast.py, 4-5x the images/s but below
#: the paper network on the held-out pairs (HA@3 0.66 vs 0.91, MS 0.57 vs 0.65; RESULTS).
PRETRAINED = {"paper": "paper.npz", "fast": "fast.npz"}
#: What ``Detector.pretrained()`` loads: the best of the named weights on the held-out pairs.
DEFAULT_PRETRAINED = "paper"

# Key of the JSON ModelConfig inside a weights file; parameter keys are "params/..." paths.
_CONFIG_KEY = "model_config"
_SEPARATOR = "/"


# ---------------------------------------------------------------------------------------------
# Weights files


def save_weights(path: str | pathlib.Path, variables: dict, model_config: ModelConfig) -> None:
    """Write ``{"params", "batch_stats"}`` as one float16 ``.npz`` plus the ModelConfig as JSON.

    Float16 halves the file; inference casts back to float32. Raises ValueError instead of
    writing a value that float16 cannot hold (|x| > 65504), so no weight is silently lost.
    """
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
    np.savez_compressed(path, **arrays, **{_CONFIG_KEY: np.array(config_json)})


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
            model_config = config_lib.from_dict(json.loads(str(data[_CONFIG_KEY])), ModelConfig)
            config_lib.validate_model(model_config)
        except (ValueError, TypeError, AttributeError) as error:
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
            if array.dtype.kind not in "fiu":
                raise ValueError(f"{path}: array {key} holds {array.dtype}, not numbers")
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
    network = (f"its {model_config.backbone} network (descriptor_dim"
               f" {model_config.descriptor_dim}, head_channels {model_config.head_channels})")
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


# ---------------------------------------------------------------------------------------------
# The compiled part: selection of points from the network's M candidates


def _neighbours(values: jax.Array, cells_h: int, cells_w: int, reach: int, fill) -> jax.Array:
    """The values of every other cell within ``reach`` cells, [M, ...] -> [O, M, ...].

    O = (2 reach + 1)^2 - 1 offsets; cells outside the grid read ``fill``.
    """
    rest = values.shape[1:]
    grid = values.reshape(cells_h, cells_w, *rest)
    pad = ((reach, reach), (reach, reach)) + ((0, 0),) * len(rest)
    padded = jnp.pad(grid, pad, constant_values=fill)
    offsets = [
        (dy, dx)
        for dy in range(-reach, reach + 1)
        for dx in range(-reach, reach + 1)
        if (dy, dx) != (0, 0)
    ]
    return jnp.stack(
        [
            padded[reach + dy : reach + dy + cells_h, reach + dx : reach + dx + cells_w].reshape(
                cells_h * cells_w, *rest
            )
            for dy, dx in offsets
        ]
    )


#: Largest neighbourhood (in cells each way) :func:`radius_nms` compares cell by cell; beyond,
#: its memory ((2 reach + 1)^2 M) would grow with the radius, and the greedy loop takes over.
NEIGHBOUR_REACH = 3


def radius_nms(
    keypoints: jax.Array,
    scores: jax.Array,
    valid: jax.Array,
    cells_h: int,
    cells_w: int,
    radius: float,
    cell: float = CELL,
    limit: int | None = None,
) -> jax.Array:
    """Greedy radius NMS of one image's M candidates (one per cell), the paper's "NMS = 4".

    keypoints [M, 2], scores [M], valid [M] bool (row-major cells) -> keep [M] bool. Same result
    as ``evaluation.nms_radius`` on the valid points: by decreasing score (ties: lower index
    first), a point is kept unless a kept point lies within ``radius`` px (inclusive).
    ``limit``: stop once this many points are kept (the strongest of the full result; for a
    top-N cut after NMS, N). Raises ValueError for a radius that is negative, NaN or infinite.

    ``cell`` is a cell's side in the keypoints' pixels (8; 8 / s for a network run on the image
    enlarged s times). A point stays inside its cell, so points d cells apart are at least
    ``cell * (d - 1)`` px apart and only cells within ``floor(radius / cell) + 1`` can interact
    (3x3 cells for radius 4 at 8 px), never more than the grid. Up to ``NEIGHBOUR_REACH`` cells
    each way, every cell is compared with those neighbours at once, and the greedy result is the
    unique fixed point of ``keep_i = valid_i and no kept stronger neighbour``: iterating that
    map from ``keep = valid`` settles one more level of the dependency chain per step, so the
    loop stops after (longest chain of suppressions) steps, usually a handful. For a larger
    radius (or with ``limit``) it runs the greedy order itself, one kept point per step: memory
    O(M) whatever the radius, and the larger the radius the fewer points, so the fewer steps.
    """
    radius = float(radius)
    if not (math.isfinite(radius) and radius >= 0):
        raise ValueError(f"NMS radius must be a finite number >= 0, got {radius}")
    m = scores.shape[0]
    reach = min(int(radius // cell) + 1, max(cells_h, cells_w) - 1)
    if reach < 1:  # a single cell: nothing to suppress
        return jnp.asarray(valid, bool) if limit is None else _greedy_nms(
            keypoints, scores, valid, radius, limit)
    if reach > NEIGHBOUR_REACH or limit is not None:
        return _greedy_nms(keypoints, scores, valid, radius, limit)

    def around(values, fill):
        return _neighbours(values, cells_h, cells_w, reach, fill)

    index = jnp.arange(m)
    other_index = around(index, m)
    other_scores = around(scores, -jnp.inf)
    stronger = (other_scores > scores) | ((other_scores == scores) & (other_index < index))
    close = jnp.sum((around(keypoints, jnp.inf) - keypoints) ** 2, axis=-1) <= radius**2
    suppressors = around(valid, False) & stronger & close  # [O, M]

    def step(state):
        keep, _ = state
        new = valid & ~jnp.any(suppressors & around(keep, False), axis=0)
        return new, jnp.any(new != keep)

    keep, _ = jax.lax.while_loop(lambda state: state[1], step, (valid, jnp.bool_(True)))
    return keep


def _greedy_nms(keypoints, scores, valid, radius: float, limit: int | None) -> jax.Array:
    """:func:`radius_nms` in the greedy order itself: each step keeps the strongest point not yet
    suppressed and suppresses every point within ``radius`` of it. O(M) memory; as many steps
    as points kept (at most ``limit``)."""
    keypoints, valid = jnp.asarray(keypoints), jnp.asarray(valid, bool)
    m = scores.shape[0]
    # Rank in the greedy order: decreasing score, ties by lower index (as a stable argsort).
    order = jnp.argsort(-jnp.asarray(scores), stable=True)
    rank = jnp.zeros(m, jnp.int32).at[order].set(jnp.arange(m, dtype=jnp.int32))

    def running(state):
        _, remaining, count = state
        going = jnp.any(remaining)
        return going if limit is None else going & (count < limit)

    def step(state):
        keep, remaining, count = state
        best = jnp.argmin(jnp.where(remaining, rank, m))
        close = jnp.sum((keypoints - keypoints[best]) ** 2, axis=-1) <= radius**2
        return (keep.at[best].set(True), remaining & ~close & (jnp.arange(m) != best),
                count + 1)

    keep, _, _ = jax.lax.while_loop(
        running, step, (jnp.zeros(m, bool), valid, jnp.zeros((), jnp.int32))
    )
    return keep


def _select_points(
    predictions,
    sizes: jax.Array,
    cells_h: int,
    cells_w: int,
    top_n: int | None,
    nms_radius: float,
    border: float,
    cell: float,
) -> tuple[jax.Array, ...]:
    """Drop padding/border points, NMS, top-N: batched Predictions -> fixed-size outputs.

    sizes: int32 [B, 2] (height, width) of each image before padding, in the keypoints' pixels;
    ``cell``: a cell's side in those pixels (:func:`radius_nms`). A point is kept when it is
    at least ``border`` px from the image edges, which lie at -0.5 and size - 0.5 in pixel-centre
    coordinates. Returns keypoints [B, K, 2], scores [B, K], descriptors [B, K, F] sorted by
    score, and counts [B]: only the first counts[b] entries of image b are points.
    """
    keypoints, scores = predictions.keypoints, predictions.scores
    extent = sizes[:, None, ::-1].astype(jnp.float32)  # [B, 1, 2] (width, height)
    inside = (keypoints >= border - 0.5) & (keypoints < extent - 0.5 - border)
    keep = jnp.all(inside, axis=-1)
    k = cells_h * cells_w if top_n is None else min(top_n, cells_h * cells_w)
    if nms_radius > 0:
        # Past the neighbourhood the greedy loop runs, which may stop at the k kept points the
        # top-k cut below takes anyway.
        greedy = int(nms_radius // cell) + 1 > NEIGHBOUR_REACH
        limit = k if greedy and top_n is not None else None
        keep = jax.vmap(radius_nms, in_axes=(0, 0, 0, None, None, None, None, None))(
            keypoints, scores, keep, cells_h, cells_w, nms_radius, cell, limit
        )
    ranked, order = jax.lax.top_k(jnp.where(keep, scores, -jnp.inf), k)
    counts = jnp.minimum(jnp.sum(keep, axis=-1), k)
    return (
        jnp.take_along_axis(keypoints, order[..., None], axis=1),
        ranked,
        jnp.take_along_axis(predictions.descriptors, order[..., None], axis=1),
        counts,
    )


def _detect_padded(
    variables: dict,
    images: jax.Array,
    sizes: jax.Array,
    *,
    model: UnsuperPoint,
    top_n: int | None,
    nms_radius: float,
    border: float,
    upsample: int = 1,
) -> tuple[jax.Array, ...]:
    """uint8 [B, H, W, 3] (H, W multiples of 8) + sizes [B, 2] -> :func:`_select_points` output.

    ``upsample`` s > 1 runs the network on the images enlarged s times (bilinear, pixel centres
    aligned) and maps its keypoints back: the cells shrink to 8 / s input pixels, and positions
    regressed to a roughly constant precision in the network's pixels come back finer (LE 0.69
    -> 0.45 px at s = 2 on the held-out pairs; SIFT doubles its input for the same reason).
    """
    pixels = images.astype(jnp.float32) / 255.0
    if upsample > 1:
        batch, height, width, channels = pixels.shape
        shape = (batch, height * upsample, width * upsample, channels)
        pixels = jax.image.resize(pixels, shape, "linear")
    predictions = model.apply(variables, pixels, train=False)
    if upsample > 1:
        # Pixel centres sit at integers: input pixel x spans [x - 0.5, x + 0.5], s network pixels.
        predictions = predictions._replace(
            keypoints=(predictions.keypoints + 0.5) / upsample - 0.5
        )
    cells_h, cells_w = pixels.shape[1] // CELL, pixels.shape[2] // CELL
    return _select_points(
        predictions, sizes, cells_h, cells_w, top_n, nms_radius, border, CELL / upsample
    )


def _unbatch(outputs) -> list[Features]:
    """Fixed-size device outputs -> one Features per image (numpy, float32)."""
    keypoints, scores, descriptors, counts = jax.device_get(outputs)
    return [
        Features(
            np.asarray(keypoints[b, :n], np.float32),
            np.asarray(scores[b, :n], np.float32),
            np.asarray(descriptors[b, :n], np.float32),
        )
        for b, n in enumerate(counts)
    ]


# ---------------------------------------------------------------------------------------------
# Host side: validation and padding


def _padding(height: int, width: int) -> tuple[int, int]:
    return -height % CELL, -width % CELL


def _check_size(shape: tuple[int, ...], height: int, width: int) -> None:
    if min(height, width) < CELL:
        raise ValueError(f"image of shape {shape} is smaller than {CELL} px on a side")


def _as_rgb(image: Any) -> np.ndarray:
    """Validate one image and return it as uint8 [H, W, 3] (gray replicated to 3 channels)."""
    image = np.asarray(image)
    shape = image.shape
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and shape[2] == 3)):
        raise ValueError(
            f"expected a uint8 HxWx3 RGB or HxW gray image, got shape {shape} dtype {image.dtype}"
        )
    _check_size(shape, *shape[:2])
    return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image


def _pad(images: np.ndarray) -> np.ndarray:
    """Edge-pad uint8 [..., H, W, 3] at the bottom/right to whole cells (module docstring)."""
    pad_h, pad_w = _padding(*images.shape[-3:-1])
    return np.pad(
        images, [(0, 0)] * (images.ndim - 3) + [(0, pad_h), (0, pad_w), (0, 0)], mode="edge"
    )


# ---------------------------------------------------------------------------------------------
# The detector


class Detector:
    """UnsuperPoint as a keypoint detector/descriptor for uint8 images of any size >= 8x8.

    ``top_n``: keep at most this many points (None: all, one per 8x8 cell). ``nms_radius``:
    greedy radius suppression in px before the top-N cut (0: off; the paper's "NMS = 4" is 4).
    ``border``: drop points within this many px of the image edges. ``upsample``: run the
    network on the image enlarged this many times (1: the paper's detector). 2 gives one
    candidate per 4x4 input pixels and about 1.5x finer keypoints for 4x the compute
    (experiments/RESULTS.md); keypoints are always in the input image's pixels.

    The network runs in float32 on CPU (where bfloat16 convolutions are emulated and slower) and
    in ``model_config.dtype`` elsewhere. One function is compiled per padded input shape, batch
    size and ``top_n``; images that pad to the same shape share it.
    """

    def __init__(
        self,
        variables: dict,
        model_config: ModelConfig = ModelConfig(),
        *,
        top_n: int | None = None,
        nms_radius: float = 0,
        border: float = 0,
        upsample: int = 1,
    ):
        _check_top_n(top_n)
        if not all(math.isfinite(v) and v >= 0 for v in (nms_radius, border)):
            raise ValueError(
                f"nms_radius and border must be finite and >= 0, got nms_radius={nms_radius},"
                f" border={border}"
            )
        integer = isinstance(upsample, (int, np.integer)) and not isinstance(upsample, bool)
        if not integer or upsample < 1:
            raise ValueError(f"upsample must be a positive integer, got {upsample!r}")
        if jax.default_backend() == "cpu":
            model_config = dataclasses.replace(model_config, dtype="float32")
        self.model_config = model_config
        self.variables = jax.device_put(
            jax.tree.map(
                lambda x: jnp.asarray(x, jnp.float32),
                {"params": variables["params"], "batch_stats": variables["batch_stats"]},
            )
        )
        self.top_n = top_n
        self.nms_radius = float(nms_radius)
        self.border = float(border)
        self.upsample = int(upsample)
        self._function = functools.partial(
            _detect_padded,
            model=UnsuperPoint(model_config),
            nms_radius=self.nms_radius,
            border=self.border,
            upsample=self.upsample,
        )
        self._forward = jax.jit(
            self._function, static_argnames="top_n", compiler_options=compiler_options()
        )

    @classmethod
    def from_checkpoint(cls, path: str | pathlib.Path, **options) -> Detector:
        """From the latest checkpoint of a training workdir, its ``checkpoints/`` or a step."""
        config, variables = checkpoint.load_variables(path)
        return cls(variables, config.model, **options)

    @classmethod
    def from_weights(cls, path: str | pathlib.Path, **options) -> Detector:
        """From a float16 weights file (:func:`save_weights`, ``usp-jax export --save-weights``)."""
        model_config, variables = load_weights(path)
        return cls(variables, model_config, **options)

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None, **options) -> Detector:
        """The default shipped weights (``path`` None), a ``.npz`` weights file, or a training
        workdir, its ``checkpoints/`` or one step: what the CLI's ``--checkpoint PATH`` accepts."""
        if path is None:
            return cls.pretrained(**options)
        if pathlib.Path(path).suffix == ".npz":
            return cls.from_weights(path, **options)
        return cls.from_checkpoint(path, **options)

    @classmethod
    def pretrained(cls, name: str | None = None, **options) -> Detector:
        """Weights shipped with the package, by name (``PRETRAINED``); None loads
        ``DEFAULT_PRETRAINED``, the best of them on the held-out pairs. Raises ValueError
        listing the names for an unknown one."""
        name = DEFAULT_PRETRAINED if name is None else name
        if name not in PRETRAINED:
            raise ValueError(
                f"unknown weights {name!r}; the shipped weights are {', '.join(PRETRAINED)}"
            )
        with importlib.resources.as_file(WEIGHTS_DIR / PRETRAINED[name]) as path:
            if not path.is_file():
                raise FileNotFoundError(
                    f"the {name!r} weights do not ship with this usp-jax ({path} is missing);"
                    " train a model with `usp-jax train --workdir WORKDIR --data IMAGES` and load"
                    " it with Detector.from_checkpoint(WORKDIR) (`--checkpoint WORKDIR` in the CLI)"
                )
            return cls.from_weights(path, **options)

    def detect(self, image: np.ndarray, top_n: int | None = None) -> Features:
        """Keypoints of one uint8 [H, W, 3] RGB or [H, W] gray image, H, W >= 8.

        Returns Features: keypoints float32 [N, 2] (x, y) in the image's pixels, scores [N]
        sorted descending, descriptors float32 [N, F] of unit length. ``top_n`` overrides the
        detector's. Raises ValueError naming the shape for a wrong dtype, ndim or size.
        """
        return self._run(_as_rgb(image)[None], top_n)[0]

    def detect_batch(
        self, images: np.ndarray | Sequence[np.ndarray], top_n: int | None = None
    ) -> list[Features]:
        """:meth:`detect` for a uint8 [B, H, W, 3] stack (one compiled call) or a list of images
        of any sizes (one call per padded shape). Results are in input order."""
        if isinstance(images, np.ndarray) and images.ndim == 4:
            if images.dtype != np.uint8 or images.shape[-1] != 3:
                raise ValueError(
                    f"expected a uint8 [B, H, W, 3] stack, got shape {images.shape}"
                    f" dtype {images.dtype}"
                )
            _check_size(images.shape, *images.shape[1:3])
            return self._run(images, top_n)
        rgb = [_as_rgb(image) for image in images]
        groups: dict[tuple[int, int], list[int]] = {}
        for i, image in enumerate(rgb):
            height, width = image.shape[:2]
            pad_h, pad_w = _padding(height, width)
            groups.setdefault((height + pad_h, width + pad_w), []).append(i)
        results: list[Features] = [None] * len(rgb)
        for members in groups.values():
            padded = np.stack([_pad(rgb[i]) for i in members])
            sizes = np.array([rgb[i].shape[:2] for i in members], np.int32)
            for i, features in zip(members, self._call(padded, sizes, top_n)):
                results[i] = features
        return results

    def _run(self, stack: np.ndarray, top_n: int | None) -> list[Features]:
        """A same-size uint8 [B, H, W, 3] stack of any H, W >= 8."""
        sizes = np.tile(np.array(stack.shape[1:3], np.int32), (len(stack), 1))
        return self._call(_pad(stack), sizes, top_n)

    def _call(self, padded: np.ndarray, sizes: np.ndarray, top_n: int | None) -> list[Features]:
        top_n = self.top_n if top_n is None else _check_top_n(top_n)
        return _unbatch(self._forward(self.variables, padded, sizes, top_n=top_n))


def _check_top_n(top_n: int | None) -> int | None:
    if top_n is not None and top_n < 1:
        raise ValueError(f"top_n must be positive or None, got {top_n}")
    return top_n


def as_method(detector: Detector, name: str = "UnsuperPoint") -> Method:
    """The detector as an evaluation Method (L2 descriptors) returning ALL its candidate points:
    the evaluation applies NMS and top-k to every method alike, so ``detector``'s ``top_n``,
    ``nms_radius`` and ``border`` are not used (its ``upsample`` is)."""
    every_point = Detector(detector.variables, detector.model_config, upsample=detector.upsample)
    return Method(name, every_point.detect, cv2.NORM_L2)


def to_cv2(features: Features) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """OpenCV keypoints (``pt`` = (x, y), ``size`` = one 8 px cell, ``response`` = score) and the
    float32 [N, F] descriptors, ready for ``cv2.BFMatcher(cv2.NORM_L2)``."""
    keypoints = [
        cv2.KeyPoint(float(x), float(y), float(CELL), response=float(score))
        for (x, y), score in zip(features.keypoints, features.scores)
    ]
    return keypoints, np.ascontiguousarray(features.descriptors, dtype=np.float32)


# ---------------------------------------------------------------------------------------------
# Ahead-of-time export


def export(
    detector: Detector,
    path: str | pathlib.Path,
    height: int,
    width: int,
    batch: str | int = "b",
) -> None:
    """Serialise the whole detector (weights included) for uint8 images [batch, height, width, 3].

    ``batch`` is a symbolic dimension name (any batch size at run time) or a fixed int. The file
    holds a ``jax.export`` artifact for the current platform computing ``(keypoints [B, K, 2],
    scores [B, K], descriptors [B, K, F], counts [B])`` with the detector's top_n, NMS and border;
    padding to whole cells happens inside. Read it back with :func:`load_exported`.
    """
    _check_size((height, width, 3), height, width)
    (batch_dim,) = (batch,) if isinstance(batch, int) else jax.export.symbolic_shape(batch)
    pad_h, pad_w = _padding(height, width)

    def detect(images):
        padded = jnp.pad(images, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        sizes = jnp.broadcast_to(jnp.array([height, width], jnp.int32), (images.shape[0], 2))
        return detector._function(detector.variables, padded, sizes, top_n=detector.top_n)

    spec = jax.ShapeDtypeStruct((batch_dim, height, width, 3), jnp.uint8)
    exported = jax.export.export(jax.jit(detect))(spec)
    pathlib.Path(path).write_bytes(exported.serialize())


def load_exported(path: str | pathlib.Path):
    """A file written by :func:`export` as ``uint8 [B, H, W, 3] -> list[Features]``; needs only
    JAX (``jax.export.deserialize``), not the model code."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"exported detector {path} does not exist")
    exported = jax.export.deserialize(bytearray(path.read_bytes()))

    def detect_batch(images: np.ndarray) -> list[Features]:
        return _unbatch(exported.call(images))

    return detect_batch
