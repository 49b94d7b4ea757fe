"""Issue 53's fourth fine-tune: the dual-softmax matching loss (``losses.dual_softmax_loss``,
LoFTR's and XFeat's) beside the paper's hinge, on the parallax pairs, from the ``parallax``
weights.

Why: on the real pairs the failure sits in the descriptor (graf: 39% of repeatable points have
the right nearest neighbour), and the hardest-negative term of ``real_pairs_hard.py`` sat at its
margin: for the typical point some wrong point is as similar as its partner. Eq. 13 pushes each
negative below 0.2 on its own; the dual softmax weighs the partner against every competitor of
its row and its column, which is what a mutual nearest neighbour needs. Its weight puts the
term near the hinge's (about 200 of a total near 1,600 at the parallax run's end).

What changes against ``parallax_pairs.py``: ``losses.alpha_match`` 40 at temperature 0.1, a new
seed, 1,000 steps (as many as the CPU time at hand allows on 2 cores).

From the repository root, after ``experiments/render_pairs.py`` (see ``parallax_pairs.py``)::

    usp-jax train --config experiments/matching_loss.py --init usp_jax/weights/parallax.npz \\
        --data pairs:data/parallax-pairs --workdir runs/matching
    usp-jax export --checkpoint runs/matching --save-weights runs/matching.npz

Re-running the train command resumes it.
"""

import pathlib

from usp_jax import config as config_lib

_PARALLAX = str(pathlib.Path(__file__).with_name("parallax_pairs.py"))


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.load(_PARALLAX),
        [
            "seed=534",
            "num_steps=1000",
            "optim.decay_steps=950",
            "loss.alpha_match=40.0",
            "checkpoint_every=100",
        ],
    )
