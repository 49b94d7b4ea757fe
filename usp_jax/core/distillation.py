"""Distillation: a frozen teacher network's per-cell outputs as dense targets for a student.

Both networks map every 8x8 cell to one point (paper section 2), so on the same image the
teacher's M points and the student's M points are cell for cell the same points. On each branch
of a siamese pair (paper section 3) the student S is pulled towards the teacher T by

* the score term, mean squared error of the cell scores (s in [0, 1], eq. 2's s)::

      L_s = 1/M sum_m (s^S_m - s^T_m)^2

* the position term, the teacher-score-weighted distance of the points in pixels (eq. 1's
  positions; a cell's position matters as much as the teacher would keep the point)::

      L_p = sum_m s^T_m ||p^S_m - p^T_m|| / sum_m s^T_m

* the descriptor term, relational so that it needs no common descriptor width (the fast network
  has 128-d descriptors, the paper network 256-d): across the pair, each point of A has a
  distribution over B's points, softmax of the cosine similarities at temperature tau, and the
  student's must match the teacher's (KL divergence, both directions, mean over points)::

      P^N_ij = softmax_j(<f^N_A,i, f^N_B,j> / tau)          N in {S, T}
      L_f = 1/2 [ 1/M_A sum_i KL(P^T_i. || P^S_i.) + 1/M_B sum_j KL(P^T_.j || P^S_.j) ]

  The teacher's distributions carry both what eq. 13's hinge asks (which points correspond) and
  how alike the non-corresponding ones look, which a hinge with fixed margins throws away.

The distillation loss of a pair is ``beta_score (L_s^A + L_s^B) + beta_position (L_p^A + L_p^B)
+ beta_descriptor L_f``; training adds ``alpha_self`` times the paper's own eq. 4 so that the
student still learns from the homography's ground truth where the teacher is wrong, and the run
stays label-free. Every term is 0 when the student's outputs equal the teacher's.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from usp_jax.core.model import Predictions


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """A frozen teacher's outputs as targets (module docstring); ``teacher=""`` turns it off.

    ``teacher``: shipped weights by name (``paper``), a ``.npz`` weights file or a training
    workdir. ``alpha_self`` weighs the paper's eq. 4 beside the distillation terms: 0 trains on
    the teacher alone.
    """

    teacher: str = ""
    alpha_self: float = 1.0
    beta_score: float = 100.0
    beta_position: float = 10.0
    beta_descriptor: float = 100.0
    temperature: float = 0.1


def score_loss(student: jax.Array, teacher: jax.Array) -> jax.Array:
    """L_s: scores [M] and [M] -> scalar mean squared difference."""
    return jnp.mean((student - teacher) ** 2)


def position_loss(student: jax.Array, teacher: jax.Array, teacher_scores: jax.Array) -> jax.Array:
    """L_p: keypoints [M, 2] and [M, 2] in pixels, teacher scores [M] -> scalar, in pixels."""
    squared = jnp.sum((student - teacher) ** 2, axis=-1)
    # sqrt's gradient at 0 is infinite (NaN through the chain rule): where the points agree the
    # distance is 0 and so is its gradient, through a square root that never sees 0.
    positive = squared > 0
    distance = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)
    return jnp.sum(teacher_scores * distance) / jnp.maximum(jnp.sum(teacher_scores), 1e-6)


def _kl_rows(teacher_logits: jax.Array, student_logits: jax.Array) -> jax.Array:
    """Mean over rows of KL(softmax(teacher row) || softmax(student row)); logits [R, C]."""
    log_p = jax.nn.log_softmax(teacher_logits, axis=-1)
    log_q = jax.nn.log_softmax(student_logits, axis=-1)
    return jnp.mean(jnp.sum(jnp.exp(log_p) * (log_p - log_q), axis=-1))


def descriptor_loss(
    student_a: jax.Array,
    student_b: jax.Array,
    teacher_a: jax.Array,
    teacher_b: jax.Array,
    temperature: float,
) -> jax.Array:
    """L_f: descriptors [M_A, F_S], [M_B, F_S] (student) and [M_A, F_T], [M_B, F_T] (teacher),
    L2-normalised; F_S and F_T may differ -> scalar."""
    student = student_a @ student_b.T / temperature  # [M_A, M_B]
    teacher = teacher_a @ teacher_b.T / temperature
    return 0.5 * (_kl_rows(teacher, student) + _kl_rows(teacher.T, student.T))


def pair_distillation_loss(
    student_a: Predictions,
    student_b: Predictions,
    teacher_a: Predictions,
    teacher_b: Predictions,
    config: DistillConfig,
) -> tuple[jax.Array, dict]:
    """The distillation loss of one pair (module docstring): Predictions of one image each
    (scores [M], keypoints [M, 2], descriptors [M, F]) -> (scalar, metrics)."""
    l_score = score_loss(student_a.scores, teacher_a.scores) + score_loss(
        student_b.scores, teacher_b.scores
    )
    l_position = position_loss(
        student_a.keypoints, teacher_a.keypoints, teacher_a.scores
    ) + position_loss(student_b.keypoints, teacher_b.keypoints, teacher_b.scores)
    l_descriptor = descriptor_loss(
        student_a.descriptors,
        student_b.descriptors,
        teacher_a.descriptors,
        teacher_b.descriptors,
        config.temperature,
    )
    loss = (
        config.beta_score * l_score
        + config.beta_position * l_position
        + config.beta_descriptor * l_descriptor
    )
    metrics = {
        "distill/score": l_score,
        "distill/position": l_position,
        "distill/descriptor": l_descriptor,
        "distill/total": loss,
    }
    return loss, metrics


def distillation_loss(
    student_a: Predictions,
    student_b: Predictions,
    teacher_a: Predictions,
    teacher_b: Predictions,
    config: DistillConfig,
) -> tuple[jax.Array, dict]:
    """Batched :func:`pair_distillation_loss`: Predictions with a leading batch axis [B, ...],
    averaged over the batch (as ``losses.total_loss``)."""
    values, metrics = jax.vmap(
        lambda sa, sb, ta, tb: pair_distillation_loss(sa, sb, ta, tb, config)
    )(student_a, student_b, teacher_a, teacher_b)
    return jnp.mean(values), jax.tree.map(jnp.mean, metrics)
