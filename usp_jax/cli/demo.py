"""``usp-jax demo``: the whole pipeline on the bundled photos, offline (``usp_jax.demo``)."""

from __future__ import annotations

from usp_jax.cli import arguments, outputs


def add_parser(subparsers) -> None:
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
    arguments.add_weights_name(p)


def run(args) -> int | None:
    """Runs the demo into ``--out``."""
    from usp_jax.quickstart import DEFAULT_OUT, demo

    out = args.out or str(DEFAULT_OUT)
    outputs.check_output_folder(out, "--out")
    demo(out, args.weights)
