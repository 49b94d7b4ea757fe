"""Multi-process training on JAX's distributed runtime, run here: two `usp-jax train` processes on
this machine, one CPU device each, joined through gloo, against one process with two devices."""

import re
import signal
import socket
import subprocess
import time

import jax
import numpy as np
import pytest
from conftest import TINY, USP_JAX, child_env, train_args

from usp_jax import config as config_lib
from usp_jax.cli import main
from usp_jax.inference import weights as weights_lib
from usp_jax.training import distributed
from usp_jax.training import metrics as metrics_lib
from usp_jax.training.distributed import Launch, check_launch, split_address

# Generous: the processes compile while the rest of the suite runs beside them.
TIMEOUT_S = 600


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def train_argv(workdir, steps, *extra) -> list[str]:
    return [*USP_JAX, *train_args(workdir, steps, "--no-progress", *TINY, *extra)]


def start(argv, devices=1) -> subprocess.Popen:
    """``argv`` in a process with ``devices`` CPU devices."""
    # child_env: the tests' compilation cache, so process 0 of the resumed run, and every run of
    # a rerun, compile nothing. (JAX lets only process 0 write it.)
    env = {
        **child_env(),
        "JAX_PLATFORMS": "cpu",
        # LLVM's optimisations take half of the compile time of a train step, which dominates
        # these short runs; every run here is compiled alike, so they still compute the same.
        "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}"
        " --xla_backend_optimization_level=0",
    }
    return subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


def start_processes(workdir, steps, *extra, count=2, data=None) -> list[subprocess.Popen]:
    """``count`` processes of one run on localhost; ``data`` may give each its own --data."""
    address = f"127.0.0.1:{free_port()}"
    return [
        start(
            train_argv(
                workdir,
                steps,
                "--coordinator",
                address,
                "--num-processes",
                str(count),
                "--process-id",
                str(i),
                *extra,
                *(["--data", data[i]] if data else []),
            )
        )
        for i in range(count)
    ]


def finish(process) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return process.returncode, out, err


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "error" in line.lower()]


def losses(workdir) -> dict[int, float]:
    return {row["step"]: row["loss"] for row in metrics_lib.read_metrics(workdir)}


def weights(path) -> list[np.ndarray]:
    _, variables = weights_lib.read_checkpoint(path)
    return [np.asarray(leaf) for leaf in jax.tree.leaves(variables)]


def assert_same_weights(a, b):
    for x, y in zip(weights(a), weights(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two processes train 4 steps, beside one process with two devices training 6; then the
    two-process run resumes to step 6. Returns (workdirs, the processes' outputs)."""
    root = tmp_path_factory.mktemp("distributed")
    one, two = root / "one-process", root / "two-processes"
    single = start(train_argv(one, 6), devices=2)
    first = [finish(p) for p in start_processes(two, 4)]
    weights_at_4 = weights(two)  # before the resume adds checkpoints
    resumed = [finish(p) for p in start_processes(two, 6)]
    return one, two, weights_at_4, finish(single), first, resumed


@pytest.mark.slow
def test_two_processes_train_as_one_process_with_two_devices_and_resume_exactly(runs):
    one, two, weights_at_4, single, first, resumed = runs
    for code, out, err in (single, *first, *resumed):
        assert code == 0, err
    for i, (_, out, _) in enumerate(first):
        assert f"process {i} of 2: done: step 4" in out
    # Process 0 alone writes the metrics: each step once, the resumed steps after the first run's.
    assert [row["step"] for row in metrics_lib.read_metrics(two)] == [1, 2, 3, 4, 5, 6]
    assert (two / "config.json").is_file() and any((two / "tensorboard").iterdir())
    want = losses(one)
    got = losses(two)
    np.testing.assert_allclose(
        [got[s] for s in range(1, 7)], [want[s] for s in range(1, 7)], rtol=1e-5
    )
    for x, y in zip(weights_at_4, weights(one / "checkpoints" / "4"), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    assert_same_weights(two, one)  # step 6, after the resume


@pytest.mark.slow
def test_a_failing_process_ends_every_process_of_the_run_with_its_error(tmp_path):
    missing = str(tmp_path / "no-photos")
    # Process 0, which hosts the coordination service, fails; process 1 is then waiting for it.
    outcomes = [finish(p) for p in start_processes(tmp_path / "run", 4, data=[missing, "sample"])]
    (code0, _, err0), (code1, _, err1) = outcomes
    assert (code0, code1) == (2, 2), (err0, err1)
    assert error_lines(err0) == [f"usp-jax train: error: image folder {missing} does not exist"]
    assert error_lines(err1) == [
        f"usp-jax train: error: process 0 of 2 failed: image folder {missing} does not exist"
    ]


@pytest.mark.slow
def test_sigterm_to_one_process_stops_every_process_at_one_step_with_its_checkpoint(tmp_path):
    run = tmp_path / "run"
    processes = start_processes(run, 10_000, "checkpoint_every=10000")
    deadline = time.monotonic() + TIMEOUT_S
    while not metrics_lib.read_metrics(run) and time.monotonic() < deadline:  # training has begun
        assert all(p.poll() is None for p in processes), [finish(p) for p in processes]
        time.sleep(0.2)
    processes[1].send_signal(signal.SIGTERM)  # as a scheduler does before it ends the job
    outcomes = [finish(p) for p in processes]
    assert [code for code, _, _ in outcomes] == [143, 143], outcomes
    stops = [
        re.search(r"process (\d) of 2: stopped at step (\d+) of 10000 on SIGTERM", out)
        for _, out, _ in outcomes
    ]
    assert [m.group(1) for m in stops] == ["0", "1"]
    step = int(stops[0].group(2))
    assert int(stops[1].group(2)) == step < 10_000
    assert weights_lib.resolve_checkpoint(run) == (
        run / "checkpoints",
        step,
    )  # the only one: saved at the stop
    assert metrics_lib.read_metrics(run)[-1]["step"] == step


@pytest.mark.slow
def test_a_wrong_coordinator_address_ends_the_wait_with_one_line(tmp_path):
    address = f"127.0.0.1:{free_port()}"  # nothing listens there
    began = time.monotonic()
    code, _, err = finish(
        start(
            train_argv(
                tmp_path / "run",
                2,
                "--coordinator",
                address,
                "--num-processes",
                "2",
                "--process-id",
                "1",
                "--init-timeout",
                "2",
            )
        )
    )
    assert code == 2
    assert error_lines(err) == [
        f"usp-jax train: error: process 1: nothing answered at the coordinator address {address}"
        " within 2 s; start process 0 there first, or fix --coordinator"
    ]
    assert time.monotonic() - began < 120  # import, 2 s, exit: no wait for JAX's own deadline
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--num-processes", "2", "--process-id", "2"],
            "process id 2 is out of range for 2 processes (0 to 1)",
        ),
        (
            ["--num-processes", "2", "--process-id", "0", "batch_size=3"],
            "the global batch_size 3 is not divisible by the 2 processes; use a multiple of 2",
        ),
        (["--coordinator", "localhost"], "--coordinator 'localhost' is not HOST:PORT"),
    ],
)
def test_a_launch_that_cannot_work_is_one_line_before_waiting_for_anyone(
    argv, message, tmp_path, capsys
):
    code = main(["train", "--data", "sample", "--workdir", str(tmp_path / "run"), *TINY, *argv])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"usp-jax train: error: {message}") and "\n" not in err
    assert not (tmp_path / "run").exists()


def test_coordinator_addresses_parse_with_ipv6_brackets_and_ports_in_range():
    assert split_address("10.0.0.1:1234") == ("10.0.0.1", 1234)
    assert split_address("[::1]:8476") == ("::1", 8476)
    assert split_address("node-17.cluster:65535") == ("node-17.cluster", 65535)
    for bad in ("node:0", "node:65536", ":1234", "node:", "node:port"):
        with pytest.raises(ValueError, match="is not HOST:PORT"):
            split_address(bad)
    check_launch(Launch("node:1234", 4, 3), batch_size=8)  # valid: no error


def test_join_checks_the_config_and_the_launch_before_it_waits_and_names_the_process(monkeypatch):
    joined = []
    monkeypatch.setattr(distributed, "initialize", lambda *args: joined.append(args))
    rotated = config_lib.override(config_lib.cpu(), ["homography.rotation_range=(-180, 180)"])
    with pytest.raises(ValueError, match="needs data.context_window=True"):
        distributed.join(Launch("node:1234", 2, 0), rotated)
    with pytest.raises(ValueError, match="batch_size 5 is not divisible by the 2 processes"):
        distributed.join(Launch("node:1234", 2, 0), config_lib.paper())
    assert joined == []  # neither waited for the other processes
    report = print
    launch = Launch("node:1234", 2, 1)
    # initialize is replaced, so JAX still counts this process alone.
    assert distributed.join(launch, config_lib.cpu(), report) == "process 0 of 1: "
    assert joined == [(launch, report)]
