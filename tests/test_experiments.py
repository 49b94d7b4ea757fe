"""The experiments' recipes (loaded as config files) and the analysis behind their tables:
Table 1's configurations and relative changes, bootstrap intervals, breakdowns by view and
rotation. Everything is imported through the package; scripts are only run."""

import ast
import dataclasses
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from usp_jax.evaluation import analysis, paper_tables, statistics
from usp_jax.evaluation.protocol import METRICS
from usp_jax.training import metrics as metrics_lib
from usp_jax.training import step as step_lib

EXPERIMENTS = pathlib.Path(__file__).parents[1] / "experiments"


def recipe(spec):
    """``experiments/FILE.py[:FUNCTION]`` as ``usp-jax train --config`` loads it."""
    from usp_jax import config as config_lib

    return config_lib.load(str(EXPERIMENTS / spec))


def docstring(name):
    """The module docstring of ``experiments/NAME.py``, read as text."""
    return ast.get_docstring(ast.parse((EXPERIMENTS / f"{name}.py").read_text()))


def test_table1_configurations_switch_exactly_the_three_modules():
    base = recipe("table1.py:c4")
    assert base.model.interpolate_descriptors and base.loss.alpha_uni_xy == 100.0
    assert base.loss.alpha_decorr == 0.03 and base.num_steps == 2000
    assert base.optim.decay_steps == 2000
    c0 = recipe("table1.py:c0")
    assert not c0.model.interpolate_descriptors
    assert c0.loss.alpha_uni_xy == 0.0 and c0.loss.alpha_decorr == 0.0
    # Everything else is the C4 run's: same data, descriptor weights and score term.
    assert c0.data == base.data and c0.loss.lambda_d == base.loss.lambda_d
    assert c0.loss.alpha_uni_score == base.loss.alpha_uni_score
    assert c0.loss.alpha_score_mean == base.loss.alpha_score_mean == 1.0
    c2 = recipe("table1.py:c2")
    assert c2.loss.alpha_uni_xy == 100.0 and c2.loss.alpha_decorr == 0.0


def test_table1_changes_are_percent_of_c0_with_lower_le_counted_as_better():
    c0 = {"rs": 0.5, "le": 2.0, "ha1": 0.2, "ha3": 0.4, "ha5": 0.5, "ms": 0.25}
    c1 = {**c0, "rs": 0.55, "le": 1.5, "ms": 0.2}
    changes = statistics.relative_changes({"C0": c0, "C1": c1})
    assert changes["C0"] == pytest.approx(dict.fromkeys(c0, 0.0))
    assert changes["C1"]["rs"] == pytest.approx(10.0)
    assert changes["C1"]["le"] == pytest.approx(25.0)
    assert changes["C1"]["ms"] == pytest.approx(-20.0)


def _rows(config, values):
    """Evaluation rows (``evaluation.to_json``'s "pairs") of one configuration, one per value."""
    metrics = ("rs", "le", "ha1", "ha3", "ha5", "ms")
    return [{"method": config, **dict.fromkeys(metrics, v)} for v in values]


def test_table1_bootstrap_is_paired_so_a_change_on_every_pair_has_a_tight_interval():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 1.0, size=50)
    pairs = statistics.per_pair(_rows("C0", base) + _rows("C1", 1.1 * base))
    intervals = statistics.bootstrap_intervals(pairs, rounds=200)
    # Every resample sees C1 = 1.1 x C0: +10% (LE, lower is better, -10%) with no spread. Drawing
    # the two configurations' pairs independently would spread it by tens of percent.
    assert intervals["C1"]["rs"] == pytest.approx((10.0, 10.0))
    assert intervals["C1"]["le"] == pytest.approx((-10.0, -10.0))
    assert intervals["C0"]["ms"] == pytest.approx((0.0, 0.0))


def test_table1_bootstrap_interval_widens_with_pair_to_pair_noise_and_skips_undefined_le():
    rng = np.random.default_rng(1)
    base = rng.uniform(0.2, 1.0, size=80)
    noisy = base * rng.uniform(0.8, 1.3, size=80)
    rows = _rows("C0", base) + _rows("C1", noisy)
    rows[0]["le"] = None
    intervals = statistics.bootstrap_intervals(statistics.per_pair(rows), rounds=500)
    low, high = intervals["C1"]["rs"]
    point = 100.0 * (noisy.mean() - base.mean()) / base.mean()
    assert low < point < high and high - low > 2.0
    assert np.isfinite(intervals["C1"]["le"]).all()


def test_table1_markdown_puts_the_papers_numbers_beside_ours():
    values = {"rs": 0.5, "le": 2.0, "ha1": 0.2, "ha3": 0.4, "ha5": 0.5, "ms": 0.25}
    summary = {name: values for name in paper_tables.CONFIGS}
    changes = statistics.relative_changes(summary)
    intervals = {name: dict.fromkeys(values, (-1.0, 2.0)) for name in paper_tables.CONFIGS}
    lines = paper_tables.table1_markdown(
        summary, changes, intervals, steps=10, pairs=3
    ).splitlines()
    assert lines[2].startswith("| C0 base |  |  |  | 0.500 (0.633) | 2.000 (0.898) |")
    assert "| +0.0% (+15.3%)<br>[-1.0, +2.0] |" in lines[4]  # C2, HA e=1
    assert lines[-3].startswith("| C4 UnsuperPoint | x | x | x | 0.500 (0.612) |")


def test_table1_report_renders_again_from_its_own_json():
    values = {"rs": 0.5, "le": 2.0, "ha1": 0.0, "ha3": 1.0, "ha5": 1.0, "ms": 0.25}
    evaluated = {
        "summary": {name: {"all": {**values, "pairs": 2}} for name in paper_tables.CONFIGS},
        "pairs": [row for name in paper_tables.CONFIGS for row in _rows(name, [0.5, 0.5])],
    }
    training = {
        name: dict.fromkeys(paper_tables.TRAINING_STATS, 0.5) for name in paper_tables.CONFIGS
    }
    written, table = paper_tables.report(evaluated, steps=7, training=training)
    written = json.loads(json.dumps(written))
    assert written["evaluation"] == evaluated
    assert (
        table
        == paper_tables.report(written["evaluation"], written["steps"], written["training"])[1]
    )
    assert "7 steps each from scratch, seed 0; 2 held-out pairs" in table
    assert "| C3 | 0.500 | 0 | 0.500 | 0.500 | 0.500 |" in table
    # C0 scored HA e=1 on no pair: its change is undefined, not a division error.
    assert "| n/a (+0.0%) |" in table


def test_table1_table_option_rejects_a_missing_or_old_file_in_one_line(tmp_path):
    script = str(EXPERIMENTS / "table1.py")
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"steps": 10, "summary": {}, "relative": {}}))
    for path, message in ((tmp_path / "none.json", "no such file"), (old, "no per-pair results")):
        run = subprocess.run(
            [sys.executable, script, "--table", str(path)], capture_output=True, text=True
        )
        assert run.returncode == 2 and message in run.stderr
        assert "Traceback" not in run.stderr


def test_table1_training_stats_average_only_the_runs_last_steps():
    rows = [
        {"step": step, **dict.fromkeys(paper_tables.TRAINING_STATS, float(step))}
        for step in range(20, 1001, 20)
    ]
    stats = paper_tables.training_stats(rows, last=100)
    assert stats["usp/mean_d"] == pytest.approx(np.mean([920, 940, 960, 980, 1000]))


def test_paper_tables_put_the_papers_value_beside_ours():
    ours = {"SIFT": {"all": {"rs": 0.6, "le": None}}, "Mine": {"all": {"rs": 0.7, "le": 1.0}}}
    lines = paper_tables.table(ours, paper_tables.PAPER["240x320"], ("rs", "le"))
    assert lines[2] == "| SIFT | 0.600 (0.451) | - (0.855) |"
    assert lines[3] == "| Mine | 0.700 | 1.000 |"


def test_paper_tables_show_the_upsampled_model_under_the_paper_detector_when_evaluated(tmp_path):
    ours = {"UnsuperPoint": {"all": {"rs": 0.7}}, "SIFT": {"all": {"rs": 0.6}}}
    missing = tmp_path / "heldout_240x320_up2.json"
    assert paper_tables.with_upsampled(ours, missing) == ours
    missing.write_text(json.dumps({"summary": {"UnsuperPoint": {"all": {"rs": 0.8}}}}))
    merged = paper_tables.with_upsampled(ours, missing)
    assert list(merged) == ["UnsuperPoint", paper_tables.UPSAMPLED, "SIFT"]
    lines = paper_tables.table(merged, paper_tables.PAPER["240x320"], ("rs",))
    assert lines[3] == "| UnsuperPoint, upsample 2 | 0.800 |"


def test_speed_table_puts_the_papers_fps_beside_ours_per_batch():
    rows = [
        {"method": "UnsuperPoint", "batch": 1, "height": 240, "width": 320, "fps": 14.06},
        {"method": "UnsuperPoint", "batch": 10, "height": 240, "width": 320, "fps": 13.2},
        {"method": "SIFT", "batch": 1, "height": 480, "width": 640, "fps": 20.0},
    ]
    lines = paper_tables.speed_table({"rows": rows})
    assert lines[2] == "| UnsuperPoint, b1 | 14.1 (119) | - (65) |"
    assert lines[3] == "| UnsuperPoint, b10 | 13.2 (323) | - (90) |"
    assert lines[4] == "| SIFT | - (47) | 20.0 (12) |"


LATER_STAGES = ["stage2", "stage3", "stage6", "stage7", "stage10"]
# The stages at the paper's own crop size.
PAPER_SIZE_STAGES = ["stage6", "stage7", "stage10"]


@pytest.mark.parametrize("later", LATER_STAGES)
def test_a_later_stage_continues_the_first_with_a_new_seed_and_a_schedule_nearly_spent_at_its_last_step(
    later,
):

    first = recipe("paper_network.py")
    stage = recipe(f"paper_network.py:{later}")
    # Same network, so the earlier weights load.
    assert stage.model == first.model
    assert stage.seed != first.seed
    rate = step_lib.learning_rate(stage.optim)
    peak = stage.optim.learning_rate
    assert float(rate(0)) == 0.0
    assert float(rate(stage.optim.warmup_steps)) == pytest.approx(peak)
    # The run stops late on the cosine, where the last steps barely move the weights.
    assert float(rate(stage.num_steps - 1)) < 0.05 * peak
    assert stage.optim.warmup_steps + stage.optim.decay_steps >= stage.num_steps


@pytest.mark.parametrize("later", LATER_STAGES[:2])
def test_the_128x160_stages_train_on_the_first_stages_crops_and_losses(later):

    first = recipe("paper_network.py")
    stage = recipe(f"paper_network.py:{later}")
    assert (stage.data, stage.loss) == (first.data, first.loss)


@pytest.mark.parametrize("later", PAPER_SIZE_STAGES)
def test_the_paper_size_stages_keep_the_pixel_scale_of_the_128x160_crops_and_the_papers_loss(later):
    from usp_jax import config as config_lib

    first = recipe("paper_network.py")
    stage = recipe(f"paper_network.py:{later}")
    assert (stage.data.height, stage.data.width) == (240, 320)
    # Output pixels per unit of the photo's extent: the same range of content scales.
    assert np.allclose(
        np.divide(stage.data.width, stage.data.scale_range),
        np.divide(first.data.width, first.data.scale_range),
    )
    # At the paper's size the paper's descriptor weights hold the balance the 128x160 stages
    # rescaled lambda_d and alpha_desc for.
    assert stage.loss == config_lib.paper().loss
    assert stage.batch_size == config_lib.paper().batch_size


def test_the_lighting_stage_adds_gamma_and_wider_intensity_changes_and_changes_nothing_else():
    import dataclasses

    from usp_jax import config as config_lib

    stage7 = recipe("paper_network.py:stage7")
    stage10 = recipe("paper_network.py:stage10")
    # Every stage before trained on the default: linear changes of up to 30 %, no gamma.
    assert stage7.photometric == config_lib.paper().photometric
    assert (stage7.photometric.gamma, stage7.photometric.brightness) == (0.0, 0.3)
    assert (
        stage10.photometric.gamma,
        stage10.photometric.brightness,
        stage10.photometric.contrast,
    ) == (0.5, 0.5, 0.5)
    assert (
        dataclasses.replace(stage10.photometric, gamma=0.0, brightness=0.3, contrast=0.3)
        == stage7.photometric
    )
    assert (stage10.model, stage10.loss, stage10.homography, stage10.data) == (
        stage7.model,
        stage7.loss,
        stage7.homography,
        stage7.data,
    )


def test_each_stage_has_its_own_seed_so_it_sees_other_crops_and_homographies():

    names = ("get_config", *LATER_STAGES)
    seeds = [recipe(f"paper_network.py:{name}").seed for name in names]
    assert len(set(seeds)) == len(seeds)


def test_chained_stages_share_one_step_axis_and_a_resumed_steps_later_row_wins():
    first = [{"step": 1, "loss": 9.0}, {"step": 2, "loss": 8.0}, {"step": 3, "loss": 7.0}]
    # Killed after step 2's checkpoint at step 3, resumed: step 3 is logged again.
    second = [
        {"step": 1, "loss": 6.0},
        {"step": 2, "loss": 5.0},
        {"step": 3, "loss": 4.5},
        {"step": 2, "loss": 5.5},
        {"step": 3, "loss": 4.0},
    ]
    rows, starts = metrics_lib.chain_stages([first, second])
    assert [row["step"] for row in rows] == [1, 2, 3, 4, 5, 6]
    assert [row["loss"] for row in rows] == [9.0, 8.0, 7.0, 6.0, 5.5, 4.0]
    assert starts == [3]


def _pair_row(method, split, k, corner_error, scene="v_a", **metrics):
    """A row as ``usp-jax evaluate --json`` writes it: a failed estimate's corner error is null."""
    ha = {f"ha{eps}": float(corner_error is not None and corner_error <= eps) for eps in (1, 3, 5)}
    base = {"rs": 0.5, "le": 1.0, **ha, "ms": 0.5}
    return {
        "method": method,
        "scene": scene,
        "split": split,
        "k": k,
        "corner_error": corner_error,
        **base,
        **metrics,
    }


def test_by_view_averages_each_viewpoint_strength_and_a_failed_estimate_counts_as_infinite():
    rows = [
        _pair_row("M", "v", 2, 0.5),
        _pair_row("M", "v", 2, 2.0, le=None),
        _pair_row("M", "v", 3, 4.0),
        _pair_row("M", "v", 3, None),
        _pair_row("M", "i", 2, 9.0),  # illumination pairs are not viewpoint strengths
    ]
    table = analysis.by_view(rows)
    assert list(table["M"]) == [2, 3]
    assert table["M"][2]["pairs"] == 2
    assert (table["M"][2]["ha1"], table["M"][2]["ha3"], table["M"][2]["ha5"]) == (0.5, 1.0, 1.0)
    assert table["M"][2]["median_corner_error"] == pytest.approx(1.25)
    assert table["M"][2]["le"] == 1.0  # the undefined LE is skipped, not counted as 0
    assert (table["M"][3]["ha3"], table["M"][3]["ha5"]) == (0.0, 0.5)
    assert table["M"][3]["median_corner_error"] == float("inf")


def test_paired_change_of_a_new_model_is_exact_when_every_pair_moves_alike():
    scenes = [f"v_{i}" for i in range(30)]
    base = [
        _pair_row("UnsuperPoint", "v", 2, 1.0, scene=s, ms=0.2 + 0.02 * i)
        for i, s in enumerate(scenes)
    ]
    # Listed in another order, with a baseline's row in between: pairs are matched by scene.
    new = [_pair_row("ORB", "v", 2, 1.0, scene="v_0")] + [
        {**row, "ms": 1.1 * row["ms"]} for row in reversed(base)
    ]
    change = statistics.paired_change(base, new, rounds=200)
    assert change["ms"][0] == pytest.approx(10.0)
    assert change["ms"][1] == pytest.approx((10.0, 10.0))
    assert change["rs"][0] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="same pairs"):
        statistics.paired_change(base, new[:-1])


def test_paired_difference_is_the_mean_difference_with_lower_le_counted_as_better():
    base = [
        _pair_row("UnsuperPoint", "v", 2, 1.0, scene=f"v_{i}", ms=0.02 * i, le=1.0 + 0.1 * i)
        for i in range(30)
    ]
    new = [{**row, "ms": row["ms"] + 0.05, "le": row["le"] - 0.2} for row in reversed(base)]
    difference = statistics.paired_difference(base, new, rounds=200)
    assert difference["ms"][0] == pytest.approx(0.05)
    assert difference["ms"][1] == pytest.approx((0.05, 0.05))  # every pair moved alike
    assert difference["le"][0] == pytest.approx(0.2)  # 0.2 px lower: better
    noisy = [{**row, "ms": row["ms"] + (0.1 if i % 2 else -0.1)} for i, row in enumerate(base)]
    low, high = statistics.paired_difference(base, noisy, rounds=500)["ms"][1]
    assert low < 0.0 < high and high - low > 0.02
    with pytest.raises(ValueError, match="same pairs"):
        statistics.paired_difference(base, new[:-1])


def test_in_plane_rotation_reads_opencvs_rotation_and_the_local_jacobian_of_a_keystone():
    import cv2

    rotation = np.vstack([cv2.getRotationMatrix2D((159.5, 119.5), 30.0, 1.3), [0, 0, 1]])
    # OpenCV's positive angle turns the image counter-clockwise on screen.
    assert analysis.in_plane_rotation(rotation, (240, 320)) == pytest.approx(-30.0)
    # Under perspective the angle is that of the Jacobian at the centre, here by finite differences.
    keystone = np.array([[1.0, 0.1, 5.0], [0.2, 0.9, -3.0], [4e-4, -3e-4, 1.0]]) @ rotation
    centre, step = np.array([159.5, 119.5]), 1e-3
    points = np.array([centre, centre + [step, 0], centre + [0, step]])[None]
    moved = cv2.perspectiveTransform(points, keystone)[0]
    jacobian = np.stack([moved[1] - moved[0], moved[2] - moved[0]], axis=1) / step
    expected = np.degrees(
        np.arctan2(jacobian[1, 0] - jacobian[0, 1], jacobian[0, 0] + jacobian[1, 1])
    )
    assert analysis.in_plane_rotation(keystone, (240, 320)) == pytest.approx(expected, abs=1e-3)


def test_by_rotation_groups_viewpoint_pairs_by_the_rotation_of_their_homography(tmp_path):
    import cv2

    image = np.zeros((60, 80, 3), np.uint8)
    angles = {2: 5.0, 3: -25.0, 4: 12.0}
    for scene in ("v_a", "i_a"):
        (tmp_path / scene).mkdir()
        for k in (1, *angles):
            cv2.imwrite(str(tmp_path / scene / f"{k}.ppm"), image)
        for k, angle in angles.items():
            h = np.vstack([cv2.getRotationMatrix2D((39.5, 29.5), angle, 1.0), [0, 0, 1]])
            np.savetxt(tmp_path / scene / f"H_1_{k}", h)
    rows = [
        _pair_row("M", "v", 2, 0.5, scene="v_a"),
        _pair_row("M", "v", 3, None, scene="v_a"),
        _pair_row("M", "v", 4, 2.0, scene="v_a"),
        _pair_row("M", "i", 3, 0.1, scene="i_a"),
    ]
    table = analysis.by_rotation(rows, tmp_path)
    assert list(table["M"]) == ["0-10", "10-20", ">=20"]  # in order of the ranges, not of the text
    assert [s["pairs"] for s in table["M"].values()] == [1, 1, 1]  # the "i" pair is not counted
    assert table["M"][">=20"]["ha5"] == 0.0 and table["M"]["0-10"]["ha1"] == 1.0
    with pytest.raises(ValueError, match="lacks 1 evaluated pairs"):
        analysis.by_rotation(rows + [_pair_row("M", "v", 5, 1.0, scene="v_a")], tmp_path)


def test_inlier_residuals_measure_the_ransac_inliers_against_the_true_homography():
    from usp_jax import evaluation

    points = np.array([[10.0, 10.0], [50.0, 20.0], [30.0, 60.0], [70.0, 70.0]])
    shift = np.array([[1.0, 0, 4], [0, 1, 0], [0, 0, 1]])  # x + 4
    # Image 2's points: three exactly where H puts them (one 3 px off in y), and an outlier.
    second = evaluation.project_points(points, shift) + [[0, 0], [0, 3], [0, 0], [40, 0]]
    matching = evaluation.Matching(
        matches=np.array([[0, 0], [1, 1], [2, 2], [3, 3]]),
        inliers=np.array([True, True, True, False]),
        homography=shift,
    )
    row = analysis.inlier_residuals(points, second, matching, shift, (100, 200))
    assert row["inliers"] == 3
    assert row["rms"] == pytest.approx(np.sqrt(9 / 3))
    assert row["over_2px"] == pytest.approx(1 / 3)
    # The three inliers' triangle (shoelace): |40 * 50 - 20 * 10| / 2 = 900 px of 100 x 200.
    assert row["coverage"] == pytest.approx(900 / 20000)
    assert (row["offset_x"], row["offset_y"]) == pytest.approx((0.0, 1.0))  # the 3 px, over 3
    none = evaluation.Matching(np.zeros((0, 2), np.int64), np.zeros(0, bool), None)
    empty = analysis.inlier_residuals(points, second, none, shift, (100, 200))
    assert np.isnan(empty["rms"]) and np.isnan(empty["offset_x"]) and empty["coverage"] == 0


def test_the_fast_recipe_trains_the_fast_network_in_the_paper_networks_two_crop_regimes():
    from usp_jax import config as config_lib

    stage1 = config_lib.load(str(EXPERIMENTS / "fast.py"))
    finetune = config_lib.load(f"{EXPERIMENTS / 'fast.py'}:finetune")
    assert stage1.model.backbone == finetune.model.backbone == "fast"
    # Stage 1 at the first paper stage's crops and rescaled descriptor weights; stage 2 at the
    # paper's own size and loss, with the pixel scale of the first.
    paper_stage1 = recipe("paper_network.py")
    assert (stage1.data, stage1.loss) == (paper_stage1.data, paper_stage1.loss)
    assert (finetune.data.height, finetune.data.width) == (240, 320)
    assert finetune.loss == config_lib.paper().loss
    assert stage1.seed != finetune.seed
    for stage in (stage1, finetune):
        assert stage.optim.decay_steps + stage.optim.warmup_steps == stage.num_steps
        assert stage.photometric.gamma == 0.5


def test_a_config_file_function_is_named_after_a_colon_and_a_missing_one_is_a_clear_error():
    from usp_jax import config as config_lib

    with pytest.raises(ValueError, match="defines no nothing()"):
        config_lib.load(f"{EXPERIMENTS / 'fast.py'}:nothing")
    with pytest.raises(FileNotFoundError, match="neither a preset"):
        config_lib.load(f"{EXPERIMENTS / 'absent.py'}:finetune")


def test_mean_intervals_resample_the_pairs_alike_for_every_method_and_skip_undefined_le():
    rng = np.random.default_rng(3)
    ms = rng.uniform(0.2, 0.8, 40)
    le = np.where(np.arange(40) % 4 == 0, np.nan, rng.uniform(0.5, 1.5, 40))
    pairs = {
        "A": {m: ms if m == "ms" else le if m == "le" else np.full(40, 0.7) for m in METRICS},
        "B": {m: ms + 0.1 if m == "ms" else np.full(40, 0.7) for m in METRICS},
    }
    table = statistics.mean_intervals(pairs, rounds=300, seed=5)
    # Known answer: the same draws done by hand.
    draws = np.random.default_rng(5).integers(0, 40, size=(300, 40))
    expected = np.percentile(ms[draws].mean(axis=1), [2.5, 97.5])
    assert table["A"]["ms"][0] == pytest.approx(ms.mean())
    assert table["A"]["ms"][1] == pytest.approx(tuple(expected))
    assert table["B"]["ms"][1] == pytest.approx(tuple(expected + 0.1))  # the same draws
    assert table["A"]["le"][0] == pytest.approx(np.nanmean(le))
    mean, (low, high) = table["A"]["rs"]
    assert mean == pytest.approx(0.7) and high - low == pytest.approx(0.0)  # no spread, no width


def test_compare_intervals_add_the_second_files_model_as_its_own_row(tmp_path):
    base = [
        _pair_row(m, "v", 2, 1.0, scene=f"v_{i}") for i in range(6) for m in ("UnsuperPoint", "ORB")
    ]
    new = [{**r, "ms": 0.9} for r in base if r["method"] == "UnsuperPoint"]
    (tmp_path / "fast").mkdir()
    for path, rows in ((tmp_path / "a.json", base), (tmp_path / "fast" / "b.json", new)):
        path.write_text(json.dumps({"pairs": rows}))
    run = subprocess.run(
        [sys.executable, str(EXPERIMENTS / "compare.py"), str(tmp_path / "a.json")]
        + ["--against", str(tmp_path / "fast" / "b.json"), "--intervals", "--rounds", "50"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "| ORB | 0.500 [0.500, 0.500] |" in run.stdout
    assert "| UnsuperPoint [fast] | 0.500 [0.500, 0.500] |" in run.stdout
    assert "0.900 [0.900, 0.900] |\n" in run.stdout  # its MS, the last column
    assert "ms    +80.0%" in run.stdout and "difference +0.400" in run.stdout


def test_compare_refuses_files_whose_ha_is_over_different_ransac_orders(tmp_path):
    rows = [_pair_row("UnsuperPoint", "v", 2, 1.0, scene="v_0")]
    for name, orders in (("a.json", 1), ("b.json", 20)):
        (tmp_path / name).write_text(
            json.dumps({"config": {"ransac_orders": orders}, "pairs": rows})
        )
    run = subprocess.run(
        [sys.executable, str(EXPERIMENTS / "compare.py"), str(tmp_path / "a.json")]
        + ["--against", str(tmp_path / "b.json")],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert "different numbers of RANSAC orders" in run.stderr and "b.json: 20" in run.stderr


def test_compare_versus_baselines_pools_draws_of_the_same_scenes_pair_by_pair(tmp_path):
    # Two draws of the same four scenes: ORB fails every pair of the first and none of the
    # second, the --against model none of either, so over the 8 pooled pairs its HA@3 is 0.5
    # above ORB's. Illumination rows stay out of the comparison.
    def draw(orb_error):
        base = [_pair_row("ORB", "v", 2, orb_error, scene=f"v_{i}") for i in range(4)]
        base += [_pair_row("ORB", "i", 2, 9.0, scene="i_0")]
        # The first file's own model (an older one) is not a baseline.
        base += [_pair_row("UnsuperPoint", r["split"], 2, 9.0, scene=r["scene"]) for r in base]
        new = [_pair_row("UnsuperPoint", "v", 2, 1.0, scene=f"v_{i}", ms=0.7) for i in range(4)]
        return base, new + [_pair_row("UnsuperPoint", "i", 2, 1.0, scene="i_0")]

    paths = []
    for index, orb_error in enumerate((9.0, 1.0)):
        for name, rows in zip(("base", "new"), draw(orb_error)):
            paths.append(tmp_path / f"{name}{index}.json")
            paths[-1].write_text(json.dumps({"pairs": rows}))
    command = [sys.executable, str(EXPERIMENTS / "compare.py"), str(paths[0])]
    run = subprocess.run(
        command
        + ["--against", str(paths[1]), "--versus-baselines", "--rounds", "50"]
        + ["--pool", str(paths[2]), str(paths[3])],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "8 viewpoint pairs of 2 draw(s)" in run.stdout
    table = run.stdout.split("viewpoint pairs of 2 draw(s)")[1]
    row = next(line for line in table.splitlines() if line.startswith("| ORB |"))
    ha1, ha3, ha5, ms = row.split(" | ")[1:]
    assert ha3.startswith("+0.500 [") and ms.startswith("+0.200 [+0.200, +0.200]")
    refused = subprocess.run(
        command + ["--pool", str(paths[2]), str(paths[3])], capture_output=True, text=True
    )
    assert refused.returncode == 2 and "give --against" in refused.stderr
    # A pooled draw whose two files hold different pairs: one line, no traceback.
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"pairs": [_pair_row("UnsuperPoint", "v", 2, 1.0, scene="v_9")]}))
    mismatched = subprocess.run(
        command
        + ["--against", str(paths[1]), "--versus-baselines"]
        + ["--pool", str(paths[2]), str(other)],
        capture_output=True,
        text=True,
    )
    assert mismatched.returncode == 2 and "Traceback" not in mismatched.stderr
    assert "a draw's two files differ in their pairs" in mismatched.stderr


def _zoomed_pairs(root, zooms):
    """A pairs folder whose scene v_i's pair (1, 2) is zoomed by zooms[i] about image 1's centre."""
    import cv2

    image = np.zeros((60, 80, 3), np.uint8)
    for i, zoom in enumerate(zooms):
        scene = root / f"v_{i}"
        scene.mkdir(parents=True)
        for k in (1, 2):
            cv2.imwrite(str(scene / f"{k}.ppm"), image)
        centre = np.array([[1, 0, 39.5], [0, 1, 29.5], [0, 0, 1]])
        np.savetxt(scene / "H_1_2", centre @ np.diag([zoom, zoom, 1]) @ np.linalg.inv(centre))
    return root


def test_compare_versus_baselines_breaks_pooled_draws_down_by_zoom_with_a_folder_per_draw(
    tmp_path,
):
    # Two draws of four scenes, two zoomed out (0.5x) and two in (2x) in each: ORB fails the
    # zoomed-in pairs only, the --against model none, so it is 1.0 above ORB on HA@3 at >=1.41
    # over 4 pooled pairs and level below 0.71.
    folders = [_zoomed_pairs(tmp_path / f"pairs{d}", (0.5, 0.5, 2.0, 2.0)) for d in range(2)]
    paths = []
    for draw in range(2):
        base = [_pair_row("ORB", "v", 2, 1.0 if i < 2 else 9.0, scene=f"v_{i}") for i in range(4)]
        new = [_pair_row("UnsuperPoint", "v", 2, 1.0, scene=f"v_{i}") for i in range(4)]
        # The first file's own model (an older one) is not a baseline.
        base += [_pair_row("UnsuperPoint", "v", 2, 9.0, scene=f"v_{i}") for i in range(4)]
        for name, rows in (("base", base), ("new", new)):
            paths.append(tmp_path / f"{name}{draw}.json")
            paths[-1].write_text(json.dumps({"pairs": rows}))
    command = [sys.executable, str(EXPERIMENTS / "compare.py"), str(paths[0])]
    command += ["--against", str(paths[1]), "--versus-baselines", "--rounds", "50"]
    command += ["--pool", str(paths[2]), str(paths[3])]
    run = subprocess.run(
        command + ["--zoom", *map(str, folders)], capture_output=True, text=True, check=True
    )

    def orb_ha3(label):
        table = run.stdout.split(f"zoom {label}: ")[1]
        assert "4 viewpoint pairs of 2 draw(s)" in table.split("\n")[0]
        row = next(line for line in table.splitlines() if line.startswith("| ORB |"))
        return row.split(" | ")[2]

    assert orb_ha3("<0.71").startswith("+0.000 [+0.000, +0.000]")
    assert orb_ha3(">=1.41").startswith("+1.000 [+1.000, +1.000]")
    assert "zoom 0.71-1" not in run.stdout  # empty bins are left out
    # One folder for two draws: one line naming the count, no traceback.
    refused = subprocess.run(
        command + ["--zoom", str(folders[0]), str(folders[0]), str(folders[1])],
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2 and "one per draw (2), got 3" in refused.stderr


def test_compare_prints_the_rotation_table_of_every_method_in_30_degree_ranges_up_to_180(tmp_path):
    import cv2

    image = np.zeros((60, 80, 3), np.uint8)
    angles = {2: 5.0, 3: -40.0, 4: 95.0, 5: 170.0, 6: -180.0}
    (tmp_path / "v_a").mkdir()
    for k in (1, *angles):
        cv2.imwrite(str(tmp_path / "v_a" / f"{k}.ppm"), image)
    for k, angle in angles.items():
        h = np.vstack([cv2.getRotationMatrix2D((39.5, 29.5), angle, 1.0), [0, 0, 1]])
        np.savetxt(tmp_path / "v_a" / f"H_1_{k}", h)
    methods = ("UnsuperPoint", "ORB", "SIFT")
    rows = [
        _pair_row(m, "v", k, 1.0 if m == "SIFT" else 9.0, scene="v_a")
        for m in methods
        for k in angles
    ]
    table = analysis.by_rotation(rows, tmp_path)
    assert list(table) == list(methods)
    for ranges in table.values():
        assert list(ranges) == ["0-30", "30-60", "90-120", "150-180"]  # empty ranges left out
        assert [s["pairs"] for s in ranges.values()] == [1, 1, 1, 2]
    assert table["SIFT"]["150-180"]["ha3"] == 1.0 and table["ORB"]["150-180"]["ha3"] == 0.0
    # The command prints one row per method and range.
    results = tmp_path / "results.json"
    results.write_text(json.dumps({"pairs": rows}))
    (tmp_path / "turned").mkdir()  # a second model's evaluation joins as one more method
    (tmp_path / "turned" / "r.json").write_text(json.dumps({"pairs": rows[: len(angles)]}))
    run = subprocess.run(
        [sys.executable, str(EXPERIMENTS / "compare.py"), str(results)]
        + ["--rotation", str(tmp_path), "--against", str(tmp_path / "turned" / "r.json")],
        capture_output=True,
        text=True,
        check=True,
    )
    printed = run.stdout.split("| rotation (deg) |")[1]
    for method in (*methods, "UnsuperPoint [turned]"):
        for label in ("0-30", "30-60", "90-120", "150-180"):
            assert f"| {method} | {label} | " in printed


def test_upright_pairs_keep_the_fine_rotation_ranges():
    assert analysis.rotation_ranges([3.0, -25.0, 37.0]) == analysis.ROTATION_RANGES
    assert analysis.rotation_ranges([3.0, -61.0]) == analysis.WIDE_ROTATION_RANGES


def test_the_rotation_config_is_the_fast_recipe_turned_over_the_full_circle():
    from usp_jax import config as config_lib
    from usp_jax.core.model import fast_config

    stages = [
        config_lib.load(str(EXPERIMENTS / spec))
        for spec in ("rotation.py", "rotation.py:finetune", "rotation.py:finetune2")
    ]
    for cfg in stages:
        assert cfg.model == fast_config() and cfg.data.context_window
        assert cfg.homography.rotation_range == (-180.0, 180.0)
        assert cfg.homography.rotation_distribution == "uniform"
    sizes = [(c.data.height, c.data.width) for c in stages]
    assert sizes == [(128, 160), (240, 320), (240, 320)]
    # Stage 3 is stage 2 on a longer cosine with new draws, nothing else.
    undone = {"seed": stages[1].seed, "num_steps": 1500, "optim": stages[1].optim}
    assert dataclasses.replace(stages[2], **undone) == stages[1]
    doc = " ".join(docstring("rotation").replace("\\\n", " ").split())  # as a shell reads it
    for command in (
        "usp-jax train --config experiments/rotation.py --data data/corpus/train --workdir runs/rotation",
        "usp-jax export --checkpoint runs/rotation --save-weights runs/rotation-stage1.npz",
        "usp-jax train --config experiments/rotation.py:finetune --init runs/rotation-stage1.npz "
        "--data data/corpus/train --workdir runs/rotation-finetune",
        "usp-jax export --checkpoint runs/rotation-finetune2 --save-weights usp_jax/weights/rotation.npz",
        "usp-jax train --config experiments/rotation.py:paper --data data/corpus/train "
        "--workdir runs/rotation-paper",
    ):
        assert command in doc
    # The paper network's version: its own stages 1 and 6, turned the same way.
    for spec, upright, size in (
        ("rotation.py:paper", "paper_network.py", (128, 160)),
        ("rotation.py:paper_finetune", "paper_network.py:stage6", (240, 320)),
    ):
        cfg, base = (config_lib.load(str(EXPERIMENTS / s)) for s in (spec, upright))
        assert cfg.model == base.model == config_lib.paper().model and cfg.data.context_window
        assert (cfg.data.height, cfg.data.width) == size and cfg.loss == base.loss
        assert cfg.homography == stages[0].homography and cfg.photometric.gamma == 0.5
    # Measured with 4,000 draws (analysis.training_rotations): half the pairs turn by 90 degrees or more.
    angles = analysis.training_rotations(
        stages[0].homography, 128, 160, draws=400, window=stages[0].data.example_shape[:2]
    )
    assert 0.4 < np.mean(np.abs(angles) >= 90) < 0.6
