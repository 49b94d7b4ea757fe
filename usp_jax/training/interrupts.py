"""Stopping a training run cleanly: Ctrl-C, and SIGTERM in a single-process run (a scheduler
ending or preempting the job), are raised between steps, never inside one, so that
``train.fit`` can save the step reached and say where a rerun resumes."""

from __future__ import annotations

import contextlib
import signal
import threading

import jax


class Terminated(KeyboardInterrupt):
    """SIGTERM in a single-process run (a scheduler ending or preempting the job), raised where
    Ctrl-C would be, so that the run saves its step as it does on Ctrl-C."""

    signum = signal.SIGTERM


def _raise_terminated(signum, frame) -> None:
    raise Terminated


@contextlib.contextmanager
def sigterm_saves():
    """SIGTERM raises :class:`Terminated` inside the block (a single process's main thread only;
    in a multi-process run JAX's runtime takes SIGTERM and the processes stop together,
    ``distributed.preempted``)."""
    if threading.current_thread() is not threading.main_thread() or jax.process_count() > 1:
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def interrupts_deferred():
    """Ctrl-C (and SIGTERM under :func:`sigterm_saves`) inside the block is raised when the
    block ends, not inside it.

    The step donates the old state's buffers to the new one: an interrupt between the donation
    and the assignment would leave only deleted arrays to save. Only the main thread receives
    Python's signals; a handler other than ours or Python's default (a background job's
    SIG_IGN, a user's own) is left alone.
    """
    ours = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: _raise_terminated}
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    deferred = [s for s, handler in ours.items() if signal.getsignal(s) is handler]
    received = []
    for signum in deferred:
        signal.signal(signum, lambda signum, _: received.append(signum))
    try:
        yield
    finally:
        for signum in deferred:
            signal.signal(signum, ours[signum])
    if signal.SIGTERM in received:
        raise Terminated
    if received:
        raise KeyboardInterrupt


class Interrupted(KeyboardInterrupt):
    """Training stopped by Ctrl-C (``signum`` SIGINT) or, in a single-process run, SIGTERM; the
    message says from which step a rerun resumes."""

    def __init__(self, message: str, signum: int = signal.SIGINT):
        super().__init__(message)
        self.signum = signum
