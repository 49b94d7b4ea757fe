"""Stage 7 continued once more (``cpu_photos_stage7.py``): its weights, a fresh Adam, a new seed,
the same 100 warm-up steps to 1e-4 and a cosine to 0. Stage 7's training statistics were flat
(d_k 1.51 px over its first and last 500 steps) while the held-out numbers still moved, all the
same way; this stage asks whether another annealed cycle keeps paying. From the repository root::

    usp-jax train --config experiments/cpu_photos_stage8.py \
        --init runs/stage7.npz --data data/corpus/train \
        --workdir runs/corpus-cpu-stage8
    usp-jax export --checkpoint runs/corpus-cpu-stage8 --save-weights runs/stage8.npz

(``runs/stage7.npz`` is stage 7's float16 export, ``cpu_photos_stage7.py``, then the shipped
weights.) 1,800 steps, 63 min on 2 CPU cores (0.50 steps/s). Training
d_k 1.53 -> 1.56 px and K 622 -> 636 pairs per image (means over the first 500 and last 500
steps): flat. On the 160 held-out pairs at 240x320 / 300 (its float32 checkpoint against the
shipped float16 stage 7): RS 0.826 (+0.0%), LE 0.698 px (+0.5% [0.1, 1.0]), MS 0.648 (+0.5%
[0.2, 0.9]), HA 0.594 / 0.856 / 0.919 (-1.0 / -0.7 / -1.3%, all within the pairs' noise). Too
small a gain where the model already leads and none where it trails (HA): not shipped.
"""

import pathlib

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    # Stage 7's setting (itself stage 6's with a lower peak), with only what this stage changes.
    stage7 = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos_stage7.py")))
    return config_lib.override(stage7, ["seed=8", "num_steps=1800", "optim.decay_steps=1700"])
