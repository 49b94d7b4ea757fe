"""Ray-cast 3-D scenes with known camera poses, for judging relative pose (``evaluation.pose``).

A scene is a room: four walls, a floor and a ceiling, each covered by real photos, and a few
free-standing panels inside it (photos on both faces) that hide parts of the walls from some
viewpoints, so two views differ by parallax and occlusion, not by one homography. Every surface is
a textured rectangle; a pinhole camera (intrinsics K, pose R, t) sees, at each pixel, the nearest
rectangle its ray meets, and the rendering looks the photo up bilinearly there, trilinearly
between the levels of its Gaussian pyramid so that distant or slanted surfaces do not alias.

Conventions: the world is metres with z up; a camera maps a world point X to ``R X + t`` in its
own frame (x right, y down, z forward, as OpenCV), and to pixels through K, pixel centres at
integers (``core.model``'s convention). A pixel's depth is that z, so ``depth * K^-1 [x, y, 1]``
is the point in the camera's frame. Poses are float64; depth is float32, ``inf`` where no surface
is met (only outside a room).

Photos come from any folder (``load_photos``); the evaluation pairs' photos (graf, aloe, box and
scikit-image's motorcycle, ``RESERVED``) are left out so that no benchmark meets them twice.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np

from usp_jax.core import point_maps
from usp_jax.inference.images import IMAGE_SUFFIXES, read_image

#: Words in a file name that keep a photo out of every scene: the real evaluation pairs.
RESERVED = ("graf", "aloe", "box", "motorcycle")
#: Longest side a texture is kept at: finer texels than a view can resolve only cost memory.
TEXTURE_SIDE = 1280
#: Nearest a camera centre comes to a wall or a panel, metres: nothing fills the view up close.
CLEARANCE = 0.7


@dataclasses.dataclass(frozen=True)
class Surface:
    """A textured rectangle: ``origin + a * right + b * down`` for a, b in [0, 1) is the point of
    the photo at fraction (a, b) of its width and height. ``levels`` is the photo's Gaussian
    pyramid, uint8 ``[h, w, 3]`` first, each next level half the size (``cv2.pyrDown``)."""

    origin: np.ndarray  # [3]
    right: np.ndarray  # [3]
    down: np.ndarray  # [3], orthogonal to right
    levels: tuple[np.ndarray, ...]


@dataclasses.dataclass(frozen=True)
class Scene:
    """Textured rectangles, the box a camera centre may roam (``low``, ``high``: [3] each) and
    the free-standing panels' footprints on the floor (``obstacles``: [K, 2, 2], (x, y) ends)."""

    surfaces: tuple[Surface, ...]
    low: np.ndarray
    high: np.ndarray
    obstacles: np.ndarray


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``K`` [3, 3], ``R`` [3, 3] and ``t`` [3] (world -> camera), image size."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    height: int
    width: int

    @property
    def centre(self) -> np.ndarray:
        """The camera's position in the world, ``-R^T t`` [3]."""
        return -self.R.T @ self.t


def intrinsics(height: int, width: int, fov_degrees: float = 60.0) -> np.ndarray:
    """K [3, 3] of square pixels with a horizontal field of view ``fov_degrees`` and the principal
    point at the image centre ``((width - 1) / 2, (height - 1) / 2)`` (centres at integers)."""
    focal = 0.5 * width / math.tan(math.radians(fov_degrees) / 2)
    return np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])


def look_at(centre, target, roll_degrees: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) of a camera at ``centre`` looking at ``target`` with the world's z up in
    the image (then turned by ``roll_degrees`` about the optical axis)."""
    centre, target = np.asarray(centre, np.float64), np.asarray(target, np.float64)
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)  # undefined looking straight up or down: never drawn here
    down = np.cross(forward, right)
    roll = math.radians(roll_degrees)
    right, down = (
        math.cos(roll) * right + math.sin(roll) * down,
        math.cos(roll) * down - math.sin(roll) * right,
    )
    R = np.stack([right, down, forward])
    return R, -R @ centre


def relative_pose(first: Camera, second: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) taking the first camera's frame to the second's, ``x2 = R x1 + t``: what
    ``cv2.recoverPose`` estimates (its t only up to scale)."""
    R = second.R @ first.R.T
    return R, second.t - R @ first.t


def project(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (pixels [N, 2], depth [N]) through ``K [R | t]``."""
    local = points @ camera.R.T + camera.t
    pixels = local @ camera.K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return pixels[:, :2] / pixels[:, 2:], local[:, 2]


def backproject(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """The world point [H, W, 3] seen at each pixel of a view with this ``depth`` [H, W]."""
    rays = _pixel_rays(camera)  # camera frame, z = 1
    local = rays * depth.reshape(-1, 1)
    return ((local - camera.t) @ camera.R).reshape(*depth.shape, 3)


def reproject(depth: np.ndarray, first: Camera, second: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the first view lands in the second: (pixels [H, W, 2], depth [H, W]
    in the second camera's frame), from the first view's ``depth`` [H, W]."""
    return point_maps.transfer(depth, first.K, second.K, *relative_pose(first, second))


def covisible(
    depth1: np.ndarray, first: Camera, depth2: np.ndarray, second: Camera, tolerance: float = 0.01
) -> np.ndarray:
    """bool [H, W]: the first view's pixels whose surface point the second view sees too: inside
    its image, in front of it, and not hidden (its depth there within ``tolerance`` relative)."""
    return point_maps.seen(*reproject(depth1, first, second), depth2, tolerance)


def _pixel_rays(camera: Camera) -> np.ndarray:
    """[H * W, 3] rays through the pixel centres in the camera's frame, scaled to z = 1."""
    return _pixels(camera) @ np.linalg.inv(camera.K).T


def _pixels(camera: Camera, dtype=np.float64) -> np.ndarray:
    """[H * W, 3] homogeneous pixel centres (x, y, 1), row by row."""
    ys, xs = np.mgrid[0 : camera.height, 0 : camera.width].astype(dtype)
    return np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size, dtype)], axis=1)


def _footprint_box(surface: Surface, camera: Camera) -> tuple[slice, slice] | None:
    """The rows and columns of the image the surface can cover: the box around its corners'
    projections, the rectangle first clipped to the space in front of the camera (None: none of
    it is in front, or its box misses the image)."""
    corners = surface.origin + np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) @ np.stack(
        [surface.right, surface.down]
    )
    local = corners @ camera.R.T + camera.t
    near = 1e-3
    kept = [p for p in local if p[2] >= near]
    for p, q in zip(local, np.roll(local, -1, axis=0), strict=True):
        if (p[2] - near) * (q[2] - near) < 0:  # the edge crosses the near plane
            kept.append(p + (q - p) * (near - p[2]) / (q[2] - p[2]))
    if not kept:
        return None
    pixels = np.stack(kept) @ camera.K.T
    pixels = pixels[:, :2] / pixels[:, 2:]
    left, top = np.maximum(np.floor(pixels.min(axis=0)).astype(int), 0)
    right = min(int(np.ceil(pixels[:, 0].max())), camera.width - 1)
    bottom = min(int(np.ceil(pixels[:, 1].max())), camera.height - 1)
    if left > right or top > bottom:
        return None
    return slice(top, bottom + 1), slice(left, right + 1)


def _linear(vector: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """float32 [h, w]: ``p . vector`` at the homogeneous pixel centres p = (x, y, 1) of ``box``."""
    xs = np.arange(box[1].start, box[1].stop, dtype=np.float32)
    ys = np.arange(box[0].start, box[0].stop, dtype=np.float32)
    v = vector.astype(np.float32)
    return (ys[:, None] * v[1] + v[2]) + xs[None, :] * v[0]


def cast(scene: Scene, camera: Camera) -> dict[str, np.ndarray]:
    """The nearest surface each pixel's ray meets: ``surface`` int [H, W] (-1: none), ``depth``
    float32 [H, W] (z in the camera frame, inf: none), ``a``, ``b`` float32 [H, W] (the hit's
    fraction of the surface's width and height) and ``cosine`` [H, W] (of the angle between ray and
    surface normal). A depth buffer over the surfaces, each within the box it can cover.

    The ray through pixel p is ``C + z M p`` (``M = R^T K^-1``, C the centre), so a plane with
    normal n through O is met at ``z = n.(O - C) / p.(M^T n)``, and the fraction along an edge u
    is ``(C - O).u / |u|^2 + z p.(M^T u) / |u|^2``: linear functions of p and one division."""
    shape = (camera.height, camera.width)
    hits = {"surface": np.full(shape, -1), "depth": np.full(shape, np.inf, np.float32)}
    hits |= {k: np.zeros(shape, np.float32) for k in ("a", "b", "cosine")}
    to_world = camera.R.T @ np.linalg.inv(camera.K)  # M
    centre = camera.centre
    # |K^-1 p|, the length of each pixel's ray per unit of depth.
    ray_length = np.linalg.norm(_pixel_rays(camera), axis=1).astype(np.float32).reshape(shape)
    for index, surface in enumerate(scene.surfaces):
        box = _footprint_box(surface, camera)
        if box is None:
            continue
        normal = np.cross(surface.right, surface.down)
        facing = _linear(to_world.T @ normal, box)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.float32(np.dot(surface.origin - centre, normal)) / facing
        fractions = []
        for edge in (surface.right, surface.down):
            scale = np.dot(edge, edge)
            start = np.float32(np.dot(centre - surface.origin, edge) / scale)
            fractions.append(start + depth * _linear(to_world.T @ edge / scale, box))
        a, b = fractions
        nearer = (depth > 1e-6) & (depth < hits["depth"][box])
        nearer &= (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
        cosine = np.abs(facing) / (np.linalg.norm(normal) * ray_length[box])
        for key, value in (
            ("surface", index),
            ("depth", depth),
            ("a", a),
            ("b", b),
            ("cosine", cosine),
        ):
            np.copyto(hits[key][box], value, where=nearer)
    return hits


def _texture_level(hits: dict, surface: Surface, focal: float, mask: np.ndarray) -> np.ndarray:
    """The pyramid level (float, [M]) whose texels match each pixel's footprint on ``surface``:
    the footprint's two axes are depth / f across the ray and depth / (f cos) along the slant;
    their geometric mean keeps slanted surfaces sharp without aliasing much."""
    texel = np.linalg.norm(surface.right) / surface.levels[0].shape[1]
    footprint = hits["depth"][mask] / (focal * np.sqrt(np.maximum(hits["cosine"][mask], 1e-3)))
    level = np.log2(np.maximum(footprint / texel, 1.0))
    return np.minimum(level, len(surface.levels) - 1)


def _shade(hits: dict, surface: Surface, mask: np.ndarray, level: np.ndarray) -> np.ndarray:
    """float32 [M, 3] colours of the pixels in ``mask`` on ``surface``: bilinear lookups in the
    two pyramid levels around ``level`` [M], blended linearly (trilinear filtering)."""
    rows, cols = np.nonzero(mask)
    top, left = rows.min(), cols.min()
    box = (slice(top, rows.max() + 1), slice(left, cols.max() + 1))
    inside = mask[box]
    colour = np.zeros((rows.size, 3), np.float32)
    for index in range(int(level.min()), min(int(level.max()) + 2, len(surface.levels))):
        weight = np.clip(1.0 - np.abs(level - index), 0.0, 1.0)
        if not weight.any():
            continue
        texture = surface.levels[index]
        # Fractions -> this level's pixel coordinates, centres at integers.
        u = hits["a"][box] * texture.shape[1] - 0.5
        v = hits["b"][box] * texture.shape[0] - 0.5
        sample = cv2.remap(texture, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        colour += weight[:, None] * sample[inside].astype(np.float32)
    return colour


def render(scene: Scene, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(image uint8 [H, W, 3] RGB, depth float32 [H, W]) of the scene seen by ``camera``."""
    hits = cast(scene, camera)
    image = np.zeros((camera.height, camera.width, 3), np.float32)
    focal = math.sqrt(camera.K[0, 0] * camera.K[1, 1])
    for index, surface in enumerate(scene.surfaces):
        mask = hits["surface"] == index
        if mask.any():
            level = _texture_level(hits, surface, focal, mask)
            image[mask] = _shade(hits, surface, mask, level)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), hits["depth"]


def load_photos(folder: str | Path, exclude: tuple[str, ...] = RESERVED) -> list[np.ndarray]:
    """The photos in ``folder`` (sorted by name) as uint8 RGB, none whose file name contains a
    word of ``exclude`` (any case). Raises ValueError when none is left."""
    paths = sorted(
        p
        for p in Path(folder).iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and not any(w in p.name.lower() for w in exclude)
    )
    if not paths:
        raise ValueError(
            f"{folder}: no photos to texture a scene with (after leaving out {exclude})"
        )
    return [read_image(p) for p in paths]


def _texture(photo: np.ndarray, aspect: float, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """The pyramid of a random crop of ``photo`` with width / height = ``aspect``, the crop's
    longer side at most TEXTURE_SIDE, down to a level of about 8 pixels."""
    height, width = photo.shape[:2]
    crop_w, crop_h = min(width, round(height * aspect)), min(height, round(width / aspect))
    top, left = rng.integers(0, height - crop_h + 1), rng.integers(0, width - crop_w + 1)
    crop = photo[top : top + crop_h, left : left + crop_w]
    scale = min(1.0, TEXTURE_SIDE / max(crop_h, crop_w))
    if scale < 1.0:
        size = (max(1, round(crop_w * scale)), max(1, round(crop_h * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
    return pyramid(crop)


def pyramid(photo: np.ndarray) -> tuple[np.ndarray, ...]:
    """A surface's ``levels``: ``photo`` uint8 [h, w, 3], then ``cv2.pyrDown`` halvings until a
    side would be under 8 pixels."""
    levels = [np.ascontiguousarray(photo)]
    while min(levels[-1].shape[:2]) >= 16:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


def _surface(origin, right, down, photo, rng) -> Surface:
    right, down = np.asarray(right, np.float64), np.asarray(down, np.float64)
    aspect = np.linalg.norm(right) / np.linalg.norm(down)
    return Surface(np.asarray(origin, np.float64), right, down, _texture(photo, aspect, rng))


def _shell(size: np.ndarray, photos, rng) -> list[Surface]:
    """Floor, ceiling and four walls of a room spanning [0, size]; walls wider than 3 m are
    split into tiles, each its own photo, so that no photo is stretched thin."""
    width, depth, height = size
    up = np.array([0.0, 0.0, height])
    surfaces = [
        _surface((0, 0, 0), (width, 0, 0), (0, depth, 0), photos(), rng),
        _surface((0, depth, height), (width, 0, 0), (0, -depth, 0), photos(), rng),
    ]
    corners = np.array([[0, 0, 0], [width, 0, 0], [width, depth, 0], [0, depth, 0]], np.float64)
    for start, end in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        tiles = max(1, math.ceil(np.linalg.norm(end - start) / 3.0))
        step = (end - start) / tiles
        for k in range(tiles):
            surfaces.append(_surface(start + k * step + up, step, -up, photos(), rng))
    return surfaces


def _panels(size: np.ndarray, count: int, photos, rng) -> list[Surface]:
    """``count`` upright panels 0.8-1.6 m wide and 1-2 m tall at random places and headings
    inside the room, at least 1 m from its walls, both faces covered."""
    surfaces = []
    for _ in range(count):
        width, tall = rng.uniform(0.8, 1.6), rng.uniform(1.0, 2.0)
        heading = rng.uniform(0, math.pi)
        along = np.array([math.cos(heading), math.sin(heading), 0.0])
        centre = np.array([*rng.uniform(1.0, size[:2] - 1.0), rng.uniform(0.0, 0.5) + tall])
        origin = centre - along * width / 2
        down = np.array([0.0, 0.0, -tall])
        surfaces.append(_surface(origin, along * width, down, photos(), rng))
        # The back face, its photo the right way round when seen from behind.
        surfaces.append(_surface(origin + along * width, -along * width, down, photos(), rng))
    return surfaces


def room(photos: list[np.ndarray], seed: int = 0, panels: int = 4) -> Scene:
    """A random room 4-7 m by 4-7 m by 2.6-3.2 m high with ``panels`` free-standing panels, every
    surface a crop of a photo drawn from ``photos`` (each used once while any is left unused).
    Deterministic for a seed and a list of photos."""
    rng = np.random.default_rng(seed)
    size = np.array([rng.uniform(4, 7), rng.uniform(4, 7), rng.uniform(2.6, 3.2)])
    order: list[int] = []

    def next_photo() -> np.ndarray:
        if not order:
            order.extend(rng.permutation(len(photos)).tolist())
        return photos[order.pop()]

    inner = _panels(size, panels, next_photo, rng)
    surfaces = _shell(size, next_photo, rng) + inner
    obstacles = np.array([[s.origin[:2], s.origin[:2] + s.right[:2]] for s in inner[::2]])
    low = np.array([CLEARANCE, CLEARANCE, 1.0])
    high = np.array([size[0] - CLEARANCE, size[1] - CLEARANCE, min(2.0, size[2] - CLEARANCE)])
    return Scene(tuple(surfaces), low, high, obstacles.reshape(-1, 2, 2))


def is_clear(scene: Scene, centre: np.ndarray) -> bool:
    """Whether a camera centre [3] lies in the scene's free box and at least CLEARANCE from the
    floor footprint of every panel."""
    if np.any(centre < scene.low) or np.any(centre > scene.high):
        return False
    for start, end in scene.obstacles:
        along = end - start
        fraction = np.clip(np.dot(centre[:2] - start, along) / np.dot(along, along), 0.0, 1.0)
        if np.linalg.norm(centre[:2] - start - fraction * along) < CLEARANCE:
            return False
    return True


def scaled(camera: Camera, factor: float) -> Camera:
    """The same camera with an image ``factor`` times the size (a cheap preview of the view)."""
    height, width = max(1, round(camera.height * factor)), max(1, round(camera.width * factor))
    # Pixel centres at integers: x' + 0.5 = factor (x + 0.5).
    to_scaled = np.array([[factor, 0, (factor - 1) / 2], [0, factor, (factor - 1) / 2], [0, 0, 1]])
    return dataclasses.replace(camera, K=to_scaled @ camera.K, height=height, width=width)


def camera_path(
    scene: Scene, count: int, height: int = 480, width: int = 640, seed: int = 0
) -> list[Camera]:
    """``count`` poses of a camera walking a smooth curve through the room's free space while
    its heading sways (up to about 60 degrees either way) and it looks slightly down: a hand-held
    video's path. Curves that would pass a panel too closely are drawn again."""
    rng = np.random.default_rng(seed)
    K = intrinsics(height, width)
    s = np.linspace(0.0, 1.0, count)[:, None]
    middle, half = (scene.low + scene.high) / 2, (scene.high - scene.low) / 2
    for _ in range(1000):
        frequency, phase = rng.uniform(0.2, 0.5, 3), rng.uniform(0, 2 * math.pi, 3)
        centres = middle + half * np.sin(2 * math.pi * frequency * s + phase)
        yaw = rng.uniform(0, 2 * math.pi) + np.sin(2 * math.pi * rng.uniform(0.2, 0.6) * s[:, 0])
        pitch = -0.15 + 0.1 * np.sin(2 * math.pi * rng.uniform(0.2, 0.6) * s[:, 0])
        if all(is_clear(scene, c) for c in centres):
            break
    else:
        raise ValueError("no clear path in this scene: its panels leave too little room")
    ahead = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], 1)
    return [
        Camera(K, *look_at(c, c + a), height, width) for c, a in zip(centres, ahead, strict=True)
    ]


def _random_view(scene: Scene, K: np.ndarray, height: int, width: int, rng) -> Camera | None:
    """A camera at a clear random place, heading anywhere, pitched -25..10 degrees, rolled up to
    5 degrees; None when the place drawn is not clear."""
    centre = rng.uniform(scene.low, scene.high)
    if not is_clear(scene, centre):
        return None
    yaw, pitch = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(-25, 10))
    ahead = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch)])
    target = centre + np.array([*ahead, math.sin(pitch)])
    return Camera(K, *look_at(centre, target, rng.uniform(-5, 5)), height, width)


def rotation_angle(R: np.ndarray) -> float:
    """The angle of a rotation matrix [3, 3], degrees."""
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def _partner(scene: Scene, first: Camera, rng, baseline, max_angle, min_overlap) -> Camera | None:
    """A second view for ``first``, or None when the one drawn fails a check (see view_pairs)."""
    preview1 = scaled(first, 1 / 8)
    depth1 = cast(scene, preview1)["depth"]
    if depth1.min() < 2 * CLEARANCE / 3:
        return None  # a panel's edge right in front of the lens
    looked_at = backproject(depth1, preview1)[preview1.height // 2, preview1.width // 2]
    direction = rng.normal(size=3)
    centre = first.centre + rng.uniform(*baseline) * direction / np.linalg.norm(direction)
    if not is_clear(scene, centre):
        return None
    spread = 0.1 * np.linalg.norm(looked_at - centre)
    target = looked_at + rng.normal(0.0, spread, 3)
    second = Camera(
        first.K, *look_at(centre, target, rng.uniform(-5, 5)), first.height, first.width
    )
    if rotation_angle(relative_pose(first, second)[0]) > max_angle:
        return None
    preview2 = scaled(second, 1 / 8)
    depth2 = cast(scene, preview2)["depth"]
    if depth2.min() < 2 * CLEARANCE / 3:
        return None
    if covisible(depth1, preview1, depth2, preview2, 0.02).mean() < min_overlap:
        return None
    return second


def view_pairs(
    scene: Scene,
    count: int,
    height: int = 480,
    width: int = 640,
    seed: int = 0,
    baseline: tuple[float, float] = (0.2, 1.0),
    max_angle: float = 30.0,
    min_overlap: float = 0.3,
) -> list[tuple[Camera, Camera]]:
    """``count`` two-view pairs: the first camera at a clear random place and heading; the second
    moved by ``baseline`` metres (uniform) in a random direction and aimed near the point the first
    looks at (10% of the distance, normal), so the views differ by translation and rotation, with
    parallax and occlusion. A pair is kept when the cameras turn by at most ``max_angle`` degrees,
    nothing stands within 2/3 CLEARANCE of either lens, and the second view sees at least
    ``min_overlap`` of the first (checked on 1/8-size previews). Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    K = intrinsics(height, width)
    pairs = []
    for _ in range(1000 * count):
        if len(pairs) == count:
            return pairs
        first = _random_view(scene, K, height, width, rng)
        second = first and _partner(scene, first, rng, baseline, max_angle, min_overlap)
        if second is not None:
            pairs.append((first, second))
    raise ValueError(f"found {len(pairs)} of {count} pairs: the scene leaves too little room")
