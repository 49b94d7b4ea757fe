"""Issue 41's fine-tune: the shipped paper network trained on a wider scale range, for
``--any-scale``. An experiment, not shipped weights: RESULTS.md ("Matching across zoom") says
what it did to the zoomed and the upright pairs.

The pyramid (``usp_jax.inference.pyramid``) shrinks each image by 1/sqrt(2) a level, so a pair's
zoom is matched to within a factor of 2 ** 0.25 = 1.19 by the nearest pair of levels, and the
shipped weights' last stage magnified B by 1.15x-1.45x against A (5th-95th percentile at the
crop's centre, median 1.29: a 0.85 patch scaled by U(0.8, 1.2) that must fit inside the crop).
The fine-tune asks whether descriptors taught a wider range match better across the pyramid's
levels: the patch scaled by U(0.6, 1.4), B magnified 1.01x-1.95x (median 1.32). A scaled-up
patch leaves the crop, so B is rendered from a context window around it
(``data.context_window``, as ``rotation.py`` does for angles); the angles stay the upright
stages' U(-45, 45) degrees.

From the repository root, after ``experiments/build_corpus.py``::

    usp-jax train --config experiments/zoom.py --init usp_jax/weights/paper.npz \\
        --data data/corpus/train --workdir runs/zoom
    usp-jax export --checkpoint runs/zoom --save-weights runs/zoom.npz

Re-running the train command resumes it. Everything else is the shipped weights' last stage
(``paper_network.py:stage10``: 240x320 crops, its lighting changes, a warm-up to 1e-4 and a
cosine to 0) over 1,200 steps.
"""

import pathlib

from usp_jax import config as config_lib

_PAPER = str(pathlib.Path(__file__).with_name("paper_network.py"))


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.load(f"{_PAPER}:stage10"),
        [
            "seed=41",
            "num_steps=1200",
            "optim.decay_steps=1100",
            "data.context_window=True",
            "homography.scaling=0.4",
            "checkpoint_every=100",
        ],
    )
