"""Third stage of the shipped weights: stage 2 (``cpu_photos_stage2.py``) continued from its
12,500-step weights with a fresh optimiser, a new seed and a cosine that runs all the way to 0.

At the end of stage 2 the training d_k was still falling (1.64 px) and the held-out HA at
eps 3 was still rising (0.769 at stage-2 step 8,000, 0.806 at 12,500): the network is
step-limited, not capacity-limited. The restart peaks lower than stage 2's (3e-4 instead of
5e-4) because the weights are closer to a minimum and a high rate first undoes some of it
(stage 2's d_k rose from 1.87 to 1.92 px during its warm restart). 10,000 steps, 102 min on 2
CPU cores (1.63 steps/s). From the repository root::

    usp-jax export --checkpoint runs/corpus-cpu-stage2 --save-weights runs/stage2.npz
    usp-jax train --config experiments/cpu_photos_stage3.py --init runs/stage2.npz \
        --data data/corpus/train --workdir runs/corpus-cpu-stage3
    usp-jax export --checkpoint runs/corpus-cpu-stage3 --save-weights usp_jax/weights/paper.npz
"""

import pathlib

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    stage1 = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos.py")))
    return config_lib.override(
        stage1,
        [
            "seed=2",
            "optim.learning_rate=3e-4",
            "optim.warmup_steps=200",
            "num_steps=10000",
            "optim.decay_steps=9800",
        ],
    )
