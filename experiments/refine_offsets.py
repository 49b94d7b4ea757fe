"""Train the sub-pixel offset network of ``usp_jax.inference.refine``, label-free, on top of the
frozen shipped detector.

    python3 experiments/refine_offsets.py --photos data/corpus/train --out usp_jax/weights/refine.npz

trains the shipped network (16, 16, 16 channels; 999 s of CPU). ``--channels`` sets another width
and depth (the first shipped one was ``16,16``); ``--weights distilled`` trains one for the
distilled network's points instead.

Pairs: a random 240x320 crop A of a training photo and B = H(A), H drawn from the training
homographies (paper section 3, ``core.geometry.sample_homography``), B's brightness, contrast
and gamma changed. The frozen detector (``Detector.pretrained(refine=False)``) finds points in
both; a point p_A pairs with the nearest point p_B of B within ``--radius`` px of H(p_A). The
loss is the mean position distance of the refined pairs, ``|| H(p_A + o_A) - (p_B + o_B) ||``
(the paper's d_k, eq. 6): no label says where a point should go, only that both views agree.
Prints the held-back pairs' mean distance before and after training, and the CPU time.
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optax

from usp_jax.core.geometry import HomographyConfig, sample_homography, warp_points
from usp_jax.inference import Detector, refine
from usp_jax.inference.images import read_image

HEIGHT, WIDTH = 240, 320


def crop(rng: np.random.Generator, photo: np.ndarray) -> np.ndarray:
    """A random HEIGHT x WIDTH crop of ``photo`` shrunk to cover 1-1.6x that size."""
    scale = rng.uniform(1.0, 1.6) * max(HEIGHT / photo.shape[0], WIDTH / photo.shape[1])
    size = (max(round(photo.shape[1] * scale), WIDTH), max(round(photo.shape[0] * scale), HEIGHT))
    small = cv2.resize(photo, size, interpolation=cv2.INTER_AREA)
    y = rng.integers(0, small.shape[0] - HEIGHT + 1)
    x = rng.integers(0, small.shape[1] - WIDTH + 1)
    return np.ascontiguousarray(small[y : y + HEIGHT, x : x + WIDTH])


def photometric(rng: np.random.Generator, image: np.ndarray) -> np.ndarray:
    """Brightness +-20%, contrast 0.7-1.3x and gamma 0.7-1.4: what the illumination pairs vary."""
    x = (image / 255.0) ** rng.uniform(0.7, 1.4)
    x = (x - 0.5) * rng.uniform(0.7, 1.3) + 0.5 + rng.uniform(-0.2, 0.2)
    return np.clip(x * 255 + 0.5, 0, 255).astype(np.uint8)


def correspondences(detector, a, b, homography, radius, margin):
    """Point pairs (p_A [N, 2], p_B [N, 2]) of two detections under ``homography`` (A -> B)."""
    found_a, found_b = detector.detect_batch(np.stack([a, b]))
    projected = np.asarray(warp_points(jnp.asarray(homography), jnp.asarray(found_a.keypoints)))
    distance = np.linalg.norm(projected[:, None] - found_b.keypoints[None], axis=-1)
    nearest = np.argmin(distance, axis=1)
    inside = np.all((projected > margin) & (projected < [WIDTH - margin, HEIGHT - margin]), axis=1)
    keep = inside & (distance[np.arange(len(nearest)), nearest] < radius)
    return found_a.keypoints[keep], found_b.keypoints[nearest[keep]]


@functools.partial(jax.jit, static_argnames="side")
def _patches(image, keypoints, side):
    return refine.sample_patches(refine.grey(image.astype(jnp.float32) / 255.0), keypoints, side)


def build(photos, pairs, radius, seed, weights=None, side=refine.PATCH, views=HomographyConfig()):
    """Patches [N, 2, side, side], points [N, 2, 2] and homographies [N, 3, 3] of every point
    pair the ``weights`` (shipped name; None: the default) find."""
    rng = np.random.default_rng(seed)
    detector = Detector.pretrained(weights, top_n=500, refine=False)
    key = jax.random.PRNGKey(seed)
    patches, points, homographies = [], [], []
    for i in range(pairs):
        a = crop(rng, photos[rng.integers(len(photos))])
        homography = np.asarray(sample_homography(jax.random.fold_in(key, i), HEIGHT, WIDTH, views))
        b = cv2.warpPerspective(a, homography, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
        b = photometric(rng, b)
        p_a, p_b = correspondences(detector, a, b, homography, radius, side)
        patches.append(np.stack([_patches(a, p_a, side), _patches(b, p_b, side)], axis=1))
        points.append(np.stack([p_a, p_b], axis=1))
        homographies.append(np.broadcast_to(homography, (len(p_a), 3, 3)))
    return (np.concatenate(x).astype(np.float32) for x in (patches, points, homographies))


def moves(params, patches):
    """The offsets [N, 2, 2] of both points of each pair."""
    flat = patches.reshape(-1, *patches.shape[2:])
    return refine.patch_offsets(params, flat).reshape(-1, 2, 2)


def distances(params, patches, points, homographies):
    """|| H(p_A + o_A) - (p_B + o_B) || per pair [N] (``params`` None: the raw points)."""
    p_a, p_b = points[:, 0], points[:, 1]
    if params is not None:
        moved = moves(params, patches)
        p_a, p_b = p_a + moved[:, 0], p_b + moved[:, 1]
    projected = jax.vmap(lambda h, p: warp_points(h, p[None])[0])(homographies, p_a)
    return jnp.linalg.norm(projected - p_b, axis=-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", required=True, help="folder of training photos")
    parser.add_argument("--out", required=True, help="the trained OffsetNet's .npz")
    parser.add_argument(
        "--weights", help="the frozen detector's shipped weights (default: the package's)"
    )
    parser.add_argument("--pairs", type=int, default=300, help="image pairs drawn")
    parser.add_argument(
        "--radius",
        type=float,
        default=3.0,
        help="point-pair distance, px (also filters the pairs of a --cache built at a larger one)",
    )
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--batch", type=int, default=256, help="point pairs per step")
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--mean-weight",
        type=float,
        default=0.0,
        help="weight of the squared mean offset per batch: the distance barely changes when"
        " every point shifts alike, so without it the points may drift together",
    )
    parser.add_argument(
        "--channels",
        default=",".join(map(str, refine.CHANNELS)),
        help="hidden widths of the offset network, comma-separated (default: the shipped one's);"
        " each adds a convolution and a pixel a side to the patch",
    )
    parser.add_argument(
        "--perspective",
        type=float,
        default=HomographyConfig().perspective,
        help="keystone range of the training homographies (core.geometry.HomographyConfig;"
        " default: training's)",
    )
    parser.add_argument("--cache", help="keep the point pairs in this .npz and reuse them")
    args = parser.parse_args()
    try:
        channels = tuple(int(width) for width in args.channels.split(","))
    except ValueError:
        parser.error(f"--channels takes comma-separated integers, got {args.channels!r}")
    side = refine.patch_side(channels)
    start_wall, start_cpu = time.time(), time.process_time()

    photos = [read_image(p) for p in sorted(pathlib.Path(args.photos).iterdir())]
    if args.cache and pathlib.Path(args.cache).is_file():
        with np.load(args.cache) as data:
            patches, points, homographies = data["patches"], data["points"], data["homographies"]
        if patches.shape[-1] != side:
            parser.error(f"--cache {args.cache} holds {patches.shape[-1]} px patches, not {side}")
        # A cache built at a larger radius holds every pair a smaller one would find (each
        # point's nearest neighbour is the same), and more.
        near = np.asarray(distances(None, None, points, homographies))  # the raw points
        patches, points, homographies = (
            x[near < args.radius] for x in (patches, points, homographies)
        )
    else:
        patches, points, homographies = build(
            photos,
            args.pairs,
            args.radius,
            args.seed,
            args.weights,
            side,
            HomographyConfig(perspective=args.perspective),
        )
        if args.cache:
            np.savez(args.cache, patches=patches, points=points, homographies=homographies)
    held = np.arange(len(points)) % 10 == 0
    print(f"{len(points)} point pairs from {args.pairs} image pairs ({held.sum()} held back)")
    print(
        f"data: {time.time() - start_wall:.0f} s wall, {time.process_time() - start_cpu:.0f} s CPU"
    )

    train = tuple(jnp.asarray(x[~held]) for x in (patches, points, homographies))
    test = tuple(jnp.asarray(x[held]) for x in (patches, points, homographies))
    params = refine.init_params(jax.random.PRNGKey(args.seed), channels)
    # A zero last layer: uniform logits, so training starts from the raw points (offset 0).
    last = f"Conv_{len(channels)}"
    params = {**params, last: jax.tree.map(jnp.zeros_like, params[last])}
    optimizer = optax.adam(optax.cosine_decay_schedule(args.lr, args.steps))
    state = optimizer.init(params)

    @jax.jit
    def step(params, state, indices):
        batch = tuple(x[indices] for x in train)

        def loss_of(p):
            drift = jnp.sum(jnp.mean(moves(p, batch[0]), axis=(0, 1)) ** 2)
            return jnp.mean(distances(p, *batch)) + args.mean_weight * drift

        loss, grads = jax.value_and_grad(loss_of)(params)
        updates, state = optimizer.update(grads, state, params)
        return optax.apply_updates(params, updates), state, loss

    rng = np.random.default_rng(args.seed)
    raw = float(jnp.mean(distances(None, *test)))
    for i in range(args.steps):
        params, state, loss = step(params, state, rng.integers(0, len(train[0]), args.batch))
        if i % 500 == 0 or i == args.steps - 1:
            held_out = float(jnp.mean(distances(params, *test)))
            print(f"step {i}: train {float(loss):.3f}, held back {held_out:.3f} (raw {raw:.3f}) px")
    median_raw = float(jnp.median(distances(None, *test)))
    median = float(jnp.median(distances(params, *test)))
    print(f"held-back median distance: raw {median_raw:.3f} px, refined {median:.3f} px")
    mean_move = np.asarray(jnp.mean(moves(params, test[0]), axis=(0, 1)))
    print(f"held-back mean move (x, y): {mean_move[0]:+.3f}, {mean_move[1]:+.3f} px")
    refine.save_params(args.out, params)
    print(
        f"total: {time.time() - start_wall:.0f} s wall, {time.process_time() - start_cpu:.0f} s CPU"
        f" ({args.steps} steps)"
    )


if __name__ == "__main__":
    main()
