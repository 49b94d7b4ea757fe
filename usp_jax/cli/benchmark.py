"""``usp-jax benchmark``: images per second of the network beside OpenCV's detectors and XFeat
(``evaluation.benchmark``), every shipped network side by side unless weights are named."""

from __future__ import annotations

import json

from usp_jax.cli import arguments, outputs


def add_parser(subparsers) -> None:
    """The ``benchmark`` subcommand: frames per second of the model and OpenCV."""
    p = subparsers.add_parser("benchmark", help="frames per second, model and OpenCV side by side")
    arguments.add_checkpoint(p)
    p.add_argument(
        "--res",
        type=arguments.resolution,
        nargs="+",
        default=[(240, 320), (480, 640)],
        metavar="HxW",
        help="image sizes to time (default 240x320 480x640)",
    )
    p.add_argument(
        "--batch",
        type=arguments.positive,
        nargs="+",
        default=[1, 10],
        metavar="B",
        help="batch sizes the model is timed at (default 1 10); OpenCV takes one image at a time",
    )
    p.add_argument(
        "--top", type=arguments.positive, help="points kept (default: 300 up to 240x320, else 1000)"
    )
    p.add_argument(
        "--repeats",
        type=arguments.positive,
        default=10,
        metavar="N",
        help="timed calls per row, after 2 warm-up calls; the median is reported (default 10)",
    )
    p.add_argument(
        "--no-opencv", action="store_true", help="time the model only (no OpenCV, no XFeat)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", help="write the settings and every timed row as JSON here")
    arguments.add_network_options(p)


def run(args) -> int | None:
    """Times the networks (and OpenCV, XFeat) and prints the table."""
    from usp_jax.evaluation import benchmark

    outputs.check_output_file(args.json, "--json")
    if args.weights or args.checkpoint:
        detector = arguments.load_detector(args, any_scale=False)
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
        outputs.write_text(args.json, json.dumps(result, indent=1))
        print(f"wrote {args.json}")
