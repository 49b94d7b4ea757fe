"""``usp-jax detect IMAGE``: the keypoints of one image, drawn and as JSON."""

from __future__ import annotations

import json

from usp_jax.cli import arguments, outputs
from usp_jax.inference.detector import MAX_SIDE


def add_parser(subparsers) -> None:
    """The ``detect`` subcommand: the keypoints of one image."""
    p = subparsers.add_parser("detect", help="keypoints of one image")
    p.add_argument("image", help="a photo in any format OpenCV reads")
    arguments.add_checkpoint(p)
    p.add_argument(
        "--top",
        type=arguments.positive,
        default=500,
        help="most keypoints kept, best first (default 500)",
    )
    # Spread points condition a homography or pose better: radius 4 cut the corner error of
    # the held-out viewpoint pairs by a third (experiments/RESULTS.md).
    arguments.add_nms_radius(
        p, 0.0, "NMS radius in px, default 0 (try 4 for homography or pose estimation)"
    )
    arguments.add_max_side(
        p,
        f"detect on a copy at most this long (default {MAX_SIDE}; 0: native size);"
        " keypoints are in the original's pixels",
    )
    p.add_argument("--out", help="PNG with the keypoints drawn")
    p.add_argument("--json", help="keypoints, scores and descriptors as JSON")
    arguments.add_network_options(p)


def run(args) -> int | None:
    """Detects, prints the count, and writes the figure and JSON asked for."""
    from usp_jax.evaluation import plotting
    from usp_jax.inference.images import read_image

    args.out = outputs.figure_file(args.out, "--out")
    outputs.check_output_file(args.json, "--json")
    detector = arguments.load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    features = detector.detect(image := read_image(args.image), top_n=args.top)
    print(f"{args.image}: {len(features.keypoints)} keypoints")
    if args.out:
        plotting.plot_detections(image, features.keypoints, args.out)
        print(f"wrote {args.out}")
    if args.json:
        outputs.write_text(
            args.json,
            json.dumps(
                {
                    "keypoints": features.keypoints.tolist(),
                    "scores": features.scores.tolist(),
                    "descriptors": features.descriptors.tolist(),
                    "sizes": None if features.scales is None else features.scales.tolist(),
                }
            ),
        )
        print(f"wrote {args.json}")
