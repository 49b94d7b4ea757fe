"""The ``usp-jax`` parser: the commands, in the order ``usp-jax -h`` lists them, each from its own
module (``add_parser`` builds its options, ``run`` runs it)."""

from __future__ import annotations

import argparse

from usp_jax.cli import (
    arguments,
    benchmark,
    demo,
    detect,
    evaluate,
    export,
    make_pairs,
    match,
    reconstruct,
    track,
    train,
)

COMMANDS = {
    "train": train,
    "evaluate": evaluate,
    "make-pairs": make_pairs,
    "benchmark": benchmark,
    "detect": detect,
    "match": match,
    "export": export,
    "demo": demo,
    "track": track,
    "reconstruct": reconstruct,
}


def build_parser() -> argparse.ArgumentParser:
    """The ``usp-jax`` parser: every command's subparser, each option's range applied."""
    parser = arguments.Parser(
        prog="usp-jax", description="UnsuperPoint keypoints in JAX: train, evaluate, benchmark."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS.values():
        command.add_parser(sub)
    for choice in sub._choices_actions:  # `usp-jax COMMAND -h` opens with what it does
        subparser = sub.choices[choice.dest]
        subparser.description = subparser.description or choice.help
    arguments.apply_ranges(parser)
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
