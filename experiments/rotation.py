"""The fast network (``usp_jax.fast_config``) trained from scratch to be rotation-robust: the
recipe of ``experiments/fast.py``, both stages, with training homographies that rotate over the
full circle, uniformly in [-180, 180] degrees, from the first step.

Build the corpus first (``experiments/build_corpus.py``), then from the repository root::

    usp-jax train --config experiments/rotation.py --data data/corpus/train --workdir runs/rotation
    usp-jax export --checkpoint runs/rotation --save-weights runs/rotation-stage1.npz
    usp-jax train --config experiments/rotation.py:finetune --init runs/rotation-stage1.npz \\
        --data data/corpus/train --workdir runs/rotation-finetune
    usp-jax export --checkpoint runs/rotation-finetune --save-weights usp_jax/weights/rotation.npz

Re-running a train command resumes it. The shipped models are upright detectors because their
training homographies rarely rotate: a rotated patch must fit inside the crop, so only 4.8% of
them turn by 20 degrees or more (``experiments/training_rotations.py``). Here every example comes
with a square context window around its crop (``data.context_window``: the crop's diagonal, at
the same pixel scale), branch A is the centre crop and branch B is rendered from the whole window
(``training.step.make_window_branches``), so B shows real photo content at any angle, and the angle
follows its distribution exactly (``homography.rotation_range``; half the pairs turn by 90
degrees or more). Everything else is ``fast.py``'s: see there for why each setting.

To see how it fares by rotation, make rotated held-out pairs (``usp-jax make-pairs --rotation
180``), evaluate them with ``--json`` and break the result down with ``experiments/compare.py
RESULT.json --rotation PAIRS``.
"""

import pathlib

from usp_jax import config as config_lib

_FAST = str(pathlib.Path(__file__).with_name("fast.py"))
# What rotation needs, and nothing else.
_ROTATION = [
    "data.context_window=True",
    "homography.rotation_range=(-180.0, 180.0)",
    "homography.rotation_distribution=uniform",
]


def get_config() -> config_lib.Config:
    return config_lib.override(config_lib.load(_FAST), _ROTATION)


def finetune() -> config_lib.Config:
    return config_lib.override(config_lib.load(f"{_FAST}:finetune"), _ROTATION)
