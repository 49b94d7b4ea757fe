"""The options the ``usp-jax`` commands share: argument types that reject a bad value in one line
before anything runs, the range of every numeric option, the options several commands take
(weights, checkpoint, upsampling, NMS, rotation and scale) and what they load (``load_detector``,
``guide``), and the parser class (one-line errors, every default in the help). Each command's
module builds its subcommand from them.
"""

from __future__ import annotations

import argparse
import math

from usp_jax.core.model import CELL
from usp_jax.inference.detector import MAX_SIDE
from usp_jax.inference.weights import DEFAULT_PRETRAINED, PRETRAINED

# The largest --upsample and --res side: beyond, the activations alone outgrow any memory.
MAX_UPSAMPLE = 8

MAX_RESOLUTION = 16384


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
    "--epipolar": (0, 1000),
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


def apply_ranges(parser: argparse.ArgumentParser) -> None:
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


def resolution(text: str) -> tuple[int, int]:
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
    value = positive(text)
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


positive = _integer_at_least(1, "positive")
non_negative = _integer_at_least(0, "non-negative")


def zoom_range(text: str) -> tuple[float, float]:
    """``MIN,MAX`` zoom factors for make-pairs (``evaluation.zoom.ZOOM_LIMITS``)."""
    from usp_jax.evaluation.zoom import ZOOM_LIMITS

    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        low = high = math.nan
    if not ZOOM_LIMITS[0] <= low <= high <= ZOOM_LIMITS[1]:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not MIN,MAX with {ZOOM_LIMITS[0]:g} <= MIN <= MAX <= {ZOOM_LIMITS[1]:g}"
        )
    return low, high


def add_any_scale(parser) -> None:
    parser.add_argument(
        "--any-scale",
        action="store_true",
        help="match across zoom: detect on an image pyramid too (steps of 1/sqrt(2) down to a"
        " 64 px side, 1.85x the time at 240x320); keypoints get sizes from their level",
    )


def add_refine(parser) -> None:
    """``--refine`` / ``--no-refine``: the sub-pixel refinement on or off; neither: the
    weights' own default (on for ``paper`` only)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--refine",
        action="store_true",
        default=None,
        help="move each point by the sub-pixel refinement (inference.refine) whatever the"
        " weights (default: only the paper network's points; on distilled's it gains as much"
        " at about 1.8x its time)",
    )
    group.add_argument(
        "--no-refine",
        dest="refine",
        action="store_false",
        default=None,  # store_false's own True would read as "on" in the help; neither = weights'
        help="keep the network's raw positions: skip the sub-pixel refinement of each point"
        " (for the ablation)",
    )


def add_upsample(parser) -> None:
    # SIFT doubles its input for the same reason: the positions come back finer (RESULTS.md).
    parser.add_argument(
        "--upsample",
        type=_upsample,
        default=1,
        metavar="S",
        help="run the network on the image enlarged S times (default 1, the"
        " paper's detector; 2: finer keypoints for 4x the compute)",
    )


def add_network_options(parser) -> None:
    """``--upsample``, ``--refine``/``--no-refine`` and ``--any-scale``: how the network runs,
    for every command that runs it on photos (track and reconstruct take no ``--refine``)."""
    add_upsample(parser)
    add_refine(parser)
    add_any_scale(parser)


def add_any_rotation(parser, turn_back: bool = False) -> None:
    """``--any-rotation``, ``--guide`` and ``--[no-]turn-back`` (on by default where
    ``turn_back``; read with :func:`turns_back`)."""
    parser.add_argument(
        "--any-rotation",
        action="store_true",
        help="match across any in-plane rotation: rotation-invariant weights (--guide) estimate"
        " how far image 2 is turned, and the model matches it turned back",
    )
    parser.add_argument(
        "--guide",
        default=None,
        help="--any-rotation's rotation-invariant weights: a shipped name, a .npz weights file"
        " or a training workdir (default: the shipped rotation weights)",
    )
    parser.add_argument(
        "--turn-back",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="for the moderate turns of hand-held photos, without a guide: when the upright"
        " matches' homography turns by 10 degrees or more, detect image 2 turned back by it and"
        " keep that if it matches as well or better"
        f" (default: {'on, unless --any-rotation' if turn_back else 'off'})",
    )


def turns_back(args, default: bool = False) -> bool:
    """Whether image 2 is turned back by the upright matches' turn: ``--turn-back`` or
    ``--no-turn-back`` as given, else ``default`` unless ``--any-rotation`` turns it instead."""
    if args.turn_back and args.any_rotation:
        raise ValueError("--turn-back and --any-rotation are two ways to turn image 2: give one")
    return default and not args.any_rotation if args.turn_back is None else args.turn_back


def add_weights_name(parser, default: str = DEFAULT_PRETRAINED, why: str = "") -> None:
    """``--weights NAME``; ``default`` (and ``why``) only for the help: ``None`` still means
    "not given", so that ``--checkpoint`` can exclude it."""
    why = why or "the best on the held-out pairs"
    parser.add_argument(
        "--weights",
        metavar="NAME",
        help=f"shipped weights by name: {', '.join(PRETRAINED)} (default {default}, {why};"
        " README's 'Which weights' table says which suits what)",
    )


def add_checkpoint(parser, **weights_default) -> None:
    """``--checkpoint PATH`` or ``--weights NAME`` (:func:`add_weights_name`'s options)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--checkpoint",
        metavar="PATH",
        help="training workdir, one of its checkpoints, or a .npz weights file"
        " from `usp-jax export --save-weights` (default: the shipped weights)",
    )
    add_weights_name(group, **weights_default)


def add_nms_radius(parser, default: float, help: str) -> None:
    """``--nms``: the detector's NMS radius in px, any finite value >= 0 (detect, match, export)."""
    parser.add_argument("--nms", type=_radius, default=default, help=help)


def add_max_side(parser, help: str, flag: str = "--max-side", default: int | None = MAX_SIDE):
    """``--max-side``: the longest side the network sees (``Detector``'s max_side; detect, match,
    track; track's ``--network-side`` too): 0 or at least one 8 px cell."""
    parser.add_argument(flag, type=_side, default=default, metavar="PX", help=help)


def _side(text: str) -> int:
    """A longest side in px: 0 (native size) or ``CELL`` px and more (``--max-side``)."""
    value = non_negative(text)
    if 0 < value < CELL:
        raise argparse.ArgumentTypeError(
            f"{text!r} is under {CELL} px, one cell; give 0 (native size) or {CELL} or more"
        )
    return value


def load_detector(args, **options):
    """The detector the weight options name (``--weights``, ``--checkpoint``, else the shipped
    default), with the options ``--upsample``, ``--any-scale`` and ``--refine`` where the command
    has them; ``options`` override."""
    from usp_jax.inference.detector import Detector

    options.setdefault("upsample", getattr(args, "upsample", 1))
    options.setdefault("any_scale", getattr(args, "any_scale", False))
    options.setdefault("refine", getattr(args, "refine", None))
    if getattr(args, "weights", None):
        return Detector.pretrained(args.weights, **options)
    return Detector.load(getattr(args, "checkpoint", None) or None, **options)


def guide(args, checked_only: bool = False, **options):
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


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's help with every option's default shown: a help text that does not state its
    default itself gets "(default: X)" appended (an unset None is no default, and neither is a
    flag's: ``--no-x`` is off unless given, whatever its dest holds then)."""

    def _get_help_string(self, action) -> str:
        text = action.help or ""
        default = action.default
        if (
            action.option_strings
            and action.nargs != 0
            and default not in (None, False, argparse.SUPPRESS)
            and "default" not in text
        ):
            text += " (default: %(default)s)"
        return text


class Parser(argparse.ArgumentParser):
    """argparse with its errors in one line (the usage is one ``-h`` away), exit status 2, and
    every option's default in its help (:class:`_HelpFormatter`, subcommands' parsers too)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        text = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {text} (see {self.prog} -h)\n")
