"""The fast network (``usp_jax.fast_config``): its recipe, both stages in one place.

Build the corpus first (``experiments/build_corpus.py``), then from the repository root::

    usp-jax train --config experiments/fast.py --data data/corpus/train --workdir runs/fast
    usp-jax export --checkpoint runs/fast --save-weights runs/fast-stage1.npz
    usp-jax train --config experiments/fast.py:finetune --init runs/fast-stage1.npz \\
        --data data/corpus/train --workdir runs/fast-finetune
    usp-jax export --checkpoint runs/fast-finetune --save-weights usp_jax/weights/fast.npz

Re-running a train command resumes it. Both stages keep the paper's losses, batch (5 per
branch) and homographies, and the stronger lighting changes of the paper network's last stage
(random gamma, brightness and contrast up to 50%), from the first step.

Stage 1 (``get_config``), from scratch: 128x160 crops cut from 25-50% of a photo's extent, the
same pixel scale as the paper's 240x320 crops at a quarter of the cost per step, with the
descriptor weights rescaled to the cell count as in ``paper_network.py`` (at M = 320 cells the
paper's lambda_d = 250 lets positives outweigh negatives and the descriptors collapse). Adam at
1e-3 after 300 warm-up steps, decaying to 0 on a cosine.

Stage 2 (``finetune``): stage 1's weights at the paper's own 240x320, lambda_d and alpha_desc,
as the paper network's stage 6 did; a fresh Adam, 100 warm-up steps to 3e-4 and a cosine to 0.
"""

from usp_jax import config as config_lib
from usp_jax import fast_config

_COMMON = [
    "photometric.gamma=0.5",
    "photometric.brightness=0.5",
    "photometric.contrast=0.5",
    "checkpoint_every=500",
    "log_every=20",
    "keep_checkpoints=2",
]


def _fast(overrides: list[str]) -> config_lib.Config:
    base = config_lib.override(config_lib.paper(), _COMMON + overrides)
    return config_lib.dataclasses.replace(base, model=fast_config())


def get_config() -> config_lib.Config:
    return _fast(
        [
            "seed=23",
            "data.height=128",
            "data.width=160",
            "data.scale_range=(0.25, 0.5)",
            "loss.lambda_d=62.5",
            "loss.alpha_desc=0.004",
            "num_steps=18000",
            "optim.warmup_steps=300",
            "optim.decay_steps=17700",
        ]
    )


def finetune() -> config_lib.Config:
    return _fast(
        [
            "seed=24",
            "optim.learning_rate=3e-4",
            "optim.warmup_steps=100",
            "num_steps=1500",
            "optim.decay_steps=1400",
        ]
    )
