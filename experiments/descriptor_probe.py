"""Two probes of whether descriptors describe content or position, without a homography.

1. Spread: the mean cosine similarity between the descriptors of different cells of one image,
   at 128x160 (the training crops), 240x320 and 480x640. Descriptors that tell cells apart by
   their distance to the border (zero padding seen through the receptive field) spread on small
   images and collapse towards one vector on large ones, where most cells see no border.
2. Translation: two 240x320 crops of one image, the second shifted by 8, 16 or 32 px on both
   axes; the share of interior cells whose nearest neighbour (by descriptor) in the other crop
   is the cell showing the same content. For shifts in whole cells a translation-equivariant
   network moves its outputs by whole cells, so this isolates the descriptors.

Images: the first views of the held-out viewpoint scenes. From the repository root::

    python3 experiments/descriptor_probe.py --hpatches data/heldout-pairs \\
        --weights usp_jax/weights/paper.npz runs/fast-stage1.npz
"""

import argparse
import pathlib

import cv2
import jax.numpy as jnp
import numpy as np

from usp_jax.core.model import CELL, UnsuperPoint
from usp_jax.inference import load_weights

SIZES = ((128, 160), (240, 320), (480, 640))
SHIFTS = (8, 16, 32)


def first_views(folder: pathlib.Path, count: int) -> list[np.ndarray]:
    """RGB uint8 [H, W, 3] first images of the first ``count`` viewpoint (v_*) scenes."""
    paths = sorted(folder.glob("v_*/1.ppm"))[:count]
    if not paths:
        raise SystemExit(f"{folder} has no v_*/1.ppm")
    return [cv2.imread(str(path))[..., ::-1] for path in paths]


def descriptors(model: UnsuperPoint, variables, images: list[np.ndarray]) -> np.ndarray:
    """[N, H/8, W/8, F] descriptors sampled at each cell's point, for uint8 [H, W, 3] images."""
    batch = jnp.asarray(np.stack(images), jnp.float32) / 255.0
    pred = model.apply(variables, batch)
    n, height, width, _ = batch.shape
    return np.asarray(pred.descriptors).reshape(n, height // CELL, width // CELL, -1)


def mean_cosine(maps: np.ndarray) -> float:
    """Mean cosine between different cells of each map [N, h, w, F] (unit descriptors)."""
    flat = maps.reshape(len(maps), -1, maps.shape[-1])
    cosine = flat @ flat.transpose(0, 2, 1)
    cells = cosine.shape[-1]
    return float((cosine.sum(axis=(1, 2)) - cells).mean() / (cells * (cells - 1)))


def translation_accuracy(model, variables, images, shift: int, margin: int = 2) -> float:
    """Share of interior cells of crop A whose nearest descriptor in crop B (shifted by ``shift``
    px, a multiple of 8) is the same content; ``margin`` cells at the border are left out."""
    cells = shift // CELL
    hits = []
    for image in images:
        image = cv2.resize(image, (384, 288), interpolation=cv2.INTER_AREA)
        a, b = descriptors(
            model, variables, [image[:240, :320], image[shift : 240 + shift, shift : 320 + shift]]
        )
        a = a[margin + cells : -margin, margin + cells : -margin].reshape(-1, a.shape[-1])
        b = b[margin : -margin - cells, margin : -margin - cells].reshape(-1, b.shape[-1])
        hits.append(np.mean(np.argmax(a @ b.T, axis=1) == np.arange(len(a))))
    return float(np.mean(hits))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hpatches", type=pathlib.Path, required=True)
    parser.add_argument("--weights", type=pathlib.Path, nargs="+", required=True)
    parser.add_argument("--images", type=int, default=6)
    args = parser.parse_args()
    images = first_views(args.hpatches, args.images)
    header = [f"cosine {h}x{w}" for h, w in SIZES] + [f"NN {s}px" for s in SHIFTS]
    print(f"{'weights':32s} " + " ".join(f"{h:>15s}" for h in header))
    for path in args.weights:
        config, variables = load_weights(path)
        model = UnsuperPoint(config)
        spread = [
            mean_cosine(
                descriptors(
                    model,
                    variables,
                    [cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA) for image in images],
                )
            )
            for h, w in SIZES
        ]
        moved = [translation_accuracy(model, variables, images, shift) for shift in SHIFTS]
        print(f"{str(path):32s} " + " ".join(f"{v:15.3f}" for v in spread + moved))


if __name__ == "__main__":
    main()
