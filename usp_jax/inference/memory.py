"""Whether an image fits in memory before the network runs on it: an estimate of the network's
activations at that size against the memory free now, so that a photo too large for native
size is refused in one line naming ``max_side`` instead of aborting the process (a failed
allocation inside XLA ends it with ``std::bad_alloc``).
"""

from __future__ import annotations

import math
import os
import pathlib

import jax

from usp_jax.core.model import CELL, ModelConfig

#: Bytes of one activation value: float32, as the network runs on CPU (conservative elsewhere).
_VALUE_BYTES = 4
#: Headroom over the estimate for XLA's own buffers and the host's copies of the image.
_MARGIN = 1.25


class ImageTooLarge(ValueError):
    """An image whose activations would not fit in the memory free now."""


def activation_bytes(model_config: ModelConfig, batch: int, height: int, width: int) -> int:
    """Peak bytes of the network's activations on ``batch`` images of ``height x width`` px
    (network pixels, after any enlargement).

    The peak is the first full-resolution convolution's input and output, with the output of
    the next one being written ([B, H, W, 3 + 2 * C1] values, C1 = ``backbone_channels[0]``), plus
    the heads at cell resolution; XLA's own figure (``memory_analysis``) is 256 B per pixel for
    the paper network, where this gives 268 B before the margin (a test compares them).
    """
    first = model_config.backbone_channels[0]
    per_pixel = 3 + 2 * first
    per_cell = 2 * model_config.head_channels + model_config.descriptor_dim
    per_cell += model_config.backbone_channels[-1]
    values = batch * height * width * (per_pixel + per_cell / CELL**2)
    return int(_MARGIN * _VALUE_BYTES * values)


def packing_bytes(model_config: ModelConfig, batch: int, height: int, width: int) -> int:
    """Bytes XLA:CPU's convolutions reserve (address space, mostly never touched) on ``batch``
    images of ``height x width`` network pixels: Eigen packs a 3x3 convolution's input as
    [pixels, 9 C_in] before its matrix product, so the largest such layer asks for
    4 x 9 x C_in bytes per pixel of its resolution at once, whatever is free. The paper
    network's second full-resolution convolution (C_in 32: 1,152 B per pixel) makes a 6000x4000
    photo ask for 28 GB, which the kernel refuses on a 24 GB machine (``std::bad_alloc``), while
    4600x3400 (18 GB) runs with 4.5 GB resident."""
    channels = model_config.backbone_channels
    if model_config.backbone == "vgg":  # (C_in, 2^-level resolution) of each conv layer
        layers = [(3, 0), (channels[0], 0)] + [(c, 1 + i // 2) for i, c in enumerate(channels[1:7])]
    else:  # fast: one conv per resolution into it, then residual convs at 1/4 and 1/8
        layers = [(3, 0), (channels[0], 1), (channels[1], 2), (channels[2], 2), (channels[3], 3)]
    layers.append((channels[-1], 3))  # the heads' first convs
    per_pixel = max(9 * c / 4**level for c, level in layers)
    return int(_VALUE_BYTES * per_pixel * batch * height * width)


def reservable_bytes() -> int | None:
    """The largest single allocation the system grants (Linux' overcommit policy): RAM plus
    swap under its default heuristic, the commit limit left under strict accounting, no limit
    (None) when it always overcommits, or on an accelerator (Eigen packs only on CPU)."""
    if jax.local_devices()[0].platform != "cpu":
        return None
    try:
        mode = pathlib.Path("/proc/sys/vm/overcommit_memory").read_text().strip()
        info = {
            line.split(":")[0]: int(line.split()[1]) * 1024
            for line in pathlib.Path("/proc/meminfo").read_text().splitlines()
            if line.split()[1:2] and line.split()[1].isdigit()
        }
    except (OSError, ValueError, IndexError):
        return None
    if mode == "1":
        return None
    if mode == "2":
        return info.get("CommitLimit", 0) - info.get("Committed_AS", 0)
    return info.get("MemTotal", 0) + info.get("SwapTotal", 0) or None


def available_bytes() -> int | None:
    """Memory free for the computation now: the device's free memory on an accelerator, else
    the host's ``MemAvailable`` (``/proc/meminfo``) within the process's cgroup limit, else
    ``os.sysconf``'s available pages; None when nothing says."""
    device = jax.local_devices()[0]
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
        return None
    free = []
    try:
        for line in pathlib.Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                free.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = pathlib.Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = pathlib.Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit.isdigit() and used.isdigit():
            free.append(int(limit) - int(used))
    except OSError:
        pass
    if not free:
        try:
            free.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            return None
    return min(free)


#: (network, batch shape, enlargement) that fitted once: checked again, they would only cost
#: time (a millisecond, as much as a small image's detection), and XLA reuses their buffers.
_FITTED: set[tuple] = set()


#: Side of the image at which :func:`measured_bytes_per_pixel` asks XLA.
REFERENCE_SIDE = 128
#: Below this share of the free memory the network's own estimate decides alone: whatever the
#: compiled function adds (the refinement, the pyramid) stays within it.
_CLEAR_SHARE = 0.25


def measured_bytes_per_pixel(
    forward, variables, top_n: int | None, any_scale: bool = False
) -> float:
    """XLA's own figure (``memory_analysis``: temporaries and outputs) for the jitted detector
    function ``forward`` on one ``REFERENCE_SIDE`` square image, per input pixel. One small
    compile; covers every stage the function runs. The pyramid's function (``any_scale``) takes
    the images alone, the single-scale one their sizes too."""
    side = REFERENCE_SIDE
    images = jax.ShapeDtypeStruct((1, side, side, 3), "uint8")
    sizes = () if any_scale else (jax.ShapeDtypeStruct((1, 2), "int32"),)
    analysis = forward.lower(variables, images, *sizes, top_n=top_n).compile().memory_analysis()
    return (analysis.temp_size_in_bytes + analysis.output_size_in_bytes) / side**2


def check_fits(
    model_config: ModelConfig, shape: tuple[int, ...], upsample: int = 1, measure=None
) -> None:
    """Raises ImageTooLarge unless the activations on a uint8 [B, H, W, 3] batch of ``shape``,
    enlarged ``upsample`` times, fit in the memory free now. The network's estimate
    (:func:`activation_bytes`) decides when it is far below the free memory; otherwise
    ``measure()`` (bytes per input pixel, :func:`measured_bytes_per_pixel`) gives the need of
    the whole compiled function. The message names the ``max_side`` (``--max-side``) at which
    it would fit."""
    key = (model_config, tuple(shape), upsample)
    if key in _FITTED:
        return
    batch, height, width = shape[:3]
    need = activation_bytes(model_config, batch, height * upsample, width * upsample)
    free = available_bytes()
    if free is not None and need > _CLEAR_SHARE * free and measure is not None:
        need = int(_MARGIN * measure() * batch * height * width)
    reserve = packing_bytes(model_config, batch, height * upsample, width * upsample)
    limit = reservable_bytes()
    if limit is not None and reserve > limit:  # an abort inside XLA, however much is free
        need, free = reserve, limit
        what = "to reserve for its convolutions, the system grants at most"
    elif free is None or need <= free:
        _FITTED.add(key)
        return
    else:
        what = "for the network,"
    # The need grows with the pixel count: the side that fits, to whole cells.
    # A tenth below: smaller images pad to whole cells.
    side = max(CELL, int(0.9 * max(height, width) * math.sqrt(free / need)) // CELL * CELL)
    images = f"{batch} images" if batch > 1 else "an image"
    raise ImageTooLarge(
        f"{images} of {width}x{height} px{f' enlarged {upsample}x' if upsample > 1 else ''}"
        f" needs about {need / 2**30:.1f} GiB {what} {max(free, 0) / 2**30:.1f} GiB"
        f"{' are free' if what.endswith(',') else ''}; detect on a smaller copy:"
        f" --max-side {side} or less (max_side={side})"
    )
