"""Running a trained UnsuperPoint: images of any size in, sorted keypoints and descriptors out.

One jitted function per detector does everything on the device: uint8 -> float, an optional
enlargement (``upsample``), the network, dropping points in the padding and the border, radius
NMS, top-N selection and the descriptors of the selected points alone (interpolated as inside
the model, paper section 2.4: ``model.describe`` runs the descriptor head's last convolution on
the kept points only). The host only pads images to whole 8x8 cells and slices the fixed-size
results. Coordinates follow the project's convention (``usp_jax.core.model`` docstring): (x, y),
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
import math
import pathlib
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.cpu_kernels import compiler_options
from usp_jax.core.model import (
    CELL,
    ModelConfig,
    Predictions,
    UnsuperPoint,
    describe_points,
    pad_descriptor_features,
)
from usp_jax.inference import points, pyramid, weights
from usp_jax.inference import refine as refine_lib
from usp_jax.inference.compiled import BoundedJit
from usp_jax.inference.features import Features
from usp_jax.inference.memory import check_fits, measured_bytes_per_pixel
from usp_jax.inference.nms import NEIGHBOUR_REACH, radius_nms

# ---------------------------------------------------------------------------------------------
# The compiled part: selection of points from the network's M candidates


def _select_points(
    keypoints: jax.Array,
    scores: jax.Array,
    sizes: jax.Array,
    cells_h: int,
    cells_w: int,
    top_n: int | None,
    nms_radius: float,
    border: float,
    cell: float,
    valid: jax.Array | None = None,
    slack: float = 0.0,
) -> tuple[jax.Array, ...]:
    """Drop padding/border points, NMS, top-N: keypoints [B, M, 2] and scores [B, M] ->
    keypoints [B, K, 2], scores [B, K] sorted descending, the order [B, K] they were taken in
    (indices into M) and counts [B]: only the first counts[b] entries of image b are points.

    sizes: int32 [B, 2] (height, width) of each image before padding, in the keypoints' pixels;
    ``cell``: a cell's side in those pixels and ``slack`` how far a point may have left its cell
    (:func:`radius_nms`, which needs the M points on the cells_h x cells_w grid; without NMS any
    M will do); ``valid`` [B, M] marks the candidates at all (None: every one). A point is kept
    when it is at least ``border`` px from the image edges, which lie at -0.5 and size - 0.5 in
    pixel-centre coordinates.
    """
    keep = points.inside(keypoints, sizes[:, None, ::-1], border)
    keep = keep if valid is None else keep & valid
    m = scores.shape[-1]
    k = m if top_n is None else min(top_n, m)
    if nms_radius > 0:
        # Past the neighbourhood the greedy loop runs, which may stop at the k kept points the
        # top-k cut below takes anyway.
        greedy = int((nms_radius + 2 * slack) // cell) + 1 > NEIGHBOUR_REACH
        limit = k if greedy and top_n is not None else None
        keep = jax.vmap(radius_nms, in_axes=(0, 0, 0, None, None, None, None, None, None))(
            keypoints, scores, keep, cells_h, cells_w, nms_radius, cell, limit, slack
        )
    ranked, order = jax.lax.top_k(jnp.where(keep, scores, -jnp.inf), k)
    counts = jnp.minimum(jnp.sum(keep, axis=-1), k)
    return points.take(keypoints, order), ranked, order, counts


def _network(
    variables: dict,
    images: jax.Array,
    *,
    model: UnsuperPoint,
    upsample: int = 1,
    sparse: bool = False,
) -> tuple[jax.Array, Predictions, jax.Array | None, jax.Array | None]:
    """uint8 [B, H, W, 3] (H, W multiples of 8) -> (the network's input float32 [B, sH, sW, 3],
    its Predictions in its own pixels, anchors [B, M, 2], descriptor features [B, h, w, C]).

    ``sparse``: the model skips its descriptors and returns the anchors and features that the
    kept points' descriptors are computed from (``model.sparse_descriptors``); else both None.

    ``upsample`` s > 1 runs the network on the images enlarged s times (bilinear, pixel centres
    aligned): the cells shrink to 8 / s input pixels, and positions regressed to a roughly
    constant precision in the network's pixels come back finer (LE 0.69 -> 0.45 px at s = 2 on
    the held-out pairs; SIFT doubles its input for the same reason).
    """
    pixels = images.astype(jnp.float32) / 255.0
    if upsample > 1:
        batch, height, width, channels = pixels.shape
        shape = (batch, height * upsample, width * upsample, channels)
        pixels = jax.image.resize(pixels, shape, "linear")
    outputs = model.clone(sparse_descriptors=sparse).apply(variables, pixels, train=False)
    predictions, features, anchors = outputs if sparse else (outputs, None, None)
    return pixels, predictions, anchors, features


def _detect_padded(
    variables: dict,
    images: jax.Array,
    sizes: jax.Array,
    *,
    network: Callable,
    descriptors: Callable,
    top_n: int | None,
    nms_radius: float,
    border: float,
    upsample: int = 1,
    refiner: dict | None = None,
) -> tuple[jax.Array, ...]:
    """uint8 [B, H, W, 3] (H, W multiples of 8) + sizes [B, 2] -> keypoints [B, K, 2], scores
    [B, K] sorted descending, descriptors [B, K, F] and counts [B] (:func:`_select_points`);
    ``network`` is :func:`_network` with its model and ``upsample`` bound, ``descriptors``
    ``model.describe_points`` with its dtype.

    With a ``refiner`` the border test and NMS judge the refined points, and the ranking their
    scores times the certainty of their moves (``refine.patch_moves``). Without NMS only the
    strongest ``refine.refined_count`` points that the move can bring inside are refined: 501 of
    1,200 at 240x320 / 300. Descriptors are read where the network placed the points; only the
    kept points' are computed when they are few (``points.describes_sparsely``).
    """
    cells_h, cells_w = (side * upsample // CELL for side in images.shape[1:3])
    sparse = points.describes_sparsely(top_n, cells_h * cells_w)
    pixels, predictions, anchors, features = network(variables, images, sparse=sparse)
    keypoints, scores = predictions.keypoints, predictions.scores
    # What the kept points' descriptors come from: their anchors, or the model's descriptors.
    carried = anchors if sparse else predictions.descriptors
    valid, slack = None, 0.0
    if refiner is not None:
        keypoints, scores, valid = refine_lib.refine_on_grid(
            refiner, pixels, keypoints, scores, sizes, top_n, nms_radius, border, upsample
        )
        # Moves carry points out of their cells; neighbours that converge on one corner are one
        # point, whatever NMS the caller asked for.
        slack = refine_lib.REACH / upsample
        nms_radius = max(nms_radius, refine_lib.DUPLICATE_RADIUS)
    keypoints, ranked, order, counts = _select_points(
        points.to_input(keypoints, upsample),
        scores,
        sizes,
        cells_h,
        cells_w,
        top_n,
        nms_radius,
        border,
        CELL / upsample,
        valid,
        slack,
    )
    carried = points.take(carried, order)
    if sparse:
        maps = tuple(jnp.full(order.shape, n) for n in (*features.shape[1:3], 0))
        carried = descriptors(variables["params"], pad_descriptor_features(features), carried, maps)
    return keypoints, ranked, carried, counts


def unbatch(outputs) -> list[Features]:
    """Fixed-size device outputs -> one Features per image (numpy, float32); a fifth output,
    the pyramid's point sizes, becomes ``Features.scales``."""
    keypoints, scores, descriptors, counts, *sizes = jax.device_get(outputs)
    return [
        Features(
            np.asarray(keypoints[b, :n], np.float32),
            np.asarray(scores[b, :n], np.float32),
            np.asarray(descriptors[b, :n], np.float32),
            np.asarray(sizes[0][b, :n], np.float32) if sizes else None,
        )
        for b, n in enumerate(counts)
    ]


# ---------------------------------------------------------------------------------------------
# Host side: validation and padding


def padding(height: int, width: int) -> tuple[int, int]:
    return -height % CELL, -width % CELL


def check_size(shape: tuple[int, ...], height: int, width: int) -> None:
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
    check_size(shape, *shape[:2])
    return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image


def _pad(images: np.ndarray) -> np.ndarray:
    """Edge-pad uint8 [..., H, W, 3] at the bottom/right to whole cells (module docstring)."""
    pad_h, pad_w = padding(*images.shape[-3:-1])
    return np.pad(
        images, [(0, 0)] * (images.ndim - 3) + [(0, pad_h), (0, pad_w), (0, 0)], mode="edge"
    )


# ---------------------------------------------------------------------------------------------
# The detector

#: Longest side photos are detected at by ``usp-jax detect`` and ``match`` (1280x960 for 4:3).
MAX_SIDE = 1280


def shrink(image: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """``image`` shrunk to ``max_side`` on its longer side if it is longer (``INTER_AREA``),
    and the float32 [2] (x, y) factors that take the copy's pixels back to the original's
    (:func:`grow`). Others, and any image when ``max_side`` is 0, come back as they are, with
    factors 1. A 12-megapixel photo at native size takes gigabytes of activations and seconds
    on a CPU, and the network was trained on 240x320 views anyway."""
    height, width = image.shape[:2]
    if not 0 < max_side < max(height, width):
        return image, np.ones(2, np.float32)
    scale = max(height, width) / max_side
    size = (max(round(width / scale), CELL), max(round(height / scale), CELL))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return small, np.array([width / size[0], height / size[1]], np.float32)


def grow(features: Features, factors: np.ndarray) -> Features:
    """``features`` of a :func:`shrink`-ed copy in the original's pixels:
    ``x = (x' + 0.5) * factors - 0.5`` (``cv2.resize`` scales about pixel corners), sizes by
    the mean factor."""
    scales = None if features.scales is None else features.scales * np.mean(factors)
    return features._replace(keypoints=(features.keypoints + 0.5) * factors - 0.5, scales=scales)


class Detector:
    """UnsuperPoint as a keypoint detector/descriptor for uint8 images of any size >= 8x8.

    ``top_n``: keep at most this many points (None: all, one per 8x8 cell). ``nms_radius``:
    greedy radius suppression in px before the top-N cut (0: off; the paper's "NMS = 4" is 4).
    ``border``: drop points within this many px of the image edges. ``upsample``: run the
    network on the image enlarged this many times (1: the paper's detector). 2 gives one
    candidate per 4x4 input pixels and about 1.5x finer keypoints for 4x the compute
    (experiments/RESULTS.md); keypoints are always in the input image's pixels. ``max_side``:
    detect on a copy shrunk to at most this many px on its longer side (0: always at native
    size; ``MAX_SIDE`` suits photos), keypoints mapped back to the original's pixels.
    ``any_scale``: detect on an image pyramid too (``inference.pyramid``), for pairs that differ
    by zoom; each point's size is in ``Features.scales``; one function compiled per input size.
    ``refine``: move each point by the sub-pixel offset network of ``inference.refine``, and
    scale its score by how sure the move is, so better localised points rank higher (True:
    the shipped one; a path: an ``.npz`` from ``refine.save_params``; False: the raw cells;
    None: the shipped one for the paper's network, which it was trained on, else none. On the
    distilled network's points it gains as much, at about 1.8x that network's time:
    ``refine=True``).

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
        max_side: int = 0,
        any_scale: bool = False,
        refine: bool | str | pathlib.Path | None = None,
    ):
        top_n = _check_top_n(top_n)
        if not all(math.isfinite(v) and v >= 0 for v in (nms_radius, border)):
            raise ValueError(
                f"nms_radius and border must be finite and >= 0, got nms_radius={nms_radius},"
                f" border={border}"
            )
        integer = isinstance(upsample, (int, np.integer)) and not isinstance(upsample, bool)
        if not integer or upsample < 1:
            raise ValueError(f"upsample must be a positive integer, got {upsample!r}")
        max_side = check_max_side(max_side)
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
        self.max_side = int(max_side)
        if refine is None:
            # Trained on the paper network's upright points, it moves the fast and rotation
            # networks' points off (a 120-degree turn no longer registers).
            refine = model_config == dataclasses.replace(ModelConfig(), dtype=model_config.dtype)
        self.refine = refine
        self.refiner = (
            None if refine is False else refine_lib.load_params(None if refine is True else refine)
        )
        self.any_scale = bool(any_scale)
        options = dict(
            network=functools.partial(
                _network,
                model=UnsuperPoint(model_config),
                upsample=self.upsample,
            ),
            descriptors=functools.partial(describe_points, dtype=model_config.dtype),
            nms_radius=self.nms_radius,
            border=self.border,
            upsample=self.upsample,
            refiner=self.refiner,
        )
        # (variables, uint8 images, [sizes,] top_n=...) -> fixed-size outputs; jax.export
        # jits it itself. The pyramid takes the unpadded images: it pads each level.
        self._function = functools.partial(
            pyramid.detect_pyramid if self.any_scale else _detect_padded, **options
        )
        self._forward = BoundedJit(self._function, compiler_options=compiler_options())

    def replace(self, **changes) -> Detector:
        """A detector of the same weights with ``changes`` to its options (``__init__``'s
        keywords); every other option, ``refine`` as resolved here included, is this one's."""
        options = dict(
            top_n=self.top_n,
            nms_radius=self.nms_radius,
            border=self.border,
            upsample=self.upsample,
            max_side=self.max_side,
            any_scale=self.any_scale,
            refine=self.refine,
        )
        return Detector(self.variables, self.model_config, **{**options, **changes})

    @classmethod
    def from_checkpoint(cls, path: str | pathlib.Path, **options) -> Detector:
        """From the latest checkpoint of a training workdir, its ``checkpoints/`` or a step."""
        model_config, variables = weights.load_checkpoint(path)
        return cls(variables, model_config, **options)

    @classmethod
    def from_weights(cls, path: str | pathlib.Path, **options) -> Detector:
        """From a float16 weights file (``weights.save_weights``, ``usp-jax export
        --save-weights``)."""
        model_config, variables = weights.load_weights(path)
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
        """Weights shipped with the package, by name (``weights.PRETRAINED``); None loads
        ``weights.DEFAULT_PRETRAINED``, the best of them on the held-out pairs. Raises
        ValueError listing the names for an unknown one."""
        name = weights.DEFAULT_PRETRAINED if name is None else name
        with importlib.resources.as_file(weights.pretrained_path(name)) as path:
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
        return self.detect_batch([image], top_n)[0]

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
            check_size(images.shape, *images.shape[1:3])
            if not self._shrinks(images.shape[1:3]):
                return self._run(images, top_n)
            images = list(images)
        rgb = [_as_rgb(image) for image in images]
        if any(self._shrinks(image.shape[:2]) for image in rgb):
            return [self._detect_shrunk(image, top_n) for image in rgb]
        groups: dict[tuple[int, int], list[int]] = {}
        for i, image in enumerate(rgb):
            height, width = image.shape[:2]
            pad_h, pad_w = padding(height, width)
            groups.setdefault((height + pad_h, width + pad_w), []).append(i)
        results: list[Features] = [None] * len(rgb)
        for members in groups.values():
            padded = np.stack([_pad(rgb[i]) for i in members])
            sizes = np.array([rgb[i].shape[:2] for i in members], np.int32)
            for i, features in zip(members, self._call(padded, sizes, top_n)):
                results[i] = features
        return results

    def _shrinks(self, size: tuple[int, int]) -> bool:
        return 0 < self.max_side < max(size)

    def shrink(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`shrink` to this detector's ``max_side``."""
        return shrink(image, self.max_side)

    def detect_as_is(self, image: np.ndarray, top_n: int | None = None) -> Features:
        """:meth:`detect` at the image's own size, whatever ``max_side`` says (for an image the
        caller has already shrunk, such as a turned copy of one)."""
        return self._run(_as_rgb(image)[None], top_n)[0]

    def _detect_shrunk(self, image: np.ndarray, top_n: int | None) -> Features:
        """One image, :meth:`shrink`-ed, keypoints mapped back."""
        small, factors = self.shrink(image)
        return grow(self._run(small[None], top_n)[0], factors)

    def _run(self, stack: np.ndarray, top_n: int | None) -> list[Features]:
        """A same-size uint8 [B, H, W, 3] stack of any H, W >= 8."""
        sizes = np.tile(np.array(stack.shape[1:3], np.int32), (len(stack), 1))
        return self._call(_pad(stack), sizes, top_n)

    def _bytes_per_pixel(self) -> float:
        """XLA's memory need of this detector per input pixel (``memory.check_fits``), once."""
        if not hasattr(self, "_measured"):
            self._measured = measured_bytes_per_pixel(
                self._forward, self.variables, self.top_n, self.any_scale
            )
        return self._measured

    def _call(self, padded: np.ndarray, sizes: np.ndarray, top_n: int | None) -> list[Features]:
        top_n = self.top_n if top_n is None else _check_top_n(top_n)
        # Before compiling: an image too large for memory is one line naming max_side, not an
        # abort inside XLA.
        check_fits(self.model_config, padded.shape, self.upsample, self._bytes_per_pixel)
        if self.any_scale:
            return pyramid.detect_by_size(
                self._forward, self.variables, padded, sizes, top_n, unbatch
            )
        return unbatch(self._forward(self.variables, padded, sizes, top_n=top_n))


def _check_top_n(top_n: int | None) -> int | None:
    """``top_n`` as an int or None; else a ValueError (2.5 or NaN would reach jit as a shape)."""
    if top_n is None:
        return None
    integer = isinstance(top_n, (int, np.integer)) and not isinstance(top_n, bool)
    if not integer or top_n < 1:
        raise ValueError(f"top_n must be a positive integer or None, got {top_n!r}")
    return int(top_n)


def check_max_side(max_side: int) -> int:
    """``max_side`` as an int: 0 (native size) or at least one ``CELL``; else a ValueError."""
    integer = isinstance(max_side, (int, np.integer)) and not isinstance(max_side, bool)
    if not integer or not (max_side == 0 or max_side >= CELL):
        raise ValueError(f"max_side must be 0 or an integer >= {CELL}, got {max_side!r}")
    return int(max_side)
