"""Inference speed: the jitted network + top-N against the matmul ceiling and PyTorch.

For each batch size, on the same uint8 photo crops and in alternating blocks of calls: JAX
(``UnsuperPoint.apply`` in eval mode and ``lax.top_k``, jitted with the library's compiler
options), ``usp_jax.Detector.detect_batch`` (adds padding, NMS and the host round trip) and the
PyTorch reference (``torch.inference_mode``, channels-last). GFLOP/s count the network's
convolutions (13.6 GFLOP per 240x320 image); the ceiling is a 4096^2 float32 matmul measured in
the same run.

    python3 benchmarks/bench_inference.py                    # 240x320, batch 1 and 10
    python3 benchmarks/bench_inference.py --size 480x640 --batch 1
    python3 benchmarks/bench_inference.py --no-torch --upsample 2   # + Detector(upsample=2)

With ``--upsample S`` a ``Detector(upsample=S)`` row joins the alternation; its GFLOP/s count
the network on the S times larger image.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import common
from usp_jax import config as config_lib
from usp_jax import data
from usp_jax.model import ModelConfig, UnsuperPoint, compiler_options, init_variables


def jax_detect(config: ModelConfig, top_n: int):
    """jit(uint8 [B, H, W, 3] -> (scores, keypoints, descriptors) of the top_n points)."""
    model = UnsuperPoint(config)

    def detect(variables, images):
        pred = model.apply(variables, images.astype(jnp.float32) / 255.0)
        scores, index = jax.lax.top_k(pred.scores, min(top_n, pred.scores.shape[1]))

        def take(x):
            return jnp.take_along_axis(x, index[:, :, None], axis=1)

        return scores, take(pred.keypoints), take(pred.descriptors)

    return jax.jit(detect, compiler_options=compiler_options())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="240x320", help="HxW (default 240x320)")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 10])
    parser.add_argument("--top", type=int, default=300, help="points kept per image")
    parser.add_argument("--rounds", type=int, default=3, help="alternations of the methods")
    parser.add_argument("--block", type=int, default=5, help="timed calls per round and method")
    parser.add_argument("--no-torch", action="store_true")
    parser.add_argument("--upsample", type=int, default=1,
                        help="also time Detector(upsample=S) when S > 1")
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()

    height, width = (int(v) for v in args.size.lower().split("x"))
    config = ModelConfig()
    variables = init_variables(jax.random.PRNGKey(0), config)
    print(common.environment())
    ceiling = common.matmul_ceiling()
    gflop = common.forward_gflop(config, height, width)
    print(f"{height}x{width}: {gflop:.1f} GFLOP per image; matmul ceiling {ceiling:.0f} GFLOP/s, "
          f"so at most {ceiling / gflop:.1f} images/s")
    detect = jax_detect(config, args.top)
    from usp_jax.inference import Detector

    detector = Detector(variables, config, top_n=args.top)
    upsampled_name = f"Detector(upsample={args.upsample})"
    if args.upsample > 1:
        upsampled = Detector(variables, config, top_n=args.top, upsample=args.upsample)
    if not args.no_torch:
        import torch
        import torch_reference

        reference = torch_reference.TorchUnsuperPoint(config).to(
            memory_format=torch.channels_last).eval()
        torch_reference.load_flax_variables(reference, variables)

    sample = config_lib.override(config_lib.paper(), [
        "data.source=sample", f"data.height={height}", f"data.width={width}"]).data
    results = {"height": height, "width": width, "matmul_gflops": ceiling, "rows": []}
    # One batch of the largest size, sliced: make_dataset(..., 1, ...) overflows grain's length.
    photos = np.asarray(data.make_dataset(sample, max(max(args.batch), 2), seed=0)[0])
    for batch in args.batch:
        images = photos[:batch]
        device_images = jax.device_put(images)
        start = time.perf_counter()
        compiled = detect.lower(variables, device_images).compile()
        compile_s = time.perf_counter() - start
        runs = {"JAX jit(apply + top_k)": lambda: compiled(variables, device_images),
                "usp_jax.Detector.detect_batch": lambda: detector.detect_batch(images)}
        if args.upsample > 1:
            runs[upsampled_name] = lambda: upsampled.detect_batch(images)
        if not args.no_torch:
            torch_images = torch.from_numpy(images)

            def run_torch():
                x = torch_images.permute(0, 3, 1, 2).float().div_(255).contiguous(
                    memory_format=torch.channels_last)
                return torch_reference.detect(reference, x, args.top)

            runs["torch inference_mode"] = run_torch
        for run in runs.values():  # compiles the Detector, creates the oneDNN primitives
            jax.block_until_ready(run())
        times = common.interleaved(runs, args.rounds, args.block)
        for name, t in times.items():
            results["rows"].append({"batch": batch, "method": name, "seconds": t,
                                    "compile_s": compile_s})
    ceiling = results["matmul_gflops"] = common.settled_ceiling(ceiling)
    print(f"matmul ceiling, the better of before and after the timings: {ceiling:.0f} GFLOP/s")
    for batch in args.batch:
        rows = [row for row in results["rows"] if row["batch"] == batch]
        print(f"batch {batch} (JAX compile {rows[0]['compile_s']:.1f} s):")
        for row in rows:
            seconds = statistics.median(row["seconds"])
            scale = args.upsample**2 if row["method"] == upsampled_name else 1
            rate = batch * gflop * scale / seconds
            print(f"  {row['method']:32s} {common.summary(row['seconds'])}  "
                  f"{batch / seconds:6.2f} img/s  {rate:5.1f} GFLOP/s = {rate / ceiling:4.0%} of "
                  "the ceiling")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
