"""Second stage of the shipped weights: ``experiments/cpu_photos.py`` continued from its 10,000-step
weights with a fresh optimiser, a new seed (other crops and homographies) and a second cosine.
Stage 3 (``cpu_photos_stage3.py``) continues from these weights.

The first stage's cosine has brought the rate to 0, while the point-pair distance d_k was still
falling (2.56 px at chance until ~2,000 steps, 1.87 px at 10,000): a warm restart at half the first
peak rate gives the network more steps without re-learning what it has. A short warm-up lets the
fresh Adam moments settle before full-size steps. The cosine is laid out over 14,000 steps but
the run stops at 12,500, where the rate is down to 1.4e-5 (3% of its peak), so that the evaluation
fitted the machine time (1.74 steps/s on average, 2 h). From the repository root::

    usp-jax export --checkpoint runs/corpus-cpu --save-weights runs/stage1.npz
    usp-jax train --config experiments/cpu_photos_stage2.py --init runs/stage1.npz \
        --data data/corpus/train --workdir runs/corpus-cpu-stage2
    usp-jax export --checkpoint runs/corpus-cpu-stage2 --save-weights usp_jax/weights/paper.npz
"""

import pathlib

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    stage1 = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos.py")))
    return config_lib.override(
        stage1,
        [
            "seed=1",
            "optim.learning_rate=5e-4",
            "optim.warmup_steps=200",
            "num_steps=12500",
            "optim.decay_steps=13800",
        ],
    )
