"""Design probes of the any-scale pyramid (issue 41) that ship no option: any ``usp-jax``
command run with the levels' floor or the levels' score weights changed for that run.

    python3 experiments/pyramid_design.py --min-side 96 -- evaluate --hpatches PAIRS --any-scale ...
    python3 experiments/pyramid_design.py --level-weight 1.15 -- evaluate --hpatches PAIRS --any-scale ...

``--min-side``: levels while the shorter side stays at least this many px (the shipped
``pyramid.MIN_SIDE`` is 64; 96 drops 240x320's smallest level). ``--level-weight w``: the scores
of level l (0 = the input's size) multiplied by w ** l before the candidates of all levels are
ranked, so w > 1 keeps more coarse points, w < 1 fewer (the shipped pyramid ranks the network's
scores as they are, w = 1). Results: RESULTS.md, "Any scale: one candidate cut for all levels".
"""

from __future__ import annotations

import argparse
import functools
import sys

from usp_jax.cli import main as cli_main
from usp_jax.inference import detector, pyramid


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--min-side", type=int, default=pyramid.MIN_SIDE)
    parser.add_argument("--level-weight", type=float, default=1.0)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then a usp-jax command")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give a usp-jax command after --")
    pyramid.level_scales = functools.partial(pyramid.level_scales, min_side=args.min_side)
    if args.level_weight != 1.0:
        # While the pyramid is traced, each level is resized (level 0 too, to its own size)
        # right before the network runs on it: the resizes count the levels.
        level = {"index": -1}
        resize, network = pyramid.resize_level, detector._network

        def counted_resize(images, shape):
            level["index"] = 0 if tuple(images.shape[1:3]) == tuple(shape) else level["index"] + 1
            return resize(images, shape)

        def weighted(variables, images, **options):
            pixels, predictions = network(variables, images, **options)
            scale = args.level_weight ** level["index"]
            return pixels, predictions._replace(scores=predictions.scores * scale)

        pyramid.resize_level, detector._network = counted_resize, weighted
    return cli_main(command)


if __name__ == "__main__":
    sys.exit(main())
