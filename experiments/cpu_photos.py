"""The run behind the shipped weights: the paper's network, losses and batch on the offline photo
corpus, at 128x160 crops so a 2-core CPU gets through four times as many steps.

Build the corpus first (``experiments/build_corpus.py``), then::

    usp-jax train --config experiments/cpu_photos.py --data data/corpus/train --workdir runs/corpus-cpu

Crops are 128x160 cut from 25-50% of a photo's extent (instead of 240x320 from 50-100%), so image
content appears at the same pixel scale as in the paper's 240x320 crops. About 2 s per step on
2 CPU cores; re-running resumes from the last checkpoint (every 100 steps).
"""

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.paper(),
        [
            "data.height=128",
            "data.width=160",
            "data.scale_range=(0.25, 0.5)",
            "num_steps=50000",
            "checkpoint_every=100",
            "log_every=10",
            "keep_checkpoints=2",
        ],
    )
