"""Joining a multi-process run on JAX's distributed runtime, and ending it together on a failure.

One process per host (or per accelerator) runs the same ``usp-jax train --distributed``. Process
0 hosts JAX's coordination service at the coordinator address; the others connect to it, and
together their devices form one mesh (``train.data_mesh``). On the CPU backend the processes'
collectives go through gloo over TCP, which lets two processes on one machine run, and test, the
code path of a GPU cluster or a TPU pod slice.

A multi-process run must neither hang nor die with a C++ abort, so this module adds to JAX:

* a deadline on joining: a wrong coordinator address or a missing process ends each waiting
  process with one line when ``Launch.init_timeout_s`` has passed (JAX itself would abort with a
  stack trace);
* a shared record of the first failure: a process that fails writes its one-line error into the
  coordination service's key-value store and exits; every other process ends with
  ``process P of N failed: ...``, read by a watcher thread (which also frees a process blocked in
  a collective that waits for the dead one) or by its own error path (when the collective
  itself fails, as gloo's do when a peer's connection closes).

A process that dies without a word (killed, out of memory) is noticed by JAX's heartbeat after
``Launch.heartbeat_timeout_s``, which then aborts the others with its own message.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, NoReturn

import jax

if TYPE_CHECKING:
    from usp_jax.training.config import Config

log = logging.getLogger(__name__)

#: Key of the first failure in the coordination service: JSON {"process": P, "message": ...}.
FAILURE_KEY = "usp_jax/failure"
#: Key prefix under which each process records that it is leaving after a failure.
LEFT_KEY = "usp_jax/left/"
# JAX's own join deadline lies beyond ours, so that ours, with its one line, fires first.
_JAX_GRACE_S = 30
# How long one watcher poll blocks in the coordination service (it returns at once on a failure).
_POLL_MS = 1000
# How long process 0, which hosts the coordination service, waits for the others to read a
# failure before it exits and takes the service with it.
_LEAVE_WAIT_S = 30


class DistributedError(RuntimeError):
    """This process could not join the run, or another process of the run failed."""


@dataclasses.dataclass(frozen=True)
class Launch:
    """How this process joins a multi-process run.

    Fields left None are detected by JAX from the environment: SLURM, Open MPI, Cloud TPU and
    Kubernetes set all three, and ``JAX_COORDINATOR_ADDRESS`` sets the coordinator.
    """

    coordinator: str | None = None  # "HOST:PORT" of process 0's coordination service
    num_processes: int | None = None
    process_id: int | None = None
    # Seconds every process waits for all of them to join before it gives up with one line.
    init_timeout_s: int = 300
    # Seconds without a heartbeat after which JAX declares a process dead (JAX's default).
    heartbeat_timeout_s: int = 100


def split_address(address: str) -> tuple[str, int]:
    """ "HOST:PORT" (an IPv6 host in brackets, "[::1]:1234") -> (host, port); ValueError in one
    line for anything else."""
    host, colon, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--coordinator {address!r} is not HOST:PORT with a port in 1..65535")
    return host, int(port)


def check_launch(launch: Launch, batch_size: int | None = None) -> None:
    """Raises ValueError in one line for a launch that cannot work: a malformed coordinator, a
    process id outside [0, N), a non-positive count or timeout, or a global ``batch_size`` that
    the N processes cannot share equally. Needs no other process: run it before ``initialize``."""
    if launch.coordinator is not None:
        split_address(launch.coordinator)
    for name in ("num_processes", "init_timeout_s", "heartbeat_timeout_s"):
        value = getattr(launch, name)
        if value is not None and value < 1:
            raise ValueError(f"{name} must be at least 1, got {value}")
    if launch.process_id is not None and launch.process_id < 0:
        raise ValueError(f"process id {launch.process_id} is negative")
    count = launch.num_processes
    if count is not None and launch.process_id is not None and launch.process_id >= count:
        raise ValueError(
            f"process id {launch.process_id} is out of range for {count} processes (0 to {count - 1})"
        )
    if count is not None and batch_size is not None:
        check_batch(batch_size, count)


def check_batch(batch_size: int, process_count: int) -> None:
    """Raises ValueError unless every process gets the same share of the global batch."""
    if batch_size % process_count:
        raise ValueError(
            f"the global batch_size {batch_size} is not divisible by the {process_count}"
            f" processes; use a multiple of {process_count}"
        )


def joined() -> bool:
    """Whether this process is part of a multi-process run started by ``initialize``."""
    return _STATE.client is not None


def initialize(launch: Launch = Launch(), report: Callable[[str], None] | None = None) -> None:
    """Joins the run: selects gloo for CPU collectives, connects to the coordinator, and starts
    the watcher that ends this process when another one fails.

    Must run before anything initialises a JAX backend. ``report(line)`` shows a failure (this
    process's own join deadline, or another process's error) just before the process exits with
    status 2; by default it goes to stderr. Raises ``DistributedError`` in one line when JAX
    finds no cluster to join or the backend is already running, ValueError for a bad ``launch``.
    """
    check_launch(launch)
    report = report or _print_error
    # The CPU backend only talks to other processes through a collectives library; GPU and TPU
    # backends bring their own (NCCL, ICI) and ignore this setting.
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except AttributeError:  # a JAX that no longer offers the choice
        log.debug("this JAX has no jax_cpu_collectives_implementation option")
    joining = threading.Event()
    deadline = threading.Timer(launch.init_timeout_s, _join_timed_out, (launch, joining, report))
    deadline.daemon = True
    deadline.start()
    try:
        jax.distributed.initialize(
            coordinator_address=launch.coordinator,
            num_processes=launch.num_processes,
            process_id=launch.process_id,
            initialization_timeout=launch.init_timeout_s + _JAX_GRACE_S,
            heartbeat_timeout_seconds=launch.heartbeat_timeout_s,
        )
    except (ValueError, RuntimeError) as error:
        raise DistributedError(_join_error(error)) from error
    finally:
        joining.set()
        deadline.cancel()
    from jax._src import distributed as jax_distributed  # the runtime's client: no public handle

    _STATE.client = jax_distributed.global_state.client
    # What the watcher and the exit path need, read without the backend: a thread that asks
    # jax.process_index() while the main thread is still setting the backend up waits for it.
    _STATE.process = jax_distributed.global_state.process_id
    _STATE.count = jax_distributed.global_state.num_processes
    _STATE.report = report
    _STATE.watcher = threading.Thread(target=_watch, name="usp-jax failure watcher", daemon=True)
    _STATE.watcher.start()
    # atexit runs last-registered first: the watcher stops before JAX's shutdown barrier.
    atexit.register(stop_watching)
    log.info(
        "process %d of %d joined, %d local of %d devices",
        jax.process_index(),
        jax.process_count(),
        jax.local_device_count(),
        jax.device_count(),
    )


def join(
    launch: Launch, config: Config | None = None, report: Callable[[str], None] | None = None
) -> str:
    """Joins the run of a training ``config`` and returns ``"process P of N: "``, the prefix
    that tells this process's lines from the others'.

    Everything a process can check alone is checked before it waits for the others: the config
    (``step.check_config``), the launch and the global batch's split (:func:`check_launch`); then
    :func:`initialize` with ``report``. Raises ValueError, or ``DistributedError``, in one line.
    """
    if config is not None:
        # Imported here: the network and the optimiser behind the check are training's, which
        # joining alone (``initialize``) does not need.
        from usp_jax.training.step import check_config

        check_config(config)
    check_launch(launch, None if config is None else config.batch_size)
    initialize(launch, report)
    return f"process {jax.process_index()} of {jax.process_count()}: "


def preempted(step: int) -> bool:
    """Whether a multi-process run should stop after ``step``: True in every process at one and
    the same step once any of them got SIGTERM, which a cluster's scheduler sends before it ends
    or preempts the job. (JAX's runtime catches SIGTERM in a multi-process run, so without this
    check the run would go on until it is killed, losing the steps since its last checkpoint.)
    Always False for a single process, which SIGTERM ends at once."""
    if jax.process_count() == 1:
        return False
    from jax.experimental import multihost_utils

    try:
        return multihost_utils.reached_preemption_sync_point(step)
    except RuntimeError:  # the preemption service is switched off (jax_enable_preemption_service)
        return False


def stop_watching() -> None:
    """Stops the watcher (after a run that ended well: the processes then leave together)."""
    _STATE.stopping.set()
    watcher, _STATE.watcher = _STATE.watcher, None
    if watcher is not None and watcher is not threading.current_thread():
        watcher.join()


def leave_after_failure(code: int, message: str, show: Callable[[str], None]) -> NoReturn:
    """Ends this process after a failure, and with it the run.

    Publishes ``message`` as the run's failure unless another process's failure came first, in
    which case that one is what this process shows: a process whose collective failed because
    a peer died reports the peer's error, not the broken connection. ``show(line)`` prints the
    line (or the caller's traceback). The process then exits with ``code`` (2 when it shows
    another's failure) without JAX's shutdown barrier, which the others, gone, would never
    reach. Only one thread of a process gets to end it: a second caller waits for the exit.
    """
    if not _STATE.ending.acquire(blocking=False):
        threading.Event().wait()  # the other thread is ending the process
    other = _publish_failure(message)
    if other is not None:
        code, message = 2, other
    show(message)
    _leave(code)


def first_line(error: BaseException) -> str:
    """The first line of an error's text (gRPC and XLA errors run to many), or its type's name."""
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


# ---------------------------------------------------------------------------------------------
# Internals: the shared state of the joined process, the watcher and the exit


@dataclasses.dataclass
class _State:
    client: object = None
    process: int = 0
    count: int = 1
    report: Callable[[str], None] | None = None
    watcher: threading.Thread | None = None
    stopping: threading.Event = dataclasses.field(default_factory=threading.Event)
    ending: threading.Lock = dataclasses.field(default_factory=threading.Lock)


# One per process, as JAX's own distributed state: a process joins one run at most.
_STATE = _State()


def _print_error(line: str) -> None:
    print(f"error: {line}", file=sys.stderr, flush=True)


def _join_error(error: BaseException) -> str:
    text = " ".join(str(error).split())
    if "coordinator_address" in text or "must be defined" in text:
        return (
            "--distributed found no cluster to join (none of SLURM, Open MPI, Cloud TPU or"
            " Kubernetes, and no JAX_COORDINATOR_ADDRESS): give --coordinator HOST:PORT"
            " --num-processes N --process-id I"
        )
    if "before any JAX" in text or "should only be called once" in text:
        return f"cannot join a distributed run in this process: {text}"
    return f"cannot join the distributed run: {text}"


def _join_timed_out(launch: Launch, joining: threading.Event, report) -> None:
    """The join deadline passed: says why in one line and exits (status 2)."""
    if joining.is_set():
        return
    from jax._src import distributed as jax_distributed

    joined_as = jax_distributed.global_state  # what JAX made of the launch before it connected
    address = launch.coordinator or getattr(joined_as, "coordinator_address", None)
    count = launch.num_processes or getattr(joined_as, "num_processes", None) or "all"
    me = f"process {getattr(joined_as, 'process_id', '?')}"
    if address and not _answers(address):
        line = (
            f"{me}: nothing answered at the coordinator address {address} within"
            f" {launch.init_timeout_s} s; start process 0 there first, or fix --coordinator"
        )
    else:  # something answers, but a proxy may answer for any address: both causes remain
        line = (
            f"{me}: could not join the run at {address} within {launch.init_timeout_s} s: not all"
            f" {count} processes connected (start the missing ones, or fix --num-processes), or"
            " that is not process 0's address (fix --coordinator)"
        )
    report(line)
    _exit(2)


def _answers(address: str) -> bool:
    """Whether something accepts TCP connections at ``address`` (HOST:PORT)."""
    try:
        with socket.create_connection(split_address(address), timeout=2):
            return True
    except (OSError, ValueError):
        return False


def _watch() -> None:
    """Waits on the shared failure record; when another process fails, shows its error and ends
    this process, which may meanwhile sit in a collective that will never complete."""
    client, errors = _STATE.client, 0
    while not _STATE.stopping.is_set():
        try:
            value = client.blocking_key_value_get(FAILURE_KEY, _POLL_MS)
        except Exception as error:  # JAX raises its runtime error with the gRPC status
            if "DEADLINE_EXCEEDED" in str(error):
                errors = 0
                continue
            if _STATE.stopping.is_set():
                return
            # The coordination service is gone: process 0 ended without a word (killed?).
            errors += 1
            if errors < 3:
                time.sleep(1)
                continue
            _failed_elsewhere(f"lost the coordination service in process 0: {first_line(error)}")
            return
        failure = json.loads(value)
        if failure["process"] != _STATE.process:
            _failed_elsewhere(_describe(failure))
        return  # this process's own failure: its main thread is ending it


def _failed_elsewhere(line: str) -> None:
    if not _STATE.ending.acquire(blocking=False):
        return  # the main thread is ending the process already
    _STATE.report(line)
    _leave(2)


def _describe(failure: dict) -> str:
    return f"process {failure['process']} of {_STATE.count} failed: {failure['message']}"


def _publish_failure(message: str) -> str | None:
    """Records this process's failure as the run's; returns the earlier failure of another
    process instead when there is one (the store keeps the first record of a key)."""
    if _STATE.client is None:
        return None
    record = json.dumps({"process": _STATE.process, "message": message})
    try:
        _STATE.client.key_value_set(FAILURE_KEY, record)
        return None
    except Exception:  # ALREADY_EXISTS (another failure came first) or the service is gone
        pass
    try:
        failure = json.loads(_STATE.client.key_value_try_get(FAILURE_KEY))
    except Exception:
        return None
    return None if failure["process"] == _STATE.process else _describe(failure)


def _leave(code: int) -> NoReturn:
    """Exits now. Process 0 first waits a little for the others, as its exit ends the
    coordination service through which they read the failure."""
    client = _STATE.client
    if client is not None:
        me, count = _STATE.process, _STATE.count
        try:
            client.key_value_set(f"{LEFT_KEY}{me}", "1")
            if me == 0:
                end = time.monotonic() + _LEAVE_WAIT_S
                for other in range(1, count):
                    remaining_ms = int(max(end - time.monotonic(), 0) * 1000)
                    client.blocking_key_value_get(f"{LEFT_KEY}{other}", max(remaining_ms, 1))
        except Exception as error:  # a process that left without a word, or no service
            log.debug("leaving without every process's goodbye: %s", first_line(error))
    _exit(code)


def _exit(code: int) -> NoReturn:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
