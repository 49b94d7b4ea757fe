"""The paper network distilled into the fast backbone (``core.distillation``): one network, fast
and accurate. Build the corpus first (``experiments/build_corpus.py``), then from the repository
root::

    usp-jax train --config experiments/distill.py --data data/corpus/train --workdir runs/distill
    usp-jax export --checkpoint runs/distill --save-weights runs/distill-stage1.npz

Re-running the train command resumes it (the teacher is loaded again by name; it is not part of
the checkpoint). The student is the fast network (``fast_config``) started from the shipped fast
weights, the teacher the shipped paper network, frozen; both see the same augmented siamese pairs,
and the student learns from the paper's own losses (eq. 4) and from the teacher's scores,
positions and descriptors. Crops, homographies, lighting and the rescaled descriptor weights are
the fast network's stage 1 (``experiments/fast.py``): 128x160 crops at the paper's pixel scale,
a quarter of the cost per step. A fresh Adam, 200 warm-up steps to 3e-4 and a cosine to 0.

The ablation at equal CPU time (``ablation_distill_only`` and ``ablation_self_only``; the
``get_config`` run is the third arm, compared at the same step)::

    usp-jax train --config experiments/distill.py:ablation_distill_only --data data/corpus/train \\
        --workdir runs/distill-only
    usp-jax train --config experiments/distill.py:ablation_self_only --data data/corpus/train \\
        --workdir runs/self-only
    usp-jax train --config experiments/distill.py:ablation_no_position --data data/corpus/train \\
        --workdir runs/distill-nopos
    usp-jax train --config experiments/distill.py:ablation_descriptor_only --data data/corpus/train \\
        --workdir runs/distill-desc

The long run stopped at step 11,000 and its workdir did not outlive the machine; ``finish`` runs
the rest of its schedule from the shipped step-11,000 weights (``usp_jax/weights/distilled.npz``)::

    usp-jax train --config experiments/distill.py:finish --data data/corpus/train \\
        --workdir runs/distill-finish
"""

import dataclasses
import math

from usp_jax import config as config_lib
from usp_jax import fast_config

NUM_STEPS = 20_000
#: The ablation's length for the two arms that run a teacher; the self-supervised arm gets the
#: steps that fit in the same CPU time (it skips the teacher's forward pass).
ABLATION_STEPS = 500
SELF_ONLY_STEPS = 800
#: Where the long run stopped, and the steps ``finish`` gives the rest of its cosine.
STOPPED_AT = 11_000
FINISH_STEPS = NUM_STEPS - STOPPED_AT


def _student(overrides: list[str]) -> config_lib.Config:
    base = config_lib.override(
        config_lib.paper(),
        [
            "seed=40",
            "init_weights=fast",
            "distill.teacher=paper",
            "photometric.gamma=0.5",
            "photometric.brightness=0.5",
            "photometric.contrast=0.5",
            "data.height=128",
            "data.width=160",
            "data.scale_range=(0.25, 0.5)",
            "loss.lambda_d=62.5",
            "loss.alpha_desc=0.004",
            "optim.learning_rate=3e-4",
            "optim.warmup_steps=200",
            f"optim.decay_steps={NUM_STEPS - 200}",
            f"num_steps={NUM_STEPS}",
            "checkpoint_every=500",
            "log_every=20",
            "keep_checkpoints=3",
            *overrides,
        ],
    )
    return dataclasses.replace(base, model=fast_config())


def get_config() -> config_lib.Config:
    """Both signals: the paper's losses and the teacher's targets."""
    return _student([])


def ablation_distill_only() -> config_lib.Config:
    """The teacher's targets alone (eq. 4 weighted 0)."""
    return _student(["distill.alpha_self=0", f"num_steps={ABLATION_STEPS}"])


def ablation_self_only() -> config_lib.Config:
    """The paper's losses alone, from the same start: what the extra steps alone would give."""
    return _student(["distill.teacher=", f"num_steps={SELF_ONLY_STEPS}"])


def ablation_no_position() -> config_lib.Config:
    """Both signals without the teacher's positions (``beta_position=0``): the student keeps its
    own point in each cell and learns the teacher's scores and descriptor similarities."""
    return _student(["distill.beta_position=0", f"num_steps={ABLATION_STEPS}"])


def ablation_descriptor_only() -> config_lib.Config:
    """The paper's losses and the teacher's descriptor similarities only (score and position
    terms weighted 0): whether the teacher's scores are what costs the student repeatability."""
    return _student(
        ["distill.beta_position=0", "distill.beta_score=0", f"num_steps={ABLATION_STEPS}"]
    )


def finish() -> config_lib.Config:
    """The long run's cosine tail from its step-11,000 weights: Adam starts afresh (the moments
    were lost with the workdir), so 100 warm-up steps lead to the rate the full schedule had at
    step 11,000, then the cosine to 0 over the 9,000 steps left; a new seed, so that the crops
    are not the ones already seen."""
    warmup, full = 100, get_config().optim
    progress = (STOPPED_AT - full.warmup_steps) / full.decay_steps
    rate = full.learning_rate * 0.5 * (1 + math.cos(math.pi * progress))
    return _student(
        [
            "seed=41",
            "init_weights=distilled",
            f"optim.learning_rate={rate:.4g}",
            f"optim.warmup_steps={warmup}",
            f"optim.decay_steps={FINISH_STEPS - warmup}",
            f"num_steps={FINISH_STEPS}",
        ]
    )
