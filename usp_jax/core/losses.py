"""The four UnsuperPoint losses (paper section 4, eq. 4) as pure functions.

Reductions follow the printed equations: the USP terms sum over the K point-pairs (eq. 5), the
uniform loss over the M points of one image (eq. 12), the descriptor hinge over all MA x MB
descriptor pairs (eq. 13) and the decorrelation over the F x F off-diagonal entries (eq. 14). The
paper tuned its alpha weights for exactly these sums at 240x320, so keeping them keeps its balance
(``tests/test_losses.py`` pins that at initialisation no term is orders of magnitude above the
others). Per-image losses are then averaged over the batch, so the batch size only changes the
gradient noise, not the weighting.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from usp_jax.core import correspondence
from usp_jax.core.geometry import invert_homography, warp_points
from usp_jax.core.model import Predictions
from usp_jax.core.point_maps import PointMaps, map_points


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Loss weights and thresholds; defaults are the paper's (section 5)."""

    alpha_usp: float = 1.0
    alpha_position: float = 1.0
    alpha_score: float = 2.0
    alpha_uni_xy: float = 100.0
    # Not in the paper: M (mean score - 1/2)^2 per branch, against the score collapse (see
    # pair_loss and score_mean_loss).
    alpha_score_mean: float = 1.0
    # Not in the paper either: the uniform loss of eq. 10 on each branch's scores. Off by default:
    # a content-blind ramp of scores across the image satisfies it exactly (see pair_loss).
    alpha_uni_score: float = 0.0
    alpha_desc: float = 0.001
    alpha_decorr: float = 0.03
    lambda_d: float = 250.0
    margin_positive: float = 1.0
    margin_negative: float = 0.2
    eps_correspond: float = 4.0
    eps_descriptor: float = 8.0
    # Not in the paper: a triplet hinge on each point's hardest negative (hardest_negative_loss).
    # Off by default; experiments/real_pairs_hard.py turns it on.
    alpha_hard: float = 0.0
    margin_hard: float = 0.5
    hard_safe_radius: float = 16.0  # px: the hardest negative is sought beyond it
    # Not in the paper: the dual-softmax matching loss (dual_softmax_loss). Off by default;
    # experiments/matching_loss.py turns it on.
    alpha_match: float = 0.0
    match_temperature: float = 0.1
    # "squared" (default) decorrelates; "signed" is eq. 14 as printed, which anti-correlated
    # dimensions minimise without decorrelating (see decorrelation_loss).
    decorrelation: str = "squared"

    def __post_init__(self):
        if self.decorrelation not in ("squared", "signed"):
            raise ValueError(
                f"decorrelation must be 'squared' or 'signed', got {self.decorrelation!r}"
            )


def usp_loss(
    scores_a: jax.Array,
    scores_b: jax.Array,
    d: jax.Array,
    paired: jax.Array,
    alpha_position: float = LossConfig.alpha_position,
    alpha_score: float = LossConfig.alpha_score,
) -> tuple[jax.Array, dict]:
    """Unsupervised point loss, eqs. 5-9, summed over the K point-pairs.

    scores_a, scores_b: [K] scores of both points of each candidate pair (already gathered).
    d: [K] point-pair distances d_k; paired: [K] bool, which candidates are point-pairs.
    Returns (alpha_position * sum d_k + alpha_score * sum (s_A - s_B)^2 + sum s_k (d_k - mean d),
    metrics).
    """
    w = paired.astype(jnp.float32)
    k = jnp.sum(w)
    mean_d = jnp.sum(w * d) / jnp.maximum(k, 1.0)
    position = jnp.sum(w * d)
    score = jnp.sum(w * (scores_a - scores_b) ** 2)
    joint = 0.5 * (scores_a + scores_b)
    usp = jnp.sum(w * joint * (d - mean_d))
    loss = alpha_position * position + alpha_score * score + usp
    return loss, {"position": position, "score": score, "usp_term": usp, "K": k, "mean_d": mean_d}


def uniform_loss(values: jax.Array, low: float = 0.0, high: float = 1.0) -> jax.Array:
    """Distance of samples to U(low, high), eq. 10: sum_i ((v_i^sorted - a)/(b - a) - (i-1)/(L-1))^2.

    values: [L] (or [..., L], reduced over the last axis) -> scalar (or [...]).
    The *sorted values* are compared with the line, not argsort indices (peers note).
    """
    n = values.shape[-1]
    v = (jnp.sort(values, axis=-1) - low) / (high - low)
    line = jnp.arange(n, dtype=v.dtype) / max(n - 1, 1)
    return jnp.sum((v - line) ** 2, axis=-1)


def score_mean_loss(scores: jax.Array, target: float = 0.5) -> jax.Array:
    """M (mean(s) - target)^2 for the scores [M] of one image -> scalar.

    Each score's gradient is 2 (mean(s) - target): it counters a common shift of all scores, the
    one direction eq. 5 cannot see, and leaves their ranking and spread to the USP terms.
    """
    return scores.shape[-1] * (jnp.mean(scores, axis=-1) - target) ** 2


def descriptor_loss(
    desc_a: jax.Array,
    desc_b: jax.Array,
    c: jax.Array,
    mask: jax.Array,
    lambda_d: float = LossConfig.lambda_d,
    margin_positive: float = LossConfig.margin_positive,
    margin_negative: float = LossConfig.margin_negative,
) -> jax.Array:
    """Hinge descriptor loss, eq. 13, summed over all MA x MB pairs.

    desc_a: [MA, F], desc_b: [MB, F]; c: [MA, MB] correspondence matrix (eq. 11);
    mask: [MA, MB] which pairs count (both points visible in both views).
    The similarities come from one [MA, F] x [F, MB] matmul; no [MA, MB, F] tensor is formed.
    """
    sim = desc_a @ desc_b.T
    positive = lambda_d * c * jnp.maximum(0.0, margin_positive - sim)
    negative = (1.0 - c) * jnp.maximum(0.0, sim - margin_negative)
    return jnp.sum(mask * (positive + negative))


def hardest_negative_loss(
    desc_a: jax.Array,
    desc_b: jax.Array,
    positive: jax.Array,
    negative: jax.Array,
    margin: float = LossConfig.margin_hard,
) -> jax.Array:
    """Triplet hinge on each point's hardest negative, from A to B and from B to A (not in the
    paper; HardNet's sampling with D2-Net's safe radius): max(0, margin + max_k s_ik - max_j
    s_ij) over the positives j and the negatives k of point i, averaged over the points that
    have both.

    Eq. 13's negative hinge averages over all M^2 pairs, almost all of them far apart and
    already dissimilar; what makes a nearest neighbour wrong on a real pair is the one most
    similar non-corresponding point, which this term pushes below the true match. The
    negatives should lie beyond a safe radius (``LossConfig.hard_safe_radius``): descriptors
    are sampled from a map at 1/8 of the resolution, so points in neighbouring cells share
    their features and cannot be told apart.

    desc_a: [MA, F], desc_b: [MB, F] (unit rows); positive, negative: [MA, MB] bool.
    """
    sim = desc_a @ desc_b.T

    def one_way(sim, positive, negative):
        best = jnp.max(jnp.where(positive, sim, -2.0), axis=1)  # sims lie in [-1, 1]
        hardest = jnp.max(jnp.where(negative, sim, -2.0), axis=1)
        counted = jnp.any(positive, axis=1) & jnp.any(negative, axis=1)
        hinge = jnp.maximum(0.0, margin + hardest - best)
        return jnp.sum(jnp.where(counted, hinge, 0.0)), jnp.sum(counted)

    loss_a, count_a = one_way(sim, positive, negative)
    loss_b, count_b = one_way(sim.T, positive.T, negative.T)
    return (loss_a + loss_b) / jnp.maximum(count_a + count_b, 1)


def dual_softmax_loss(
    desc_a: jax.Array,
    desc_b: jax.Array,
    nearest: jax.Array,
    paired: jax.Array,
    keep: jax.Array,
    temperature: float = LossConfig.match_temperature,
) -> jax.Array:
    """Negative log-likelihood of each point-pair under the dual softmax (not in the paper; the
    matching loss of LoFTR and XFeat): with l_ij = s_ij / t, P_ij = softmax_j(l_i.) *
    softmax_i(l_.j), averaged -log P_i,nearest(i) over A's paired points i.

    Eq. 13 pushes every negative below a fixed margin on its own; a nearest-neighbour match
    goes wrong when one other point is more similar than the true partner, which is what each
    softmax here weighs: the partner against every competitor of its row and its column.

    desc_a: [MA, F], desc_b: [MB, F] (unit rows); nearest: int [MA], paired: bool [MA]
    (``Correspondences``); keep: bool [MA, MB], the pairs in the softmaxes (the partners are
    always in). Returns the scalar mean over paired points (0 when none).
    """
    logits = desc_a @ desc_b.T / temperature
    partner = jax.nn.one_hot(nearest, desc_b.shape[0], dtype=bool) & paired[:, None]
    # A large finite floor, not -inf: a column with nothing kept would give inf - inf, and its
    # NaN would reach the gradient through the softmax's backward pass.
    logits = jnp.where(keep | partner, logits, -1e9)
    log_p = 2 * logits - jax.nn.logsumexp(logits, axis=1, keepdims=True)
    log_p = log_p - jax.nn.logsumexp(logits, axis=0, keepdims=True)
    picked = jnp.sum(jnp.where(partner, log_p, 0.0), axis=1)
    return -jnp.sum(jnp.where(paired, picked, 0.0)) / jnp.maximum(jnp.sum(paired), 1)


def decorrelation_loss(descriptors: jax.Array, mode: str = "squared") -> jax.Array:
    """Off-diagonal correlation between descriptor dimensions of one branch, eqs. 14-15.

    descriptors: [M, F] -> scalar. ``mode="signed"`` sums r_ij as printed; for standardised
    columns that sum equals 1'R1 - F >= -F and is minimised by anti-correlation, so the default
    ``"squared"`` sums r_ij^2, which is zero exactly when the dimensions are decorrelated.
    """
    centered = descriptors - jnp.mean(descriptors, axis=0, keepdims=True)
    norms = jnp.sqrt(jnp.maximum(jnp.sum(centered**2, axis=0), 1e-12))
    r = (centered.T @ centered) / (norms[:, None] * norms[None, :])
    off = r * (1.0 - jnp.eye(r.shape[0], dtype=r.dtype))
    return jnp.sum(off**2) if mode == "squared" else jnp.sum(off)


def branch_correspondences(
    pred_a: Predictions,
    pred_b: Predictions,
    warp: jax.Array | PointMaps,
    height: int,
    width: int,
    eps_correspond: float = LossConfig.eps_correspond,
) -> correspondence.Correspondences:
    """Point-pairs of section 4 between unbatched branch predictions. ``warp`` maps A's pixels to
    B's: a homography T [3, 3], or ``PointMaps`` (each [H, W, 2]) for views with parallax."""
    if isinstance(warp, PointMaps):
        a_in_b = map_points(warp.a_to_b, pred_a.keypoints)
        b_in_a = map_points(warp.b_to_a, pred_b.keypoints)
    else:
        a_in_b = warp_points(warp, pred_a.keypoints)
        b_in_a = warp_points(invert_homography(warp), pred_b.keypoints)
    return correspondence.find_correspondences(
        a_in_b, b_in_a, pred_b.keypoints, height, width, eps_correspond
    )


def pair_loss(
    pred_a: Predictions,
    pred_b: Predictions,
    warp: jax.Array | PointMaps,
    height: int,
    width: int,
    config: LossConfig = LossConfig(),
) -> tuple[jax.Array, dict]:
    """Total loss of eq. 4 for one image pair (unbatched ``Predictions``, M points each).

    warp: T, mapping branch-A pixels to branch-B pixels: a homography [3, 3], or ``PointMaps``
    ([H, W, 2] each) for two views of a 3-D scene.
    Returns the scalar loss and a dict of metrics (every weighted term, K, mean d_k).
    """
    corr = branch_correspondences(pred_a, pred_b, warp, height, width, config.eps_correspond)

    usp, usp_metrics = usp_loss(
        pred_a.scores,
        pred_b.scores[corr.nearest],
        corr.d,
        corr.paired,
        config.alpha_position,
        config.alpha_score,
    )
    uni = sum(uniform_loss(pred.relative[:, axis]) for pred in (pred_a, pred_b) for axis in (0, 1))
    # The score terms of eq. 5 are blind to a common shift of all scores (sum_k (d_k - mean d)
    # = 0) while (s_A - s_B)^2 shrinks as the sigmoid saturates, so nothing stops every score
    # sliding to 0, where gradients vanish: the collapse peers reported. Anchoring the mean at
    # 1/2 removes that direction only. A uniform target on the score distribution (uni_score)
    # also stops the slide, but the cheapest way to meet it is a ramp of scores across the
    # image read off the zero padding, the same in both views: trained with it, the network
    # scored a uniform grey image 0.06 at the top and 0.94 at the bottom.
    score_mean = score_mean_loss(pred_a.scores) + score_mean_loss(pred_b.scores)
    uni_score = (
        uniform_loss(pred_a.scores) + uniform_loss(pred_b.scores)
        if config.alpha_uni_score
        else jnp.zeros(())  # off by default: skip its two sorts
    )
    c = correspondence.correspondence_matrix(corr, config.eps_descriptor)
    mask = (corr.valid_a[:, None] & corr.valid_b[None, :]).astype(jnp.float32)
    desc = descriptor_loss(
        pred_a.descriptors,
        pred_b.descriptors,
        c,
        mask,
        config.lambda_d,
        config.margin_positive,
        config.margin_negative,
    )
    decorr = decorrelation_loss(pred_a.descriptors, config.decorrelation) + decorrelation_loss(
        pred_b.descriptors, config.decorrelation
    )
    hard = (
        _hard_term(pred_a.descriptors, pred_b.descriptors, corr, c, mask, config)
        if config.alpha_hard
        else jnp.zeros(())
    )
    match = (
        _match_term(pred_a.descriptors, pred_b.descriptors, corr, c, mask, config)
        if config.alpha_match
        else jnp.zeros(())
    )
    terms = {
        "usp": config.alpha_usp * usp,
        "uni_xy": config.alpha_uni_xy * uni,
        "score_mean": config.alpha_score_mean * score_mean,
        "uni_score": config.alpha_uni_score * uni_score,
        "desc": config.alpha_desc * desc,
        "decorr": config.alpha_decorr * decorr,
        "hard": config.alpha_hard * hard,
        "match": config.alpha_match * match,
    }
    total = sum(terms.values())
    metrics = {
        "loss": total,
        **{f"loss/{k}": v for k, v in terms.items()},
        **{f"usp/{k}": v for k, v in usp_metrics.items()},
        **_similarity_metrics(pred_a.descriptors, pred_b.descriptors, c, mask),
    }
    return total, metrics


def _hard_term(desc_a, desc_b, corr, c, mask, config: LossConfig) -> jax.Array:
    """:func:`hardest_negative_loss` with the negatives beyond ``config.hard_safe_radius``."""
    far = jax.lax.stop_gradient(corr.distances) > config.hard_safe_radius
    positive, negative = c * mask > 0, far & (c == 0) & (mask > 0)
    return hardest_negative_loss(desc_a, desc_b, positive, negative, config.margin_hard)


def _match_term(desc_a, desc_b, corr, c, mask, config: LossConfig) -> jax.Array:
    """:func:`dual_softmax_loss` over the visible pairs. Pairs within eps_descriptor of each
    other but not a point-pair stay out of the softmaxes: neighbouring cells share their
    features at 1/8 resolution and cannot be told apart."""
    keep = (c == 0) & (mask > 0)
    return dual_softmax_loss(
        desc_a, desc_b, corr.nearest, corr.paired, keep, config.match_temperature
    )


def _similarity_metrics(desc_a, desc_b, c, mask) -> dict:
    """Positive pairs counted, and the mean similarity of positive and of negative pairs: both
    near 1 means the descriptors have collapsed to one vector (the hinge's positive term,
    weighted lambda_d, outweighs the negatives when few cells compete; see
    experiments/paper_network.py)."""
    sim = jax.lax.stop_gradient(desc_a @ desc_b.T)
    positive, negative = c * mask, (1.0 - c) * mask
    return {
        "positives": jnp.sum(positive),
        "desc/sim_positive": jnp.sum(sim * positive) / jnp.maximum(jnp.sum(positive), 1.0),
        "desc/sim_negative": jnp.sum(sim * negative) / jnp.maximum(jnp.sum(negative), 1.0),
    }


def total_loss(
    pred_a: Predictions,
    pred_b: Predictions,
    warps: jax.Array | PointMaps,
    height: int,
    width: int,
    config: LossConfig = LossConfig(),
) -> tuple[jax.Array, dict]:
    """Batched eq. 4: ``pair_loss`` per image pair [B], averaged over the batch.

    pred_a, pred_b: ``Predictions`` with a leading batch axis; warps: homographies [B, 3, 3] or
    ``PointMaps`` ([B, H, W, 2] each).
    """
    losses, metrics = jax.vmap(lambda pa, pb, w: pair_loss(pa, pb, w, height, width, config))(
        pred_a, pred_b, warps
    )
    return jnp.mean(losses), jax.tree.map(jnp.mean, metrics)
