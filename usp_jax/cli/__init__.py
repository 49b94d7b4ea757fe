"""The ``usp-jax`` command: train, evaluate, make-pairs, benchmark, detect, match, export, demo,
track and reconstruct, one module each in this package (``parser.COMMANDS``). Each command
parses its options, checks its outputs can be written, and calls the Python API; ``arguments``
holds the options they share, ``outputs`` the checked and atomic writes, ``errors`` how a failure
is reported.

Every failure a user can cause (a missing folder, a corrupt image, a bad override, an
unwritable output, a full disk) ends in one line on stderr and exit status 2, never a
traceback; options are checked before anything is written. An internal error (a bug) still
shows its traceback.
"""

from __future__ import annotations

import logging
import os
import sys
import traceback
import warnings

from usp_jax.cli import errors
from usp_jax.cli.errors import user_error
from usp_jax.cli.parser import COMMANDS, parse_args

__all__ = ["main", "parse_args"]


def main(argv: list[str] | None = None) -> int:
    """Runs the command; returns its exit status (0; 2 for a user error; 130 on Ctrl-C, 143 when
    SIGTERM stopped a single-process `train`).

    Run as the program (``argv`` None), a user error ends the process at once after its one
    line: the native threads of a checkpoint save that failed (a full disk) may still call back
    into a closed asyncio loop while the interpreter shuts down, each printing a traceback.
    """
    if argv is None:
        sys.unraisablehook = errors.without_closed_loop_callbacks(sys.unraisablehook)
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
    warnings.showwarning = errors.plain_warnings(args.command, warnings.showwarning)
    from usp_jax.training import distributed

    try:
        code = COMMANDS[args.command].run(args) or 0
    except BaseException as err:
        code, message = errors.classify(err)
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
                    errors.show(args.command, code, message)

            distributed.leave_after_failure(code, own, report)
        if message is None:
            raise
        errors.show(args.command, code, message)
        return code
    return code
