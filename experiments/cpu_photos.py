"""Stage 1 of the shipped weights (continued by ``cpu_photos_stage2.py``, ``cpu_photos_stage3.py``,
``cpu_photos_stage6.py``, ``cpu_photos_stage7.py`` and ``cpu_photos_stage10.py``): the paper's
network, losses and batch on the offline photo corpus, at 128x160 crops so a 2-core CPU gets
through four times as many steps.

Build the corpus first (``experiments/build_corpus.py``), then::

    usp-jax train --config experiments/cpu_photos.py --data data/corpus/train --workdir runs/corpus-cpu

Crops are 128x160 cut from 25-50% of a photo's extent (instead of 240x320 from 50-100%), so image
content appears at the same pixel scale as in the paper's 240x320 crops. 10,000 steps (50,000
crops per branch) with the learning rate decaying from 1e-3 to 0 on a cosine; 2.09 steps/s
on average on 2 CPU cores (81 min). Re-running resumes from the last checkpoint (every 500 steps).

A 128x160 crop has M = 320 cells instead of 1,200, and the descriptor loss (eq. 13) sums over
M x M pairs, of which only ~2.4 per point are positives: with the paper's lambda_d = 250 the
positives then outweigh the negatives 2.4:1 (at 240x320 the negatives weigh ~2:1), and every
descriptor collapsed onto one vector (mean similarity of negative pairs 0.97 after 80 steps,
logged as ``desc/sim_negative``). lambda_d and alpha_desc are rescaled by the cell count
(250 / 4 ~ 250 x 320 / 1200; 0.001 x 4) so both terms keep the balance they have at the paper's
size; with it negatives fall to ~0.25 and positives stay ~0.55 over the same steps.
"""

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.paper(),
        [
            "data.height=128",
            "data.width=160",
            "data.scale_range=(0.25, 0.5)",
            "loss.lambda_d=62.5",
            "loss.alpha_desc=0.004",
            "num_steps=10000",
            "optim.decay_steps=10000",
            "checkpoint_every=500",
            "log_every=20",
            "keep_checkpoints=2",
        ],
    )
