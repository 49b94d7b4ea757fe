"""The fourth stage of the shipped weights, at the paper's own crop size: stage 3's weights
(``cpu_photos_stage3.py``) fine-tuned on 240x320 crops cut from 50-100% of a photo's extent.

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
        --init runs/stage3.npz --data data/corpus/train \
        --workdir runs/corpus-cpu-stage6
    usp-jax export --checkpoint runs/corpus-cpu-stage6 --save-weights runs/stage6.npz

2,400 steps, 92 min on 2 CPU cores (0.43 steps/s). Against stage 3 on the 160 held-out pairs
(paired bootstrap, RESULTS.md): repeatability +0.8% and localisation error -1.8% (both beyond
the pairs' noise; LE -2.0% at 480x640), HA and MS within noise; graf1 -> graf3 corner error
2.76 px (stage 3 2.66; one RANSAC pair, within its noise). Shipped until stage 7
(``cpu_photos_stage7.py``) continued it.
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
