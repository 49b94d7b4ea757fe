"""Self-supervised training (paper section 3), the loop: ``fit`` trains or resumes the run in a
workdir, one jitted step (:mod:`usp_jax.training.step`) per batch, logging, checkpoints, and
one-line errors for what a user can cause (a diverged run, a full disk, a workdir in use).

Branch A is the (photometrically augmented) image, branch B the same image warped by a random
homography T and augmented independently (``step.make_branches``; with ``data.context_window``,
B is rendered from a larger window around A so that T may rotate by any angle,
``step.make_window_branches``). The host only decodes and crops: homographies, warps and
augmentation are sampled on the device inside the jitted step, from a key derived from the step
number, so a resumed run sees exactly the randomness an uninterrupted one would.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pathlib
import re
import shutil
import signal
import time
from collections.abc import Iterator
from typing import Any

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from usp_jax.inference.weights import damaged_checkpoint
from usp_jax.training import config as config_lib
from usp_jax.training import distributed as multihost
from usp_jax.training.interrupts import Interrupted, interrupts_deferred, sigterm_saves
from usp_jax.training.metrics import (
    MetricsWriter,
    TrainingDiverged,
    check_finite,
    collapse_warnings,
    progress_postfix,
)
from usp_jax.training.step import (
    TrainState,
    check_config,
    create_state,
    data_mesh,
    jit_train_step,
)
from usp_jax.training.workdir import (
    CONFIG_CHANGES_FILE,
    ConfigChanged,
    WorkdirError,
    WorkdirLock,
    check_resume,
    check_workdir_path,
    recorded_config,
    with_resolved_paths,
)

log = logging.getLogger(__name__)


def _first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def _write_failed(error: OSError, what: str, workdir: pathlib.Path, mngr) -> WorkdirError:
    latest = _last_complete_step(workdir / "checkpoints") if mngr is not None else None
    where = error.filename or workdir
    kept = f"; the last complete checkpoint is step {latest}" if latest is not None else ""
    return WorkdirError(f"{what}: {where}: {error.strerror or _first_line(error)}{kept}")


#: A checkpoint being written: orbax saves step N into N.orbax-checkpoint-tmp..., then renames it.
_SAVING = re.compile(r"(?:^|/)(\d+)\.orbax-checkpoint-tmp")


def _failed_step(error: OSError, done: int) -> int:
    """The step whose write failed: the checkpoint named in the error's path, else ``done``.
    Orbax saves in the background, so step 8's failed save may surface while step 12 runs."""
    saving = _SAVING.search(str(error.filename or ""))
    return int(saving.group(1)) if saving else done


def _last_complete_step(directory: pathlib.Path) -> int | None:
    """The latest checkpoint on disk: orbax renames a step's folder to its number only once the
    step is complete (the manager's own record may list a save that failed afterwards)."""
    try:
        steps = [int(p.name) for p in directory.iterdir() if p.name.isdigit() and p.is_dir()]
    except OSError:
        return None
    return max(steps, default=None)


def _os_error_in(error: BaseException) -> OSError | None:
    """The OSError behind ``error``, or None. Orbax's writes (TensorStore) fail with a
    ValueError that carries the system's error code in its text: ``[os_error_code='28']``."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno is not None:
            return error
        code = re.search(r"os_error_code='(\d+)'", str(error))
        if code:
            path = re.search(r'(?:file|Failed writing:) "([^"]+)"', str(error))
            number = int(code.group(1))
            return OSError(number, os.strerror(number), path.group(1) if path else None)
        error = error.__cause__ or error.__context__
    return None


def fit(
    config: config_lib.Config,
    workdir: str | pathlib.Path,
    *,
    progress: bool = True,
    distributed: bool | multihost.Launch = False,
    num_steps: int | None = None,
    allow_config_change: bool = False,
) -> TrainState:
    """Trains (or resumes) the run in ``workdir`` up to ``num_steps`` (default config.num_steps).

    Re-running with the same workdir resumes from its latest complete checkpoint. A workdir
    trained with other settings is refused (``ConfigChanged``, naming the keys) unless
    ``allow_config_change``; the keys of ``RESUMABLE_KEYS`` (the step count, logging and
    checkpoint intervals, data loading) may always change, and a network or optimizer whose
    arrays do not fit the checkpoints never continues. Everything is checked before the
    workdir is created or changed; ``config.json`` is (re)written only once the run starts.
    A lock on ``WORKDIR/train.lock`` keeps a second run out (``WorkdirError`` naming the holder).

    Writes ``config.json``, ``checkpoints/``, ``metrics.jsonl`` and ``tensorboard/`` into workdir.
    Raises ``TrainingDiverged`` on a non-finite loss, keeping the last good checkpoint, and
    ``WorkdirError`` when a write fails (a full disk), naming the last complete checkpoint.
    ``distributed`` (True, or a ``distributed.Launch`` with explicit coordinator, process count
    and id) joins a multi-process run first unless this process has joined one already
    (``distributed.initialize``). Every process then runs ``fit`` with the same arguments and
    loads only its share of each global batch; only process 0 writes the config, metrics and
    TensorBoard files, all of them take part in every checkpoint save and restore (the workdir
    must be on storage they share). When one of them gets SIGTERM, which JAX's runtime catches
    there, all save a checkpoint at the same step and return early (``state.step < num_steps``).
    After a failure in a multi-process run the process must
    exit (the CLI does, ``distributed.leave_after_failure``): its checkpoint manager is left
    as it is, because closing it waits on processes that are gone.
    """
    from usp_jax.training import data

    workdir = pathlib.Path(workdir).expanduser().absolute()
    config = with_resolved_paths(config)  # one folder however typed, recorded as resolved
    num_steps = config.num_steps if num_steps is None else num_steps
    teacher = check_config(config)
    _check_num_steps(num_steps)
    _join_and_check_devices(config, distributed)
    check_workdir_path(workdir)
    # What can reject the inputs (the --init weights, the data path) runs before the workdir is
    # written, so a bad argument leaves no half-made run behind to be resumed later.
    initial = create_state(config)
    dataset = data.make_dataset(
        config.data,
        config.batch_size // jax.process_count(),
        seed=config.seed,
        process_index=jax.process_index(),
        process_count=jax.process_count(),
    )
    run = _open_run(config, workdir, initial, allow_config_change)
    step_fn = jit_train_step(config, run.mesh, teacher)
    with sigterm_saves():
        return _train_steps(config, run, step_fn, dataset, num_steps, progress)


def _check_num_steps(num_steps) -> None:
    if isinstance(num_steps, bool) or not isinstance(num_steps, (int, np.integer)) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")


def _join_and_check_devices(config: config_lib.Config, distributed) -> None:
    """Joins the multi-process run ``distributed`` asks for (unless joined already); checks the
    batch divides among the processes and devices."""
    if distributed and not jax.distributed.is_initialized():
        launch = distributed if isinstance(distributed, multihost.Launch) else multihost.Launch()
        multihost.join(launch, config)
    multihost.check_batch(config.batch_size, jax.process_count())
    if config.batch_size % jax.device_count():
        raise ValueError(
            f"batch_size {config.batch_size} is not divisible by the {jax.device_count()} devices"
        )


@dataclasses.dataclass
class _Run:
    """A run whose workdir is locked and checked: the state to continue from (at ``start``),
    its checkpoint manager, metrics writer and device mesh."""

    workdir: pathlib.Path
    state: TrainState
    start: int
    mngr: Any
    lock: WorkdirLock | None
    writer: MetricsWriter
    mesh: Any

    @property
    def is_main(self) -> bool:
        return jax.process_index() == 0


def _open_run(
    config: config_lib.Config,
    workdir: pathlib.Path,
    initial: TrainState,
    allow_config_change: bool,
) -> _Run:
    """Creates or resumes the run in ``workdir``: takes the lock, checks the recorded config,
    restores the latest checkpoint and (re)writes the record. On any failure everything opened
    is closed again, and a workdir this call created is removed."""
    from usp_jax.training import checkpoint

    is_main = jax.process_index() == 0
    created = not workdir.exists()
    lock = mngr = None
    try:
        lock = _lock_workdir(workdir, is_main)
        previous = recorded_config(workdir)
        changes = {}
        if previous is not None:
            resolved = with_resolved_paths(previous)
            changes = check_resume(workdir, resolved, config, allow_config_change)
        # Every process has read the record before process 0 rewrites it below.
        _sync_processes("usp_jax: workdir checked")
        mesh = data_mesh()
        state = jax.device_put(initial, NamedSharding(mesh, P()))
        mngr = checkpoint.manager(workdir / "checkpoints", keep=config.keep_checkpoints)
        state = _restore_latest(mngr, state, workdir)
        start = int(state.step)
        if is_main:  # the run starts: only now is its record (re)written
            _write_record(workdir, config, previous, changes, start)
        writer = MetricsWriter(workdir, enabled=is_main)
    except BaseException as error:
        if mngr is not None:
            mngr.close()
        if lock is not None:
            lock.release()
        # Made by this call for a run that never started. Process 0's to remove: another
        # process may have found it already made.
        if created and is_main and workdir.is_dir():
            shutil.rmtree(workdir, ignore_errors=True)
        cause = _os_error_in(error)
        if cause is not None and not isinstance(error, (WorkdirError, ConfigChanged)):
            raise _write_failed(cause, "cannot start the run", workdir, None) from error
        raise
    return _Run(workdir, state, start, mngr, lock, writer, mesh)


def _lock_workdir(workdir: pathlib.Path, is_main: bool) -> WorkdirLock | None:
    """Makes ``workdir`` and takes its lock (process 0 only); a failure is one line."""
    try:
        workdir.mkdir(parents=True, exist_ok=True)
        return WorkdirLock(workdir) if is_main else None
    except OSError as error:
        raise WorkdirError(f"workdir {workdir}: {error.strerror or _first_line(error)}") from None


def _restore_latest(mngr, state: TrainState, workdir: pathlib.Path) -> TrainState:
    """``state`` restored from the latest complete checkpoint, or as it is when there is none."""
    from usp_jax.training import checkpoint

    latest = mngr.latest_step()
    if latest is None:
        return state
    try:
        state = checkpoint.restore_state(mngr, state)
    except Exception as error:  # a damaged checkpoint: one line, the cause chained
        directory = workdir / "checkpoints"
        raise WorkdirError(damaged_checkpoint(directory, latest, error, resuming=True)) from error
    log.info("resumed from step %d", int(state.step))
    return state


def _write_record(
    workdir: pathlib.Path,
    config: config_lib.Config,
    previous: config_lib.Config | None,
    changes: dict,
    start: int,
) -> None:
    """(Re)writes ``config.json`` when the settings are new, and appends the changes a resume
    was allowed to make to ``config_changes.jsonl``."""
    if previous is None or previous != config:
        config_lib.save(config, workdir / "config.json")
    if changes:
        with open(workdir / CONFIG_CHANGES_FILE, "a") as file:
            file.write(
                json.dumps(
                    {
                        "step": start,
                        "changes": {k: [old, new] for k, (old, new) in changes.items()},
                    }
                )
                + "\n"
            )


class _StepLog:
    """What the loop reports every ``log_every`` steps: metrics rows, the progress bar's
    postfix, and each collapse warning once."""

    def __init__(self, config: config_lib.Config, writer: MetricsWriter, bar, dataset, start: int):
        self.config, self.writer, self.bar, self.dataset = config, writer, bar, dataset
        self.last_time, self.last_step = time.perf_counter(), start
        self.warned: set[str] = set()

    def write(self, done: int, metrics: dict, mngr) -> None:
        """Checks and records the metrics (device arrays) of step ``done``."""
        from usp_jax.training import data

        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        check_finite(metrics, done, mngr)
        now = time.perf_counter()
        steps_per_s = (done - self.last_step) / max(now - self.last_time, 1e-9)
        self.last_time, self.last_step = now, done
        metrics.update({"steps_per_s": steps_per_s, **data.stats(self.dataset)})
        # Warn once per kind, after the first steps have had a chance to move away from init.
        for what, message in (collapse_warnings(metrics) if done >= 100 else {}).items():
            if what not in self.warned:
                self.warned.add(what)
                log.warning("step %d: %s", done, message)
        self.writer.write(done, metrics)
        self.bar.set_postfix(progress_postfix(metrics, steps_per_s, self.config.batch_size))


def _train_steps(
    config: config_lib.Config, run: _Run, step_fn, dataset, num_steps: int, progress: bool
) -> TrainState:
    """Runs the steps ``run.start`` .. ``num_steps`` of an opened run, logging and saving as the
    config says; closes the run, also on failure (a failed write: ``WorkdirError``)."""
    from tqdm.auto import tqdm

    from usp_jax.training import checkpoint, data

    single = jax.process_count() == 1
    mngr, state = run.mngr, run.state
    bar = tqdm(
        total=num_steps,
        initial=run.start,
        disable=not (progress and run.is_main),
        unit="step",
        dynamic_ncols=True,
    )
    step_log = _StepLog(config, run.writer, bar, dataset, run.start)
    batch_sharding = NamedSharding(run.mesh, P("data"))
    batches: Iterator[np.ndarray] = data.iterate(dataset, run.start)
    previous_metrics = None
    done = run.start
    finished = False
    try:
        try:
            for step in range(run.start, num_steps):
                local = next(batches)
                images = jax.tree.map(
                    lambda x: jax.make_array_from_process_local_data(batch_sharding, x), local
                )
                with interrupts_deferred():
                    state, metrics = step_fn(state, images)
                done = step + 1
                # Checking the previous step while this one runs keeps the device busy.
                check_finite(previous_metrics, done - 1, mngr)
                previous_metrics = metrics
                stop = multihost.preempted(done)
                last = stop or done == num_steps
                if done % config.log_every and done % config.checkpoint_every and not last:
                    bar.update(1)
                    continue
                step_log.write(done, metrics, mngr)
                bar.update(1)
                if done % config.checkpoint_every == 0 or last:
                    checkpoint.save(mngr, done, state, config)
                if stop:
                    log.warning(
                        "stopping at step %d: a process got SIGTERM (its job is ending or"
                        " being preempted); rerun to resume",
                        done,
                    )
                    break
            mngr.wait_until_finished()
            finished = True
        except TrainingDiverged:
            raise
        except KeyboardInterrupt as stop:
            if not single:  # the others would wait for this one's part of the save
                raise
            signum = getattr(stop, "signum", signal.SIGINT)
            raise _save_interrupted(config, run, state, previous_metrics, signum) from None
        except Exception as error:
            cause = _os_error_in(error)
            if cause is None:
                raise
            if single:
                _settle(mngr)
            failed = _failed_step(cause, done)
            raise _write_failed(
                cause, f"writing step {failed} failed", run.workdir, mngr
            ) from error
    finally:
        _close_run(run, bar, settle=finished or single)
    return state


def _close_run(run: _Run, bar, settle: bool) -> None:
    """Closes the checkpoints (waiting for a pending save when ``settle``), the progress bar,
    the metric writer and the workdir lock. A failed multi-process run leaves its pending save
    unsettled: finishing it would wait for processes that have stopped."""
    if settle:
        _settle(run.mngr)
        run.mngr.close()
    bar.close()
    _close_quietly(run.writer)
    if run.lock is not None:
        run.lock.release()


def _save_interrupted(
    config, run: _Run, state: TrainState, metrics, signum: int = signal.SIGINT
) -> Interrupted:
    """Saves ``state`` on Ctrl-C or SIGTERM, as a checkpoint would have, unless it is saved
    already or its loss was not finite; returns the error that says which step a rerun resumes
    from."""
    from usp_jax.training import checkpoint

    how = "interrupted" if signum == signal.SIGINT else f"stopped by {signal.Signals(signum).name}"

    step, latest = int(state.step), run.mngr.latest_step()
    saved = f"; checkpoint step {step} saved in {run.workdir / 'checkpoints'}"
    if step > (latest or 0):
        if metrics is not None and not float(metrics["finite"]):
            check_finite(metrics, step, run.mngr)  # a diverged state is not worth resuming
        checkpoint.save(run.mngr, step, state, config)
        run.mngr.wait_until_finished()
    elif latest is None:
        return Interrupted(f"{how} before the first step; nothing to resume", signum)
    else:
        saved = f"; its checkpoint is in {run.workdir / 'checkpoints'}"
    return Interrupted(
        f"{how} at step {step}{saved}; rerun the same command to resume from step {step}", signum
    )


def _sync_processes(name: str) -> None:
    """Waits until every process of a multi-process run gets here (a no-op for one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def _settle(mngr) -> None:
    """Waits for a pending save; a failed one leaves only orbax's temporary folder, which
    ``latest_step`` never reports."""
    try:
        mngr.wait_until_finished()
    except Exception as error:  # reported by the caller's own error, or already raised
        log.debug("pending checkpoint save failed: %s", _first_line(error))


def _close_quietly(writer: MetricsWriter) -> None:
    try:
        writer.close()
    except OSError as error:  # a full disk fails the final flush too
        log.debug("closing the metrics writer failed: %s", _first_line(error))
