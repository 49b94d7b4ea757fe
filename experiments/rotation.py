"""Rotation-robust weights (``Detector.pretrained("rotation")``): the fast network
(``usp_jax.fast_config``) trained from scratch on training homographies that rotate over the
full circle, uniformly in [-180, 180] degrees, from the first step; ``fast.py``'s two stages and
a third, longer 240x320 stage.

Build the corpus first (``experiments/build_corpus.py``), then from the repository root::

    usp-jax train --config experiments/rotation.py --data data/corpus/train --workdir runs/rotation
    usp-jax export --checkpoint runs/rotation --save-weights runs/rotation-stage1.npz
    usp-jax train --config experiments/rotation.py:finetune --init runs/rotation-stage1.npz \\
        --data data/corpus/train --workdir runs/rotation-finetune
    usp-jax export --checkpoint runs/rotation-finetune --save-weights runs/rotation-stage2.npz
    usp-jax train --config experiments/rotation.py:finetune2 --init runs/rotation-stage2.npz \\
        --data data/corpus/train --workdir runs/rotation-finetune2
    usp-jax export --checkpoint runs/rotation-finetune2 --save-weights usp_jax/weights/rotation.npz

Re-running a train command resumes it. The upright weights are upright detectors because their
training homographies rarely rotate: a rotated patch must fit inside the crop, so only 4.8% of
them turn by 20 degrees or more (``evaluation.analysis.training_rotations``, 4,000 draws). Here
every example comes with a square context window around its crop (``data.context_window``: the
crop's diagonal, at the same pixel scale), branch A is the centre crop and branch B is rendered
from the whole window (``training.step.make_window_branches``), so B shows real photo content
at any angle, and the angle follows its distribution exactly (``homography.rotation_range``; half
the pairs turn by 90 degrees or more). Everything else is ``fast.py``'s: see there for why each
setting.

The same on the paper network (the default network), not yet shipped (RESULTS.md says how far
it has run): ``paper`` is ``paper_network.py``'s stage 1 on one cosine over its stages 1-3's
32,500 steps, ``paper_finetune`` its 240x320 stage 6, both turned and with its strongest
lighting changes::

    usp-jax train --config experiments/rotation.py:paper --data data/corpus/train --workdir runs/rotation-paper
    usp-jax export --checkpoint runs/rotation-paper --save-weights runs/rotation-paper-stage1.npz
    usp-jax train --config experiments/rotation.py:paper_finetune --init runs/rotation-paper-stage1.npz \\
        --data data/corpus/train --workdir runs/rotation-paper-finetune

To see how weights fare by rotation, make rotated held-out pairs (``usp-jax make-pairs --rotation
180``), evaluate them with ``--json`` and break the result down with ``experiments/compare.py
RESULT.json --rotation PAIRS``.
"""

import pathlib

from usp_jax import config as config_lib

_FAST = str(pathlib.Path(__file__).with_name("fast.py"))
_PAPER = str(pathlib.Path(__file__).with_name("paper_network.py"))
# What rotation needs, and nothing else.
_ROTATION = [
    "data.context_window=True",
    "homography.rotation_range=(-180.0, 180.0)",
    "homography.rotation_distribution=uniform",
]
# The shipped paper network's strongest lighting changes (its stage 10), from the first step.
_LIGHTING = ["photometric.gamma=0.5", "photometric.brightness=0.5", "photometric.contrast=0.5"]


def get_config() -> config_lib.Config:
    return config_lib.override(config_lib.load(_FAST), _ROTATION)


def finetune() -> config_lib.Config:
    return config_lib.override(config_lib.load(f"{_FAST}:finetune"), _ROTATION)


def finetune2() -> config_lib.Config:
    """Stage 3: stage 2's weights, 3,000 more steps at 240x320 on a fresh cosine (same rate)."""
    more = ["seed=25", "num_steps=3000", "optim.decay_steps=2900"]
    return config_lib.override(finetune(), more)


def paper() -> config_lib.Config:
    """The paper network, stage 1: paper_network.py's stage 1 at 128x160 turned over the full
    circle, on one cosine over the 32,500 steps its stages 1-3 took."""
    more = ["seed=31", "num_steps=32500", "optim.decay_steps=32500"]
    return config_lib.override(config_lib.load(_PAPER), _ROTATION + _LIGHTING + more)


def paper_finetune() -> config_lib.Config:
    """The paper network, stage 2: paper_network.py's 240x320 stage 6, turned, 3,000 steps."""
    more = ["seed=32", "num_steps=3000", "optim.decay_steps=2900"]
    return config_lib.override(config_lib.load(f"{_PAPER}:stage6"), _ROTATION + _LIGHTING + more)


def paper_from_upright() -> config_lib.Config:
    """The paper network turned starting from the shipped upright weights instead of from
    scratch (``--init usp_jax/weights/paper.npz``): paper_network.py's stage 3 setting (128x160,
    a warm-up to 3e-4 and a cosine) turned over the full circle with the strongest lighting
    changes, 6,000 steps. Not the issue's "rotations from the first step": an experiment on
    whether the upright network's distinctive descriptors survive being taught invariance."""
    more = [
        "seed=33",
        "optim.learning_rate=3e-4",
        "optim.warmup_steps=200",
        "num_steps=6000",
        "optim.decay_steps=6000",
    ]
    return config_lib.override(config_lib.load(_PAPER), _ROTATION + _LIGHTING + more)
