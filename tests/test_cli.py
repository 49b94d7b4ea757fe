import json

import cv2
import jax
import numpy as np
import pytest
from conftest import TINY_RUN, USP_JAX, child_env, train_args

from usp_jax import evaluation
from usp_jax.cli import main, parse_args
from usp_jax.evaluation.plotting import DPI, PANEL_INCHES
from usp_jax.inference import turning
from usp_jax.inference import weights as weights_lib


@pytest.fixture(scope="module")
def pairs_dir(tmp_path_factory, photo):
    root = tmp_path_factory.mktemp("cli")
    images = root / "photos"
    images.mkdir()
    cv2.imwrite(str(images / "astronaut.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    assert (
        main(
            [
                "make-pairs",
                "--images",
                str(images),
                "--out",
                str(root / "pairs"),
                "--size",
                "120x160",
                "--no-progress",
            ]
        )
        == 0
    )
    return root / "pairs"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    work = tmp_path_factory.mktemp("run")
    assert main(train_args(work, 2, *TINY_RUN)) == 0
    return work


def test_make_pairs_writes_hpatches_layout(pairs_dir):
    assert sorted(p.name for p in pairs_dir.iterdir()) == [
        "i_astronaut",
        "make-pairs.json",
        "v_astronaut",
    ]
    assert (pairs_dir / "v_astronaut" / "H_1_6").exists()


def test_make_pairs_rotation_flags_turn_the_viewpoint_pairs(photo, tmp_path):
    from usp_jax.evaluation.pairs import pair_rotations

    images = tmp_path / "photos"
    images.mkdir()
    small = cv2.resize(photo, (160, 160), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(images / "astronaut.png"), cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    common = [
        "make-pairs",
        "--images",
        str(images),
        "--size",
        "60x80",
        "--views",
        "3",
        "--no-progress",
    ]
    assert main([*common, "--out", str(tmp_path / "listed"), "--rotation-angles", "180", "90"]) == 0
    assert main([*common, "--out", str(tmp_path / "drawn"), "--rotation", "180"]) == 0
    for name, options in (
        ("listed", dict(rotation_angles=[180, 90])),
        ("drawn", dict(rotation=180)),
    ):
        turns = pair_rotations(0, 3, **options)
        for k, turn in zip((2, 3), turns):
            homography = np.loadtxt(tmp_path / name / "v_astronaut" / f"H_1_{k}")
            # The rotation of H's Jacobian at the centre, with cv2.getRotationMatrix2D's sign.
            centre = np.array([39.5, 29.5])
            moved = cv2.perspectiveTransform(
                np.array([[centre, centre + [0.01, 0], centre + [0, 0.01]]]), homography
            )[0]
            jacobian = np.stack([moved[1] - moved[0], moved[2] - moved[0]], axis=1) / 0.01
            angle = -np.degrees(
                np.arctan2(jacobian[1, 0] - jacobian[0, 1], jacobian[0, 0] + jacobian[1, 1])
            )
            assert abs((angle - turn + 180) % 360 - 180) < 40  # the view's own turn and keystone
    assert sorted(pair_rotations(0, 3, rotation_angles=[180, 90])) == [90, 180]


def test_match_across_any_rotation_turns_image_2_back_and_recovers_the_homography(
    photo, tmp_path, capsys
):
    small = cv2.cvtColor(cv2.resize(photo, (256, 256)), cv2.COLOR_RGB2BGR)
    truth = np.vstack([cv2.getRotationMatrix2D((127.5, 127.5), 120, 0.9), [0, 0, 1]])
    first, second, out = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "m.json"
    cv2.imwrite(str(first), small)
    cv2.imwrite(str(second), cv2.warpPerspective(small, truth, (256, 256)))
    argv = ["match", str(first), str(second), "--top", "500", "--json", str(out)]
    assert main([*argv, "--any-rotation"]) == 0
    assert "image 2 turned back by " in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["turned_back_degrees"] == pytest.approx(-120, abs=3)
    assert evaluation.corner_error(truth, np.array(result["homography"]), (256, 256)) < 3
    assert main([*argv, "--no-turn-back"]) == 0  # without a turning option nothing is turned
    assert json.loads(out.read_text())["turned_back_degrees"] is None
    assert main(argv) == 0  # 120 degrees: past what --turn-back's upright matches can read
    assert json.loads(out.read_text())["turned_back_degrees"] == 0.0
    # A guide given as a weights file works like the shipped name it was copied from.
    guide = tmp_path / "guide.npz"
    guide.write_bytes((weights_lib.WEIGHTS_DIR / "rotation.npz").read_bytes())
    assert main([*argv, "--any-rotation", "--guide", str(guide)]) == 0
    assert json.loads(out.read_text())["turned_back_degrees"] == result["turned_back_degrees"]
    assert main([*argv, "--any-rotation", "--guide", str(tmp_path / "missing.npz")]) == 2
    assert main([*argv, "--guide", str(guide)]) == 2  # a guide without --any-rotation
    assert "--guide is only used with --any-rotation" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--rotation", "90", "--rotation-angles", "0", "90"], "not allowed with"),
        (["--rotation", "ninety"], "invalid float"),
    ],
)
def test_make_pairs_rotation_flags_are_parsed_strictly(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(["make-pairs", "--images", "x", "--out", "y", *argv])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


def test_evaluate_ransac_orders_reach_the_protocol_and_the_json(pairs_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    argv = ["evaluate", "--hpatches", str(pairs_dir), "--baselines-only", "--baselines", "orb"]
    assert main([*argv, "--ransac-orders", "3", "--json", str(out), "--no-progress"]) == 0
    assert "HA: share of 3 random orders" in capsys.readouterr().out
    assert json.loads(out.read_text())["config"]["ransac_orders"] == 3
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--ransac-orders", "0"])
    assert exit_info.value.code == 2
    assert "--ransac-orders" in capsys.readouterr().err


def test_evaluate_baselines_prints_table_and_writes_json(pairs_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--hpatches",
                str(pairs_dir),
                "--baselines-only",
                "--baselines",
                "sift,orb",
                "--json",
                str(out),
                "--plots",
                str(tmp_path / "plots"),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "SIFT" in capsys.readouterr().out
    summary = json.loads(out.read_text())["summary"]
    assert {"SIFT", "ORB"} <= set(summary)
    # Baselines get headroom over the top 300, so the shared-view filter leaves ORB its 300
    # points on every viewpoint pair (SIFT finds fewer than 300 in some of these small views).
    assert summary["ORB"]["v"]["num_points"] == 300
    # Plots of the first method, here a baseline.
    assert [p.name for p in (tmp_path / "plots").glob("*_matches.png")] == [
        "SIFT_v_astronaut_1_6_matches.png"
    ]


@pytest.mark.slow
def test_train_resumes_and_the_checkpoint_detects_and_evaluates(
    workdir, pairs_dir, tmp_path, photo, capsys
):
    assert main(train_args(workdir, 4, *TINY_RUN)) == 0
    assert "done: step 4" in capsys.readouterr().out
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), photo[:100, :150])
    out = tmp_path / "k.json"
    detect = ["detect", str(image), "--checkpoint", str(workdir), "--top", "20", "--json", str(out)]
    assert main([*detect, "--out", str(tmp_path / "k.png")]) == 0
    result = json.loads(out.read_text())
    assert len(result["keypoints"]) == 20 and len(result["descriptors"][0]) == 16
    # With radius-4 NMS no two of the kept points lie within 4 px of each other.
    assert main([*detect, "--nms", "4"]) == 0
    spread = np.asarray(json.loads(out.read_text())["keypoints"])
    gaps = np.linalg.norm(spread[:, None] - spread[None], axis=-1) + 1e9 * np.eye(len(spread))
    assert gaps.min() > 4
    # One panel of the one image, not the image twice as "reference" and "target".
    assert cv2.imread(str(tmp_path / "k.png")).shape[1] == PANEL_INCHES * DPI
    evaluate = ["evaluate", "--hpatches", str(pairs_dir), "--checkpoint", str(workdir)]
    evaluate += ["--no-progress"]
    assert main([*evaluate, "--baselines", "orb", "--plots", str(tmp_path / "plots")]) == 0
    assert "UnsuperPoint" in capsys.readouterr().out
    assert list((tmp_path / "plots").glob("*_matches.png"))
    assert main([*evaluate, "--baselines", "", "--upsample", "2"]) == 0
    assert "model on 2x enlarged images" in capsys.readouterr().out
    assert main([*evaluate, "--baselines", "", "--any-rotation"]) == 0
    assert "model matching across any rotation" in capsys.readouterr().out


def test_match_recovers_a_known_homography_between_a_photo_and_its_warp(photo, tmp_path, capsys):
    # A 20 degree rotation with some scale and keystone: the shipped weights' matches and RANSAC
    # should land within the protocol's 3 px at the corners, image 2 turned back by the turn the
    # upright matches read (the default; --no-turn-back: test_match_across_any_rotation_...).
    truth = cv2.getRotationMatrix2D((256, 256), 20, 0.9)
    truth = np.vstack([truth, [2e-4, -1e-4, 1]])
    first, second = tmp_path / "a.png", tmp_path / "b.jpg"
    cv2.imwrite(str(first), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    cv2.imwrite(
        str(second), cv2.warpPerspective(cv2.cvtColor(photo, cv2.COLOR_RGB2BGR), truth, (512, 512))
    )
    out = tmp_path / "m.json"
    assert (
        main(
            [
                "match",
                str(first),
                str(second),
                "--top",
                "500",
                "--json",
                str(out),
                "--out",
                str(tmp_path / "m.png"),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "RANSAC inliers" in printed and "homography image1 -> image2" in printed
    result = json.loads(out.read_text())
    turn = turning.in_plane_rotation(truth, (512, 512))  # the keystone adds 2.5 degrees
    assert result["turned_back_degrees"] == pytest.approx(turn, abs=1)
    assert len(result["matches"]) == len(result["inliers"]) >= sum(result["inliers"]) >= 20
    error = evaluation.corner_error(truth, np.array(result["homography"]), (512, 512))
    assert error < 3
    assert (tmp_path / "m.png").stat().st_size > 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "--data", "{tmp}/missing", "--workdir", "{tmp}/w", "--steps", "1"], "missing"),
        (
            ["train", "--data", "sample", "--workdir", "{tmp}/w", "loss.nope=1"],
            "unknown config key",
        ),
        (["train", "--data", "sample", "--workdir", "{tmp}/w", "batch_size=five"], "batch_size"),
        (["evaluate", "--hpatches", "{tmp}/nothing", "--baselines-only"], "nothing"),
        (
            ["evaluate", "--hpatches", "{tmp}", "--baselines-only", "--guide", "rotation"],
            "--guide is only used with --any-rotation",
        ),
        (
            [
                "evaluate",
                "--hpatches",
                "{tmp}",
                "--baselines-only",
                "--turn-back",
                "--any-rotation",
            ],
            "give one",
        ),
        (["detect", "{tmp}/absent.png", "--checkpoint", "{tmp}/none"], "none"),
        (["evaluate", "--hpatches", "{tmp}", "--checkpoint", "{tmp}/gone.npz"], "gone.npz"),
        (["match", "{tmp}/absent.png", "{tmp}/other.png"], "absent.png"),
        (["make-pairs", "--images", "{tmp}/void", "--out", "{tmp}/o"], "void"),
        (["make-pairs", "--images", "{tmp}", "--out", "{tmp}/o", "--rotation", "200"], "[0, 180]"),
        (["export", "--checkpoint", "{tmp}/none", "--save-weights", "{tmp}/w.npz"], "none"),
        (["detect", "{tmp}/absent.png", "--weights", "vgg"], "the shipped weights are paper"),
        (["benchmark", "--weights", "tiny"], "unknown weights 'tiny'"),
        (["demo", "--out", "{tmp}/d", "--weights", "best"], "unknown weights 'best'"),
        (["export", "--weights", "x", "--save-weights", "{tmp}/w.npz"], "unknown weights 'x'"),
    ],
)
def test_user_errors_are_one_line_with_exit_status_2(argv, message, tmp_path, capsys):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith("usp-jax")


def test_export_writes_weights_and_an_artifact_that_load_without_the_model(
    workdir, tmp_path, photo
):
    from usp_jax import inference

    weights, artifact = tmp_path / "w.npz", tmp_path / "detector.bin"
    assert (
        main(
            [
                "export",
                "--checkpoint",
                str(workdir),
                "--save-weights",
                str(weights),
                "--artifact",
                str(artifact),
                "--res",
                "64x96",
                "--top",
                "10",
            ]
        )
        == 0
    )
    config, variables = inference.load_weights(weights)
    assert config.descriptor_dim == 16 and weights.stat().st_size > 0
    image = photo[:64, :96]
    expected = inference.Detector.from_checkpoint(workdir).detect(image, top_n=10)
    (exported,) = inference.load_exported(artifact)(image[None])
    np.testing.assert_allclose(exported.keypoints, expected.keypoints, atol=1e-3)
    # The exported weights file is itself a --checkpoint.
    image_file, out = tmp_path / "a.png", tmp_path / "k.json"
    cv2.imwrite(str(image_file), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    assert (
        main(
            [
                "detect",
                str(image_file),
                "--checkpoint",
                str(weights),
                "--top",
                "10",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    from_file = inference.Detector(variables, config).detect(image, top_n=10)
    np.testing.assert_allclose(
        json.loads(out.read_text())["keypoints"], from_file.keypoints, atol=1e-5
    )


def test_train_overrides_may_sit_between_options_in_the_order_given():
    args = parse_args(
        ["train", "seed=1", "--workdir", "w", "data.height=64", "--steps", "9", "data.width=96"]
    )
    assert args.overrides == ["seed=1", "data.height=64", "data.width=96"]
    assert (args.workdir, args.steps) == ("w", 9)


@pytest.mark.parametrize("value", ["0", "1.5", "two"])
def test_upsample_below_one_or_not_an_integer_is_a_parser_error(value, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(["detect", "a.png", "--upsample", value])
    assert exit_info.value.code == 2
    assert "is not a positive integer" in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--workdir", "w", "seed=1", "--stesp", "9"],
        ["evaluate", "--hpatches", "x", "seed=1"],
    ],
)
def test_a_misspelt_option_or_an_override_outside_train_is_a_parser_error(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2
    assert "unrecognized arguments" in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluate", "--hpatches", "x", "--top", "0"], "'0' is not a positive integer"),
        (["evaluate", "--hpatches", "x", "--top", "-1"], "'-1' is not a positive integer"),
        (["evaluate", "--hpatches", "x", "--res", "0x320"], "at least 8 px"),
        (["make-pairs", "--images", "x", "--out", "y", "--views", "0"], "positive integer"),
        (["benchmark", "--batch", "1", "0"], "positive integer"),
        (["match", "a.png", "b.png", "--max-side", "-5"], "'-5' is not a non-negative integer"),
    ],
)
def test_sizes_and_counts_below_one_are_rejected_by_the_parser(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.slow
def test_demo_runs_offline_on_the_shipped_weights_and_writes_its_pngs(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    # Its steps count from 1, and every column of its table is explained in one line.
    steps = [err.find(f"[{k}/3]") for k in (1, 2, 3)]
    assert -1 not in steps and steps == sorted(steps)
    legend = out.split("\n\n")[-1].splitlines()
    for column in ("RS", "LE", "HA", "MS"):
        assert sum(line.startswith(f"{column}") for line in legend) == 1
    assert "weights shipped with usp-jax" in out and "never saw" in out
    assert all(name in out for name in ("UnsuperPoint", "ORB", "SIFT"))
    assert len(list(tmp_path.glob("UnsuperPoint_v_*_keypoints.png"))) == 1
    assert len(list(tmp_path.glob("UnsuperPoint_v_*_matches.png"))) == 1
    # One header above the table, and every PNG written is announced.
    assert out.count("240x320, top 300 points") == 1
    for png in tmp_path.glob("*.png"):
        assert f"wrote {png}" in out


@pytest.mark.parametrize(
    "command",
    [
        ["detect", "a.png"],
        ["match", "a.png", "b.png"],
        ["evaluate", "--hpatches", "p"],
        ["benchmark"],
        ["export"],
    ],
)
def test_weights_name_and_checkpoint_exclude_each_other(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args([*command, "--weights", "fast", "--checkpoint", "runs/x"])
    assert exit_info.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_detect_with_named_weights_uses_that_network(photo, tmp_path, monkeypatch):
    from usp_jax import inference
    from usp_jax.core.model import fast_config, init_variables

    # A second named network, as the fast one will ship: random weights suffice to tell them apart.
    config = fast_config(
        backbone_channels=(4, 8, 8, 16),
        head_channels=8,
        descriptor_head_channels=8,
        descriptor_dim=32,
    )
    inference.save_weights(
        tmp_path / "fast.npz", init_variables(jax.random.PRNGKey(0), config), config
    )
    monkeypatch.setitem(inference.PRETRAINED, "fast", str(tmp_path / "fast.npz"))
    image = tmp_path / "photo.png"
    cv2.imwrite(str(image), cv2.cvtColor(photo[:240, :320], cv2.COLOR_RGB2BGR))
    out = {}
    for name in ("paper", "fast"):
        out[name] = tmp_path / f"{name}.json"
        assert (
            main(["detect", str(image), "--weights", name, "--top", "50", "--json", str(out[name])])
            == 0
        )
    dims = {name: len(json.loads(path.read_text())["descriptors"][0]) for name, path in out.items()}
    assert dims == {"paper": 256, "fast": 32}


@pytest.mark.slow
def test_verbose_flag_shows_usp_jax_info_lines_although_imports_install_a_root_handler(tmp_path):
    import subprocess

    def train(*flags):
        # A fresh interpreter: the package's imports run before the CLI configures logging.
        return subprocess.run(
            [*USP_JAX, *flags, *train_args(tmp_path / "w", len(flags) + 1, *TINY_RUN)],
            capture_output=True,
            text=True,
            timeout=600,
            env=child_env(),
        )

    quiet = train()
    assert quiet.returncode == 0 and "INFO" not in quiet.stderr
    verbose = train("-v")  # resumes the first run
    assert verbose.returncode == 0, verbose.stderr
    assert "INFO usp_jax.training.train: resumed from step 1" in verbose.stderr
    assert "INFO absl" not in verbose.stderr
