"""``usp-jax match IMAGE1 IMAGE2``: mutual-nearest-neighbour matches and a RANSAC homography
between two images, across any rotation with ``--any-rotation``; an estimate from too few inliers
is reported as none."""

from __future__ import annotations

import json
import sys

import numpy as np

from usp_jax.cli import arguments, outputs
from usp_jax.inference.detector import MAX_SIDE


def add_parser(subparsers) -> None:
    """The ``match`` subcommand: matches and a RANSAC homography between two images."""
    p = subparsers.add_parser("match", help="matches and a RANSAC homography between two images")
    p.add_argument("image1", help="the first photo (any format OpenCV reads)")
    p.add_argument("image2", help="the second photo; H maps image 1's pixels to image 2's")
    arguments.add_checkpoint(p)
    p.add_argument(
        "--top",
        type=arguments.positive,
        default=1000,
        help="most keypoints kept per image (default 1000: more than detect's 500, for RANSAC)",
    )
    arguments.add_nms_radius(
        p, 4.0, "NMS radius in px, default 4 (spread points condition a homography better)"
    )
    arguments.add_max_side(
        p, f"detect on copies at most this long (default {MAX_SIDE}; 0: native size)"
    )
    p.add_argument("--out", help="PNG of the inlier matches and image 1's border warped by H")
    p.add_argument("--json", help="homography, matches, inlier mask and keypoints as JSON")
    arguments.add_network_options(p)
    arguments.add_any_rotation(p, turn_back=True)


def run(args) -> int | None:
    """Detects in both images, matches, estimates the homography, writes what is asked for."""
    from usp_jax.evaluation import plotting
    from usp_jax.inference import matching as matching_lib
    from usp_jax.inference import turning
    from usp_jax.inference.images import read_image

    args.out = outputs.figure_file(args.out, "--out")
    outputs.check_output_file(args.json, "--json")
    detector = arguments.load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    guide = arguments.guide(args, max_side=args.max_side)
    turn_back = arguments.turns_back(args, default=True)
    image1, image2 = read_image(args.image1), read_image(args.image2)
    angle = None
    if turn_back:
        features1, features2, angle = turning.turn_back_pair(detector, image1, image2, args.top)
        if angle:
            print(f"image 2 turned back by {angle:.1f} degrees before detection (--turn-back)")
    elif guide is None:
        features1, features2 = (detector.detect(image, args.top) for image in (image1, image2))
    else:
        features1, features2, angle = turning.detect_pair(detector, guide, image1, image2, args.top)
        print(f"image 2 turned back by {angle:.1f} degrees before detection")
    matching = matching_lib.match_and_estimate(features1, features2)
    print(
        f"{len(features1.keypoints)} and {len(features2.keypoints)} keypoints,"
        f" {len(matching.matches)} mutual nearest-neighbour matches,"
        f" {int(matching.inliers.sum())} RANSAC inliers"
        f" ({matching_lib.RANSAC_THRESHOLD:g} px)"
    )
    # An estimate from too few inliers is a chance fit: reported as none (it stays in the JSON).
    homography = matching.homography if matching.reliable else None
    if matching.homography is None:
        print("no homography: fewer than 4 matches, or RANSAC found none")
    elif homography is None:
        inliers = f"{int(matching.inliers.sum())} RANSAC inliers, under {matching_lib.MIN_INLIERS}"
        print(f"no reliable homography: {inliers}; the images may not show one scene")
        print(f"usp-jax match: warning: no reliable homography ({inliers})", file=sys.stderr)
    else:
        print("homography image1 -> image2:")
        print(np.array2string(homography, precision=6, suppress_small=True))
    if args.out:
        plotting.plot_matches(
            image1,
            image2,
            features1.keypoints,
            features2.keypoints,
            matching.matches,
            matching.inliers,
            None,
            homography,
            args.out,
        )
        print(f"wrote {args.out}")
    if args.json:
        estimate = None if matching.homography is None else matching.homography.tolist()
        outputs.write_text(
            args.json,
            json.dumps(
                {
                    "homography": None if homography is None else homography.tolist(),
                    "reliable": matching.reliable,
                    "min_inliers": matching_lib.MIN_INLIERS,
                    "ransac_estimate": estimate,
                    "matches": matching.matches.tolist(),
                    "inliers": matching.inliers.tolist(),
                    "keypoints1": features1.keypoints.tolist(),
                    "keypoints2": features2.keypoints.tolist(),
                    "turned_back_degrees": angle,
                }
            ),
        )
        print(f"wrote {args.json}")
