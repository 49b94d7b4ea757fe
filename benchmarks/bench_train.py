"""Side-by-side timing of one training step: usp_jax's jitted step against the PyTorch reference.

Both run in this process on the same uint8 photo crops, in alternating blocks of steps so that
machine-load drift hits both alike (``common.interleaved``). The JAX step is
``usp_jax.training.step.jit_train_step`` exactly as ``fit`` uses it (homography sampling, warp,
photometric augmentation, one forward over both branches, all loss terms, backward, Adam, the
finiteness guard, donated state); the PyTorch step does the same work
(``torch_reference.TrainStep``). Compile time is reported separately.

    python3 benchmarks/bench_train.py                 # paper setting: 240x320, batch 5 per branch
    python3 benchmarks/bench_train.py --check         # also: same loss and gradients as PyTorch
    python3 benchmarks/bench_train.py --profile       # JAX step time by op category
    python3 benchmarks/bench_train.py --no-torch      # without the optional torch dependency
    python3 benchmarks/bench_train.py --no-torch --source data/corpus/train   # its pipeline rate

Beside the step it times the input pipeline alone (``data.measure_throughput``: decoding and
cropping threads, no training) on ``--source`` and prints both as photos per second, and the
step's images per second per device: on an accelerator, a pipeline slower than the step it
feeds shows at once. Each process of a multi-process run decodes only its share of a batch, so
the pipeline's rate on one host compares with the step's photos/s divided by the process count.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import common
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from usp_jax import config as config_lib
from usp_jax.core import geometry
from usp_jax.training import data
from usp_jax.training import step as step_lib


def photo_batch(config: config_lib.Config, batch: int) -> np.ndarray:
    """uint8 [batch, H, W, 3] random crops of the photos bundled with the installed packages."""
    sample = config_lib.override(config, ["data.source=sample"]).data
    return np.asarray(data.make_dataset(sample, batch, seed=0)[0])


def jax_step(config: config_lib.Config, images: np.ndarray):
    """(compiled step, initial state, device images, compile seconds) of the real train step."""
    mesh = step_lib.data_mesh()
    state = jax.device_put(step_lib.create_state(config), NamedSharding(mesh, P()))
    device_images = jax.device_put(images, NamedSharding(mesh, P("data")))
    start = time.perf_counter()
    compiled = step_lib.jit_train_step(config, mesh).lower(state, device_images).compile()
    return compiled, state, device_images, time.perf_counter() - start


def homographies_for(config: config_lib.Config, count: int, batch: int) -> np.ndarray:
    """[count, batch, 3, 3] homographies from the JAX sampler, for the PyTorch steps."""
    height, width = config.data.height, config.data.width
    keys = jax.random.split(jax.random.PRNGKey(1), count * batch)
    sample = jax.jit(
        jax.vmap(lambda k: geometry.sample_homography(k, height, width, config.homography))
    )
    return np.array(sample(keys)).reshape(count, batch, 3, 3)


def input_report(config: config_lib.Config, step_s: float, source: str, steps: int) -> dict:
    """Photos per second the step consumes (per process) against what the input pipeline alone
    delivers on this host, with the step's images per second per device.

    One photo feeds both branches: a step over ``batch_size`` photos runs 2 x batch_size images
    through the network, spread over every device.
    """
    consumed = config.batch_size / jax.process_count() / step_s
    pipeline = config_lib.override(config, [f"data.source={source}"]).data
    delivered = data.measure_throughput(pipeline, config.batch_size // jax.process_count(), steps)
    return {
        "images_per_s_per_device": 2 * config.batch_size / step_s / jax.device_count(),
        "step_photos_per_s_per_process": consumed,
        "pipeline_photos_per_s": delivered,
        "pipeline_threads": pipeline.num_workers,
        "pipeline_over_step": delivered / consumed,
    }


def check_against_torch(config: config_lib.Config, images: np.ndarray) -> dict:
    """Loss and gradient norms of both implementations on identical branch images, homographies
    and weights: the evidence that the two steps do the same work."""
    import torch
    import torch_reference

    state = step_lib.create_state(config)
    floats = jnp.asarray(images, jnp.float32) / 255.0
    images_a, images_b, homographies = jax.jit(
        lambda key, x: step_lib.make_branches(key, x, config.homography, config.photometric)
    )(jax.random.PRNGKey(2), floats)

    def loss_fn(params):  # the train step's loss (step.siamese_loss), without its metrics
        return step_lib.siamese_loss(
            params, state.batch_stats, images_a, images_b, homographies, config
        )[0]

    jax_loss, jax_grads = jax.jit(jax.value_and_grad(loss_fn))(state.params)
    reference = torch_reference.TrainStep(config)
    torch_reference.load_flax_variables(
        reference.model, {"params": state.params, "batch_stats": state.batch_stats}
    )

    def nchw(x):
        return (
            torch.from_numpy(np.asarray(x))
            .permute(0, 3, 1, 2)
            .contiguous(memory_format=torch.channels_last)
        )

    torch_loss = reference.loss(
        nchw(images_a), nchw(images_b), torch.from_numpy(np.asarray(homographies))
    )
    torch_loss.backward()
    torch_norm = float(torch.sqrt(sum((p.grad**2).sum() for p in reference.model.parameters())))
    return {
        "jax_loss": float(jax_loss),
        "torch_loss": float(torch_loss),
        "jax_grad_norm": float(jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(jax_grads)))),
        "torch_grad_norm": torch_norm,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="paper", help="preset or config file (default paper)")
    parser.add_argument("--batch", type=int, help="images per branch (default: the config's)")
    parser.add_argument("--size", help="HxW crop, e.g. 240x320 (default: the paper's 240x320)")
    parser.add_argument("--rounds", type=int, default=3, help="alternations of JAX and torch")
    parser.add_argument("--block", type=int, default=2, help="timed steps per round and library")
    parser.add_argument("--no-torch", action="store_true", help="time the JAX step alone")
    parser.add_argument("--check", action="store_true", help="compare loss and gradients")
    parser.add_argument("--profile", action="store_true", help="JAX step by op category")
    parser.add_argument(
        "--source",
        default="sample",
        help="data source whose input pipeline is timed (default: the photos"
        " bundled with the installed packages)",
    )
    parser.add_argument(
        "--pipeline-steps", type=int, default=10, help="batches the input pipeline is timed over"
    )
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()

    config = config_lib.load(args.config)
    overrides = [f"batch_size={args.batch}"] if args.batch else []
    if args.size:
        height, width = args.size.lower().split("x")
        overrides += [f"data.height={height}", f"data.width={width}"]
    config = config_lib.override(config, overrides)
    batch, height, width = config.batch_size, config.data.height, config.data.width
    print(common.environment())
    ceiling = common.matmul_ceiling()
    gflop = 2 * batch * common.train_gflop(config.model, height, width)
    print(
        f"step: {batch} images per branch at {height}x{width}, {gflop:.0f} GFLOP of convolutions;"
        f" matmul ceiling {ceiling:.0f} GFLOP/s"
    )

    images = photo_batch(config, batch)
    compiled, state, device_images, compile_s = jax_step(config, images)
    print(f"JAX compile: {compile_s:.1f} s")
    results = {
        "config": args.config,
        "batch": batch,
        "height": height,
        "width": width,
        "compile_s": compile_s,
        "matmul_gflops": ceiling,
        "gflop_per_step": gflop,
    }

    def run_jax():
        nonlocal state
        state, metrics = compiled(state, device_images)
        return metrics

    runs = {"jax": run_jax}
    if not args.no_torch:
        import torch
        import torch_reference

        reference = torch_reference.TrainStep(config)
        torch_images = torch.from_numpy(images)
        homographies = iter(
            torch.from_numpy(homographies_for(config, args.rounds * (args.block + 1), batch))
        )
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
        runs["torch"] = lambda: reference(torch_images, next(homographies))
    times = common.interleaved(runs, args.rounds, args.block)
    ceiling = common.settled_ceiling(ceiling)
    results["matmul_gflops"] = ceiling
    print(f"matmul ceiling, the better of before and after the timings: {ceiling:.0f} GFLOP/s")
    jax_times, torch_times = times["jax"], times.get("torch")

    jax_s = statistics.median(jax_times)
    print(
        f"JAX   step {common.summary(jax_times)}  {2 * batch / jax_s:5.2f} img/s  "
        f"{gflop / jax_s:5.1f} GFLOP/s = {gflop / jax_s / ceiling:.0%} of the matmul ceiling"
    )
    results.update(jax_step_s=jax_times)
    feed = input_report(config, jax_s, args.source, args.pipeline_steps)
    print(
        f"JAX   step {feed['images_per_s_per_device']:.2f} img/s per device"
        f" ({jax.device_count()} {jax.devices()[0].platform}); it consumes"
        f" {feed['step_photos_per_s_per_process']:.1f} photos/s per process, the input"
        f" pipeline alone delivers {feed['pipeline_photos_per_s']:.1f} photos/s on"
        f" {args.source!r} with {feed['pipeline_threads']} threads:"
        f" {feed['pipeline_over_step']:.1f}x the step's need (below 1: input starves the step)"
    )
    results.update(input=feed)
    if torch_times:
        torch_s = statistics.median(torch_times)
        print(
            f"torch step {common.summary(torch_times)}  {2 * batch / torch_s:5.2f} img/s  "
            f"{gflop / torch_s:5.1f} GFLOP/s = {gflop / torch_s / ceiling:.0%} of the matmul "
            "ceiling"
        )
        print(f"JAX / torch step time: {jax_s / torch_s:.2f} (below 1: JAX faster)")
        results.update(torch_step_s=torch_times, ratio=jax_s / torch_s)
    if args.check:
        check = check_against_torch(config, images)
        print(
            "check (same branch images, homographies and weights): "
            + ", ".join(f"{k} {v:.6g}" for k, v in check.items())
        )
        results["check"] = check
    if args.profile:
        print("JAX step by op category (wall time per step):")
        rows = common.op_profile(run_jax, compiled)
        common.print_profile(rows)
        results["profile_ms"] = dict(rows)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
