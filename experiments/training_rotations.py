"""How far the training homographies of experiment configs rotate the image: the in-plane rotation
(``compare.in_plane_rotation``, at the image centre) of many draws of ``geometry.sample_homography``
with each config's ranges and crop size.

    python3 experiments/training_rotations.py experiments/paper_network.py:stage10 \
        experiments/rotation.py

A rotated patch must fit inside the image, so the accepted rotations depend on the patch ratio as
much as on the angle range (``HomographyConfig``); a config with ``data.context_window`` draws
its patch inside a window around the crop instead, where any angle fits.
"""

from __future__ import annotations

import argparse

import numpy as np

from usp_jax import config as config_lib
from usp_jax.evaluation.analysis import training_rotations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("configs", nargs="+", help="experiment config files (get_config())")
    parser.add_argument("--draws", type=int, default=4000, help="homographies per config")
    args = parser.parse_args()
    if args.draws < 1:
        parser.error("--draws must be >= 1")
    for path in args.configs:
        try:
            cfg = config_lib.load(path)
        except (OSError, ValueError, AttributeError) as error:
            parser.error(f"cannot load {path}: {error}")
        window = cfg.data.example_shape[:2] if cfg.data.context_window else None
        size = np.abs(
            training_rotations(
                cfg.homography, cfg.data.height, cfg.data.width, args.draws, window=window
            )
        )
        print(
            f"{path} ({cfg.data.height}x{cfg.data.width}, patch {cfg.homography.patch_ratio:g}, "
            f"{args.draws} draws): |rotation| median {np.median(size):.1f} deg, 90th percentile "
            f"{np.percentile(size, 90):.1f}; >= 20 deg {np.mean(size >= 20):.1%}, "
            f">= 30 deg {np.mean(size >= 30):.1%}, >= 90 deg {np.mean(size >= 90):.1%}"
        )


if __name__ == "__main__":
    main()
