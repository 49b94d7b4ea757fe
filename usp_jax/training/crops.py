"""Random crops of training photos (paper section 5: 240x320 crops of COCO images), and their
square context windows for training at any rotation (``DataConfig.context_window``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from usp_jax.core.geometry import window_origin


def _draw_step(
    rng: np.random.Generator,
    image: np.ndarray,
    height: int,
    width: int,
    scale_range: tuple[float, float],
) -> float:
    """Photo pixels per output pixel of a random crop of ``image`` [H, W, 3]: the largest window of
    the output's aspect ratio inside the photo is fit * [height, width], and the crop's window is
    a fraction f ~ U(low, high) of it, ``scale_range`` raised where needed so that the window is
    at least the output size. Returns f * fit."""
    rows, cols = image.shape[:2]
    fit = min(rows / height, cols / width)
    smallest = min(1 / fit, 1.0)  # The fraction at which the window equals the output size.
    low, high = (max(s, smallest) for s in scale_range)
    return rng.uniform(low, high) * fit


def random_crop(
    rng: np.random.Generator,
    image: np.ndarray,
    height: int,
    width: int,
    scale_range: tuple[float, float] = (0.5, 1.0),
) -> np.ndarray:
    """A random rescale and crop of ``image`` [H, W, 3] -> uint8 [height, width, 3].

    Picks a window of the output's aspect ratio whose side is a fraction f ~ U(scale_range)
    (0 < low <= high <= 1) of the largest such window that fits, at a uniform position, and
    resizes it to the output. Up to resampling, that is rescaling the whole image by
    height / window height and then cropping, but it resizes only the pixels kept. f is raised
    so that the window is at least the output size; an image smaller than the output yields its
    largest window, upscaled.
    """
    rows, cols = image.shape[:2]
    step = _draw_step(rng, image, height, width, scale_range)
    window_rows = min(rows, round(step * height))
    window_cols = min(cols, round(step * width))
    top = rng.integers(rows - window_rows + 1)
    left = rng.integers(cols - window_cols + 1)
    window = image[top : top + window_rows, left : left + window_cols]
    # INTER_AREA averages the source pixels when shrinking (no aliasing); it is blocky when
    # enlarging, where bilinear is the usual choice.
    interpolation = cv2.INTER_AREA if window_rows > height else cv2.INTER_LINEAR
    return cv2.resize(window, (width, height), interpolation=interpolation)


def context_side(height: int, width: int) -> int:
    """Side of the square context window around a [height, width] crop: its diagonal, rounded up,
    so that the crop turned by any angle about its centre stays inside the window."""
    return math.ceil(math.hypot(height, width))


def _window_offset(
    length: int, crop: int, side: int, origin: int, step: float, rng: np.random.Generator
) -> float:
    """Photo coordinate of the window's first pixel centre along one axis, uniform over the
    positions that keep the crop inside the photo and, where the photo is long enough, the whole
    window too (else the whole photo inside the window, which pads least). Window pixel i shows
    photo coordinate offset + step * i; the crop covers window pixels [origin, origin + crop)."""
    # Both ends of the range that keeps the whole window inside the photo; swapped when the photo is
    # the shorter, they keep the whole photo inside the window instead.
    low, high = sorted((0.0, length - 1 - step * (side - 1)))
    low = max(low, -step * origin)
    high = min(high, length - 1 - step * (origin + crop - 1))
    return rng.uniform(low, max(low, high))


def random_context_crop(
    rng: np.random.Generator,
    image: np.ndarray,
    height: int,
    width: int,
    scale_range: tuple[float, float] = (0.5, 1.0),
) -> np.ndarray:
    """A random crop of ``image`` [H, W, 3] inside its context: uint8 [S, S, 4], S =
    ``context_side(height, width)``, for rotation-robust training (paper section 3's T drawn from
    the window, ``geometry.sample_window_homography``).

    The scale is drawn as in ``random_crop`` (a window of the crop's aspect ratio whose side is a
    fraction f ~ U(scale_range) of the largest that fits, f raised to keep it at least the output
    size), but one scale serves both axes and the square around the crop is kept too, at the same
    pixel scale. The crop, at ``geometry.window_origin(height, width, (S, S))``, lies inside the
    photo; so does the whole window when the photo is large enough, else it is padded with zeros.
    Channels 0-2 are RGB, channel 3 is 255 where the pixel shows the photo and 0 where it is padding
    (whose RGB is 0).
    """
    rows, cols = image.shape[:2]
    side = context_side(height, width)
    origin_x, origin_y = window_origin(height, width, (side, side))
    # Photo pixels per output pixel, the same on both axes so that a rotation is a rotation.
    step = _draw_step(rng, image, height, width, scale_range)
    # Pixel centres: window pixel (u, v) shows photo point (left + step * u, top + step * v).
    top = _window_offset(rows, height, side, origin_y, step, rng)
    left = _window_offset(cols, width, side, origin_x, step, rng)

    # Shrink (with INTER_AREA, no aliasing) only the part of the photo the window shows, to about
    # the output scale; the affine warp below then resamples it by a factor near 1.
    y0 = max(0, math.floor(top) - 1)
    y1 = min(rows, math.ceil(top + step * (side - 1)) + 2)
    x0 = max(0, math.floor(left) - 1)
    x1 = min(cols, math.ceil(left + step * (side - 1)) + 2)
    region = image[y0:y1, x0:x1]
    if step > 1:
        shrunk_rows = max(1, round((y1 - y0) / step))
        shrunk_cols = max(1, round((x1 - x0) / step))
        region = cv2.resize(region, (shrunk_cols, shrunk_rows), interpolation=cv2.INTER_AREA)
    scale_y, scale_x = (y1 - y0) / region.shape[0], (x1 - x0) / region.shape[1]
    # Window pixel -> region pixel, with cv2.resize's pixel-centre mapping of the shrinking.
    to_region = np.array(
        [
            [step / scale_x, 0.0, (left - x0 + 0.5) / scale_x - 0.5],
            [0.0, step / scale_y, (top - y0 + 0.5) / scale_y - 0.5],
        ]
    )
    # Replicating the border only fills the half region pixel at the photo's edge; pixels outside
    # the photo are zeroed by the mask below.
    rgb = cv2.warpAffine(
        region,
        to_region,
        (side, side),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    along = np.arange(side) * step
    inside_y = (top + along >= 0) & (top + along <= rows - 1)
    inside_x = (left + along >= 0) & (left + along <= cols - 1)
    valid = inside_y[:, None] & inside_x[None, :]
    window = np.zeros((side, side, 4), np.uint8)
    window[..., :3] = np.where(valid[..., None], rgb, 0)
    window[..., 3] = 255 * valid
    return window
