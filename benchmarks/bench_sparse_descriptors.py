"""What computing only the kept points' descriptors saves, side by side in one run.

A top-N detector keeps N of its M candidates; while N is at most ``points.SPARSE_SHARE`` of M it
runs the descriptor head's last convolution on the N kept points alone (``model.describe``)
instead of on every cell. The same detectors, built once with that share (``sparse``) and once
with it at 0 (``dense``, the whole descriptor map as the model computes it in training), are
timed in alternating blocks of calls (``common.interleaved``) on one held-out-sized photo, host
round trips included. Their outputs are equal (``tests/test_inference.py``).

From the repository root::

    python3 benchmarks/bench_sparse_descriptors.py [--size 240x320] [--top 300]
"""

from __future__ import annotations

import argparse
import statistics

import common
import cv2
import skimage.data

from usp_jax.inference import Detector, points

DETECTORS = {
    "paper": dict(name="paper"),
    "distilled": dict(name="distilled"),
    "distilled --refine": dict(name="distilled", refine=True),
    "paper --any-scale": dict(name="paper", any_scale=True),
    "distilled --any-scale": dict(name="distilled", any_scale=True),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="240x320", help="HxW of the photo")
    parser.add_argument("--top", type=int, default=300, help="points kept")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--block", type=int, default=10)
    args = parser.parse_args()
    height, width = (int(v) for v in args.size.split("x"))
    photo = cv2.resize(skimage.data.astronaut(), (width, height), interpolation=cv2.INTER_AREA)
    runs, share = {}, points.SPARSE_SHARE
    # The share is read while a detector compiles, on its first call.
    for mode, value in (("sparse", share), ("dense", 0.0)):
        points.SPARSE_SHARE = value
        for label, options in DETECTORS.items():
            options = dict(options)
            detector = Detector.pretrained(options.pop("name"), top_n=args.top, **options)
            detector.detect(photo)
            runs[f"{label}, {mode}"] = lambda detector=detector: detector.detect(photo)
    points.SPARSE_SHARE = share
    times = common.interleaved(runs, args.rounds, args.block)
    print(f"{height}x{width}, top {args.top}, median of {args.rounds * args.block} calls:")
    for label in DETECTORS:
        sparse, dense = times[f"{label}, sparse"], times[f"{label}, dense"]
        change = statistics.median(sparse) / statistics.median(dense) - 1
        print(f"  {label + ', dense':<30} {common.summary(dense)}")
        print(f"  {label + ', sparse':<30} {common.summary(sparse)}   {100 * change:+.1f}%")


if __name__ == "__main__":
    main()
