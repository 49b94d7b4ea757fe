"""A match, then the next frame's detection: the match's matrix product on every BLAS thread
against one (``usp_jax.inference.threads``), side by side in one run.

OpenBLAS's worker threads busy-wait after a multi-threaded product before they sleep; what runs
next on those cores pays for it. This times the tracker's pattern on the bundled photos: the
product of two frames' 1000 x 128 descriptors (with the two norm columns, as
``inference.matching`` computes it), then ``track``'s default detector on the next frame, in
alternating blocks; and the detection alone. From the repository root::

    python3 benchmarks/bench_blas_threads.py
    python3 benchmarks/bench_blas_threads.py --rounds 10 --json out.json
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import itertools
import json
import statistics
import time

import common
import cv2
import jax
import numpy as np

from usp_jax.evaluation import benchmark
from usp_jax.inference import tracking
from usp_jax.inference.threads import one_blas_thread


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=6, help="alternations of the modes")
    parser.add_argument("--block", type=int, default=5, help="timed calls per round and mode")
    parser.add_argument("--points", type=int, default=1000, help="descriptors per frame")
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()
    print(common.environment())

    detector = tracking.default_detector()
    frames = [
        cv2.resize(p, (640, 480), interpolation=cv2.INTER_AREA)
        for p in benchmark.benchmark_photos()
    ]
    rng = np.random.default_rng(0)
    # 128-d unit descriptors plus the two norm columns of matching's product.
    a, b = (rng.standard_normal((args.points, 130)).astype(np.float32) for _ in range(2))
    jax.block_until_ready(detector.detect(frames[0]).keypoints)  # compiles
    next_frame = itertools.cycle(frames)
    modes = {"every BLAS thread": contextlib.nullcontext(), "one BLAS thread": one_blas_thread}
    parts = {name: {"product": [], "detection": []} for name in modes}

    def match_then_detect(name: str) -> None:
        start = time.perf_counter()
        with modes[name]:
            a @ b.T
        middle = time.perf_counter()
        detector.detect(next(next_frame))
        parts[name]["product"].append(middle - start)
        parts[name]["detection"].append(time.perf_counter() - middle)

    runs = {name: functools.partial(match_then_detect, name) for name in modes}
    runs["detection alone"] = lambda: detector.detect(next(next_frame))
    totals = common.interleaved(runs, args.rounds, args.block)
    results = {}
    for name, times in totals.items():
        row = {f"{k}_ms": 1e3 * statistics.median(v) for k, v in parts.get(name, {}).items()}
        row["total_ms"] = 1e3 * statistics.median(times)
        results[name] = row
        line = ", ".join(f"{k[:-3]} {v:.1f} ms" for k, v in row.items())
        print(f"{name:18s} {line} (medians of {len(times)})")
    if args.json:
        with open(args.json, "w") as file:
            document = {"environment": common.environment(), "points": args.points, **results}
            json.dump(document, file, indent=1)


if __name__ == "__main__":
    main()
