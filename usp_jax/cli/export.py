"""``usp-jax export``: a float16 weights file, or a ``jax.export`` artifact that runs the
compiled detector with JAX alone."""

from __future__ import annotations

from usp_jax.cli import arguments, outputs


def add_parser(subparsers) -> None:
    """The ``export`` subcommand: a float16 weights file or a jax.export artifact."""
    p = subparsers.add_parser(
        "export", help="float16 weights file or a jax.export inference artifact"
    )
    arguments.add_checkpoint(p)
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
        type=arguments.resolution,
        default=(240, 320),
        metavar="HxW",
        help="artifact input size (default 240x320)",
    )
    p.add_argument(
        "--top",
        type=arguments.positive,
        default=1000,
        help="artifact keeps this many points (default 1000)",
    )
    arguments.add_nms_radius(p, 0.0, "artifact NMS radius in px (default 0)")
    arguments.add_network_options(p)


def run(args) -> int | None:
    """Writes the weights file and/or the artifact asked for (at least one)."""
    from usp_jax.inference import weights
    from usp_jax.inference.export import export

    if not (args.save_weights or args.artifact):
        raise ValueError("nothing to export: give --save-weights FILE.npz and/or --artifact FILE")
    # What is written and printed: NAME.npz for a NAME without .npz.
    args.save_weights = outputs.suffixed_file(
        args.save_weights, "--save-weights", weights.weights_file
    )
    outputs.check_output_file(args.artifact, "--artifact")
    detector = arguments.load_detector(args)
    if args.save_weights:
        weights.save_weights(args.save_weights, detector.variables, detector.model_config)
        print(f"wrote {args.save_weights} (float16)")
    if args.artifact:
        detector = detector.replace(top_n=args.top, nms_radius=args.nms)
        export(detector, args.artifact, *args.res)
        print(f"wrote {args.artifact} (jax.export, uint8 [b, {args.res[0]}, {args.res[1]}, 3])")
