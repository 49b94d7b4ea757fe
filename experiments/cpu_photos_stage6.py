"""A sixth training stage at the paper's own crop size: the shipped weights (stage 3,
``cpu_photos_stage3.py``) fine-tuned on 240x320 crops cut from 50-100% of a photo's extent.

Stages 1-5 trained on 128x160 crops from 25-50% of the extent: the same pixel scale as the
paper's crops, at a quarter of the cost per step. The evaluation, though, runs on whole 240x320
and 480x640 images. A 128x160 crop is 16x20 cells, a fifth of them in the outer ring, where
the network sees zero padding on one side; at 240x320 (30x40 cells) it is a ninth, and each step
has 3.75x more cells to pair. This stage checks whether the last stretch of training at the
paper's size moves the held-out numbers. Everything else is the paper's setting (``paper()``:
batch 5 per branch, lambda_d = 250 and alpha_desc = 0.001, the values the 128x160 stages
rescaled), with a fresh Adam, a new seed, 100 warm-up steps to 2e-4 and a cosine to 0.
From the repository root::

    usp-jax train --config experiments/cpu_photos_stage6.py \
        --init usp_jax/weights/unsuperpoint.npz --data data/corpus/train \
        --workdir runs/corpus-cpu-stage6
    usp-jax evaluate --checkpoint runs/corpus-cpu-stage6 --hpatches data/heldout-pairs --baselines ""
"""

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.paper(),
        [
            "seed=6",
            "optim.learning_rate=2e-4",
            "optim.warmup_steps=100",
            "num_steps=2400",
            "optim.decay_steps=2300",
            "checkpoint_every=250",
            "log_every=20",
            "keep_checkpoints=2",
        ],
    )
