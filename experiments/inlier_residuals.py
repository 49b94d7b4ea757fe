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
``--upsample 2`` runs the model on 2x enlarged images (``Detector(upsample=2)``).
"""

from __future__ import annotations

import argparse
import collections

import cv2
import numpy as np

from usp_jax import baselines, evaluation
from usp_jax.inference import Detector, as_method


def inlier_residuals(
    keypoints1: np.ndarray,
    keypoints2: np.ndarray,
    matching: evaluation.Matching,
    homography: np.ndarray,
    shape1: tuple[int, int],
) -> dict[str, float]:
    """``{"inliers", "rms", "over_2px", "coverage"}`` of one pair's RANSAC inliers: their count,
    the RMS and share above 2 px of ``|H p1 - p2|`` under the TRUE homography ``H`` (image 1 ->
    2), and the area of their convex hull in image 1 over its area ``shape1`` (height, width).

    keypoints1 [N1, 2], keypoints2 [N2, 2] (x, y); ``matching`` as ``match_and_estimate``
    returns it for them. No inliers gives NaN for rms and over_2px, and coverage 0."""
    pairs = matching.matches[matching.inliers]
    inliers1 = keypoints1[pairs[:, 0]]
    errors = np.linalg.norm(
        evaluation.project_points(inliers1, homography) - keypoints2[pairs[:, 1]], axis=1
    )
    if not len(errors):
        return {"inliers": 0.0, "rms": np.nan, "over_2px": np.nan, "coverage": 0.0}
    hull = cv2.convexHull(np.asarray(inliers1, np.float32))
    return {
        "inliers": float(len(errors)),
        "rms": float(np.sqrt(np.mean(errors**2))),
        "over_2px": float(np.mean(errors > 2)),
        "coverage": float(cv2.contourArea(hull)) / (shape1[0] * shape1[1]),
    }


def by_view(
    methods: list[evaluation.Method], root: str, height: int, width: int, top_k: int, nms: float
) -> dict[str, dict[int, dict[str, float]]]:
    """``{method: {k: mean inliers, rms, over_2px and coverage, median corner_error}}`` over the
    "v" pairs."""
    rows: dict[tuple[str, int], list[dict]] = collections.defaultdict(list)
    for files in evaluation.scan_sequences(root):
        if files.split != "v":
            continue
        pair = evaluation.read_pair(files)
        image1, image2, homography = evaluation.resize_pair(
            pair.image1, pair.image2, pair.homography, height, width
        )
        for method in methods:
            features1, features2 = (evaluation.detect(method, im, nms) for im in (image1, image2))
            kept1, kept2, matching = evaluation.homography_matching(
                features1, features2, homography, image1.shape[:2], image2.shape[:2], top_k,
                method.norm,
            )
            row = inlier_residuals(
                kept1.keypoints, kept2.keypoints, matching, homography, image1.shape[:2]
            )
            row["corner_error"] = evaluation.corner_error(
                homography, matching.homography, image1.shape[:2]
            )
            rows[(method.name, pair.index)].append(row)
    table: dict[str, dict[int, dict[str, float]]] = {method.name: {} for method in methods}
    for (name, k), group in sorted(rows.items()):
        table[name][k] = {
            **{key: float(np.nanmean([r[key] for r in group]))
               for key in ("inliers", "rms", "over_2px", "coverage")},
            "corner_error": float(np.median([r["corner_error"] for r in group])),
        }
    return table


def markdown(table: dict[str, dict[int, dict[str, float]]]) -> str:
    methods = list(table)
    lines = [
        "| view k | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for k in sorted(next(iter(table.values()))):
        cells = [
            f"{s['inliers']:.0f} / {s['rms']:.2f} / {100 * s['over_2px']:.1f}% / "
            f"{100 * s['coverage']:.0f}% / {s['corner_error']:.2f}"
            for s in (table[m][k] for m in methods)
        ]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True, help="HPatches-layout folder")
    parser.add_argument("--checkpoint",
                        help="training workdir or .npz weights file (default: shipped weights)")
    parser.add_argument("--res", default="240x320", help="HxW")
    parser.add_argument("--top", type=int, default=300)
    parser.add_argument("--nms", type=float, default=4.0)
    parser.add_argument("--baselines", default="brisk,sift")
    parser.add_argument("--upsample", type=int, default=1,
                        help="run the model on images enlarged this many times")
    args = parser.parse_args()
    height, width = (int(v) for v in args.res.split("x"))
    try:
        detector = Detector.load(args.checkpoint, upsample=args.upsample)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    # Headroom before the shared-view filter, as `usp-jax evaluate` gives the baselines.
    methods = [as_method(detector)] + [
        baselines.opencv_method(name, 4 * args.top)
        for name in filter(None, (n.strip() for n in args.baselines.split(",")))
    ]
    try:
        table = by_view(methods, args.pairs, height, width, args.top, args.nms)
    except (FileNotFoundError, NotADirectoryError, ValueError) as error:
        parser.error(str(error))
    enlarged = f", model on {args.upsample}x enlarged images" if args.upsample > 1 else ""
    print(f"{args.pairs} viewpoint pairs at {args.res}, top {args.top}, NMS {args.nms:g}{enlarged}; "
          "each cell: inliers / RMS error (px) / share > 2 px / hull's share of image 1 / "
          "median corner error (px)")
    print(markdown(table))


if __name__ == "__main__":
    main()
