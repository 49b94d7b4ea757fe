"""A fourth training stage, not shipped (RESULTS.md): stage 3 (``cpu_photos_stage3.py``)
continued from its 10,000-step weights with a fresh optimiser, a new seed and a cosine that runs
all the way to 0.

Stage 3 still moved the held-out numbers a lot (HA at eps 3 0.806 -> 0.844, median d_k 1.34 ->
1.25 px) while its training d_k was nearly flat: the network is still step-limited. The restart
peaks lower again (2e-4 after stage 3's 3e-4) because each restart first undoes a little of the
previous minimum. From the repository root::

    usp-jax train --config experiments/cpu_photos_stage4.py \
        --init runs/stage3.npz --data data/corpus/train \
        --workdir runs/corpus-cpu-stage4
    usp-jax export --checkpoint runs/corpus-cpu-stage4 --save-weights runs/stage4.npz
"""

import pathlib

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    stage1 = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos.py")))
    return config_lib.override(
        stage1,
        [
            "seed=3",
            "optim.learning_rate=2e-4",
            "optim.warmup_steps=200",
            "num_steps=4000",
            "optim.decay_steps=3800",
        ],
    )
