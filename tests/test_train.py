import json
import pathlib
import subprocess
import sys

import conftest
import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from usp_jax import config as config_lib
from usp_jax.core import augment, geometry
from usp_jax.core.model import ModelConfig
from usp_jax.training import checkpoint, crops, train
from usp_jax.training import metrics as metrics_lib
from usp_jax.training import step as step_lib

SMALL_MODEL = ModelConfig(
    backbone_channels=(8, 8, 16, 16, 16, 16, 32, 32), head_channels=32, descriptor_dim=32
)


def tiny_config(**changes) -> config_lib.Config:
    """conftest's tiny run with this module's larger network, on 48x64 crops for 4 steps."""
    return conftest.tiny_config(SMALL_MODEL, (48, 64), 4, **changes)


def params_of(state):
    return jax.tree.leaves(jax.device_get(state.params))


def mean_of(rows, key):
    return float(np.mean([r[key] for r in rows]))


def test_short_run_on_real_photos_lowers_the_loss(tmp_path):
    cfg = tiny_config(
        num_steps=60,
        checkpoint_every=60,
        batch_size=4,
        **{"data.height": 64, "data.width": 96, "optim.learning_rate": 3e-3},
    )
    train.fit(cfg, tmp_path, progress=False)
    rows = metrics_lib.read_metrics(tmp_path)
    assert [r["step"] for r in rows] == list(range(1, 61))
    assert mean_of(rows[-10:], "loss") < 0.8 * mean_of(rows[:10], "loss")
    assert (tmp_path / "config.json").exists() and list((tmp_path / "tensorboard").iterdir())


def test_fitting_one_real_photo_pair_pulls_its_point_pairs_together(tmp_path, photo):
    """With one photo and a fixed T (no random scale, rotation, perspective or translation) the
    step has a fixed target: d_k must fall and point-pairs appear. (On random pairs d_k only
    falls after thousands of steps, once the network has learnt repeatable features.)"""
    folder = tmp_path / "photo"
    folder.mkdir()
    image = cv2.resize(photo, (96, 96), interpolation=cv2.INTER_AREA)[16:80]
    cv2.imwrite(str(folder / "a.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    cfg = tiny_config(
        num_steps=60,
        checkpoint_every=60,
        **{
            "data.source": str(folder),
            "data.height": 64,
            "data.width": 96,
            "data.scale_range": "(1.0, 1.0)",
            "optim.learning_rate": 3e-3,
            "homography.scaling": 0,
            "homography.max_angle": 0,
            "homography.perspective": 0,
            "homography.translation": 0,
        },
    )
    train.fit(cfg, tmp_path / "run", progress=False)
    rows = metrics_lib.read_metrics(tmp_path / "run")
    # Measured: mean d_k 2.40 -> 0.87 px and K 50 -> 70 (first vs last 10 steps).
    assert mean_of(rows[-10:], "usp/mean_d") < 0.6 * mean_of(rows[:10], "usp/mean_d")
    assert mean_of(rows[-10:], "usp/K") > 1.15 * mean_of(rows[:10], "usp/K")
    assert mean_of(rows[-10:], "loss") < 0.6 * mean_of(rows[:10], "loss")


def test_resuming_equals_an_uninterrupted_run(tmp_path):
    cfg = tiny_config()
    interrupted = tmp_path / "interrupted"
    train.fit(cfg, interrupted, progress=False, num_steps=2)
    resumed = train.fit(cfg, interrupted, progress=False, num_steps=4)
    straight = train.fit(cfg, tmp_path / "straight", progress=False, num_steps=4)
    assert int(resumed.step) == int(straight.step) == 4
    for a, b in zip(params_of(resumed), params_of(straight)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_learning_rate_follows_warmup_then_cosine_decay_to_zero():
    cfg = config_lib.OptimConfig(learning_rate=1e-3, warmup_steps=10, decay_steps=100)
    schedule = step_lib.learning_rate(cfg)
    steps = np.array([0, 5, 10, 35, 60, 110, 500])
    after = np.clip(steps - 10, 0, 100)
    expected = np.where(steps < 10, 1e-3 * steps / 10, 0.5e-3 * (1 + np.cos(np.pi * after / 100)))
    np.testing.assert_allclose([float(schedule(s)) for s in steps], expected, rtol=1e-5, atol=1e-9)
    constant = step_lib.learning_rate(config_lib.OptimConfig(learning_rate=2e-3))
    assert float(constant(0)) == float(constant(10**6)) == pytest.approx(2e-3)


def test_negative_schedule_lengths_are_a_clear_error():
    with pytest.raises(ValueError, match="optim.decay_steps must be >= 0"):
        tiny_config(**{"optim.decay_steps": -5})


def test_parameters_stop_moving_once_the_rate_has_decayed_to_zero(tmp_path):
    # Steps 1-2 use rates 1 and 0.5 of the peak, steps 3-4 rate 0.
    cfg = tiny_config(**{"optim.decay_steps": 2})
    two = train.fit(cfg, tmp_path / "two", progress=False, num_steps=2)
    four = train.fit(cfg, tmp_path / "four", progress=False, num_steps=4)
    first = train.fit(cfg, tmp_path / "one", progress=False, num_steps=1)
    for a, b, c in zip(params_of(two), params_of(four), params_of(first)):
        np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, c) for a, c in zip(params_of(two), params_of(first)))


def test_a_save_killed_midway_resumes_from_the_last_complete_checkpoint(tmp_path):
    cfg = tiny_config()
    train.fit(cfg, tmp_path, progress=False, num_steps=2)
    # What a process killed while writing step 4 leaves: orbax's temporary folder, never renamed.
    partial = tmp_path / "checkpoints" / "4.orbax-checkpoint-tmp-1234"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "garbage").write_bytes(b"\0" * 10)
    assert checkpoint.manager(tmp_path / "checkpoints").latest_step() == 2
    state = train.fit(cfg, tmp_path, progress=False, num_steps=4)
    assert int(state.step) == 4


def test_non_finite_loss_stops_with_a_message_and_keeps_the_last_good_checkpoint(tmp_path):
    train.fit(tiny_config(), tmp_path, progress=False, num_steps=2)
    exploding = tiny_config(**{"optim.learning_rate": 1e38})
    with pytest.raises(
        metrics_lib.TrainingDiverged, match="non-finite at step .*checkpoint: step 2"
    ):
        train.fit(exploding, tmp_path, progress=False, num_steps=6, allow_config_change=True)
    mngr = checkpoint.manager(tmp_path / "checkpoints")
    assert mngr.latest_step() == 2
    restored = checkpoint.restore_state(mngr, step_lib.create_state(tiny_config()))
    assert all(np.all(np.isfinite(p)) for p in params_of(restored))


def test_missing_data_source_stops_at_once_naming_it(tmp_path):
    cfg = tiny_config(**{"data.source": str(tmp_path / "no-such-folder")})
    with pytest.raises(FileNotFoundError, match="no-such-folder"):
        train.fit(cfg, tmp_path / "run", progress=False)


def test_init_weights_start_the_run_from_an_exported_model(tmp_path):
    from usp_jax import inference

    source = step_lib.create_state(tiny_config(seed=7))
    weights = tmp_path / "start.npz"
    inference.save_weights(
        weights, {"params": source.params, "batch_stats": source.batch_stats}, SMALL_MODEL
    )
    state = step_lib.create_state(tiny_config(seed=0, init_weights=str(weights)))
    # float16 storage: equal to the source within half precision, unlike seed 0's random init.
    for got, want in zip(params_of(state), params_of(source)):
        np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-4)
    assert int(state.step) == 0


def test_init_weights_of_another_network_is_a_clear_error(tmp_path):
    from usp_jax import inference

    other = ModelConfig(
        backbone_channels=(4, 4, 8, 8, 8, 8, 16, 16), head_channels=16, descriptor_dim=16
    )
    weights = tmp_path / "other.npz"
    variables = step_lib.init_variables(jax.random.PRNGKey(0), other)
    inference.save_weights(weights, variables, other)
    with pytest.raises(ValueError, match="network"):
        step_lib.create_state(tiny_config(init_weights=str(weights)))


@pytest.mark.parametrize("bad", ["init", "data"])
def test_a_bad_init_file_or_data_path_stops_the_run_before_it_writes_the_workdir(tmp_path, bad):
    if bad == "init":
        weights = tmp_path / "junk.npz"
        weights.write_bytes(b"not a zip archive")
        cfg, match = tiny_config(init_weights=str(weights)), "not a readable .npz"
    else:
        cfg, match = tiny_config(**{"data.source": str(tmp_path / "missing")}), "missing"
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        train.fit(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_init_weights_load_into_a_run_that_differs_only_in_settings_that_shape_no_weight(tmp_path):
    from usp_jax import inference

    weights = tmp_path / "start.npz"
    source = step_lib.create_state(tiny_config(seed=7))
    inference.save_weights(
        weights, {"params": source.params, "batch_stats": source.batch_stats}, SMALL_MODEL
    )
    changes = {
        "init_weights": str(weights),
        "model.dtype": "bfloat16",
        "model.batch_norm_momentum": 0.99,
        "model.position_init_scale": 1.0,
    }
    state = step_lib.create_state(tiny_config(**changes))
    for got, want in zip(params_of(state), params_of(source)):
        np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-4)


def test_batch_not_divisible_by_devices_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(jax, "device_count", lambda: 4)
    with pytest.raises(ValueError, match="not divisible by the 4 devices"):
        train.fit(tiny_config(batch_size=6), tmp_path, progress=False)


DEVICE_SCRIPT = """
import json, sys
import jax
jax.config.update("jax_num_cpu_devices", int(sys.argv[1]))
import numpy as np
sys.path.insert(0, sys.argv[2])
from test_train import tiny_config
from usp_jax.training import step as step_lib
cfg = tiny_config(batch_size=4)
mesh = step_lib.data_mesh()
step = step_lib.jit_train_step(cfg, mesh)
state = jax.device_put(step_lib.create_state(cfg), jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
images = np.random.default_rng(0).integers(0, 256, size=(3, 4, 48, 64, 3), dtype=np.uint8)
losses, grad_norms = [], []
for batch in images:
    state, metrics = step(state, batch)
    losses.append(float(metrics["loss"]))
    grad_norms.append(float(metrics["grad_norm"]))
print(json.dumps({"devices": jax.device_count(), "losses": losses, "grad_norms": grad_norms}))
"""


def run_on_devices(*counts):
    """DEVICE_SCRIPT's output for each device count, the processes run side by side."""
    # With the tests' compilation cache, so a rerun compiles nothing.
    env = {**conftest.child_env(), "JAX_PLATFORMS": "cpu"}
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", DEVICE_SCRIPT, str(n), str(pathlib.Path(__file__).parent)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for n in counts
    ]
    results = []
    for process in processes:
        out, err = process.communicate()
        assert process.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def test_four_devices_compute_what_one_device_computes():
    one, four = run_on_devices(1, 4)
    assert (one["devices"], four["devices"]) == (1, 4)
    # Same loss and gradient on the first step up to float summation order...
    np.testing.assert_allclose(four["losses"][0], one["losses"][0], rtol=1e-5)
    np.testing.assert_allclose(four["grad_norms"][0], one["grad_norms"][0], rtol=1e-4)
    # ...after which Adam's normalisation amplifies rounding in near-zero gradients a little.
    np.testing.assert_allclose(four["losses"], one["losses"], rtol=5e-3)


def test_collapse_warnings_name_the_collapse_and_its_fix():
    healthy = {"pred/score_std": 0.25, "pred/score_mean": 0.5, "desc/sim_negative": 0.2}
    assert metrics_lib.collapse_warnings(healthy) == {}
    scores = metrics_lib.collapse_warnings(
        {**healthy, "pred/score_std": 0.003, "pred/score_mean": 0.005}
    )
    assert list(scores) == ["scores"] and "alpha_score_mean" in scores["scores"]
    # Near-constant scores at 1/2 are how a run starts before positions are repeatable.
    assert metrics_lib.collapse_warnings({**healthy, "pred/score_std": 0.015}) == {}
    descriptors = metrics_lib.collapse_warnings({**healthy, "desc/sim_negative": 0.97})
    assert list(descriptors) == ["descriptors"] and "lambda_d" in descriptors["descriptors"]
    ramp = metrics_lib.collapse_warnings({**healthy, "pred/score_position_r2": 0.9})
    assert list(ramp) == ["score ramp"] and "alpha_uni_score" in ramp["score ramp"]


def test_score_position_r2_is_one_for_a_ramp_and_small_for_content():
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(15.0)), -1).reshape(1, -1, 2)
    ramp = 0.02 * grid[..., 0] + 0.05 * grid[..., 1]
    assert float(step_lib.score_position_r2(jnp.asarray(ramp), jnp.asarray(grid))) == pytest.approx(
        1.0
    )
    noise = np.random.default_rng(0).uniform(size=ramp.shape)
    assert float(step_lib.score_position_r2(jnp.asarray(noise), jnp.asarray(grid))) < 0.05
    # Matches NumPy's correlation coefficients.
    mixed = ramp + noise
    expected = sum(np.corrcoef(mixed[0], grid[0, :, i])[0, 1] ** 2 for i in (0, 1))
    got = float(step_lib.score_position_r2(jnp.asarray(mixed), jnp.asarray(grid)))
    assert got == pytest.approx(expected, rel=1e-4)


# Identity photometric augmentation, so that branches can be compared with OpenCV pixel by pixel.
NEUTRAL_LIGHT = augment.PhotometricConfig(
    brightness=0, contrast=0, saturation=0, noise_std=0, blur_sigma=0
)


@pytest.mark.parametrize("angle", [90.0, 180.0])
def test_window_branches_turn_b_by_the_sampled_homography_and_fill_it_from_the_whole_window(
    photo, angle
):
    side = crops.context_side(48, 64)
    origin_x, origin_y = geometry.window_origin(48, 64, (side, side))
    # A real photo with no black pixel (so that 0 means "masked"), its top 12 rows padding.
    rgb = 0.1 + 0.9 * cv2.resize(photo, (side, side), interpolation=cv2.INTER_AREA) / 255.0
    alpha = np.ones((side, side), np.float32)
    alpha[:12] = 0
    rgb = (rgb * alpha[..., None]).astype(np.float32)
    windows = jnp.asarray(np.concatenate([rgb, alpha[..., None]], -1)[None])
    pure_turn = geometry.HomographyConfig(
        patch_ratio=1.0,
        scaling=0.0,
        perspective=0.0,
        translation=0.0,
        rotation_range=(angle, angle),
    )
    images_a, images_b, homographies, valid = (
        np.asarray(x)[0]
        for x in step_lib.make_window_branches(
            jax.random.PRNGKey(0), windows, 48, 64, pure_turn, NEUTRAL_LIGHT
        )
    )

    turn = np.vstack([cv2.getRotationMatrix2D((31.5, 23.5), angle, 1.0), [0, 0, 1]])
    np.testing.assert_allclose(homographies, turn, atol=1e-4)
    np.testing.assert_allclose(
        images_a, rgb[origin_y : origin_y + 48, origin_x : origin_x + 64], atol=1e-6
    )
    # B is the whole window seen through T after the crop's offset, as OpenCV renders it; its pixels
    # whose source is padding or outside the window are 0 and invalid.
    from_window = turn @ np.array([[1, 0, -origin_x], [0, 1, -origin_y], [0, 0, 1]])
    expected_valid = cv2.warpPerspective(alpha, from_window, (64, 48)) >= 1 - 1e-3
    expected_b = cv2.warpPerspective(rgb, from_window, (64, 48)) * expected_valid[..., None]
    np.testing.assert_array_equal(valid, expected_valid)
    np.testing.assert_allclose(images_b, expected_b, atol=1e-4)
    assert (images_b[valid] > 0.05).all() and (images_b[~valid] == 0).all()
    # Valid pixels of B show real content from outside A too: what makes any angle possible.
    ys, xs = np.mgrid[0:48, 0:64]
    source = cv2.perspectiveTransform(
        np.stack([xs, ys], -1).reshape(1, -1, 2).astype(np.float64), np.linalg.inv(turn)
    )[0].reshape(48, 64, 2)
    outside_a = (source < -0.5).any(-1) | (source[..., 0] > 63.5) | (source[..., 1] > 47.5)
    if angle == 90.0:
        assert (valid & outside_a).sum() >= 4 * 48 and (~valid).any()
    else:
        assert valid.all() and not outside_a.any()


def test_upright_branches_draw_what_they_drew_before_the_context_window_existed():
    homography = geometry.sample_homography(jax.random.PRNGKey(0), 48, 64)
    np.testing.assert_allclose(
        homography,
        [
            [7.8681439e-01, 3.9201874e-01, -1.7099504e01],
            [-6.0852289e-01, 1.2928408e00, 1.1539849e01],
            [-1.1136544e-02, 9.0182815e-03, 1.0],
        ],
        rtol=1e-5,
        atol=1e-6,
    )
    images = jnp.asarray(np.random.default_rng(0).uniform(size=(2, 48, 64, 3)).astype(np.float32))
    images_a, images_b, _ = step_lib.make_branches(
        jax.random.PRNGKey(1), images, geometry.HomographyConfig(), augment.PhotometricConfig()
    )
    assert float(images_a.sum()) == pytest.approx(10429.866, rel=1e-4)
    assert float(images_b.sum()) == pytest.approx(8377.0986, rel=1e-4)


def test_a_rotation_range_without_context_windows_stops_the_run_before_it_writes_the_workdir(
    tmp_path,
):
    cfg = tiny_config(**{"homography.rotation_range": "(-180, 180)"})
    with pytest.raises(ValueError, match="data.context_window=True"):
        train.fit(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_on_context_windows_trains_and_logs_how_much_of_b_is_real(tmp_path):
    cfg = tiny_config(
        num_steps=2, **{"data.context_window": True, "homography.rotation_range": "(-180, 180)"}
    )
    train.fit(cfg, tmp_path, progress=False)
    rows = metrics_lib.read_metrics(tmp_path)
    assert [r["step"] for r in rows] == [1, 2]
    assert all(np.isfinite(r["loss"]) and 0.5 < r["data/valid_b"] <= 1.0 for r in rows)


def test_ctrl_c_inside_a_step_is_raised_after_the_step_has_returned_its_state():
    import os
    import signal

    from usp_jax.training.interrupts import interrupts_deferred

    finished = []
    # Python's own Ctrl-C handler, whatever the suite inherited (a background job's SIG_IGN).
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(1000):  # the handler runs between bytecodes, here at the latest
                    pass
                finished.append(True)  # the assignment the interrupt must not cut short
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, inherited)
    assert finished == [True]


def test_without_ctrl_c_the_deferred_block_raises_nothing():
    from usp_jax.training.interrupts import interrupts_deferred

    with interrupts_deferred():
        value = 1
    assert value == 1


def test_sigterm_inside_a_step_is_raised_after_it_as_terminated():
    import os
    import signal

    from usp_jax.training.interrupts import Terminated, interrupts_deferred, sigterm_saves

    finished, before = [], signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), sigterm_saves():
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                pass
            finished.append(True)
    assert finished == [True]
    assert signal.getsignal(signal.SIGTERM) is before
