"""What matching across any rotation costs: one pair matched, side by side in one run.

On the same photo pair (a held-out-sized photo and its copy turned by 120 degrees, at
``--size``), in alternating blocks of calls (``common.interleaved``), host round trips and
matching included:

* ``upright``: ``Detector.detect`` of both images with the default weights, then
  ``match_and_estimate``;
* ``any rotation``: ``usp_jax.inference.match_any_rotation`` with the same weights and the
  shipped ``rotation`` weights as the guide (two guide detections, one upright detection, one
  on the turned-back canvas, then ``match_and_estimate``);
* ``rotation weights``: both images with the ``rotation`` weights alone, then
  ``match_and_estimate``;
* ``upright, upsample 2`` and ``any rotation, upsample 2``: the first two with the default
  weights run on 2x enlarged images (``Detector(upsample=2)``; the guide stays as it is);
* ``unsure guide`` at both settings: what ``match_any_rotation`` costs on a pair whose guide
  homography rests on too few inliers (chessboards, printed grids): the guide's detections,
  then ``turning.search_turn`` (image 2 at 12 turns and once more at the angle they read).

From the repository root::

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 python3 benchmarks/bench_any_rotation.py
"""

from __future__ import annotations

import argparse

import common
import cv2
import skimage.data

from usp_jax.inference import Detector, match_and_estimate, match_any_rotation, turning


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="240x320", help="HxW of both images")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--block", type=int, default=3)
    args = parser.parse_args()
    height, width = (int(v) for v in args.size.split("x"))
    photo = cv2.resize(skimage.data.astronaut(), (width, height), interpolation=cv2.INTER_AREA)
    turn = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), 120, 1.0)
    turned = cv2.warpAffine(photo, turn, (width, height))
    upright, guide = Detector.pretrained(top_n=300), Detector.pretrained("rotation", top_n=300)
    enlarged = Detector.pretrained(top_n=300, upsample=2)

    def plain(detector):
        return lambda: match_and_estimate(detector.detect(photo), detector.detect(turned))

    def unsure(detector):
        def run():
            turning.estimate_turn(guide, photo, turned)
            features1 = detector.detect(photo)
            searched, _ = turning.search_turn(detector, features1, photo.shape[:2], turned)
            return match_and_estimate(features1, searched)

        return run

    runs = {
        "upright": plain(upright),
        "any rotation": lambda: match_any_rotation(upright, photo, turned, guide),
        "rotation weights": plain(guide),
        "upright, upsample 2": plain(enlarged),
        "any rotation, upsample 2": lambda: match_any_rotation(enlarged, photo, turned, guide),
        "unsure guide": unsure(upright),
        "unsure guide, upsample 2": unsure(enlarged),
    }
    times = common.interleaved(runs, args.rounds, args.block)
    print(f"one {height}x{width} pair, 300 points per image, median of {args.rounds * args.block}:")
    for name, seconds in times.items():
        print(f"  {name:<25} {common.summary(seconds)}")


if __name__ == "__main__":
    main()
