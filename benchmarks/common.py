"""Helpers shared by the benchmark scripts: timing, the matmul ceiling, FLOP counts, op profiles.

Not part of the library. Every number a script prints comes from ``time_calls`` (median of
repeated calls after warm-up, each call waited for), so JAX's asynchronous dispatch never hides
work.
"""

from __future__ import annotations

import collections
import glob
import os
import platform
import re
import statistics
import tempfile
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp

from usp_jax.core.model import ModelConfig, UnsuperPoint, init_variables
from usp_jax.evaluation.benchmark import time_calls  # noqa: F401 (the scripts' timer)


def interleaved(
    runs: dict[str, Callable[[], object]], rounds: int, block: int
) -> dict[str, list[float]]:
    """Seconds per call of each function in ``runs``, timed in alternating blocks.

    Each round runs every function ``1 + block`` times in a row and times the last ``block``:
    alternation spreads machine-load drift over all of them, and the untimed first call of a
    block absorbs the cost of switching (one library's first call after the other's re-faults
    the memory the other just freed: ~0.5 s for a train step here).
    """
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, fn in runs.items():
            times[name] += time_calls(fn, block, warmup=1)
    return times


def summary(times: list[float]) -> str:
    """'median (min-max, n)' in milliseconds."""
    ms = [1e3 * t for t in times]
    return f"{statistics.median(ms):8.1f} ms (min {min(ms):.1f}, max {max(ms):.1f}, n={len(ms)})"


def matmul_ceiling(n: int = 4096, repeats: int = 5) -> float:
    """GFLOP/s of a jitted float32 [n, n] x [n, n] matmul: what this CPU sustains at best."""
    a = jnp.ones((n, n), jnp.float32)
    b = jnp.ones((n, n), jnp.float32)
    matmul = jax.jit(jnp.matmul)
    return 2 * n**3 / statistics.median(time_calls(lambda: matmul(a, b), repeats)) / 1e9


def settled_ceiling(before: float, n: int = 4096) -> float:
    """The larger of a ceiling measured before the timings and one measured now, after them.

    On a shared VM one measurement can land in a slow spell: on a 2-core Zen 5 VM a single one
    read 178 GFLOP/s where back-to-back measurements read 250-285, which put the
    network at "170% of the ceiling". A ceiling is a best case, so the better of two counts."""
    return max(before, matmul_ceiling(n))


def _xla_gflop(function, *specs) -> float:
    """GFLOP of one call of ``function`` on arrays of these shapes, from XLA's cost analysis of
    the compiled program (what the hardware is asked to do, not a count by hand)."""
    analysis = jax.jit(function).lower(*specs).compile().cost_analysis()
    if isinstance(analysis, list):  # older jaxlibs: one dict per partition
        analysis = analysis[0]
    return analysis["flops"] / 1e9


def _network_specs(config: ModelConfig, height: int, width: int):
    variables = jax.eval_shape(init_variables, jax.random.PRNGKey(0), config)
    return variables, jax.ShapeDtypeStruct((1, height, width, 3), jnp.float32)


def forward_gflop(config: ModelConfig, height: int, width: int) -> float:
    """Forward GFLOP of the network for one image (13.3 for the paper's at 240x320)."""
    model = UnsuperPoint(config)
    return _xla_gflop(lambda v, x: model.apply(v, x), *_network_specs(config, height, width))


def train_gflop(config: ModelConfig, height: int, width: int) -> float:
    """Forward + backward GFLOP of the network for one image in training mode (BatchNorm on
    batch statistics), gradients with respect to the parameters."""
    model = UnsuperPoint(config)

    def loss(variables, images):
        def total(params):
            pred, _ = model.apply(
                {**variables, "params": params}, images, train=True, mutable=["batch_stats"]
            )
            return sum(jnp.sum(leaf) for leaf in jax.tree.leaves(pred))

        return jax.grad(total)(variables["params"])

    return _xla_gflop(loss, *_network_specs(config, height, width))


def environment() -> str:
    """One line naming the software and the machine load, for the README's tables."""
    parts = [
        f"python {platform.python_version()}",
        f"jax {jax.__version__}",
        f"devices {jax.device_count()}x{jax.devices()[0].platform}",
        f"cpus {os.cpu_count()}",
        f"load {' '.join(f'{x:.1f}' for x in os.getloadavg())}",
    ]
    if os.environ.get("XLA_FLAGS"):
        parts.append(f"XLA_FLAGS={os.environ['XLA_FLAGS']}")
    return ", ".join(parts)


# ------------------------------------------------------------------------------------------------
# Op profile


def _hlo_sources(hlo_text: str) -> dict[str, tuple[str, str]]:
    """Instruction name -> (op_name, innermost user function) from a compiled HLO module's text.

    Fusions without metadata of their own borrow the first of their fused computation's.
    """
    tables: dict[str, dict[int, str]] = {"FileNames": {}, "FunctionNames": {}}
    locations, frames, section = {}, {}, None
    for line in hlo_text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = line
            continue
        match = re.match(r"(\d+) (.*)$", line) if section else None
        if not match:
            section = None
            continue
        key, value = int(match.group(1)), match.group(2)
        if section in tables:
            tables[section][key] = value.strip('"')
        elif section == "FileLocations":
            locations[key] = int(re.search(r"function_name_id=(\d+)", value).group(1))
        elif section == "StackFrames":
            frames[key] = int(re.search(r"file_location_id=(\d+)", value).group(1))

    def function(frame: int | None) -> str:
        if frame is None or frame not in frames:
            return ""
        return tables["FunctionNames"].get(locations.get(frames[frame], -1), "")

    sources, computation_source, calls, current = {}, {}, {}, None
    for line in hlo_text.splitlines():
        header = re.match(r"(?:ENTRY )?%([\w.\-]+) .*\{$", line)
        if header:
            current = header.group(1)
            continue
        inst = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = ", line)
        if not inst:
            continue
        op = re.search(r'op_name="([^"]*)"', line)
        frame = re.search(r"stack_frame_id=(\d+)", line)
        called = re.search(r"calls=%([\w.\-]+)", line)
        if called:
            calls[inst.group(1)] = called.group(1)
        if op:
            source = (op.group(1), function(int(frame.group(1)) if frame else None))
            sources[inst.group(1)] = source
            computation_source.setdefault(current, source)
    for name, computation in calls.items():
        if name not in sources and computation in computation_source:
            sources[name] = computation_source[computation]
    return sources


def _is_conv(op: str, fn: str) -> bool:
    return "conv_general_dilated" in op or fn == "_conv_few_outputs"


_CATEGORIES = (
    # (category, test on (op_name, function)); the first that matches wins.
    ("augmentation: blur", lambda op, fn: fn == "gaussian_blur"),
    ("augmentation: warp_image", lambda op, fn: fn in ("warp_image", "_pixel_grid")),
    (
        "augmentation: other",
        lambda op, fn: (
            fn in ("photometric_augment", "draw", "make_branches") or "sample_homography" in fn
        ),
    ),
    ("conv backward", lambda op, fn: _is_conv(op, fn) and "transpose(" in op),
    ("conv forward", _is_conv),
    ("batchnorm", lambda op, fn: "BatchNorm" in op),
    ("leaky_relu", lambda op, fn: "leaky_relu" in op),
    (
        "max pool",
        lambda op, fn: (
            fn in ("max_pool_2x2", "_quadrants", "_max_pool_forward", "_max_pool_backward")
            or "reduce_window" in op
        ),
    ),
    (
        "descriptor sampling",
        lambda op, fn: fn.startswith("bilinear_sample") or fn == "l2_normalize",
    ),
    (
        "losses",
        lambda op, fn: (
            fn
            in (
                "usp_loss",
                "uniform_loss",
                "descriptor_loss",
                "decorrelation_loss",
                "pair_loss",
                "total_loss",
                "find_correspondences",
                "pairwise_distances",
                "safe_sqrt",
                "correspondence_matrix",
                "warp_points",
                "invert_homography",
                "points_inside",
                "_normalise",
            )
            or "pair_loss" in op
        ),
    ),
    ("optimizer, finiteness check", lambda op, fn: fn.startswith("train_step") or "adam" in op),
)


def op_profile(run: Callable[[], object], compiled, steps: int = 2) -> list[tuple[str, float]]:
    """Wall-clock milliseconds per step by op category while ``run`` (which calls ``compiled``)
    runs, from a ``jax.profiler`` trace.

    XLA:CPU's trace events cover the kernels it generates, but library calls (Eigen convolutions
    and matmuls) only in part, as their worker threads are not traced: the wall time in which no
    traced kernel runs is reported as "untraced (library convolutions and matmuls)", and the
    traced time is split by the categories' share of the kernels' thread time. Returns
    [(category, ms per step)], largest first.
    """
    sources = _hlo_sources(compiled.as_text())
    thread_ns: collections.Counter = collections.Counter()
    intervals, wall_ns = [], 0
    with tempfile.TemporaryDirectory() as directory:
        jax.block_until_ready(run())
        with jax.profiler.trace(directory):
            start = time.perf_counter_ns()
            for _ in range(steps):
                jax.block_until_ready(run())
            wall_ns = time.perf_counter_ns() - start
        path = sorted(glob.glob(os.path.join(directory, "**", "*.xplane.pb"), recursive=True))[-1]
        profile = jax.profiler.ProfileData.from_file(path)
    for plane in profile.planes:
        for line in plane.lines:
            if not line.name.startswith("tf_XLA"):
                continue
            for event in line.events:
                if event.name.startswith(("ThunkExecutor", "Threadpool", "end: ", "Slinky")):
                    continue
                op, fn = sources.get(event.name, ("", ""))
                category = next((c for c, test in _CATEGORIES if test(op, fn)), "other")
                thread_ns[category] += event.duration_ns
                intervals.append((event.start_ns, event.end_ns))
    covered, reach = 0, float("-inf")
    for begin, end in sorted(intervals):
        covered += max(0, end - max(begin, reach))
        reach = max(reach, end)
    total = sum(thread_ns.values())
    rows = [(c, ns * covered / total / steps / 1e6) for c, ns in thread_ns.most_common()]
    rows.append(("untraced (library convolutions and matmuls)", (wall_ns - covered) / steps / 1e6))
    return sorted(rows, key=lambda row: -row[1])


def print_profile(rows: list[tuple[str, float]]) -> None:
    total = sum(ms for _, ms in rows)
    for category, ms in rows:
        print(f"  {ms:9.1f} ms  {100 * ms / total:5.1f}%  {category}")
    print(f"  {total:9.1f} ms  per step")
