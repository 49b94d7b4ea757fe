"""Point maps from depth and pose (host) and sampled at points (device), against closed forms."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core import losses, point_maps
from usp_jax.core.model import Predictions

K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])


def plane(depth: float, height: int = 48, width: int = 64) -> np.ndarray:
    return np.full((height, width), depth)


def test_a_sideways_step_before_a_wall_shifts_every_pixel_by_focal_times_baseline_over_depth():
    t = np.array([-0.2, 0.0, 0.0])  # camera 2 is 0.2 to the right: points move left by f*0.2/Z
    a_to_b, b_to_a = point_maps.from_depth(plane(4.0), plane(4.0), K, K, np.eye(3), t)
    ys, xs = np.mgrid[0:48, 0:64]
    shift = 100.0 * 0.2 / 4.0  # 5 px
    seen = xs >= shift
    np.testing.assert_allclose(a_to_b[seen][:, 0], (xs - shift)[seen], atol=1e-4)
    np.testing.assert_allclose(a_to_b[seen][:, 1], ys[seen], atol=1e-4)
    assert np.isnan(a_to_b[~seen]).all()
    np.testing.assert_allclose(b_to_a[xs <= 63 - shift][:, 0], (xs + shift)[xs <= 63 - shift])


def test_a_slanted_plane_maps_as_the_homography_it_induces():
    """H = K2 (R + t n^T / d) K1^-1 for the plane n . X = d in camera 1: X2 = R X + t (n . X) / d
    (Hartley and Zisserman, result 13.1, whose plane is n . X + d = 0)."""
    height, width = 48, 64
    n, d = np.array([0.0, -0.3, 1.0]) / np.linalg.norm([0.0, -0.3, 1.0]), 3.0
    rays = np.stack([*np.mgrid[0:height, 0:width][::-1], np.ones((height, width))], -1)
    rays = rays @ np.linalg.inv(K).T
    depth1 = d / (rays @ n)  # z of the ray's meeting with the plane (rays have z = 1)
    angle = np.radians(5.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([0.1, 0.05, 0.02])
    H = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
    # View 2's depth of the same plane: n2 = R n, d2 = d + n2 . t.
    n2, d2 = R @ n, d + (R @ n) @ t
    depth2 = d2 / (rays @ n2)
    a_to_b, _ = point_maps.from_depth(depth1, depth2, K, K, R, t)
    expected = cv2.perspectiveTransform(
        np.stack(np.mgrid[0:height, 0:width][::-1], -1).reshape(1, -1, 2).astype(np.float64), H
    ).reshape(height, width, 2)
    seen = np.isfinite(a_to_b[..., 0])
    assert seen.mean() > 0.5
    np.testing.assert_allclose(a_to_b[seen], expected[seen], atol=1e-3)


def test_what_a_nearer_surface_hides_in_the_second_view_has_no_partner():
    near = plane(4.0)
    near[16:32, 24:40] = 2.0  # a box 2 m away before a wall 4 m away
    t = np.array([-0.2, 0.0, 0.0])  # the box moves 10 px left, the wall 5 px
    a_to_b, b_to_a = point_maps.from_depth(near, near_in_view_2(), K, K, np.eye(3), t)
    # Wall pixels just left of the box land where view 2 sees the box: hidden.
    assert np.isnan(a_to_b[20, 20]).all()
    np.testing.assert_allclose(a_to_b[20, 30], [20.0, 20.0], atol=1e-4)  # the box itself
    np.testing.assert_allclose(a_to_b[20, 50], [45.0, 20.0], atol=1e-4)  # the wall, clear of it
    assert np.isfinite(b_to_a[20, 20]).all()


def near_in_view_2() -> np.ndarray:
    depth = plane(4.0)
    depth[16:32, 14:30] = 2.0  # the box, 10 px further left
    return depth


def test_points_between_pixels_are_mapped_bilinearly_and_unseen_ones_leave_the_image():
    field = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), -1) * 2.0  # (x, y) -> (2x, 2y)
    field[0, 7] = np.nan
    mapped = point_maps.map_points(
        jnp.asarray(field, jnp.float32), jnp.array([[2.0, 3.0], [2.25, 3.5], [6.5, 0.5]])
    )
    np.testing.assert_allclose(mapped[:2], [[4.0, 6.0], [4.5, 7.0]], atol=1e-6)
    np.testing.assert_array_equal(mapped[2], [point_maps.OUTSIDE, point_maps.OUTSIDE])


def test_the_gradient_through_a_map_is_finite_beside_unseen_pixels():
    field = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), -1).astype(np.float32)
    field[2, 3] = np.nan

    def total(xy):
        return jnp.sum(point_maps.map_points(jnp.asarray(field), xy))

    grad = jax.grad(total)(jnp.array([[2.5, 1.5], [5.5, 4.5]]))
    assert np.isfinite(grad).all()
    np.testing.assert_allclose(grad[1], [1.0, 1.0], atol=1e-6)


def affine_maps(H: np.ndarray, height: int, width: int) -> point_maps.PointMaps:
    grid = np.stack(np.mgrid[0:height, 0:width][::-1], -1).reshape(1, -1, 2).astype(np.float64)

    def mapped(h):
        xy = cv2.perspectiveTransform(grid, h).reshape(height, width, 2)
        inside = (xy >= -0.5).all(-1) & (xy[..., 0] <= width - 0.5) & (xy[..., 1] <= height - 0.5)
        return jnp.asarray(np.where(inside[..., None], xy, np.nan), jnp.float32)

    return point_maps.PointMaps(mapped(H), mapped(np.linalg.inv(H)))


def test_the_loss_on_point_maps_equals_the_loss_on_the_homography_they_sample():
    """An affine T is exact under bilinear interpolation, so every term must agree."""
    height, width, m = 32, 48, 24
    H = np.array([[0.97, 0.05, 2.3], [-0.04, 1.02, -1.7], [0, 0, 1]])
    rng = np.random.default_rng(0)

    def prediction():
        xy = rng.uniform([0, 0], [width - 1, height - 1], (m, 2))
        desc = rng.normal(size=(m, 16))
        return Predictions(
            scores=jnp.asarray(rng.uniform(size=m), jnp.float32),
            keypoints=jnp.asarray(xy, jnp.float32),
            relative=jnp.asarray(rng.uniform(size=(m, 2)), jnp.float32),
            descriptors=jnp.asarray(
                desc / np.linalg.norm(desc, axis=1, keepdims=True), jnp.float32
            ),
        )

    a, b = prediction(), prediction()
    b = b._replace(
        keypoints=b.keypoints.at[:12].set(
            jnp.asarray(
                cv2.perspectiveTransform(np.asarray(a.keypoints[:12], np.float64)[None], H)[0]
                + 0.7,
                jnp.float32,
            )
        )
    )
    on_h, metrics_h = losses.pair_loss(a, b, jnp.asarray(H, jnp.float32), height, width)
    on_maps, metrics_m = losses.pair_loss(a, b, affine_maps(H, height, width), height, width)
    assert metrics_h["usp/K"] >= 10
    np.testing.assert_allclose(on_maps, on_h, rtol=1e-4)
    for key in ("usp/K", "usp/position", "loss/desc", "positives"):
        np.testing.assert_allclose(metrics_m[key], metrics_h[key], rtol=1e-4, err_msg=key)
