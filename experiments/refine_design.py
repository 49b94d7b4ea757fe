"""Sub-pixel refinement candidates side by side on one set of pairs (choose on the training-photo
design pairs, report on the held-out ones):

    python3 experiments/refine_design.py --pairs data/design-pairs --every 4 --learned usp_jax/weights/refine.npz

(``--weights NAME``: another shipped network's points, raw and refined.)

- ``raw``: the shipped detector's cells (``Detector(refine=False)``);
- ``learned:FILE``: the offset network of ``inference.refine`` with those weights;
- ``harris``: each point moved to the strongest Harris response within half a cell (the same
  9x9 window the offset network may reach), then to the vertex of a parabola through that
  maximum and its neighbours, per axis (the sub-pixel fit SIFT and ORB use on their responses).

Every method runs the evaluation's own path (``evaluation.protocol.evaluate``, 240x320, top 300,
NMS 0); ``--every N`` keeps every N-th scene of the folder (through a temporary folder of links).
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile

import cv2
import numpy as np
from scipy import ndimage

from usp_jax.evaluation import protocol
from usp_jax.inference import Detector
from usp_jax.inference.refine import REACH


def harris_refined(image: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """Keypoints [N, 2] moved to the sub-pixel maximum of the Harris response within REACH px."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    response = cv2.cornerHarris(grey, blockSize=3, ksize=3, k=0.04)
    steps = np.arange(-REACH, REACH + 1, dtype=np.float32)
    xs = keypoints[:, None, None, 0] + steps[None, None, :]
    ys = keypoints[:, None, None, 1] + steps[None, :, None]
    xs, ys = np.broadcast_arrays(xs, ys)
    window = ndimage.map_coordinates(response, [ys, xs], order=1, mode="nearest")
    flat = window.reshape(len(keypoints), -1).argmax(axis=1)
    row, col = np.divmod(flat, window.shape[-1])
    # Parabola through the maximum and its two neighbours per axis; none at the window's edge.
    inner_r = np.clip(row, 1, window.shape[1] - 2)
    inner_c = np.clip(col, 1, window.shape[2] - 2)
    n = np.arange(len(keypoints))
    centre = window[n, inner_r, inner_c]

    def vertex(minus, plus):
        curvature = minus - 2 * centre + plus
        return np.where(
            curvature < 0, 0.5 * (minus - plus) / np.where(curvature < 0, curvature, -1), 0
        )

    dx = np.where(
        col == inner_c, vertex(window[n, inner_r, inner_c - 1], window[n, inner_r, inner_c + 1]), 0
    )
    dy = np.where(
        row == inner_r, vertex(window[n, inner_r - 1, inner_c], window[n, inner_r + 1, inner_c]), 0
    )
    moves = np.stack(
        [col - REACH + np.clip(dx, -0.5, 0.5), row - REACH + np.clip(dy, -0.5, 0.5)], axis=1
    )
    return keypoints + moves.astype(np.float32)


def subset(root: pathlib.Path, every: int) -> pathlib.Path:
    """A temporary folder linking every ``every``-th scene of ``root``."""
    if every == 1:
        return root
    folder = pathlib.Path(tempfile.mkdtemp(prefix="refine-design-"))
    for scene in sorted(p for p in root.iterdir() if p.is_dir())[::every]:
        (folder / scene.name).symlink_to(scene.resolve())
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True, help="HPatches-layout folder")
    parser.add_argument("--every", type=int, default=1, help="keep every N-th scene")
    parser.add_argument("--weights", help="the detector's shipped weights (default: the package's)")
    parser.add_argument("--learned", nargs="*", default=[], help="OffsetNet .npz files")
    parser.add_argument("--harris", action="store_true", help="add the Harris candidate")
    parser.add_argument("--ransac-orders", type=int, default=1)
    parser.add_argument("--json", help="write the evaluation here")
    args = parser.parse_args()

    raw = Detector.pretrained(args.weights, refine=False)
    methods = [protocol.Method("raw", raw.detect)]
    if args.harris:

        def harris(image):
            features = raw.detect(image)
            return features._replace(keypoints=harris_refined(image, features.keypoints))

        methods.append(protocol.Method("harris", harris))
    for path in args.learned:
        methods.append(
            protocol.Method(
                f"learned:{pathlib.Path(path).stem}",
                Detector.pretrained(args.weights, refine=path).detect,
            )
        )
    results = protocol.evaluate(
        methods, subset(pathlib.Path(args.pairs), args.every), ransac_orders=args.ransac_orders
    )
    print(protocol.format_table(results))
    if args.json:
        import json

        pathlib.Path(args.json).write_text(json.dumps(protocol.to_json(results)))


if __name__ == "__main__":
    main()
