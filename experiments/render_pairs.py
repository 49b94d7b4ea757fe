"""Render training pairs with parallax: two views of a room of photos, with depth and pose, in
the layout a ``pairs:`` training source reads (``usp_jax.training.pairs``).

Issue 53: one photo under a homography never shows what two real exposures do: surfaces at
several depths moving against each other, occlusion, slanted walls and floors seen at grazing
angles. ``evaluation.scenes`` ray-casts rooms whose walls, floor and free-standing panels carry
photos; each pair here is two cameras 0.2-1.5 m apart, turned up to 40 degrees, seeing at least
30% of each other's view. Rooms are textured with training photos only (``scenes.load_photos``
also drops every photo of a real evaluation pair by name).

From the repository root (1,600 pairs at 240x320: about 5 minutes and 1.4 GB)::

    python3 experiments/render_pairs.py --photos data/corpus/train --out data/parallax-pairs

then train on them with ``experiments/parallax_pairs.py``.
"""

from __future__ import annotations

import argparse
import pathlib
import shutil

import numpy as np
from tqdm import tqdm

from usp_jax.evaluation import pose, scenes


def render_room(photos, seed: int, count: int, height: int, width: int):
    """``count`` (PosePair, (depth1, depth2)) of one room."""
    room = scenes.room(photos, seed=seed)
    views = scenes.view_pairs(
        room, count, height, width, seed=seed, baseline=(0.2, 1.5), max_angle=40.0
    )
    for i, (first, second) in enumerate(views):
        image1, depth1 = scenes.render(room, first)
        image2, depth2 = scenes.render(room, second)
        R, t = scenes.relative_pose(first, second)
        name = f"room{seed:05d}-{i}"
        yield pose.PosePair(name, image1, image2, first.K, second.K, R, t), (depth1, depth2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", required=True, help="folder of training photos")
    parser.add_argument("--out", required=True, help="new folder for the pairs")
    parser.add_argument("--rooms", type=int, default=200)
    parser.add_argument("--per-room", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0, help="rooms are seeds seed*10^4 + r")
    parser.add_argument("--size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    if out.exists():
        parser.error(f"{out} exists: pairs are written into a new folder")
    photos = scenes.load_photos(args.photos)
    partial = out.with_name(out.name + ".rendering")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    for r in tqdm(range(args.rooms), desc="rooms", unit="room"):
        try:
            rendered = list(render_room(photos, args.seed * 10_000 + r, args.per_room, *args.size))
        except ValueError as error:  # a room too cluttered for the pairs asked
            print(f"room {r} left out: {error}")
            continue
        folder = partial / f"room{r:05d}"
        pose.write_pairs(folder, [pair for pair, _ in rendered])
        for pair, depths in rendered:
            for index, depth in enumerate(depths, 1):
                np.save(folder / pair.name / f"depth{index}.npy", depth.astype(np.float32))
        # One level: pairs:OUT reads OUT/NAME/pose.json.
        for pair, _ in rendered:
            (folder / pair.name).rename(partial / pair.name)
        folder.rmdir()
    partial.rename(out)
    print(f"{len(list(out.glob('*/pose.json')))} pairs in {out}")


if __name__ == "__main__":
    main()
