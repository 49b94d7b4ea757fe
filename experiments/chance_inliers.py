"""How many RANSAC inliers does a homography get by chance? ``usp-jax match`` reports a homography
only from ``inference.matching.MIN_INLIERS`` inliers on; this measures true pairs against pairs of
different scenes and against a black image, with what ``match`` runs (shipped weights, NMS 4,
top 1000, ``--max-side`` 1280, mutual nearest neighbours, RANSAC at 3 px):

    python3 experiments/chance_inliers.py --pairs data/design-pairs --sample 30

For ``--sample`` random pairs (1, k) it prints the inlier counts of the true pair, of image 1
against image k of the next sampled pair (a different source photo), and of image 1 against a
black image, sorted, then each pair's counts.
"""

from __future__ import annotations

import argparse
import random

import numpy as np

from usp_jax.evaluation import sequences
from usp_jax.inference import matching
from usp_jax.inference.detector import MAX_SIDE, Detector


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True, help="HPatches-layout folder")
    parser.add_argument("--sample", type=int, default=30, help="pairs drawn (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="draw of the pairs (default 0)")
    args = parser.parse_args()
    files = sequences.scan_sequences(args.pairs)
    sample = random.Random(args.seed).sample(files, min(args.sample, len(files)))
    detector = Detector.pretrained(nms_radius=4.0, max_side=MAX_SIDE)
    cache = {}

    def features(path):
        if path not in cache:
            cache[path] = detector.detect(sequences.read_image(path), 1000)
        return cache[path]

    def inliers(first, second) -> tuple[int, int]:
        found = matching.match_and_estimate(first, second)
        return int(found.inliers.sum()), len(found.matches)

    black = detector.detect(np.zeros((480, 640, 3), np.uint8), 1000)
    true, other, blank = [], [], []
    for i, pair in enumerate(sample):
        true.append((pair.scene, pair.index, *inliers(features(pair.path1), features(pair.path2))))
        following = sample[(i + 1) % len(sample)]
        if following.scene[2:] != pair.scene[2:]:  # v_X and i_X share their source photo
            other.append(
                (
                    pair.scene,
                    following.scene,
                    *inliers(features(pair.path1), features(following.path2)),
                )
            )
        if i < 5:
            blank.append((pair.scene, "black", *inliers(features(pair.path1), black)))
    for name, rows in (("true pairs", true), ("other scenes", other), ("black image", blank)):
        print(f"{name}: inliers {sorted(row[2] for row in rows)}")
    for row in true + other + blank:
        print(*row)


if __name__ == "__main__":
    main()
