"""A fifth training stage, not shipped: stage 3's weights (``cpu_photos_stage3.py``, shipped at the
time) fine-tuned on stronger viewpoint changes, KP2D's homography ranges instead of SuperPoint's.

The held-out numbers put the weak spot at viewpoint: at 240x320 HA at eps 3 is 0.963 on
the illumination pairs and 0.725 on the viewpoint ones, with a localisation error twice as large
(0.96 vs 0.48 px). Stages 1-3 trained with patch_ratio 0.85 and a keystone of up to 0.2, and a
0.85 patch of a 4:3 image leaves so little room that most strong keystones are rejected: the mean
perspective entry |H[2, :2]| of the accepted training homographies is 0.0024 at 128x160. Real
viewpoint pairs (HPatches' "v" scenes, SfM and SLAM frames) have far more. A 0.75 patch with a
keystone of up to 0.3 (KP2D trains with 0.7 and 0.4 as a truncated normal) accepts 5x stronger
perspective (0.0127); rotation and scale ranges stay. Stage 4 showed that more of the same training
at a lower rate no longer moves the held-out numbers, so this stage changes the data, not the
schedule: a fresh Adam, a new seed, 200 warm-up steps to 3e-4 and a cosine to 0. 8,000 steps,
75 min on 2 CPU cores (1.78 steps/s with other work beside it). From the repository root::

    usp-jax train --config experiments/cpu_photos_stage5.py \
        --init runs/stage3.npz --data data/corpus/train \
        --workdir runs/corpus-cpu-stage5
    usp-jax evaluate --checkpoint runs/corpus-cpu-stage5 --hpatches data/heldout-pairs --baselines ""

Result (RESULTS.md): no change beyond the pairs' noise except a 1-2% lower matching score, so
it was not shipped. The viewpoint gap is localisation, not the range of viewpoints trained on.
"""

import pathlib

from usp_jax import config as config_lib


def get_config() -> config_lib.Config:
    stage1 = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos.py")))
    return config_lib.override(
        stage1,
        [
            "seed=4",
            "homography.patch_ratio=0.75",
            "homography.perspective=0.3",
            "optim.learning_rate=3e-4",
            "optim.warmup_steps=200",
            "num_steps=8000",
            "optim.decay_steps=7800",
        ],
    )
