"""The ``usp-jax`` command: train, evaluate, make-pairs, benchmark, detect, match, export, demo,
track and reconstruct.
Each command parses its options, checks its outputs can be written, and calls the Python API.

Every failure a user can cause (a missing folder, a corrupt image, a bad override, an
unwritable output, a full disk) ends in one line on stderr and exit status 2, never a
traceback; options are checked before anything is written. An internal error (a bug) still
shows its traceback.
"""

from __future__ import annotations

import json
import logging
import os
import pathlib
import signal
import sys
import traceback
import warnings

import numpy as np

from usp_jax import cli_errors
from usp_jax.cli_errors import user_error
from usp_jax.cli_options import parse_args


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


def _figure_file(path: str | None, what: str) -> str | None:
    """The file a figure option writes, checked: a bare name gets ``.png``, as matplotlib adds it."""
    if not path:
        return path
    from usp_jax.evaluation.plotting import figure_path

    return _suffixed_file(path, what, figure_path)


def _suffixed_file(path: str | None, what: str, suffixed) -> str | None:
    """The file an option writes when ``suffixed`` may add a suffix to the name given, checked
    as given too: an existing folder is refused, not written beside as ``FOLDER.png``."""
    if not path:
        return path
    _check_output_file(path, what)
    target = str(suffixed(path))
    _check_output_file(target, what)
    return target


def _check_output_folder(path: str | None, what: str) -> None:
    """Raises ValueError unless ``path`` is, or can be made as, a writable folder."""
    from usp_jax.training.workdir import folder_problem

    problem = folder_problem(path) if path else None
    if problem:
        raise ValueError(f"{what} {path}{problem}")


def _load_detector(args, **options):
    from usp_jax.inference.detector import Detector

    options.setdefault("upsample", getattr(args, "upsample", 1))
    options.setdefault("any_scale", getattr(args, "any_scale", False))
    options.setdefault("refine", getattr(args, "refine", None))
    if getattr(args, "weights", None):
        return Detector.pretrained(args.weights, **options)
    return Detector.load(getattr(args, "checkpoint", None) or None, **options)


def _guide(args, checked_only: bool = False, **options):
    """The rotation-invariant guide of ``--any-rotation`` (None without it, or with
    ``checked_only``: the options are only checked), ``--guide``: shipped weights by name, else a
    weights file or training workdir."""
    from usp_jax.inference.detector import Detector
    from usp_jax.inference.weights import PRETRAINED

    if args.guide is not None and not args.any_rotation:
        # Silently ignoring it would hide a forgotten flag.
        raise ValueError("--guide is only used with --any-rotation")
    if checked_only or not args.any_rotation:
        return None
    guide = args.guide or "rotation"
    if guide in PRETRAINED:
        return Detector.pretrained(guide, **options)
    return Detector.load(guide, **options)


def cmd_train(args) -> None:
    from usp_jax.training import config as config_lib
    from usp_jax.training import distributed, train

    cfg = config_lib.assemble(
        args.config,
        data=args.data,
        init=args.init,
        teacher=args.teacher,
        overrides=args.overrides,
        steps=args.steps,
    )
    _check_data_given(args, cfg)
    who = ""
    if _distributed(args):
        launch = distributed.Launch(
            args.coordinator,
            args.num_processes,
            args.process_id,
            args.init_timeout,
            args.heartbeat_timeout,
        )
        who = distributed.join(launch, cfg, report=lambda line: user_error("train", line))
    print(
        f"{who}training {args.config} config on {cfg.data.source} into {args.workdir},"
        f" up to step {cfg.num_steps:,} at batch {cfg.batch_size}"
    )
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


def _check_data_given(args, cfg) -> None:
    """Raises ValueError when nothing chose the photos: no ``--data``, no ``data.source=`` and
    a config that leaves the default, so that a forgotten flag does not start a long run on
    the few bundled photos."""
    from usp_jax.training.data import DataConfig

    chosen = args.data is not None or any(
        o.split("=", 1)[0].strip() == "data.source" for o in args.overrides
    )
    if not chosen and cfg.data.source == DataConfig().source:
        raise ValueError(
            "--data is required: an image folder, tfds:NAME[:SPLIT], or 'sample' for the few"
            " photos bundled with the installed packages"
        )


def _distributed(args) -> bool:
    """Whether `train` joins a multi-process run: --distributed, or any of its explicit parts."""
    return args.distributed or any(
        value is not None for value in (args.coordinator, args.num_processes, args.process_id)
    )


def cmd_evaluate(args) -> None:
    from usp_jax.evaluation import plotting, protocol

    _check_output_file(args.json, "--json")
    _check_output_folder(args.plots, "--plots")
    if args.real and (args.res is not None or args.plots):
        raise ValueError(
            "--real scores every pair at its own size and draws no plots: drop --res and --plots"
        )
    args.top = args.top or (1000 if args.real else 300)
    detector = None if args.baselines_only else _load_detector(args)
    baselines = [name.strip() for name in args.baselines.split(",") if name.strip()]
    guide = _guide(args) if detector is not None else _guide(args, checked_only=True)
    methods = protocol.methods(detector, baselines, args.top, guide)
    if args.real:
        from usp_jax import cli_real

        return cli_real.run(args, methods)
    height, width = args.res = args.res or (240, 320)
    results = protocol.evaluate(
        methods,
        args.hpatches,
        height=height,
        width=width,
        top_k=args.top,
        nms=args.nms,
        ransac_orders=args.ransac_orders,
        progress=not args.no_progress,
    )
    enlarged = f", model on {args.upsample}x enlarged images" if args.upsample > 1 else ""
    enlarged += ", model matching across any rotation" if guide is not None else ""
    enlarged += ", model on an image pyramid (--any-scale)" if args.any_scale else ""
    print(f"{args.hpatches}{enlarged}")  # the table's first line has the size, points and NMS
    print(protocol.format_table(results))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(protocol.to_json(results), indent=1))
        print(f"wrote {args.json}")
    if args.plots and methods:
        from usp_jax.quickstart import example_pair_files

        path = plotting.plot_example_pair(
            methods[0], args.hpatches, args.plots, args.res, args.top, args.nms
        )
        for written in example_pair_files(path):
            print(f"wrote {written}")


def cmd_make_pairs(args) -> None:
    from usp_jax.evaluation.pairs import make_pairs
    from usp_jax.inference.images import sample_photos

    _check_output_folder(args.out, "--out")
    # 'sample': the photos bundled with the installed packages, as train's --data takes it.
    images = [path for _, path in sample_photos()] if args.images == "sample" else args.images
    scenes = make_pairs(
        images,
        args.out,
        seed=args.seed,
        size=args.size,
        num_views=args.views,
        rotation=args.rotation,
        rotation_angles=args.rotation_angles,
        zoom=args.zoom,
        progress=not args.no_progress,
    )
    print(f"wrote {len(scenes)} scenes to {args.out}")


def cmd_benchmark(args) -> None:
    from usp_jax.evaluation import benchmark

    _check_output_file(args.json, "--json")
    if args.weights or args.checkpoint:
        detector = _load_detector(args, any_scale=False)
    else:  # every shipped network, side by side
        detector = benchmark.shipped_networks(upsample=args.upsample, refine=args.refine)
    if args.any_scale:  # beside the single-scale rows, in the same run
        detector = benchmark.with_any_scale(detector)
    result = benchmark.benchmark(
        detector,
        resolutions=tuple(args.res),
        batch_sizes=tuple(args.batch),
        top_n=args.top,
        repeats=args.repeats,
        include_opencv=not args.no_opencv,
        include_xfeat=not args.no_opencv,
        progress=not args.no_progress,
    )
    print(benchmark.format_benchmark(result))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")


def cmd_detect(args) -> None:
    from usp_jax.evaluation import plotting
    from usp_jax.inference.images import read_image

    args.out = _figure_file(args.out, "--out")
    _check_output_file(args.json, "--json")
    detector = _load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    features = detector.detect(image := read_image(args.image), top_n=args.top)
    print(f"{args.image}: {len(features.keypoints)} keypoints")
    if args.out:
        plotting.plot_detections(image, features.keypoints, args.out)
        print(f"wrote {args.out}")
    if args.json:
        pathlib.Path(args.json).write_text(
            json.dumps(
                {
                    "keypoints": features.keypoints.tolist(),
                    "scores": features.scores.tolist(),
                    "descriptors": features.descriptors.tolist(),
                    "sizes": None if features.scales is None else features.scales.tolist(),
                }
            )
        )
        print(f"wrote {args.json}")


def cmd_match(args) -> None:
    from usp_jax.evaluation import plotting
    from usp_jax.inference import matching as matching_lib
    from usp_jax.inference import turning
    from usp_jax.inference.images import read_image

    args.out = _figure_file(args.out, "--out")
    _check_output_file(args.json, "--json")
    detector = _load_detector(args, nms_radius=args.nms, max_side=args.max_side)
    guide = _guide(args, max_side=args.max_side)
    image1, image2 = read_image(args.image1), read_image(args.image2)
    angle = None
    if guide is None:
        features1, features2 = (detector.detect(image, args.top) for image in (image1, image2))
    else:
        features1, features2, angle = turning.detect_pair(detector, guide, image1, image2, args.top)
        print(f"image 2 turned back by {angle:.1f} degrees before detection")
    matching = matching_lib.match_and_estimate(features1, features2)
    print(
        f"{len(features1.keypoints)} and {len(features2.keypoints)} keypoints,"
        f" {len(matching.matches)} mutual nearest-neighbour matches,"
        f" {int(matching.inliers.sum())} RANSAC inliers"
        f" ({matching_lib.RANSAC_THRESHOLD:g} px)"
    )
    # An estimate from too few inliers is a chance fit: reported as none (it stays in the JSON).
    homography = matching.homography if matching.reliable else None
    if matching.homography is None:
        print("no homography: fewer than 4 matches, or RANSAC found none")
    elif homography is None:
        inliers = f"{int(matching.inliers.sum())} RANSAC inliers, under {matching_lib.MIN_INLIERS}"
        print(f"no reliable homography: {inliers}; the images may not show one scene")
        print(f"usp-jax match: warning: no reliable homography ({inliers})", file=sys.stderr)
    else:
        print("homography image1 -> image2:")
        print(np.array2string(homography, precision=6, suppress_small=True))
    if args.out:
        plotting.plot_matches(
            image1,
            image2,
            features1.keypoints,
            features2.keypoints,
            matching.matches,
            matching.inliers,
            None,
            homography,
            args.out,
        )
        print(f"wrote {args.out}")
    if args.json:
        estimate = None if matching.homography is None else matching.homography.tolist()
        pathlib.Path(args.json).write_text(
            json.dumps(
                {
                    "homography": None if homography is None else homography.tolist(),
                    "reliable": matching.reliable,
                    "min_inliers": matching_lib.MIN_INLIERS,
                    "ransac_estimate": estimate,
                    "matches": matching.matches.tolist(),
                    "inliers": matching.inliers.tolist(),
                    "keypoints1": features1.keypoints.tolist(),
                    "keypoints2": features2.keypoints.tolist(),
                    "turned_back_degrees": angle,
                }
            )
        )
        print(f"wrote {args.json}")


def cmd_export(args) -> None:
    from usp_jax.inference import weights
    from usp_jax.inference.export import export

    if not (args.save_weights or args.artifact):
        raise ValueError("nothing to export: give --save-weights FILE.npz and/or --artifact FILE")
    # What is written and printed: NAME.npz for a NAME without .npz.
    args.save_weights = _suffixed_file(args.save_weights, "--save-weights", weights.weights_file)
    _check_output_file(args.artifact, "--artifact")
    detector = _load_detector(args)
    if args.save_weights:
        weights.save_weights(args.save_weights, detector.variables, detector.model_config)
        print(f"wrote {args.save_weights} (float16)")
    if args.artifact:
        detector = detector.replace(top_n=args.top, nms_radius=args.nms)
        export(detector, args.artifact, *args.res)
        print(f"wrote {args.artifact} (jax.export, uint8 [b, {args.res[0]}, {args.res[1]}, 3])")


def cmd_demo(args) -> None:
    from usp_jax.quickstart import DEFAULT_OUT, demo

    out = args.out or str(DEFAULT_OUT)
    _check_output_folder(out, "--out")
    demo(out, args.weights)


def cmd_track(args) -> None:
    from usp_jax import cli_track

    for path, what in ((args.out, "--out"), (args.json, "--json"), (args.tracks, "--tracks")):
        _check_output_file(path, what)
    return cli_track.run(args, _load_detector)


def cmd_reconstruct(args) -> None:
    from usp_jax import cli_reconstruct

    return cli_reconstruct.run(args, _load_detector)


COMMANDS = {
    "train": cmd_train,
    "evaluate": cmd_evaluate,
    "make-pairs": cmd_make_pairs,
    "benchmark": cmd_benchmark,
    "detect": cmd_detect,
    "match": cmd_match,
    "export": cmd_export,
    "demo": cmd_demo,
    "track": cmd_track,
    "reconstruct": cmd_reconstruct,
}


def main(argv: list[str] | None = None) -> int:
    """Runs the command; returns its exit status (0, 2 for a user error, 130 if interrupted).

    Run as the program (``argv`` None), a user error ends the process at once after its one
    line: the native threads of a checkpoint save that failed (a full disk) may still call back
    into a closed asyncio loop while the interpreter shuts down, each printing a traceback.
    """
    if argv is None:
        sys.unraisablehook = cli_errors.without_closed_loop_callbacks(sys.unraisablehook)
    with warnings.catch_warnings():  # _main's plain warning lines end with the command
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
    # Its asyncio tasks, abandoned by that failed save, log their errors when collected.
    if not args.verbose:
        logging.getLogger("absl").setLevel(logging.CRITICAL)
        logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    warnings.showwarning = cli_errors.plain_warnings(args.command, warnings.showwarning)
    from usp_jax.training import distributed

    try:
        code = COMMANDS[args.command](args) or 0
    except BaseException as err:
        code, message = cli_errors.classify(err)
        if distributed.joined():  # a multi-process run ends in every process
            own = message or (
                f"{type(err).__name__}: {distributed.first_line(err)} (its traceback is in its log)"
            )

            def report(text: str) -> None:
                if text != own:  # another process failed first: its error, not the broken link
                    user_error(args.command, text)
                elif message is None:
                    traceback.print_exc()
                else:
                    cli_errors.show(args.command, code, message)

            distributed.leave_after_failure(code, own, report)
        if message is None:
            raise
        cli_errors.show(args.command, code, message)
        return code
    return code
