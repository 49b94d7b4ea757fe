"""Point maps: where each pixel of one view lies in the other, for pairs no single homography
relates (two cameras in a 3-D scene: parallax and occlusion).

The paper's losses (section 4) need only the mapping of points from branch A to branch B, T p^A,
and back, to mask points the other view does not see. A homography gives it in closed form; a
pair of views with depth and a relative pose gives it per pixel (``from_depth``, on the host in
NumPy), and ``map_points`` samples such a map at the network's points on the device.

Conventions: pixel centres at integer (x, y) (``core.model``), cameras as OpenCV's (x right, y
down, z forward), a relative pose (R, t) takes the first camera's frame to the second's,
``x2 = R x1 + t``, and a pixel's depth is its z, so ``depth * K^-1 [x, y, 1]`` is the point in its
camera's frame. A map is float32 ``[H, W, 2]``, NaN where the other view does not see the pixel
(outside its image, behind it, or hidden by something nearer).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np

#: Where ``map_points`` puts a point the other view does not see: outside every image.
OUTSIDE = -1e4


class PointMaps(NamedTuple):
    """The correspondence of a pair of views, both ways: ``a_to_b`` [H, W, 2] is where each pixel
    of A lies in B (NaN: not seen there), ``b_to_a`` the same from B to A. Batched: [B, H, W, 2]."""

    a_to_b: jax.Array
    b_to_a: jax.Array


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The point [H, W, 3] each pixel sees, in its camera's frame, from ``depth`` [H, W]."""
    height, width = depth.shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    pixels = np.stack([xs, ys, np.ones_like(xs)], axis=-1)
    return (pixels @ np.linalg.inv(K).T) * depth[..., None]


def transfer(
    depth: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of view 1 lands in view 2: (pixels [H, W, 2], depth there [H, W]), from
    view 1's ``depth`` [H, W], the intrinsics [3, 3] and the relative pose (R [3, 3], t [3])."""
    local = backproject(depth, K1) @ np.asarray(R).T + np.ravel(t)
    projected = local @ np.asarray(K2).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return projected[..., :2] / projected[..., 2:], local[..., 2]


def seen(
    pixels: np.ndarray, z: np.ndarray, depth2: np.ndarray, tolerance: float = 0.01
) -> np.ndarray:
    """bool [H, W]: which transferred pixels (``transfer``'s output) view 2 sees: inside its
    image, in front of it, and not hidden, i.e. its depth ``depth2`` [H2, W2] there (nearest
    pixel) within ``tolerance`` relative of the point's."""
    height, width = depth2.shape
    x, y = pixels[..., 0], pixels[..., 1]
    with np.errstate(invalid="ignore"):
        inside = (x >= 0) & (y >= 0) & (x <= width - 1) & (y <= height - 1) & (z > 0)
        there = cv2.remap(
            depth2.astype(np.float32),
            np.where(inside, x, -1).astype(np.float32),
            np.where(inside, y, -1).astype(np.float32),
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return inside & np.isfinite(z) & (np.abs(there - z) <= tolerance * z)


def from_depth(
    depth1: np.ndarray,
    depth2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    tolerance: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Both point maps of a pair of views (float32 [H1, W1, 2] and [H2, W2, 2], NaN where the
    other view does not see the pixel) from their depths, intrinsics and relative pose
    (``x2 = R x1 + t``). ``tolerance``: the relative depth difference still called the same
    surface (module docstring)."""
    R, t = np.asarray(R, np.float64), np.ravel(t).astype(np.float64)
    maps = []
    for depth, other, Ka, Kb, Ra, ta in (
        (depth1, depth2, K1, K2, R, t),
        (depth2, depth1, K2, K1, R.T, -R.T @ t),
    ):
        pixels, z = transfer(np.asarray(depth, np.float64), Ka, Kb, Ra, ta)
        visible = seen(pixels, z, np.asarray(other), tolerance)
        maps.append(np.where(visible[..., None], pixels, np.nan).astype(np.float32))
    return maps[0], maps[1]


def map_points(point_map: jax.Array, xy: jax.Array) -> jax.Array:
    """``point_map`` [H, W, 2] sampled bilinearly at the points ``xy`` [M, 2] -> [M, 2]: T p of
    section 4 for a pair of views no homography relates. A point whose four neighbouring pixels
    are not all seen in the other view goes to ``OUTSIDE``, so ``geometry.points_inside`` drops it;
    no NaN reaches the result or its gradient, which flows to ``xy`` as a homography's would."""
    height, width = point_map.shape[:2]
    x = jnp.clip(xy[:, 0], 0.0, width - 1.0)
    y = jnp.clip(xy[:, 1], 0.0, height - 1.0)
    x0 = jnp.clip(jnp.floor(x), 0, width - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, height - 2).astype(jnp.int32)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    corners = [point_map[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)]  # 4 x [M, 2]
    valid = jnp.all(jnp.stack([jnp.isfinite(c) for c in corners]), axis=(0, 2))
    c00, c01, c10, c11 = (jnp.where(jnp.isfinite(c), c, 0.0) for c in corners)
    top = c00 * (1 - fx) + c01 * fx
    bottom = c10 * (1 - fx) + c11 * fx
    mapped = top * (1 - fy) + bottom * fy
    return jnp.where(valid[:, None], mapped, OUTSIDE)
