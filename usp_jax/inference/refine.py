"""Sub-pixel refinement of detected keypoints: a small offset network on a grey patch per point.

The network places one point per 8x8 cell to a roughly constant precision in its own pixels
(LE 0.69 px at 240x320; SIFT 0.37). This stage moves each kept point by a learned offset read
from the image around it, in the spirit of Keypt2Subpx (Kim et al., ECCV 2024):

    p' = p + o(patch(I, p)),    o = sum_{u in U} softmax(f(patch))_u * u,    U = {-R..R}^2

``patch(I, p)``: the P x P grey patch bilinearly sampled on the pixel grid centred on p
(``P = 2 R + 1 + 2 D``, the margin of D valid 3x3 convolutions: 17 for the shipped D = 4),
normalised to zero mean and unit spread so brightness and contrast changes do not move points;
``f``: D valid 3x3 convolutions (16 channels wide) to one logit per offset u in the (2R + 1)^2
window; the soft-argmax makes the offset a convex combination of window offsets, so
``|o_x|, |o_y| <= R`` by construction.
``R = CELL / 2``: a point moves at most half a cell per axis, in the network's pixels (half of
that in the input's at ``upsample`` 2).

The move also says how sure it is: the spread of the softmax over the window,
``v = Var_x + Var_y`` (px^2), is small where one offset stands out (a corner) and large where
many do (an edge, a blob). A refined point's score is the network's times ``exp(-w v)`` (``w`` =
``SPREAD_WEIGHT``), so that of two equally scored points the better localised is kept: on the
design pairs (training photos) that lowered LE by 0.06 px and raised HA@1 by 0.05
(experiments/notes/choices.md).

Training is label-free (``experiments/refine_offsets.py``): for a point p_A of image A and the
point p_B the frozen detector finds at its correspondent in B = H(A), minimise the paper's
position distance between the refined points, ``|| H(p_A + o_A) - (p_B + o_B) ||`` (eq. 6's
d_k): only an offset that lands on the same physical spot in both views, from any start the
detector gives, lowers it.

Everything is pure and jit-able; the ``Detector`` calls :func:`refine_keypoints` inside its one
compiled function (the pyramid, :func:`patch_moves` on each level's patches).
"""

from __future__ import annotations

import importlib.resources
import math
import pathlib

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core.model import CELL
from usp_jax.inference import points

#: Largest move per axis, in the network's pixels: half a cell.
REACH = CELL // 2
#: Refined points of neighbouring cells often converge on one corner (135 pairs of 500 points
#: within 0.5 px on a real photo); the detector keeps the stronger of any two closer than this
#: (input px), as an NMS of this radius on the refined points.
DUPLICATE_RADIUS = 1.0
#: Channels of the shipped network's hidden 3x3 convolutions. Other widths and depths load from
#: their weights (:func:`channels_of`); every convolution is valid, so each trims a pixel a side.
CHANNELS = (16, 16, 16)
#: How fast a refined point's score falls with the spread of its move, per px^2 of the network's
#: pixels (module docstring); 0 keeps the network's scores.
SPREAD_WEIGHT = 0.1
#: The shipped offset network, trained on top of the shipped paper weights.
WEIGHTS = importlib.resources.files("usp_jax") / "weights" / "refine.npz"


def patch_side(channels: tuple[int, ...] = CHANNELS) -> int:
    """Side of the patch read around a point: the (2 REACH + 1)^2 offset window plus one pixel a
    side for each of the ``len(channels) + 1`` valid convolutions."""
    return 2 * REACH + 1 + 2 * (len(channels) + 1)


#: The shipped network's patch side (17).
PATCH = patch_side()

# ITU-R BT.601 luma, as cv2.COLOR_RGB2GRAY.
_LUMA = (0.299, 0.587, 0.114)


class OffsetNet(nn.Module):
    """Normalised patches [N, P, P] -> offset logits [N, 2 REACH + 1, 2 REACH + 1], with
    ``P = patch_side(channels)``."""

    channels: tuple[int, ...] = CHANNELS

    @nn.compact
    def __call__(self, patches: jax.Array) -> jax.Array:
        x = patches[..., None]
        for width in self.channels:
            x = nn.relu(nn.Conv(width, (3, 3), padding="VALID")(x))
        return nn.Conv(1, (3, 3), padding="VALID")(x)[..., 0]


def init_params(key: jax.Array, channels: tuple[int, ...] = CHANNELS) -> dict:
    """Fresh OffsetNet parameters of hidden widths ``channels``."""
    side = patch_side(channels)
    return OffsetNet(channels).init(key, jnp.zeros((1, side, side)))["params"]


def channels_of(params: dict) -> tuple[int, ...]:
    """The hidden widths of OffsetNet parameters, read off their kernels [3, 3, in, out]."""
    kernels = [params[f"Conv_{i}"]["kernel"] for i in range(len(params))]
    return tuple(int(kernel.shape[-1]) for kernel in kernels[:-1])


def grey(pixels: jax.Array) -> jax.Array:
    """RGB [..., H, W, 3] -> luma [..., H, W], in the input's range."""
    return pixels @ jnp.asarray(_LUMA, pixels.dtype)


def sample_patches(image: jax.Array, keypoints: jax.Array, side: int = PATCH) -> jax.Array:
    """Bilinear grey patches [K, side, side] of image [H, W] centred on keypoints [K, 2].

    Pixel centres at integers (``core.model`` convention); outside the image the border value is
    repeated, so a point near the edge sees no artificial step.
    """
    steps = jnp.arange(side, dtype=jnp.float32) - (side - 1) / 2
    xs = keypoints[:, None, None, 0] + steps[None, None, :]  # [K, 1, side]
    ys = keypoints[:, None, None, 1] + steps[None, :, None]  # [K, side, 1]
    xs, ys = jnp.broadcast_arrays(xs, ys)
    return jax.scipy.ndimage.map_coordinates(image, [ys, xs], order=1, mode="nearest")


def normalise(patches: jax.Array, eps: float = 1e-2) -> jax.Array:
    """Zero mean, unit standard deviation per patch [K, P, P]; ``eps`` keeps flat patches flat."""
    mean = jnp.mean(patches, axis=(-2, -1), keepdims=True)
    centred = patches - mean
    spread = jnp.sqrt(jnp.mean(centred**2, axis=(-2, -1), keepdims=True))
    return centred / (spread + eps)


def soft_argmax(logits: jax.Array) -> jax.Array:
    """Logits [K, 2R + 1, 2R + 1] -> expected (x, y) offset [K, 2] in [-R, R] (columns are x)."""
    return _window_moments(logits)[0]


def spread(logits: jax.Array) -> jax.Array:
    """Logits [K, 2R + 1, 2R + 1] -> the variance of the offset under their softmax, summed over
    x and y [K] (px^2): 0 for a single peak, 2 R (R + 1) / 3 for a flat window."""
    return _window_moments(logits)[1]


def _window_moments(logits: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`soft_argmax` [K, 2] and :func:`spread` [K] from one softmax of the window."""
    reach = (logits.shape[-1] - 1) / 2
    weights = jax.nn.softmax(logits.reshape(*logits.shape[:-2], -1), axis=-1).reshape(logits.shape)
    steps = jnp.arange(logits.shape[-1], dtype=jnp.float32) - reach
    mean = jnp.stack(
        [
            jnp.sum(weights * steps[None, :], axis=(-2, -1)),
            jnp.sum(weights * steps[:, None], axis=(-2, -1)),
        ],
        axis=-1,
    )
    squares = steps[None, :] ** 2 + steps[:, None] ** 2
    return mean, jnp.sum(weights * squares, axis=(-2, -1)) - jnp.sum(mean**2, axis=-1)


def offsets(params: dict, image: jax.Array, keypoints: jax.Array) -> jax.Array:
    """The learned moves [K, 2] of keypoints [K, 2] on grey image [H, W], both in the same pixels;
    ``|move| <= REACH`` per axis."""
    return moves(params, image, keypoints)[0]


def moves(
    params: dict, image: jax.Array, keypoints: jax.Array, weight: float | None = None
) -> tuple[jax.Array, jax.Array]:
    """:func:`patch_moves` of keypoints [K, 2] on grey image [H, W]: their patches read by
    :func:`sample_patches` at the offset network's patch side."""
    patches = sample_patches(image, keypoints, patch_side(channels_of(params)))
    return patch_moves(params, patches, weight)


def patch_offsets(params: dict, patches: jax.Array) -> jax.Array:
    """The learned moves [K, 2] of the points at the centres of grey patches [K, P, P]
    (:func:`sample_patches`, ``P = patch_side(channels_of(params))``)."""
    return soft_argmax(_logits(params, patches))


def patch_moves(
    params: dict, patches: jax.Array, weight: float | None = None
) -> tuple[jax.Array, jax.Array]:
    """:func:`patch_offsets` [K, 2] and the factor ``exp(-weight * spread)`` [K] in (0, 1] that
    the points' scores are multiplied by (module docstring; ``weight`` None: ``SPREAD_WEIGHT``)."""
    mean, variance = _window_moments(_logits(params, patches))
    weight = SPREAD_WEIGHT if weight is None else weight
    return mean, jnp.exp(-weight * variance)


def _logits(params: dict, patches: jax.Array) -> jax.Array:
    channels = channels_of(params)
    return OffsetNet(channels).apply({"params": params}, normalise(patches))


def edge_cells(cells_h: int, cells_w: int, border: float, upsample: int = 1) -> int:
    """How many cells of a cells_h x cells_w grid hold a point that a move of up to ``REACH``
    network pixels can carry across the border line, ``border`` input px inside an image that
    ends anywhere in the last cell (the padding): the only points whose keeping a move decides.

    Rows of cells near the top edge: ceil((border + reach) / cell); near the bottom edge:
    ceil((8 + border + reach) / cell); columns alike (cell and reach in input px).
    """
    cell, reach = CELL / upsample, REACH / upsample
    near = math.ceil((border + reach) / cell) + math.ceil((CELL + border + reach) / cell)
    rows, cols = min(near, cells_h), min(near, cells_w)
    return rows * cells_w + cols * cells_h - rows * cols


def refined_count(candidates: int, edges: int, top_n: int | None, nms_radius: float) -> int:
    """How many of ``candidates`` points, strongest first among those a move can bring inside,
    are refined: ``top_n`` plus the ``edges`` (:func:`edge_cells`, the only points whose keeping
    a move decides); all of them where NMS (which sees the moved points) or no top-N cut needs
    them. With scores that the moves leave alone (``SPREAD_WEIGHT`` 0) the output equals
    refining all of them; with the spread, the N kept are the best re-scored of those, which on
    the design pairs placed points as well as refining all (experiments/notes/choices.md)."""
    if top_n is None or nms_radius > 0:
        return candidates
    return min(candidates, top_n + edges)


def refine_keypoints(
    params: dict, pixels: jax.Array, keypoints: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Refined keypoints [B, K, 2] of images [B, H, W, 3] (the network's input) at keypoints
    [B, K, 2] in those images' pixels, ``p + offsets(p)``, and the factors [B, K] their scores
    are multiplied by (:func:`patch_moves`), per image."""
    shifts, factors = jax.vmap(moves, in_axes=(None, 0, 0))(params, grey(pixels), keypoints)
    return keypoints + shifts, factors


def refine_on_grid(
    refiner: dict,
    pixels: jax.Array,
    keypoints: jax.Array,
    scores: jax.Array,
    sizes: jax.Array,
    top_n: int | None,
    nms_radius: float,
    border: float,
    upsample: int,
) -> tuple[jax.Array, jax.Array, jax.Array | None]:
    """The refined keypoints [B, M, 2] (network pixels) and scores [B, M] (times the certainty
    of their moves, ``refine.patch_moves``) on the network's grid, and which were refined [B, M]
    (None: all). Without NMS only the strongest ``refine.refined_count`` points that a move can
    bring inside are refined (501 of 1,200 at 240x320 / 300); the others stay in their cells,
    marked invalid, so that NMS still finds every point's neighbours by cell."""
    # The network's input is the image enlarged upsample times: one cell per CELL of its pixels.
    cells_h, cells_w = (side // CELL for side in pixels.shape[1:3])
    edges = edge_cells(cells_h, cells_w, border, upsample)
    count = refined_count(cells_h * cells_w, edges, top_n, nms_radius)
    if count == cells_h * cells_w:
        # In the network's pixels, where the offsets were learned (inference.refine).
        keypoints, factors = refine_keypoints(refiner, pixels, keypoints)
        return keypoints, scores * factors, None
    # The points a move of up to REACH can bring inside, strongest first.
    reach = REACH / upsample
    possible = points.inside(
        points.to_input(keypoints, upsample), sizes[:, None, ::-1], border - reach
    )
    _, order = jax.lax.top_k(jnp.where(possible, scores, -jnp.inf), count)
    moved, factors = refine_keypoints(refiner, pixels, points.take(keypoints, order))

    def scatter(values, chosen, new):
        return values.at[chosen].set(new)

    keypoints = jax.vmap(scatter)(keypoints, order, moved)
    scores = jax.vmap(scatter)(scores, order, points.take(scores, order) * factors)
    valid = jax.vmap(scatter)(jnp.zeros(scores.shape, bool), order, jnp.ones(order.shape, bool))
    return keypoints, scores, valid


def save_params(path: str | pathlib.Path, params: dict) -> None:
    """Write OffsetNet parameters as a float32 ``.npz`` of ``"a/b/kernel"`` keys."""
    flat = flax.traverse_util.flatten_dict(params, sep="/")
    np.savez_compressed(path, **{k: np.asarray(v, np.float32) for k, v in flat.items()})


def load_params(path: str | pathlib.Path | None = None) -> dict:
    """OffsetNet parameters from ``path`` (None: the shipped ``WEIGHTS``). Raises ValueError
    when the file's arrays do not fit the network."""
    with importlib.resources.as_file(WEIGHTS if path is None else pathlib.Path(path)) as file:
        with np.load(file) as data:
            flat = {key: jnp.asarray(data[key], jnp.float32) for key in data.files}
    params = flax.traverse_util.unflatten_dict(flat, sep="/")
    try:
        expected = jax.tree.map(jnp.shape, init_params(jax.random.PRNGKey(0), channels_of(params)))
        fits = jax.tree.map(jnp.shape, params) == expected
    except (KeyError, TypeError, IndexError, ValueError):
        fits = False
    if not fits:
        raise ValueError(f"{path or WEIGHTS} does not hold the refinement network's weights")
    return params
