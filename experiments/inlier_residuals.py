"""How precise are the matches a homography is estimated from? The RANSAC inliers of each method
on the viewpoint pairs, measured against the true homography.

    python3 experiments/inlier_residuals.py --pairs data/heldout-pairs --nms 4 --baselines brisk,sift

Each method goes through the evaluation's own HA path (``evaluation.detect`` with NMS, then
``homography_matching``: shared-view top-k, mutual nearest neighbours, RANSAC at 3 px), and
for each view k of the viewpoint scenes the script prints the mean number of inliers, the RMS of
their distances to where the true homography puts them, the share of inliers more than 2 px off,
the share of image 1 their convex hull covers, and the median corner error of the estimate.
Corner error grows with the inliers' RMS error, falls with their number, and grows as they
crowd into a small part of the image (the corners are then extrapolated), so these columns say
why one method's homographies are better than another's at the same HA tolerance.
``--upsample 2`` runs the model on 2x enlarged images (``Detector(upsample=2)``);
``--any-rotation`` matches it across any rotation (the shipped ``rotation`` weights as the guide).
Below the table, each method's mean inlier offset ``p2 - H p1`` (x, y) in image 2's pixels over
the views: a constant offset between a method's points and the truth, which cancels on upright
pairs but not on turned ones (RESULTS, "Any rotation"):

    python3 experiments/inlier_residuals.py --pairs data/heldout-rotated --nms 0 --baselines sift,akaze --any-rotation
"""

from __future__ import annotations

import argparse

import numpy as np

from usp_jax import evaluation
from usp_jax.evaluation.analysis import inlier_residuals_by_view, markdown_inlier_residuals
from usp_jax.inference import Detector


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True, help="HPatches-layout folder")
    parser.add_argument(
        "--checkpoint", help="training workdir or .npz weights file (default: shipped weights)"
    )
    parser.add_argument("--res", default="240x320", help="HxW")
    parser.add_argument("--top", type=int, default=300)
    parser.add_argument("--nms", type=float, default=4.0)
    parser.add_argument("--baselines", default="brisk,sift")
    parser.add_argument(
        "--upsample", type=int, default=1, help="run the model on images enlarged this many times"
    )
    parser.add_argument(
        "--any-rotation",
        action="store_true",
        help="match the model across any rotation (guide: the shipped rotation weights)",
    )
    args = parser.parse_args()
    height, width = (int(v) for v in args.res.split("x"))
    try:
        detector = Detector.load(args.checkpoint, upsample=args.upsample)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    guide = Detector.pretrained("rotation") if args.any_rotation else None
    # Headroom before the shared-view filter, as `usp-jax evaluate` gives the baselines.
    names = [name.strip() for name in args.baselines.split(",") if name.strip()]
    methods = evaluation.methods(detector, names, args.top, guide=guide)
    try:
        table = inlier_residuals_by_view(methods, args.pairs, height, width, args.top, args.nms)
    except (FileNotFoundError, NotADirectoryError, ValueError) as error:
        parser.error(str(error))
    enlarged = f", model on {args.upsample}x enlarged images" if args.upsample > 1 else ""
    enlarged += ", model matching across any rotation" if args.any_rotation else ""
    print(
        f"{args.pairs} viewpoint pairs at {args.res}, top {args.top}, NMS {args.nms:g}{enlarged}; "
        "each cell: inliers / RMS error (px) / share > 2 px / hull's share of image 1 / "
        "median corner error (px)"
    )
    print(markdown_inlier_residuals(table))
    for name, views in table.items():
        offset = [
            np.nanmean([view[key] for view in views.values()]) for key in ("offset_x", "offset_y")
        ]
        print(
            f"{name}: mean inlier offset p2 - H p1 (x, y) = ({offset[0]:+.3f}, {offset[1]:+.3f}) px"
        )


if __name__ == "__main__":
    main()
