"""CPU seconds per image on ONE thread: both shipped networks, OpenCV and XFeat, for a machine
too busy for wall-clock images/s.

Wall-clock rates on a shared machine measure the other processes as much as the detector, and
multi-threaded runtimes suffer most (a parallel region waits for its slowest thread, descheduled
or not). The CPU time a single-threaded call uses is close to what it costs on an idle core:
XLA runs on one thread (``--xla_cpu_multi_thread_eigen=false``), torch too
(``torch.set_num_threads(1)``), OpenCV too (``cv2.setNumThreads(1)``). Each method's number is
the median of ``--repeats`` calls' process CPU time (``time.process_time``), after a warm-up,
on the same photos as ``usp-jax benchmark``; images/s per core = 1 / that. From the repository
root::

    python3 benchmarks/bench_cpu_time.py --size 240x320 480x640
"""

from __future__ import annotations

import os

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false"
    " intra_op_parallelism_threads=1"
)

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import common  # noqa: E402
import cv2  # noqa: E402

from usp_jax.evaluation import benchmark  # noqa: E402
from usp_jax.inference import Detector  # noqa: E402
from usp_jax.inference import methods as adapters  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", nargs="+", default=["240x320"], help="HxW sizes")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()
    print(common.environment())
    cv2.setNumThreads(1)
    try:
        model = adapters.load_xfeat()
        import torch

        torch.set_num_threads(1)
    except adapters.XFeatNotInstalled as err:
        model = None
        print(f"XFeat: not timed, {err}")
    photos = benchmark.benchmark_photos()
    rows = []
    for size in args.size:
        height, width = (int(v) for v in size.lower().split("x"))
        top_n = benchmark.protocol_top_n(height, width)
        resized = [cv2.resize(p, (width, height), interpolation=cv2.INTER_AREA) for p in photos]
        methods = {
            f"UnsuperPoint {name}": Detector.pretrained(name, top_n=top_n).detect
            for name in ("paper", "fast")
        }
        methods |= {n: adapters.opencv_method(n, top_n).detect for n in ("ORB", "SIFT")}
        if model is not None:
            methods["XFeat"] = adapters.xfeat_method(top_n, model=model).detect
        print(f"{size}, top {top_n} points, one thread, CPU time per image (median):")
        for name, detect in methods.items():
            stream = itertools.cycle(resized)
            runs = common.time_calls(
                lambda: detect(next(stream)), args.repeats, clock=time.process_time
            )
            seconds = statistics.median(runs)
            rows.append({"method": name, "size": size, "cpu_s": seconds})
            print(f"  {name:20s} {1e3 * seconds:8.1f} ms  {1 / seconds:7.1f} images/s per core")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"environment": common.environment(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
