import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL_MODEL

import usp_jax
from usp_jax.core import correspondence, geometry, losses
from usp_jax.core.model import Predictions, UnsuperPoint, init_variables


def test_uniform_loss_is_eq10_on_sorted_values():
    rng = np.random.default_rng(0)
    v = rng.uniform(2.0, 5.0, size=17)
    s = np.sort(v)
    expected = sum(((s[i] - 2.0) / 3.0 - i / 16) ** 2 for i in range(17))
    assert float(losses.uniform_loss(jnp.asarray(v), 2.0, 5.0)) == pytest.approx(expected, rel=1e-5)
    # Order of the input does not matter: it is a distance between distributions.
    assert float(losses.uniform_loss(jnp.asarray(v[::-1]), 2.0, 5.0)) == pytest.approx(
        expected, rel=1e-5
    )


def test_uniform_loss_small_for_even_spread_large_for_clusters():
    even = jnp.linspace(0, 1, 1200)
    random_uniform = jax.random.uniform(jax.random.PRNGKey(0), (1200,))
    clustered = 0.5 + 0.02 * jax.random.normal(jax.random.PRNGKey(1), (1200,))
    assert float(usp_jax.uniform_loss(even)) == pytest.approx(0.0, abs=1e-9)
    assert float(usp_jax.uniform_loss(random_uniform)) < 1.0
    # All at 0.5 gives sum_i (0.5 - i / (M - 1))^2 ~ M / 12 = 100; 0.02 noise leaves ~87.
    assert float(usp_jax.uniform_loss(clustered)) > 80.0


def test_score_mean_loss_penalises_only_a_common_shift():
    rng = np.random.default_rng(3)
    s = rng.uniform(size=40)
    expected = 40 * (np.mean(s) - 0.5) ** 2
    assert float(losses.score_mean_loss(jnp.asarray(s))) == pytest.approx(expected, rel=1e-5)
    # Any spread around a mean of 1/2 costs nothing, so the ranking is left to the USP terms.
    spread = jnp.asarray(np.concatenate([s, 1.0 - s]))
    assert float(losses.score_mean_loss(spread)) == pytest.approx(0.0, abs=1e-9)
    # Each score's gradient is 2 (mean - 1/2), the same for all: it only counters the slide.
    grad = jax.grad(losses.score_mean_loss)(jnp.full(8, 0.1))
    np.testing.assert_allclose(grad, np.full(8, 2 * (0.1 - 0.5)), rtol=1e-6)


def test_descriptor_loss_matches_numpy_loop():
    rng = np.random.default_rng(1)
    fa = rng.normal(size=(5, 4)).astype(np.float32)
    fb = rng.normal(size=(6, 4)).astype(np.float32)
    fa /= np.linalg.norm(fa, axis=1, keepdims=True)
    fb /= np.linalg.norm(fb, axis=1, keepdims=True)
    c = (rng.uniform(size=(5, 6)) < 0.3).astype(np.float32)
    mask = (rng.uniform(size=(5, 6)) < 0.8).astype(np.float32)
    expected = 0.0
    for i in range(5):
        for j in range(6):
            dot = float(fa[i] @ fb[j])
            l = 250 * c[i, j] * max(0, 1 - dot) + (1 - c[i, j]) * max(0, dot - 0.2)
            expected += mask[i, j] * l
    got = losses.descriptor_loss(*map(jnp.asarray, (fa, fb, c, mask)))
    assert float(got) == pytest.approx(expected, rel=1e-5)


def test_hardest_negative_loss_matches_numpy_loop():
    rng = np.random.default_rng(4)
    fa, fb = (rng.normal(size=(n, 4)).astype(np.float32) for n in (5, 6))
    fa /= np.linalg.norm(fa, axis=1, keepdims=True)
    fb /= np.linalg.norm(fb, axis=1, keepdims=True)
    c = (rng.uniform(size=(5, 6)) < 0.3).astype(np.float32)
    mask = (rng.uniform(size=(5, 6)) < 0.8).astype(np.float32)
    sim, total, count = fa @ fb.T, 0.0, 0
    for s, cc, m in ((sim, c, mask), (sim.T, c.T, mask.T)):
        for i in range(s.shape[0]):
            pos = [s[i, j] for j in range(s.shape[1]) if m[i, j] and cc[i, j]]
            neg = [s[i, k] for k in range(s.shape[1]) if m[i, k] and not cc[i, k]]
            if pos and neg:
                total += max(0.0, 0.5 + max(neg) - max(pos))
                count += 1
    assert count > 0
    positive, negative = (c * mask) > 0, ((1 - c) * mask) > 0
    got = losses.hardest_negative_loss(*map(jnp.asarray, (fa, fb, positive, negative)), margin=0.5)
    assert float(got) == pytest.approx(total / count, rel=1e-5)


def test_hardest_negative_loss_is_zero_once_every_true_match_beats_its_hardest_negative_by_the_margin():
    eye = jnp.eye(4)  # point i of A matches point i of B; distinct points are orthogonal
    positive, negative = eye > 0, eye == 0
    assert float(losses.hardest_negative_loss(eye, eye, positive, negative, margin=0.5)) == 0.0
    hinge = losses.hardest_negative_loss(eye, eye, positive, negative, margin=1.5)
    assert float(hinge) == pytest.approx(0.5)


def test_dual_softmax_loss_matches_numpy_loop():
    rng = np.random.default_rng(5)
    fa, fb = (rng.normal(size=(n, 4)).astype(np.float32) for n in (5, 6))
    fa /= np.linalg.norm(fa, axis=1, keepdims=True)
    fb /= np.linalg.norm(fb, axis=1, keepdims=True)
    nearest = np.array([2, 0, 5, 5, 1])
    paired = np.array([True, True, False, True, True])
    keep = rng.uniform(size=(5, 6)) < 0.7
    partner = np.zeros((5, 6), bool)
    partner[np.arange(5)[paired], nearest[paired]] = True
    inside = keep | partner
    logits = (fa @ fb.T) / 0.1
    total = 0.0
    for i in np.flatnonzero(paired):
        j = nearest[i]
        row = np.log(np.sum(np.exp(logits[i][inside[i]])))
        column = np.log(np.sum(np.exp(logits[:, j][inside[:, j]])))
        total += -(2 * logits[i, j] - row - column)
    got = losses.dual_softmax_loss(*map(jnp.asarray, (fa, fb, nearest, paired, keep)), 0.1)
    assert float(got) == pytest.approx(total / paired.sum(), rel=1e-5)


def test_dual_softmax_loss_falls_as_the_partner_stands_out_and_keeps_a_finite_gradient():
    eye = jnp.eye(4)  # point i of A matches point i of B; distinct points are orthogonal
    nearest, paired = jnp.arange(4), jnp.ones(4, bool)
    none_kept = jnp.zeros((4, 4), bool)  # only the partners: a certain match
    assert float(losses.dual_softmax_loss(eye, eye, nearest, paired, none_kept)) == pytest.approx(
        0.0
    )
    every = jnp.ones((4, 4), bool)
    sharp = losses.dual_softmax_loss(eye, eye, nearest, paired, every, temperature=0.1)
    blunt = losses.dual_softmax_loss(eye, eye, nearest, paired, every, temperature=1.0)
    assert 0 < float(sharp) < float(blunt)
    # Columns with nothing kept and no partner (point 3 of B unpaired) must not poison it.
    grad = jax.grad(
        lambda a: losses.dual_softmax_loss(a, eye, nearest, paired.at[3].set(False), none_kept)
    )(eye)
    assert bool(jnp.all(jnp.isfinite(grad)))
    assert float(losses.dual_softmax_loss(eye, eye, nearest, jnp.zeros(4, bool), every)) == 0.0


@pytest.mark.parametrize("mode", ["squared", "signed"])
def test_decorrelation_loss_matches_numpy_corrcoef(mode):
    f = np.random.default_rng(2).normal(size=(50, 6)).astype(np.float32)
    f[:, 1] = f[:, 0] * 0.7 + 0.3 * f[:, 1]
    r = np.corrcoef(f, rowvar=False)
    off = r[~np.eye(6, dtype=bool)]
    expected = np.sum(off**2) if mode == "squared" else np.sum(off)
    assert float(losses.decorrelation_loss(jnp.asarray(f), mode)) == pytest.approx(
        expected, rel=1e-4
    )


def test_squared_decorrelation_is_zero_only_when_decorrelated():
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(64, 8)))
    q -= q.mean(axis=0)  # orthogonal, zero-mean columns: uncorrelated
    q, _ = np.linalg.qr(q)
    q -= q.mean(axis=0)
    decorrelated = jnp.asarray(q, jnp.float32)
    assert float(losses.decorrelation_loss(decorrelated)) < 1e-3
    # Two anti-correlated copies minimise the printed signed form without being decorrelated.
    x = np.random.default_rng(4).normal(size=(64, 1))
    anti = jnp.asarray(np.hstack([x, -x]), jnp.float32)
    assert float(losses.decorrelation_loss(anti, "signed")) == pytest.approx(-2.0, abs=1e-4)
    assert float(losses.decorrelation_loss(anti, "squared")) == pytest.approx(2.0, abs=1e-4)


def test_usp_loss_matches_hand_computation():
    sa = np.array([0.9, 0.2, 0.5, 0.7])
    sb = np.array([0.7, 0.4, 0.5, 0.1])
    d = np.array([1.0, 3.0, 2.0, 9.0])
    paired = np.array([True, True, True, False])
    k = paired.sum()
    mean_d = d[paired].mean()
    expected = (
        1 * d[paired].sum()
        + 2 * ((sa - sb)[paired] ** 2).sum()
        + (((sa + sb) / 2 - 0) * (d - mean_d))[paired].sum()
    )
    loss, metrics = losses.usp_loss(*map(jnp.asarray, (sa, sb, d, paired)))
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["K"]) == k and float(metrics["mean_d"]) == pytest.approx(mean_d)


def predict(config, images):
    # Compiled whole: op-by-op dispatch of the network costs several times the compile.
    variables = init_variables(jax.random.PRNGKey(0), config)
    return jax.jit(UnsuperPoint(config).apply)(variables, images), variables


total_loss = jax.jit(losses.total_loss, static_argnums=(3, 4))
pair_loss = jax.jit(losses.pair_loss, static_argnums=(3, 4))


def test_identity_homography_gives_zero_position_loss():
    images = jax.random.uniform(jax.random.PRNGKey(0), (1, 32, 48, 3))
    pred, _ = predict(SMALL_MODEL, images)
    _, metrics = total_loss(pred, pred, jnp.eye(3)[None], 32, 48)
    assert float(metrics["usp/K"]) == 24  # every one of the 4 x 6 cells pairs with itself
    assert float(metrics["usp/mean_d"]) == pytest.approx(0.0, abs=1e-5)
    assert float(metrics["usp/score"]) == pytest.approx(0.0, abs=1e-8)


def test_zero_correspondences_give_finite_loss_and_gradients():
    images = jax.random.uniform(jax.random.PRNGKey(1), (2, 32, 48, 3))
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    far_away = jnp.tile(jnp.array([[1.0, 0, 1000], [0, 1, 1000], [0, 0, 1]]), (2, 1, 1))

    def loss(params):
        pred = UnsuperPoint(SMALL_MODEL).apply({**variables, "params": params}, images)
        return losses.total_loss(pred, pred, far_away, 32, 48)

    (value, metrics), grads = jax.jit(jax.value_and_grad(loss, has_aux=True))(variables["params"])
    assert float(metrics["usp/K"]) == 0
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_total_loss_gradient_through_the_model_is_finite_and_nonzero():
    images = jax.random.uniform(jax.random.PRNGKey(2), (2, 32, 48, 3))
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    hs = jax.vmap(lambda k: geometry.sample_homography(k, 32, 48))(
        jax.random.split(jax.random.PRNGKey(3), 2)
    )

    def loss(params):
        pred_a = UnsuperPoint(SMALL_MODEL).apply({**variables, "params": params}, images)
        pred_b = UnsuperPoint(SMALL_MODEL).apply({**variables, "params": params}, images[:, ::-1])
        return losses.total_loss(pred_a, pred_b, hs, 32, 48)[0]

    grads = jax.jit(jax.grad(loss))(variables["params"])
    norms = [float(jnp.linalg.norm(g)) for g in jax.tree.leaves(grads)]
    assert all(np.isfinite(norms)) and max(norms) > 0


def test_no_term_swamps_the_others_at_initialisation(photo):
    """The paper's network on a real 240x320 photo pair: the four weighted terms of eq. 4 are
    within two orders of magnitude of each other at initialisation (seed 0: usp ~1.2e3,
    uni_xy ~3.7e3, desc ~3.5e2, decorr ~85)."""
    image = jnp.asarray(photo[100:340, 100:420], jnp.float32)[None] / 255.0
    h = geometry.sample_homography(jax.random.PRNGKey(0), 240, 320)
    warped, _ = geometry.warp_image(image[0], h, (240, 320))
    model = UnsuperPoint()
    variables = init_variables(jax.random.PRNGKey(0))
    # Training mode: BatchNorm normalises with batch statistics, as in the first train step.
    pred, _ = jax.jit(lambda x: model.apply(variables, x, train=True, mutable=["batch_stats"]))(
        jnp.concatenate([image, warped[None]])
    )
    pa = jax.tree.map(lambda x: x[:1], pred)
    pb = jax.tree.map(lambda x: x[1:], pred)
    _, metrics = total_loss(pa, pb, h[None], 240, 320)
    terms = {k: abs(float(metrics[f"loss/{k}"])) for k in ("usp", "uni_xy", "desc", "decorr")}
    print(terms)
    assert max(terms.values()) / min(terms.values()) < 100, terms


def test_similarity_metrics_are_the_mean_over_positive_and_negative_pairs():
    images = jax.random.uniform(jax.random.PRNGKey(4), (1, 32, 48, 3))
    pred, _ = predict(SMALL_MODEL, images)
    pred = jax.tree.map(lambda x: x[0], pred)
    _, metrics = pair_loss(pred, pred, jnp.eye(3), 32, 48)
    corr = losses.branch_correspondences(pred, pred, jnp.eye(3), 32, 48)
    c = np.asarray(correspondence.correspondence_matrix(corr, 8.0))
    visible = np.asarray(corr.valid_a)[:, None] & np.asarray(corr.valid_b)[None, :]
    desc = np.asarray(pred.descriptors)
    sim = desc @ desc.T
    assert float(metrics["desc/sim_positive"]) == pytest.approx(sim[(c > 0) & visible].mean(), 1e-5)
    assert float(metrics["desc/sim_negative"]) == pytest.approx(
        sim[(c == 0) & visible].mean(), 1e-5
    )

    one_vector = jnp.tile(pred.descriptors[:1], (pred.descriptors.shape[0], 1))
    collapsed = pred._replace(descriptors=one_vector)
    _, metrics = pair_loss(collapsed, collapsed, jnp.eye(3), 32, 48)
    assert float(metrics["desc/sim_negative"]) == pytest.approx(1.0, 1e-5)


def test_the_hardest_negative_term_seeks_negatives_beyond_the_safe_radius_only():
    images = jax.random.uniform(jax.random.PRNGKey(5), (1, 32, 48, 3))
    pred, _ = predict(SMALL_MODEL, images)
    pred = jax.tree.map(lambda x: x[0], pred)
    corr = losses.branch_correspondences(pred, pred, jnp.eye(3), 32, 48)
    c = np.asarray(correspondence.correspondence_matrix(corr, 8.0)) > 0
    visible = np.asarray(corr.valid_a)[:, None] & np.asarray(corr.valid_b)[None, :]
    distances = np.asarray(corr.distances)
    for radius in (1.0, 16.0):  # 1 px: every other point; a point's own distance is ~0
        config = losses.LossConfig(alpha_hard=1.0, hard_safe_radius=radius)
        _, metrics = jax.jit(losses.pair_loss, static_argnums=(3, 4, 5))(
            pred, pred, jnp.eye(3), 32, 48, config
        )
        expected = losses.hardest_negative_loss(
            pred.descriptors, pred.descriptors, c & visible, (distances > radius) & ~c & visible
        )
        assert float(metrics["loss/hard"]) == pytest.approx(float(expected), rel=1e-5)
    assert np.any((distances > 1) & (distances <= 16) & ~c)  # the radius does exclude some


def test_the_matching_term_leaves_neighbouring_cells_out_of_the_softmaxes():
    images = jax.random.uniform(jax.random.PRNGKey(6), (1, 32, 48, 3))
    pred, _ = predict(SMALL_MODEL, images)
    pred = jax.tree.map(lambda x: x[0], pred)
    shift = jnp.array([[1.0, 0, 3], [0, 1, 2], [0, 0, 1]])
    corr = losses.branch_correspondences(pred, pred, shift, 32, 48)
    c = np.asarray(correspondence.correspondence_matrix(corr, 8.0)) > 0
    visible = np.asarray(corr.valid_a)[:, None] & np.asarray(corr.valid_b)[None, :]
    config = losses.LossConfig(alpha_match=2.0, match_temperature=0.2)
    total, metrics = jax.jit(losses.pair_loss, static_argnums=(3, 4, 5))(
        pred, pred, shift, 32, 48, config
    )
    expected = losses.dual_softmax_loss(
        pred.descriptors, pred.descriptors, corr.nearest, corr.paired, ~c & visible, 0.2
    )
    assert float(metrics["loss/match"]) == pytest.approx(2 * float(expected), rel=1e-5)
    assert np.any(c & visible & ~np.eye(len(c), dtype=bool))  # some pairs are left out
    off = jax.jit(losses.pair_loss, static_argnums=(3, 4, 5))(pred, pred, shift, 32, 48)[1]
    assert float(off["loss/match"]) == 0.0
    assert float(total) == pytest.approx(
        float(off["loss"]) + float(metrics["loss/match"]), rel=1e-5
    )


def test_cpu_photos_descriptor_weights_keep_the_papers_balance_at_128x160():
    """lambda_d x (positive pairs) / (negative pairs) at 128x160 with experiments/paper_network.py
    is within 1.5x of its value at the paper's 240x320 with the paper's weights (with lambda_d
    = 250 at 128x160 it is ~4x off and the descriptors collapse)."""
    from usp_jax import config as config_lib

    def balance(height, width, lambda_d):
        grid = jnp.stack(jnp.meshgrid(jnp.arange(width // 8), jnp.arange(height // 8)), -1)
        points = (grid.reshape(-1, 2) + 0.5) * 8 - 0.5
        h = geometry.sample_homography(jax.random.PRNGKey(0), height, width)
        pred = Predictions(
            scores=jnp.zeros(len(points)),
            relative=jnp.full((len(points), 2), 0.5),
            keypoints=points,
            descriptors=jnp.zeros((len(points), 4)),
        )
        corr = losses.branch_correspondences(pred, pred, h, height, width)
        c = np.asarray(correspondence.correspondence_matrix(corr, 8.0))
        visible = np.asarray(corr.valid_a)[:, None] & np.asarray(corr.valid_b)[None, :]
        return lambda_d * np.sum(c * visible) / np.sum((1 - c) * visible)

    paper = config_lib.paper().loss
    cpu = config_lib.load(
        str(pathlib.Path(__file__).parents[1] / "experiments" / "paper_network.py")
    ).loss
    at_paper_size = balance(240, 320, paper.lambda_d)
    assert 1 / 1.5 < balance(128, 160, cpu.lambda_d) / at_paper_size < 1.5
    assert balance(128, 160, paper.lambda_d) / at_paper_size > 3
