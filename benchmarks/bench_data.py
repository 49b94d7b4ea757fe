"""Does the input pipeline starve the train step? Steps/s with real decoding vs cached arrays.

Three measurements on one config (default: the ``cpu`` preset, photos bundled with the installed
packages): the pipeline alone (``data.measure_throughput``: decode + crop threads, no training),
the jitted train step fed one cached batch over and over, and the train step fed by
``data.iterate`` exactly as ``train.fit`` feeds it (background decode threads, prefetch, host ->
device transfer). The last two should agree: decoding then runs in the shadow of the step.

    python3 benchmarks/bench_data.py                         # cpu preset, bundled photos
    python3 benchmarks/bench_data.py --source data/corpus/train --steps 30
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import common
import jax
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from usp_jax import config as config_lib
from usp_jax.training import data
from usp_jax.training import step as step_lib


def steps_per_second(step, state, batches, steps: int) -> tuple[float, object]:
    """Steps/s over ``steps`` steps fed by the iterator ``batches`` (after one warm-up step)."""
    state, metrics = step(state, next(batches))
    jax.block_until_ready(metrics)
    start = time.perf_counter()
    for _ in range(steps):
        state, metrics = step(state, next(batches))
    jax.block_until_ready(metrics)
    return steps / (time.perf_counter() - start), state


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="cpu", help="preset or config file (default cpu)")
    parser.add_argument("--source", help="data source (default: the config's)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per measurement")
    parser.add_argument("--rounds", type=int, default=3, help="alternations of the two feeds")
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()

    config = config_lib.load(args.config)
    if args.source:
        config = config_lib.override(config, [f"data.source={args.source}"])
    batch = config.batch_size
    print(common.environment())
    print(
        f"{args.config}: {batch} photos per step at {config.data.height}x{config.data.width}, "
        f"source {config.data.source!r}, {config.data.num_workers} decode threads"
    )

    pipeline_rate = data.measure_throughput(config.data, batch, args.steps)
    print(f"pipeline alone: {pipeline_rate:.1f} photos/s")

    mesh = step_lib.data_mesh()
    sharding = NamedSharding(mesh, P("data"))
    state = jax.device_put(step_lib.create_state(config), NamedSharding(mesh, P()))
    step = step_lib.jit_train_step(config, mesh)
    dataset = data.make_dataset(config.data, batch, seed=config.seed)
    cached = jax.make_array_from_process_local_data(sharding, dataset[0])

    def repeat_cached():
        while True:
            yield cached

    def decoded(start: int):
        for local in data.iterate(dataset, start):
            yield jax.make_array_from_process_local_data(sharding, local)

    rates = {"cached arrays": [], "real decoding (data.iterate)": []}
    for r in range(args.rounds):
        rate, state = steps_per_second(step, state, repeat_cached(), args.steps)
        rates["cached arrays"].append(rate)
        rate, state = steps_per_second(step, state, decoded(r * (args.steps + 1)), args.steps)
        rates["real decoding (data.iterate)"].append(rate)
    for name, values in rates.items():
        rate = statistics.median(values)
        print(
            f"train step, {name:28s} {rate:6.3f} steps/s = {rate * batch:6.2f} photos/s "
            f"(rounds: {', '.join(f'{v:.3f}' for v in values)})"
        )
    ratio = statistics.median(rates["real decoding (data.iterate)"]) / statistics.median(
        rates["cached arrays"]
    )
    print(f"real decoding / cached: {ratio:.3f} (1 = the pipeline never starves the step)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "config": args.config,
                    "source": config.data.source,
                    "pipeline_photos_per_s": pipeline_rate,
                    "steps_per_s": rates,
                    "ratio": ratio,
                },
                f,
                indent=1,
            )


if __name__ == "__main__":
    main()
