"""The ``usp-jax`` command: train, evaluate, make-pairs, benchmark, detect, match, export and demo.
Each command parses its options, checks its outputs can be written, and calls the Python API.

Every failure a user can cause (a missing folder, a corrupt image, a bad override, an
unwritable output, a full disk) ends in one line on stderr and exit status 2, never a
traceback; options are checked before anything is written. An internal error (a bug) still
shows its traceback.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import math
import os
import pathlib
import signal
import sys
import tempfile
import traceback

import numpy as np

from usp_jax.inference.detector import MAX_SIDE

_USER_ERRORS = (FileNotFoundError, ValueError, NotADirectoryError, IsADirectoryError)
# OSErrors a user's paths or disk cause: reported in one line like the errors above.
_USER_ERRNOS = frozenset(
    {
        errno.ENOENT,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.ENOSPC,
        errno.EDQUOT,
        errno.EEXIST,
        errno.ENOTDIR,
        errno.EISDIR,
        errno.ENAMETOOLONG,
        errno.EFBIG,
        errno.ELOOP,
    }
)
# The largest --upsample and --res side: beyond, the activations alone outgrow any memory.
MAX_UPSAMPLE = 8

MAX_RESOLUTION = 16384


def _resolution(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution {text!r} is not HxW, e.g. 240x320") from None
    if min(height, width) < 8:  # one 8x8 cell at least
        raise argparse.ArgumentTypeError(f"resolution {text!r} needs H and W of at least 8 px")
    if max(height, width) > MAX_RESOLUTION:
        raise argparse.ArgumentTypeError(
            f"resolution {text!r} exceeds {MAX_RESOLUTION} px on a side"
        )
    return height, width


def _radius(text: str) -> float:
    """An NMS radius: a finite number of pixels >= 0 (``1e9`` is fine: one point survives)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a radius in px (a finite number >= 0)")
    return value


def _upsample(text: str) -> int:
    value = _positive(text)
    if value > MAX_UPSAMPLE:
        raise argparse.ArgumentTypeError(f"{text!r} is above {MAX_UPSAMPLE}")
    return value


def _integer_at_least(minimum: int, kind: str):
    """An argparse ``type`` accepting integers >= ``minimum``, with a one-line message."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {kind} integer")
        return value

    return parse


_positive = _integer_at_least(1, "positive")
_non_negative = _integer_at_least(0, "non-negative")


def _add_upsample(parser) -> None:
    # SIFT doubles its input for the same reason: the positions come back finer (RESULTS.md).
    parser.add_argument(
        "--upsample",
        type=_upsample,
        default=1,
        metavar="S",
        help="run the network on the image enlarged S times (default 1, the"
        " paper's detector; 2: finer keypoints for 4x the compute)",
    )


def _add_weights_name(parser) -> None:
    parser.add_argument(
        "--weights",
        metavar="NAME",
        help="shipped weights by name (usp_jax.inference.PRETRAINED; an unknown"
        " name lists them); default: the best on the held-out pairs",
    )


def _add_checkpoint(parser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--checkpoint",
        metavar="PATH",
        help="training workdir, one of its checkpoints, or a .npz weights file"
        " from `usp-jax export --save-weights` (default: the shipped weights)",
    )
    _add_weights_name(group)


def _check_output_file(path: str | None, what: str) -> None:
    """Raises ValueError unless ``path`` can be written as a file (checked before any work)."""
    if not path:
        return
    target = pathlib.Path(path).expanduser()
    if target.is_dir():
        raise ValueError(f"{what} {path} is a folder, not a file")
    parent = target.absolute().parent
    if not parent.is_dir():
        raise ValueError(f"{what} {path}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or (
        target.exists() and not os.access(target, os.W_OK)
    ):
        raise ValueError(f"{what} {path} is not writable")


def _check_output_folder(path: str | None, what: str) -> None:
    """Raises ValueError unless ``path`` is, or can be made as, a writable folder."""
    from usp_jax.training.workdir import folder_problem

    problem = folder_problem(path) if path else None
    if problem:
        raise ValueError(f"{what} {path}{problem}")


def _load_detector(args, **options):
    from usp_jax.inference.detector import Detector

    options.setdefault("upsample", getattr(args, "upsample", 1))
    if getattr(args, "weights", None):
        return Detector.pretrained(args.weights, **options)
    return Detector.load(getattr(args, "checkpoint", None) or None, **options)


def cmd_train(args) -> None:
    from usp_jax.training import config as config_lib
    from usp_jax.training import train
    from usp_jax.training.step import check_config

    cfg = config_lib.load(args.config)
    overrides = list(args.overrides)
    if args.data:
        overrides.insert(0, f"data.source={args.data}")
    if args.init:
        overrides.insert(0, f"init_weights={args.init}")
    cfg = config_lib.override(cfg, overrides)
    # --steps N is num_steps=N; both at once must agree (neither silently beats the other).
    if args.steps is not None:
        given = [
            o.split("=", 1)[1].strip()
            for o in overrides
            if o.split("=", 1)[0].strip() == "num_steps"
        ]
        if given and cfg.num_steps != args.steps:
            raise ValueError(
                f"--steps {args.steps} and num_steps={given[-1]} disagree; give one of them"
            )
        cfg = config_lib.override(cfg, [f"num_steps={args.steps}"])
    who = ""
    if _distributed(args):
        from usp_jax.training import distributed

        # Everything a process can check alone is checked before it waits for the others.
        check_config(cfg)
        launch = distributed.Launch(
            args.coordinator,
            args.num_processes,
            args.process_id,
            args.init_timeout,
            args.heartbeat_timeout,
        )
        distributed.check_launch(launch, cfg.batch_size)
        distributed.initialize(launch, report=lambda line: _user_error("train", line))
        import jax

        who = f"process {jax.process_index()} of {jax.process_count()}: "
    print(f"{who}training {args.config} config on {cfg.data.source} into {args.workdir}")
    state = train.fit(
        cfg,
        args.workdir,
        progress=not args.no_progress,
        allow_config_change=args.allow_config_change,
    )
    step, checkpoints = int(state.step), pathlib.Path(args.workdir) / "checkpoints"
    if step < cfg.num_steps:  # a multi-process run stopped together on SIGTERM
        print(
            f"{who}stopped at step {step} of {cfg.num_steps} on SIGTERM, checkpoint saved in"
            f" {checkpoints}; rerun the same command to resume"
        )
        return 128 + signal.SIGTERM  # as if SIGTERM had ended it: the run is not finished
    print(f"{who}done: step {step}; checkpoints in {checkpoints}")
    return 0


def _distributed(args) -> bool:
    """Whether `train` joins a multi-process run: --distributed, or any of its explicit parts."""
    return args.distributed or any(
        value is not None for value in (args.coordinator, args.num_processes, args.process_id)
    )


def cmd_evaluate(args) -> None:
    from usp_jax.evaluation import plotting, protocol

    _check_output_file(args.json, "--json")
    _check_output_folder(args.plots, "--plots")
    detector = None if args.baselines_only else _load_detector(args)
    height, width = args.res
    baselines = [name.strip() for name in args.baselines.split(",") if name.strip()]
    methods = protocol.methods(detector, baselines, args.top)
    results = protocol.evaluate(
        methods,
        args.hpatches,
        height=height,
        width=width,
        top_k=args.top,
        nms=args.nms,
        progress=not args.no_progress,
    )
    enlarged = f", model on {args.upsample}x enlarged images" if args.upsample > 1 else ""
    print(f"{args.hpatches} at {height}x{width}, top {args.top} points, NMS {args.nms}{enlarged}")
    print(protocol.format_table(results))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(protocol.to_json(results), indent=1))
        print(f"wrote {args.json}")
    if args.plots and methods:
        path = plotting.plot_example_pair(
            methods[0], args.hpatches, args.plots, args.res, args.top, args.nms
        )
        print(f"wrote {path}")


def cmd_make_pairs(args) -> None:
    from usp_jax.evaluation.pairs import make_pairs

    _check_output_folder(args.out, "--out")
    scenes = make_pairs(
        args.images,
        args.out,
        seed=args.seed,
        size=args.size,
        num_views=args.views,
        rotation=args.rotation,
        rotation_angles=args.rotation_angles,
        progress=not args.no_progress,
    )
    print(f"wrote {len(scenes)} scenes to {args.out}")


def cmd_benchmark(args) -> None:
    from usp_jax.evaluation import benchmark
    from usp_jax.inference.detector import Detector
    from usp_jax.inference.weights import PRETRAINED

    _check_output_file(args.json, "--json")
    if args.weights or args.checkpoint:
        detector = _load_detector(args)
    else:  # every shipped network, side by side
        detector = {name: Detector.pretrained(name, upsample=args.upsample) for name in PRETRAINED}
    result = benchmark.benchmark(
        detector,
        resolutions=tuple(args.res),
        batch_sizes=tuple(args.batch),
        top_n=args.top,
        repeats=args.repeats,
        include_opencv=not args.no_opencv,
    )
    print(benchmark.format_benchmark(result))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")


def cmd_detect(args) -> None:
    from usp_jax.evaluation import plotting
    from usp_jax.inference.images import read_image

    _check_output_file(args.out, "--out")
    _check_output_file(args.json, "--json")
    detector = _load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    features = detector.detect(image := read_image(args.image), top_n=args.top)
    print(f"{args.image}: {len(features.keypoints)} keypoints")
    if args.out:
        plotting.plot_keypoints(image, features.keypoints, image, features.keypoints, args.out)
        print(f"wrote {args.out}")
    if args.json:
        pathlib.Path(args.json).write_text(
            json.dumps(
                {
                    "keypoints": features.keypoints.tolist(),
                    "scores": features.scores.tolist(),
                    "descriptors": features.descriptors.tolist(),
                }
            )
        )
        print(f"wrote {args.json}")


def cmd_match(args) -> None:
    from usp_jax.evaluation import plotting
    from usp_jax.inference import matching as matching_lib
    from usp_jax.inference.images import read_image

    _check_output_file(args.out, "--out")
    _check_output_file(args.json, "--json")
    detector = _load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    image1, image2 = read_image(args.image1), read_image(args.image2)
    features1, features2 = (detector.detect(image, top_n=args.top) for image in (image1, image2))
    matching = matching_lib.match_and_estimate(features1, features2)
    print(
        f"{len(features1.keypoints)} and {len(features2.keypoints)} keypoints,"
        f" {len(matching.matches)} mutual nearest-neighbour matches,"
        f" {int(matching.inliers.sum())} RANSAC inliers"
        f" ({matching_lib.RANSAC_THRESHOLD:g} px)"
    )
    if matching.homography is None:
        print("no homography: fewer than 4 matches, or RANSAC found none")
    else:
        print("homography image1 -> image2:")
        print(np.array2string(matching.homography, precision=6, suppress_small=True))
    if args.out:
        plotting.plot_matches(
            image1,
            image2,
            features1.keypoints,
            features2.keypoints,
            matching.matches,
            matching.inliers,
            None,
            matching.homography,
            args.out,
        )
        print(f"wrote {args.out}")
    if args.json:
        homography = None if matching.homography is None else matching.homography.tolist()
        pathlib.Path(args.json).write_text(
            json.dumps(
                {
                    "homography": homography,
                    "matches": matching.matches.tolist(),
                    "inliers": matching.inliers.tolist(),
                    "keypoints1": features1.keypoints.tolist(),
                    "keypoints2": features2.keypoints.tolist(),
                }
            )
        )
        print(f"wrote {args.json}")


def cmd_export(args) -> None:
    from usp_jax.inference import export, weights
    from usp_jax.inference.detector import Detector

    if not (args.save_weights or args.artifact):
        raise ValueError("nothing to export: give --save-weights FILE.npz and/or --artifact FILE")
    _check_output_file(args.save_weights, "--save-weights")
    _check_output_file(args.artifact, "--artifact")
    detector = _load_detector(args)
    if args.save_weights:
        weights.save_weights(args.save_weights, detector.variables, detector.model_config)
        print(f"wrote {args.save_weights} (float16)")
    if args.artifact:
        detector = Detector(
            detector.variables,
            detector.model_config,
            top_n=args.top,
            nms_radius=args.nms,
            upsample=detector.upsample,
        )
        export.export(detector, args.artifact, *args.res)
        print(f"wrote {args.artifact} (jax.export, uint8 [b, {args.res[0]}, {args.res[1]}, 3])")


def cmd_demo(args) -> None:
    from usp_jax.quickstart import demo

    _check_output_folder(args.out, "--out")
    demo(args.out, args.weights)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors in one line (the usage is one ``-h`` away), exit status 2."""

    def error(self, message: str):
        text = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {text} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="usp-jax", description="UnsuperPoint keypoints in JAX: train, evaluate, benchmark."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="self-supervised training (resumes an existing workdir)")
    p.add_argument("--data", help="image folder, tfds:NAME[:SPLIT], or 'sample' (bundled photos)")
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
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="KEY=VALUE",
        help="config overrides, e.g. loss.alpha_uni_xy=50 data.height=120",
    )
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("evaluate", help="HPatches/Oxford metrics vs OpenCV baselines")
    _add_checkpoint(p)
    p.add_argument("--hpatches", required=True, help="HPatches- or Oxford-layout folder")
    p.add_argument("--res", type=_resolution, default=(240, 320), help="HxW (default 240x320)")
    p.add_argument("--top", type=_positive, default=300, help="points kept per image")
    p.add_argument("--nms", type=int, default=0, choices=(0, 4), help="NMS radius in px")
    p.add_argument("--baselines", default="orb,sift,akaze,brisk")
    p.add_argument("--baselines-only", action="store_true", help="skip the learned model")
    p.add_argument("--json", help="write aggregate and per-pair numbers here")
    p.add_argument("--plots", help="folder for keypoint and match PNGs")
    p.add_argument("--no-progress", action="store_true")
    _add_upsample(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("make-pairs", help="HPatches-layout pairs from any folder of photos")
    p.add_argument("--images", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--size", type=_resolution, default=(480, 640), help="HxW of generated images")
    p.add_argument("--views", type=_positive, default=6)
    p.add_argument("--seed", type=int, default=0)
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
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_make_pairs)

    p = sub.add_parser("benchmark", help="frames per second, model and OpenCV side by side")
    _add_checkpoint(p)
    p.add_argument("--res", type=_resolution, nargs="+", default=[(240, 320), (480, 640)])
    p.add_argument("--batch", type=_positive, nargs="+", default=[1, 10])
    p.add_argument(
        "--top", type=_positive, help="points kept (default: 300 up to 240x320, else 1000)"
    )
    p.add_argument("--repeats", type=_positive, default=10)
    p.add_argument("--no-opencv", action="store_true")
    p.add_argument("--json")
    _add_upsample(p)
    p.set_defaults(func=cmd_benchmark)

    p = sub.add_parser("detect", help="keypoints of one image")
    p.add_argument("image")
    _add_checkpoint(p)
    p.add_argument("--top", type=_positive, default=500)
    # Spread points condition a homography or pose better: radius 4 cut the corner error of
    # the held-out viewpoint pairs by a third (experiments/RESULTS.md).
    p.add_argument(
        "--nms",
        type=_radius,
        default=0.0,
        help="NMS radius in px, default 0 (try 4 for homography or pose estimation)",
    )
    p.add_argument(
        "--max-side",
        type=_non_negative,
        default=MAX_SIDE,
        metavar="PX",
        help=f"detect on a copy at most this long (default {MAX_SIDE}; 0: native size);"
        " keypoints are in the original's pixels",
    )
    p.add_argument("--out", help="PNG with the keypoints drawn")
    p.add_argument("--json", help="keypoints, scores and descriptors as JSON")
    _add_upsample(p)
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("match", help="matches and a RANSAC homography between two images")
    p.add_argument("image1")
    p.add_argument("image2")
    _add_checkpoint(p)
    p.add_argument("--top", type=_positive, default=1000)
    p.add_argument(
        "--nms",
        type=_radius,
        default=4.0,
        help="NMS radius in px, default 4 (spread points condition a homography better)",
    )
    p.add_argument(
        "--max-side",
        type=_non_negative,
        default=MAX_SIDE,
        metavar="PX",
        help=f"detect on copies at most this long (default {MAX_SIDE}; 0: native size)",
    )
    p.add_argument("--out", help="PNG of the inlier matches and image 1's border warped by H")
    p.add_argument("--json", help="homography, matches, inlier mask and keypoints as JSON")
    _add_upsample(p)
    p.set_defaults(func=cmd_match)

    p = sub.add_parser("export", help="float16 weights file or a jax.export inference artifact")
    _add_checkpoint(p)
    p.add_argument(
        "--save-weights",
        metavar="FILE",
        help="write a float16 .npz (what --checkpoint, train --init and Detector.load take)",
    )
    p.add_argument("--artifact", help="write a serialised jax.export detector")
    p.add_argument("--res", type=_resolution, default=(240, 320), help="artifact input HxW")
    p.add_argument("--top", type=_positive, default=1000, help="artifact keeps this many points")
    p.add_argument("--nms", type=_radius, default=0.0, help="artifact NMS radius in px")
    _add_upsample(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("demo", help="the whole pipeline on bundled photos, offline, in minutes")
    p.add_argument(
        "--out",
        default=str(pathlib.Path(tempfile.gettempdir()) / "usp-jax-demo"),
        help="folder for the pairs and PNGs",
    )
    _add_weights_name(p)
    p.set_defaults(func=cmd_demo)
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
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def _user_error(command: str, message: str) -> None:
    """One line on stderr, however long the message (messages may quote multi-line values)."""
    text = " ".join(message.split()) or "failed"
    print(f"usp-jax {command}: error: {text}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Runs the command; returns its exit status (0, 2 for a user error, 130 if interrupted).

    Run as the program (``argv`` None), a user error ends the process at once after its one
    line: the native threads of a checkpoint save that failed (a full disk) may still call back
    into a closed asyncio loop while the interpreter shuts down, each printing a traceback.
    """
    code = _main(argv)
    if argv is None and code == 2:
        sys.stdout.flush()
        sys.stderr.flush()
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, 2)  # the error line is out; native threads' late prints are not
        os._exit(code)
    return code


def _main(argv: list[str] | None) -> int:
    args = parse_args(argv)
    # force: importing orbax and grain (through usp_jax) installs a root handler, which would
    # make basicConfig a no-op and -v silent. -v is about usp-jax's own steps; the libraries'
    # INFO lines (orbax logs every save) stay hidden.
    logging.basicConfig(
        level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", force=True
    )
    logging.getLogger("usp_jax").setLevel(logging.INFO if args.verbose else logging.WARNING)
    # Orbax logs a failed background save (a full disk) as ERRORs with tracebacks from each of
    # its threads; train reports it again as one line naming the last complete checkpoint.
    if not args.verbose:
        logging.getLogger("absl").setLevel(logging.CRITICAL)
    from usp_jax.training import distributed

    try:
        code = args.func(args) or 0
    except BaseException as err:
        code, message = _classify(err)
        if distributed.joined():  # a multi-process run ends in every process
            own = message or (
                f"{type(err).__name__}: {distributed.first_line(err)} (its traceback is in its log)"
            )

            def show(text: str) -> None:
                if text != own:  # another process failed first: its error, not the broken link
                    _user_error(args.command, text)
                elif message is None:
                    traceback.print_exc()
                else:
                    _show(args.command, code, message)

            distributed.leave_after_failure(code, own, show)
        if message is None:
            raise
        _show(args.command, code, message)
        return code
    return code


def _classify(err: BaseException) -> tuple[int, str | None]:
    """(exit status, one-line message) of a failure; the message is None for an internal error
    (a bug), which shows its traceback instead."""
    from usp_jax.training.distributed import DistributedError
    from usp_jax.training.metrics import TrainingDiverged
    from usp_jax.training.workdir import WorkdirError

    if isinstance(err, KeyboardInterrupt):
        return 130, "interrupted"
    user = isinstance(err, (*_USER_ERRORS, TrainingDiverged, WorkdirError, DistributedError))
    if user or (isinstance(err, OSError) and err.errno in _USER_ERRNOS):
        named = isinstance(err, OSError) and err.filename and err.strerror
        return 2, f"{err.filename}: {err.strerror}" if named else str(err)
    return 1, None


def _show(command: str, code: int, message: str) -> None:
    if code == 130:
        print(f"usp-jax {command}: {message}", file=sys.stderr)
    else:
        _user_error(command, message)
