"""Distillation (``core.distillation``, ``train --teacher``): the loss against NumPy, a frozen
teacher, exact resumption and one-line failures for a bad teacher."""

import conftest
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL_FAST, SMALL_MODEL, TINY_RUN, train_args

from usp_jax import inference
from usp_jax.cli import main
from usp_jax.core import distillation
from usp_jax.core.model import Predictions
from usp_jax.training import step as step_lib
from usp_jax.training import train


def random_predictions(key, batch: int, cells: int, dim: int) -> Predictions:
    k_s, k_r, k_d = jax.random.split(key, 3)
    relative = jax.random.uniform(k_r, (batch, cells, 2))
    descriptors = jax.random.normal(k_d, (batch, cells, dim))
    return Predictions(
        scores=jax.random.uniform(k_s, (batch, cells)),
        relative=relative,
        keypoints=relative * 8 + 8 * jnp.arange(cells)[None, :, None],
        descriptors=descriptors / jnp.linalg.norm(descriptors, axis=-1, keepdims=True),
    )


def numpy_kl_rows(p_logits, q_logits):
    def log_softmax(x):
        x = x - x.max(axis=-1, keepdims=True)
        return x - np.log(np.exp(x).sum(axis=-1, keepdims=True))

    log_p, log_q = log_softmax(p_logits), log_softmax(q_logits)
    return np.mean(np.sum(np.exp(log_p) * (log_p - log_q), axis=-1))


def test_the_loss_is_zero_when_the_student_outputs_what_the_teacher_does():
    teacher_a, teacher_b = (random_predictions(jax.random.PRNGKey(i), 2, 12, 16) for i in (0, 1))
    loss, metrics = distillation.distillation_loss(
        teacher_a, teacher_b, teacher_a, teacher_b, distillation.DistillConfig()
    )
    assert float(loss) == pytest.approx(0.0, abs=1e-5)
    assert all(float(v) == pytest.approx(0.0, abs=1e-5) for v in metrics.values())


def test_each_term_equals_its_numpy_formula_for_a_student_narrower_than_its_teacher():
    """Student descriptors 8-d, teacher's 16-d: the relational term needs no common width."""
    config = distillation.DistillConfig(beta_score=2.0, beta_position=3.0, beta_descriptor=5.0)
    s_a, s_b = (random_predictions(jax.random.PRNGKey(i), 1, 10, 8) for i in (2, 3))
    t_a, t_b = (random_predictions(jax.random.PRNGKey(i), 1, 10, 16) for i in (4, 5))
    loss, metrics = distillation.distillation_loss(s_a, s_b, t_a, t_b, config)
    n = jax.tree.map(lambda x: np.asarray(x[0], np.float64), (s_a, s_b, t_a, t_b))
    (sa, sb, ta, tb) = n
    score = np.mean((sa.scores - ta.scores) ** 2) + np.mean((sb.scores - tb.scores) ** 2)

    def position(s, t):
        distance = np.linalg.norm(s.keypoints - t.keypoints, axis=-1)
        return np.sum(t.scores * distance) / np.sum(t.scores)

    positions = position(sa, ta) + position(sb, tb)
    tau = config.temperature
    student = sa.descriptors @ sb.descriptors.T / tau
    teacher = ta.descriptors @ tb.descriptors.T / tau
    descriptor = 0.5 * (numpy_kl_rows(teacher, student) + numpy_kl_rows(teacher.T, student.T))
    np.testing.assert_allclose(float(metrics["distill/score"]), score, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["distill/position"]), positions, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["distill/descriptor"]), descriptor, rtol=1e-4)
    np.testing.assert_allclose(
        float(loss), 2.0 * score + 3.0 * positions + 5.0 * descriptor, rtol=1e-4
    )


def test_the_position_term_has_a_finite_gradient_where_student_and_teacher_agree():
    points = jnp.array([[1.0, 2.0], [3.0, 4.0]])
    grad = jax.grad(lambda p: distillation.position_loss(p, points, jnp.ones(2)))(points)
    assert np.all(np.isfinite(np.asarray(grad)))


def teacher_file(tmp_path, name="teacher.npz", poison=False):
    """A small paper-architecture teacher (SMALL_MODEL) as a weights file; ``poison`` puts a
    NaN in one of its arrays."""
    variables = step_lib.init_variables(jax.random.PRNGKey(3), SMALL_MODEL)
    if poison:
        leaves, tree = jax.tree.flatten(variables)
        leaves[0] = leaves[0].at[0].set(jnp.nan)
        variables = jax.tree.unflatten(tree, leaves)
    path = tmp_path / name
    inference.save_weights(path, variables, SMALL_MODEL)
    return path


def fast_student(tmp_path, **changes):
    """The tiny run with the fast backbone as the student of the SMALL_MODEL teacher."""
    return conftest.tiny_config(
        SMALL_FAST, (32, 48), 4, **{"distill.teacher": str(teacher_file(tmp_path)), **changes}
    )


def test_a_step_trains_the_student_and_leaves_the_teacher_as_it_was(tmp_path):
    config = fast_student(tmp_path)
    teacher = step_lib.load_teacher(config)
    before = jax.tree.map(np.array, teacher.variables)
    step = step_lib.jit_train_step(config, step_lib.data_mesh())
    state = step_lib.create_state(config)
    start = jax.tree.map(np.array, state.params)
    images = np.asarray(jax.random.randint(jax.random.PRNGKey(0), (2, 32, 48, 3), 0, 255), np.uint8)
    state, metrics = step(state, images)
    assert float(metrics["distill/total"]) > 0 and float(metrics["finite"]) == 1.0
    jax.tree.map(np.testing.assert_array_equal, jax.tree.map(np.array, teacher.variables), before)
    assert any(
        not np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(start), jax.tree.leaves(jax.device_get(state.params)))
    )


def test_a_resumed_distillation_run_continues_bit_exactly(tmp_path):
    config = fast_student(tmp_path)
    interrupted = tmp_path / "interrupted"
    train.fit(config, interrupted, progress=False, num_steps=2)
    resumed = train.fit(config, interrupted, progress=False, num_steps=4)
    straight = train.fit(config, tmp_path / "straight", progress=False, num_steps=4)
    assert int(resumed.step) == int(straight.step) == 4
    for a, b in zip(
        jax.tree.leaves(jax.device_get(resumed.params)),
        jax.tree.leaves(jax.device_get(straight.params)),
    ):
        np.testing.assert_array_equal(a, b)


def test_a_distillation_run_reads_its_teacher_once(tmp_path, monkeypatch):
    """The check before the workdir is made loads the teacher; the step reuses it."""
    config = fast_student(tmp_path)
    reads = []
    load_named = step_lib.load_named
    monkeypatch.setattr(step_lib, "load_named", lambda *a: reads.append(a) or load_named(*a))
    train.fit(config, tmp_path / "run", progress=False, num_steps=1)
    assert len(reads) == 1


def test_distillation_only_ignores_the_paper_losses(tmp_path):
    """``distill.alpha_self=0``: the loss is the distillation term alone."""
    config = fast_student(tmp_path, **{"distill.alpha_self": 0.0})
    step = step_lib.jit_train_step(config, step_lib.data_mesh())
    images = np.full((2, 32, 48, 3), 90, np.uint8)
    images[:, 8:20, 10:30] = 200
    _, metrics = step(step_lib.create_state(config), images)
    assert float(metrics["loss"]) == pytest.approx(float(metrics["distill/total"]), rel=1e-6)


@pytest.mark.parametrize("kind", ["missing", "nan", "not-weights"])
def test_a_bad_teacher_is_one_line_and_exit_2_and_leaves_no_workdir(kind, tmp_path, capsys):
    if kind == "missing":
        teacher, message = tmp_path / "nowhere.npz", "does not exist"
    elif kind == "nan":
        teacher, message = teacher_file(tmp_path, poison=True), "NaN"
    else:
        teacher = tmp_path / "junk.npz"
        teacher.write_bytes(b"not a zip archive")
        message = "not a readable"
    workdir = tmp_path / "run"
    assert main(train_args(workdir, 2, *TINY_RUN, "--teacher", str(teacher))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "teacher" in err[0] and message in err[0]
    assert not workdir.exists()


def test_the_teacher_flag_names_shipped_weights_in_the_run_config(tmp_path, capsys):
    from usp_jax.training import config as config_lib

    config = config_lib.assemble("cpu", teacher="paper")
    assert config.distill.teacher == "paper"
    assert step_lib.load_teacher(config).model.backbone == "vgg"
