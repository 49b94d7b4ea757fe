"""How the ``usp-jax`` command reports a failure: which errors a user can cause (one line on
stderr, exit status 2) and which are bugs (a traceback), the line itself, and the hooks that keep
other output to plain lines (usp-jax's own warnings) or silent (a failed save's late callbacks).
"""

from __future__ import annotations

import errno
import pathlib
import signal
import sys

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


def user_error(command: str, message: str) -> None:
    """One line on stderr, however long the message (messages may quote multi-line values)."""
    text = " ".join(message.split()) or "failed"
    print(f"usp-jax {command}: error: {text}", file=sys.stderr)


def plain_warnings(command: str, show):
    """``warnings.showwarning`` (``show``) that prints usp-jax's own warnings (a skipped photo)
    as one plain line each, ``usp-jax COMMAND: warning: ...``, without Python's file, line and
    category; other libraries' warnings keep ``show``'s form."""
    package = pathlib.Path(__file__).parent.parent  # usp_jax

    def plain(message, category, filename, lineno, file=None, line=None) -> None:
        if not pathlib.Path(filename).absolute().is_relative_to(package):
            return show(message, category, filename, lineno, file, line)
        text = " ".join(str(message).split())
        print(f"usp-jax {command}: warning: {text}", file=file or sys.stderr)

    return plain


def without_closed_loop_callbacks(hook):
    """``hook`` (a ``sys.unraisablehook``) minus TensorStore's callbacks into a closed loop.

    A checkpoint save that fails (a full disk) ends orbax's asyncio loop while TensorStore
    still finishes its other writes; each finished write then tries to wake the closed loop
    and prints a traceback from a native thread, hundreds of them, racing train's one error
    line. They say nothing the error line does not.
    """

    def filtered(unraisable) -> None:
        error = unraisable.exc_value
        if not (isinstance(error, RuntimeError) and str(error) == "Event loop is closed"):
            hook(unraisable)

    return filtered


def classify(err: BaseException) -> tuple[int, str | None]:
    """(exit status, one-line message) of a failure; the message is None for an internal error
    (a bug), which shows its traceback instead."""
    from usp_jax.training.distributed import DistributedError
    from usp_jax.training.metrics import TrainingDiverged
    from usp_jax.training.workdir import WorkdirError

    if isinstance(err, KeyboardInterrupt):  # train's says which step it resumes from
        return 128 + getattr(err, "signum", signal.SIGINT), str(err) or "interrupted"
    user = isinstance(err, (*_USER_ERRORS, TrainingDiverged, WorkdirError, DistributedError))
    if user or (isinstance(err, OSError) and err.errno in _USER_ERRNOS):
        named = isinstance(err, OSError) and err.filename and err.strerror
        return 2, f"{err.filename}: {err.strerror}" if named else str(err)
    return 1, None


def show(command: str, code: int, message: str) -> None:
    if code in (128 + signal.SIGINT, 128 + signal.SIGTERM):
        print(f"usp-jax {command}: {message}", file=sys.stderr)
    else:
        user_error(command, message)
