"""The paper's training run (section 5): COCO train2017, 240x320, batch 5 per branch, Adam 1e-3,
10 epochs (236,574 steps), the paper's loss weights.

Prepare COCO once in array_record form (needs TensorFlow and internet; see usp_jax.training.data), then::

    usp-jax train --config experiments/paper_coco.py --data tfds:coco/2017 --workdir runs/coco

or, with the photos unpacked in a folder, ``--data /path/to/coco/train2017``. Re-running the same
command resumes. Expected time: not yet measured on an accelerator; on 2 CPU cores a step takes
~3 s (benchmarks/README.md), i.e. about 8 days for the 236,574 steps.
"""

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    return config_lib.paper()
