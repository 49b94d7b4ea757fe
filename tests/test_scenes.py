"""Ray-cast scenes: points land where K [R | t] (OpenCV's projectPoints) puts them, depth is the
plane's, and two views of a room agree through the depth."""

import cv2
import numpy as np
import pytest

from usp_jax.evaluation import scenes
from usp_jax.inference.images import read_image, sample_photos


def _surface(texture, origin, right, down, levels=1):
    """A surface with the first ``levels`` levels of the texture's pyramid."""
    return scenes.Surface(
        np.asarray(origin, float),
        np.asarray(right, float),
        np.asarray(down, float),
        scenes.pyramid(texture)[:levels],
    )


def _wall(texture, origin=(-1.0, 3.0, 2.0), right=(2.0, 0.0, 0.0), down=None, levels=1):
    """A scene of one wall facing -y (its photo's right along +x), 2 m wide by default."""
    height, width = texture.shape[:2]
    down = (0.0, 0.0, -2.0 * height / width) if down is None else down
    surface = _surface(texture, origin, right, down, levels)
    return scenes.Scene((surface,), np.zeros(3), np.ones(3), np.zeros((0, 2, 2)))


def _camera(centre, target, roll=0.0, height=120, width=160):
    R, t = scenes.look_at(centre, target, roll)
    return scenes.Camera(scenes.intrinsics(height, width), R, t, height, width)


def _opencv_projection(points: np.ndarray, camera: scenes.Camera) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(camera.R)
    pixels, _ = cv2.projectPoints(points, rvec, camera.t, camera.K, None)
    return pixels[:, 0]


def test_a_bright_mark_on_a_wall_renders_where_opencv_projects_it():
    # Texels 2 cm wide seen from about 1.3 m: each spans ~3 pixels, so the bilinear lookup
    # draws the mark smoothly and its centroid is its centre's projection.
    texture = np.zeros((50, 100, 3), np.uint8)
    texture[24:27, 59:62] = 255  # a 3-texel square centred on texel (60, 25)
    scene = _wall(texture)
    camera = _camera((0.3, 1.7, 1.4), (0.2, 3.0, 1.1), roll=7.0)
    image, _ = scenes.render(scene, camera)
    surface = scene.surfaces[0]
    mark = surface.origin + (60.5 / 100) * surface.right + (25.5 / 50) * surface.down
    expected = _opencv_projection(mark[None], camera)[0]
    grey = image[..., 0].astype(float)
    ys, xs = np.mgrid[: grey.shape[0], : grey.shape[1]]
    centroid = np.array([(xs * grey).sum(), (ys * grey).sum()]) / grey.sum()
    assert np.allclose(centroid, expected, atol=0.05)


def test_every_hit_projects_back_to_its_pixel():
    scene = _wall(np.full((100, 100, 3), 128, np.uint8), right=(2.0, 0.5, 0.0))
    camera = _camera((0.0, 0.0, 1.5), (0.4, 3.0, 1.0), roll=-4.0)
    hits = scenes.cast(scene, camera)
    seen = hits["surface"] == 0
    surface = scene.surfaces[0]
    points = (
        surface.origin
        + hits["a"][seen][:, None] * surface.right
        + hits["b"][seen][:, None] * surface.down
    )
    ys, xs = np.nonzero(seen)
    assert seen.mean() > 0.2
    assert np.abs(_opencv_projection(points, camera) - np.stack([xs, ys], 1)).max() < 2e-3


def test_depth_is_the_planes_along_each_pixels_ray():
    # A slanted wall seen obliquely: in the camera frame the plane is n.X = d, so the pixel p's
    # ray K^-1 p (z = 1) meets it at depth d / (n . K^-1 p).
    scene = _wall(np.full((100, 100, 3), 128, np.uint8), right=(3.0, 1.0, 0.0), down=(0, -0.5, -3))
    camera = _camera((0.0, 0.0, 1.0), (0.5, 3.0, 0.4), roll=3.0)
    _, depth = scenes.render(scene, camera)
    surface = scene.surfaces[0]
    normal = camera.R @ np.cross(surface.right, surface.down)
    offset = normal @ (camera.R @ surface.origin + camera.t)
    ys, xs = np.mgrid[: camera.height, : camera.width]
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(camera.K).T
    expected = offset / (rays @ normal)
    seen = np.isfinite(depth)
    assert seen.mean() > 0.2
    assert np.allclose(depth[seen], expected[seen], rtol=1e-5)


def test_a_frontal_wall_has_its_distance_as_depth_everywhere():
    scene = _wall(
        np.full((400, 400, 3), 90, np.uint8), origin=(-4, 2.5, 5), right=(8, 0, 0), down=(0, 0, -10)
    )
    _, depth = scenes.render(scene, _camera((0.0, 0.0, 1.0), (0.0, 1.0, 1.0)))
    assert np.allclose(depth, 2.5, rtol=1e-6)


def test_the_nearer_of_two_walls_hides_the_farther():
    near = _surface(np.full((10, 10, 3), 50, np.uint8), (-0.5, 3.0, 2.0), (1, 0, 0), (0, 0, -1))
    far = _surface(np.full((10, 10, 3), 200, np.uint8), (-5, 6.0, 6.5), (10, 0, 0), (0, 0, -10))
    for order in ((near, far), (far, near)):
        scene = scenes.Scene(order, np.zeros(3), np.ones(3), np.zeros((0, 2, 2)))
        image, depth = scenes.render(scene, _camera((0.0, 0.0, 1.5), (0.0, 1.0, 1.5)))
        assert image[60, 80, 0] == 50 and np.isclose(depth[60, 80], 3.0)
        assert image[5, 5, 0] == 200 and np.isclose(depth[5, 5], 6.0)


def test_a_distant_fine_checkerboard_renders_as_its_mean_grey_not_aliased():
    # One-texel squares, ~3 texels per pixel: a single level aliases into a pattern, the
    # pyramid's trilinear lookup averages them to grey.
    checker = (np.indices((1024, 1024)).sum(axis=0) % 2 * 255).astype(np.uint8)
    texture = np.repeat(checker[..., None], 3, axis=2)
    camera = _camera((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    camera_near = _camera((0.0, 7.0, 0.0), (0.0, 8.0, 0.0))
    origin, right, down = (-10, 8.0, 10), (20, 0, 0), (0, 0, -20)
    aliased, _ = scenes.render(_wall(texture, origin, right, down, levels=1), camera)
    filtered, _ = scenes.render(_wall(texture, origin, right, down, levels=11), camera)
    near, _ = scenes.render(_wall(texture, origin, right, down, levels=11), camera_near)
    assert aliased[..., 0].std() > 30
    assert abs(filtered[..., 0].mean() - 127.5) < 2 and filtered[..., 0].std() < 3
    assert near[..., 0].std() > 30  # from 1 m a texel spans ~3 pixels: the full-size level


@pytest.fixture(scope="module")
def room():
    photos = [read_image(p) for _, p in sample_photos() if "motorcycle" not in p.name]
    return scenes.room(photos, seed=3)


def test_two_views_of_a_room_agree_through_the_depth(room):
    first, second = scenes.view_pairs(room, 1, height=120, width=160, seed=1)[0]
    image1, depth1 = scenes.render(room, first)
    image2, depth2 = scenes.render(room, second)
    both = scenes.covisible(depth1, first, depth2, second)
    pixels, _ = scenes.reproject(depth1, first, second)
    warped = cv2.remap(image2, *pixels.astype(np.float32).transpose(2, 0, 1), cv2.INTER_LINEAR)
    difference = np.abs(warped.astype(float) - image1)[both].mean()
    # The same pixels through the other camera's pose: they do not agree.
    shuffled, _ = scenes.reproject(
        depth1,
        first,
        scenes.Camera(second.K, second.R, second.t + 0.2, second.height, second.width),
    )
    wrong = cv2.remap(image2, *shuffled.astype(np.float32).transpose(2, 0, 1), cv2.INTER_LINEAR)
    assert both.mean() >= 0.3
    assert difference < 8.0 < np.abs(wrong.astype(float) - image1)[both].mean()


def test_the_relative_pose_takes_the_first_cameras_points_to_the_seconds(room):
    first, second = scenes.view_pairs(room, 1, height=60, width=80, seed=2)[0]
    points = np.random.default_rng(0).uniform(0, 3, (10, 3))
    R, t = scenes.relative_pose(first, second)
    in_first, in_second = points @ first.R.T + first.t, points @ second.R.T + second.t
    assert np.allclose(in_first @ R.T + t, in_second)
    assert scenes.rotation_angle(R) <= 30.0
    assert 0.2 <= np.linalg.norm(first.centre - second.centre) <= 1.0


def test_look_at_puts_the_target_at_the_principal_point_upright():
    camera = _camera((1.0, 2.0, 1.5), (3.0, -1.0, 0.5))
    pixels, depth = scenes.project(np.array([[3.0, -1.0, 0.5], [3.0, -1.0, 0.7]]), camera)
    assert np.allclose(pixels[0], camera.K[:2, 2]) and depth[0] > 0
    assert pixels[1, 1] < camera.K[1, 2]  # above the target: higher in the image
    assert np.allclose(camera.R @ camera.R.T, np.eye(3)) and np.isclose(np.linalg.det(camera.R), 1)


def test_a_scaled_camera_sees_each_point_at_the_scaled_pixel():
    camera = _camera((0.0, 0.0, 1.0), (1.0, 3.0, 1.2), height=120, width=160)
    small = scenes.scaled(camera, 0.25)
    point = np.array([[0.7, 2.9, 1.6]])
    assert (small.height, small.width) == (30, 40)
    assert np.allclose(
        scenes.project(point, small)[0], (scenes.project(point, camera)[0] + 0.5) / 4 - 0.5
    )


def test_a_camera_path_is_smooth_and_stays_clear(room):
    path = scenes.camera_path(room, 40, height=60, width=80, seed=0)
    centres = np.stack([c.centre for c in path])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    turns = [scenes.rotation_angle(b.R @ a.R.T) for a, b in zip(path, path[1:], strict=False)]
    assert len(path) == 40 and all(scenes.is_clear(room, c) for c in centres)
    assert steps.max() < 0.3 and max(turns) < 10.0 and np.ptp(centres, axis=0)[:2].max() > 0.5


def test_photos_of_the_evaluation_pairs_never_texture_a_scene(tmp_path):
    for name in ("graf1.png", "opencv-aloeL.jpg", "box_in_scene.png", "motorcycle_left.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="no photos"):
        scenes.load_photos(tmp_path)
    cv2.imwrite(str(tmp_path / "wall.png"), np.full((8, 8, 3), 7, np.uint8))
    photos = scenes.load_photos(tmp_path)
    assert len(photos) == 1 and photos[0][0, 0, 0] == 7
