"""Planar homographies in JAX: the random spatial transform T of paper section 3 and its use on points/images.

Project conventions: pixel coordinates are (x, y), x right, y down, pixel centres at integer coordinates
(OpenCV's convention); a homography is a float32 [3, 3] matrix that maps points of image 1 to image 2,
p2 ~ H @ [x1, y1, 1], like HPatches' H_1_k. Every function here is pure jnp and jit-/vmap-able; sizes
(height, width, out_shape) and configs are static Python values.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax.scipy.ndimage import map_coordinates

# cv2.perspectiveTransform treats |w| <= FLT_EPSILON as a point at infinity and returns (0, 0) for it.
_W_EPS = float(jnp.finfo(jnp.float32).eps)

# Patch corners in the order top-left, top-right, bottom-right, bottom-left, in units of the half image
# size (the image spans [-1, 1] on both axes); they map to the same corners of the output image.
_UNIT_CORNERS = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))
# Sign of each corner's perspective displacement: moving TL/BR one way and TR/BL the other shrinks one
# edge of the patch and stretches the opposite one (a keystone), i.e. a genuine projective distortion.
_KEYSTONE = (1.0, -1.0, 1.0, -1.0)
# How HomographyConfig.rotation_range is drawn from.
ROTATION_DISTRIBUTIONS = ("uniform",)


@dataclasses.dataclass(frozen=True)
class HomographyConfig:
    """Ranges of the random homography T (paper section 3); magnitudes are uniform in intervals (section 5).

    The warped image B shows a quadrilateral patch of the source image A. The patch starts as a centred
    rectangle of relative size `patch_ratio`, gets a perspective keystone, a scale change and a rotation
    about its centre, and is then translated; candidates whose patch does not fit inside A are rejected,
    so the large rotations/scales of the intervals are accepted less often than the small ones.

    Defaults: SuperPoint's patch_ratio 0.85 keeps most of a 240x320 training image in view (KP2D's 0.7
    discards half of its area, and with it half of the points the losses can pair); KP2D's max angle pi/4
    rather than SuperPoint's pi/2, because upright rotations dominate real image pairs (HPatches); on a
    4:3 image a 0.85 patch fits only up to ~34 degrees anyway. Scaling 0.2 as both. Both reach a keystone
    of 0.4 in the units used here (std 0.2); U(-0.2, 0.2) (std 0.12) is milder, so that the cells of B
    keep similar scales in A and the 4-pixel correspondence test pairs most of them. With these defaults
    about 1 candidate in 6 fits, so 64 candidates fall back with probability ~1e-5.

    Attributes:
      patch_ratio: side of the unperturbed patch relative to the image side, in (0, 1].
      scaling: the patch size is multiplied by s ~ U(1 - scaling, 1 + scaling); in [0, 1).
      max_angle: rotation angle ~ U(-max_angle, max_angle), radians.
      perspective: keystone displacement of each corner ~ U(-perspective, perspective) per axis, in
        units of the half image size.
      translation: fraction in [0, 1] of the free margin (the room left between patch and image border)
        that the random translation may use; 0 keeps the patch centred.
      num_candidates: candidates drawn in parallel; the first that fits is used. If none fits, the
        centred, unrotated patch of size patch_ratio is used (always valid).
      rotation_range: (low, high) in degrees, -360 <= low <= high <= 360, or None (the default) for
        U(-max_angle, max_angle). Drawn only by `sample_window_homography`, whose context window
        lets a rotated patch fit at any angle; `sample_homography` rejects a config that sets it,
        because inside the crop such a patch would almost never fit. Positive angles turn B's
        content counter-clockwise on screen, as cv2.getRotationMatrix2D's do.
      rotation_distribution: how the angle is drawn from rotation_range; "uniform" is the only one.
    """

    patch_ratio: float = 0.85
    scaling: float = 0.2
    max_angle: float = math.pi / 4
    perspective: float = 0.2
    translation: float = 1.0
    num_candidates: int = 64
    rotation_range: tuple[float, float] | None = None
    rotation_distribution: str = "uniform"

    def __post_init__(self):
        checks = {
            "patch_ratio": 0.0 < self.patch_ratio <= 1.0,
            "scaling": 0.0 <= self.scaling < 1.0,
            "max_angle": self.max_angle >= 0.0,
            "perspective": self.perspective >= 0.0,
            "translation": 0.0 <= self.translation <= 1.0,
            "num_candidates": self.num_candidates >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"HomographyConfig.{name}={getattr(self, name)!r} is out of range")
        if self.rotation_range is not None:
            try:
                low, high = (float(v) for v in self.rotation_range)
            except (TypeError, ValueError):
                raise ValueError(
                    f"HomographyConfig.rotation_range={self.rotation_range!r} must be "
                    "(low, high) in degrees, or None"
                ) from None
            if not -360.0 <= low <= high <= 360.0:
                raise ValueError(
                    f"HomographyConfig.rotation_range={self.rotation_range!r} must satisfy "
                    "-360 <= low <= high <= 360 (degrees)"
                )
        if self.rotation_distribution not in ROTATION_DISTRIBUTIONS:
            raise ValueError(
                f"HomographyConfig.rotation_distribution={self.rotation_distribution!r} must "
                f"be one of {', '.join(ROTATION_DISTRIBUTIONS)}"
            )


def _normalise(homography: jax.Array) -> jax.Array:
    """Scales [..., 3, 3] homographies so that H[..., 2, 2] = 1."""
    return homography / homography[..., 2:3, 2:3]


def invert_homography(homography: jax.Array) -> jax.Array:
    """Inverse of [..., 3, 3] homographies, normalised to H[..., 2, 2] = 1 (maps image 2 back to image 1)."""
    return _normalise(jnp.linalg.inv(jnp.asarray(homography, jnp.float32)))


def compose_homographies(*homographies: jax.Array) -> jax.Array:
    """Matrix product of [..., 3, 3] homographies, normalised to H[..., 2, 2] = 1.

    The order is that of the matrix product: compose_homographies(h2, h1) = h2 @ h1 applies h1 FIRST,
    e.g. compose_homographies(H_1_3, invert_homography(H_1_2)) maps image 2 to image 3.
    """
    if not homographies:
        raise ValueError("compose_homographies needs at least one homography")
    arrays = [jnp.asarray(h, jnp.float32) for h in homographies]
    return _normalise(functools.reduce(jnp.matmul, arrays))


def warp_points(homography: jax.Array, xy: jax.Array) -> jax.Array:
    """Maps points [..., 2] (x, y) through a [3, 3] homography, exactly like cv2.perspectiveTransform.

    Points whose homogeneous coordinate w satisfies |w| <= FLT_EPSILON (on the line at infinity) are
    returned as (0, 0), which is OpenCV's choice; they are finite, and their gradient is zero rather than
    NaN. Points with w < 0 (behind the "camera") are divided through like any other, as OpenCV does.
    Returns float32 [..., 2].
    """
    homography = jnp.asarray(homography, jnp.float32)
    xy = jnp.asarray(xy, jnp.float32)
    projected = xy @ homography[:, :2].T + homography[:, 2]
    w = projected[..., 2:]
    finite = jnp.abs(w) > _W_EPS
    # Divide by 1 where w vanishes so that neither the value nor the gradient of the masked branch is inf.
    return jnp.where(finite, projected[..., :2] / jnp.where(finite, w, 1.0), 0.0)


def points_inside(xy: jax.Array, height: int, width: int, border: float = 0) -> jax.Array:
    """Bool mask [...] of points [..., 2] inside [border, width-1-border] x [border, height-1-border]."""
    x, y = xy[..., 0], xy[..., 1]
    return (x >= border) & (x <= width - 1 - border) & (y >= border) & (y <= height - 1 - border)


def _pixel_grid(height: int, width: int) -> jax.Array:
    """(x, y) coordinates of every pixel centre, float32 [height, width, 2]."""
    ys, xs = jnp.meshgrid(
        jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32), indexing="ij"
    )
    return jnp.stack([xs, ys], axis=-1)


def warp_image(
    image: jax.Array, homography: jax.Array, out_shape: tuple[int, int] | None = None
) -> tuple[jax.Array, jax.Array]:
    """Renders image 2 = image warped by `homography` (image 1 -> image 2), bilinearly.

    Equals cv2.warpPerspective(image, H, (w, h), flags=INTER_LINEAR, borderMode=BORDER_CONSTANT,
    borderValue=0) up to OpenCV's 1/32-pixel quantisation of the sampling positions: every output pixel
    samples the input at H^-1 @ (x, y), and neighbours outside the input contribute 0.

    Args:
      image: [H, W, C] float image.
      homography: [3, 3], maps input pixels to output pixels.
      out_shape: (h, w) of the output; defaults to (H, W).
    Returns:
      warped: float32 [h, w, C].
      valid: bool [h, w], True where the preimage of the pixel lies inside the input image
        ([0, W-1] x [0, H-1]), i.e. where all bilinear neighbours are real content.
    """
    image = jnp.asarray(image, jnp.float32)
    if image.ndim != 3:
        raise ValueError(f"warp_image expects an [H, W, C] image, got shape {tuple(image.shape)}")
    height, width = out_shape if out_shape is not None else image.shape[:2]
    source_xy = warp_points(invert_homography(homography), _pixel_grid(height, width))
    coordinates = [source_xy[..., 1], source_xy[..., 0]]  # map_coordinates indexes (row, column)
    sample = functools.partial(
        map_coordinates, coordinates=coordinates, order=1, mode="constant", cval=0.0
    )
    warped = jax.vmap(sample, in_axes=2, out_axes=2)(image)
    return warped, points_inside(source_xy, image.shape[0], image.shape[1])


def _is_convex(quads: jax.Array) -> jax.Array:
    """[...] bool: the quadrilaterals [..., 4, 2] (corners in TL, TR, BR, BL order) are strictly convex
    with the orientation of the image rectangle; a homography maps the rectangle onto such quads only."""
    edges = jnp.roll(quads, -1, axis=-2) - quads
    following = jnp.roll(edges, -1, axis=-2)
    cross = edges[..., 0] * following[..., 1] - edges[..., 1] * following[..., 0]
    return jnp.all(cross > 0, axis=-1)


def _unit_square_to_quad(quad: jax.Array) -> jax.Array:
    """[3, 3] homography mapping (0,0), (1,0), (1,1), (0,1) to the corners of `quad` [4, 2], in closed form
    (Heckbert 1989, "Fundamentals of Texture Mapping and Image Warping", section 2.2.3)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = quad
    sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
    dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
    det = dx1 * dy2 - dx2 * dy1
    g = (sx * dy2 - dx2 * sy) / det
    h = (dx1 * sy - sx * dy1) / det
    return jnp.array(
        [
            [x1 - x0 + g * x1, x3 - x0 + h * x3, x0],
            [y1 - y0 + g * y1, y3 - y0 + h * y3, y0],
            [g, h, 1.0],
        ]
    )


def _candidate_patches(
    key_perspective: jax.Array, key_scale: jax.Array, half: jax.Array, config: HomographyConfig
) -> tuple[jax.Array, jax.Array]:
    """The num_candidates patches both samplers choose from, before rotation and translation:
    corners [n, 4, 2] of the centred patch of side patch_ratio, each moved by a keystone of up to
    ``perspective``, in pixels about the image centre (``half`` [2] = (W - 1, H - 1) / 2), and
    scale factors [n, 1, 1] ~ U(1 - scaling, 1 + scaling)."""
    n = config.num_candidates
    unit = jnp.array(_UNIT_CORNERS, jnp.float32)
    keystone = jax.random.uniform(
        key_perspective, (n, 1, 2), minval=-config.perspective, maxval=config.perspective
    )
    corners = (
        config.patch_ratio * unit + jnp.array(_KEYSTONE)[:, None] * keystone
    ) * half  # [n, 4, 2]
    scale = jax.random.uniform(
        key_scale, (n, 1, 1), minval=1 - config.scaling, maxval=1 + config.scaling
    )
    return corners, scale


def _showing(patch: jax.Array, height: int, width: int) -> jax.Array:
    """float32 [3, 3] H mapping A's pixels to those of a [height, width] image B that shows the
    quad ``patch`` [4, 2] of A (its corners in pixels, in _UNIT_CORNERS' order) as its whole."""
    to_output = jnp.diag(jnp.array([width - 1, height - 1, 1], jnp.float32))
    return compose_homographies(to_output, invert_homography(_unit_square_to_quad(patch)))


def sample_homography(
    key: jax.Array, height: int, width: int, config: HomographyConfig = HomographyConfig()
) -> jax.Array:
    """Draws the random spatial transform T of paper section 3 for a [height, width] image.

    The returned H maps pixels of the source image (branch A) to the warped image (branch B),
    B = warp_image(A, H), and B is entirely covered by A's content: the four corners of B map (through
    H^-1) onto a convex patch inside [0, width-1] x [0, height-1]. Candidates are drawn in parallel
    (fixed shapes, no data-dependent loop); see HomographyConfig for the distribution. jax.vmap over
    keys gives a batch.

    Args:
      key: PRNG key.
      height, width: image size in pixels (static), both >= 2; B has the same size as A.
      config: ranges (static).
    Returns:
      float32 [3, 3] with H[2, 2] = 1.
    """
    if height < 2 or width < 2:
        raise ValueError(
            f"sample_homography needs an image of at least 2x2 pixels, got {height}x{width}"
        )
    if config.rotation_range is not None:
        raise ValueError(
            "HomographyConfig.rotation_range is drawn by sample_window_homography only (in "
            "training: data.context_window=True); inside the crop a patch rotated that far "
            "would almost never fit"
        )
    n = config.num_candidates
    key_perspective, key_scale, key_angle, key_translation = jax.random.split(key, 4)
    half = jnp.array([(width - 1) / 2, (height - 1) / 2], jnp.float32)
    unit = jnp.array(_UNIT_CORNERS, jnp.float32)

    corners, scale = _candidate_patches(key_perspective, key_scale, half, config)
    angle = jax.random.uniform(key_angle, (n,), minval=-config.max_angle, maxval=config.max_angle)
    rotation = _rotations(angle)  # [n, 2, 2]
    # Rotating in pixel units (not in [-1, 1] units) keeps the rotation free of shear on non-square images.
    corners = scale * jnp.einsum("nij,nkj->nki", rotation, corners)
    low, high = corners.min(axis=1), corners.max(axis=1)  # [n, 2] bounding boxes
    fits = jnp.all(high - low <= 2 * half, axis=-1) & _is_convex(corners)
    chosen = jnp.where(jnp.any(fits), corners[jnp.argmax(fits)], config.patch_ratio * unit * half)

    # Centre the chosen patch's bounding box so the free margin is symmetric, then move within it.
    low, high = chosen.min(axis=0), chosen.max(axis=0)
    margin = config.translation * (half - (high - low) / 2)
    shift = jax.random.uniform(key_translation, (2,), minval=-margin, maxval=margin)
    patch = chosen + (half - (high + low) / 2 + shift)  # [4, 2] source pixels, image centre = half
    return _showing(patch, height, width)


def window_origin(height: int, width: int, window: tuple[int, int]) -> tuple[int, int]:
    """(x, y) of the top-left pixel of a [height, width] crop centred in a [window_height, window_width]
    context window: ((window_width - width) // 2, (window_height - height) // 2), Python ints."""
    window_height, window_width = window
    if window_height < height or window_width < width:
        raise ValueError(
            f"a {window_height}x{window_width} window cannot hold a {height}x{width} crop"
        )
    return (window_width - width) // 2, (window_height - height) // 2


def _rotation_angles(key: jax.Array, shape: tuple[int, ...], config: HomographyConfig) -> jax.Array:
    """Angles in radians [*shape] from rotation_range (degrees) if set, else U(-max_angle, max_angle)."""
    if config.rotation_range is None:
        low, high = -config.max_angle, config.max_angle
    else:
        low, high = (math.radians(v) for v in config.rotation_range)
    return jax.random.uniform(
        key, shape, minval=low, maxval=high
    )  # "uniform", the only distribution


def _rotations(angle: jax.Array) -> jax.Array:
    """[..., 2, 2] rotation matrices; positive angles turn (1, 0) towards +y (clockwise on screen)."""
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([jnp.stack([cos, -sin], -1), jnp.stack([sin, cos], -1)], -2)


def sample_window_homography(
    key: jax.Array,
    height: int,
    width: int,
    window: tuple[int, int],
    config: HomographyConfig = HomographyConfig(),
) -> jax.Array:
    """The random spatial transform T of paper section 3 for a crop at the centre of a context window,
    so that T can rotate by any angle without zooming in.

    Branch A is the [height, width] crop at `window_origin(height, width, window)` of a larger
    [window_height, window_width] window of the same photo at the same pixel scale; branch B, also
    [height, width], is rendered from the whole window. The returned H maps A's pixel coordinates to
    B's (what the losses expect), so B = warp_image(window, H @ shift, (height, width)) with shift the
    translation by -window_origin. The patch of A that B shows is drawn as in `sample_homography`
    (patch_ratio, keystone, scale), turned about its centre by an angle from rotation_range (or
    U(-max_angle, max_angle)), and moved by up to `translation` of the margin the unrotated patch
    leaves inside A, so B overlaps A about as much at any angle. A candidate fits when its quad lies
    inside the window: B then shows window content only. If none of num_candidates fits, the centred
    patch of size patch_ratio is used, turned by the drawn angle when that fits in the window
    (always, for a window whose sides reach the crop's diagonal, like `usp_jax.training.crops.context_side`'s)
    and unturned otherwise. All candidates share one angle, so the angles follow their
    distribution exactly.

    Args:
      key: PRNG key.
      height, width: crop (A) and output (B) size in pixels (static), both >= 2.
      window: (window_height, window_width) of the context window (static), >= (height, width).
      config: ranges (static).
    Returns:
      float32 [3, 3] with H[2, 2] = 1, mapping A's pixels to B's.
    """
    if height < 2 or width < 2:
        raise ValueError(
            f"sample_window_homography needs a crop of at least 2x2 pixels, got {height}x{width}"
        )
    origin_x, origin_y = window_origin(height, width, window)
    n = config.num_candidates
    key_perspective, key_scale, key_angle, key_translation = jax.random.split(key, 4)
    half = jnp.array([(width - 1) / 2, (height - 1) / 2], jnp.float32)
    unit = jnp.array(_UNIT_CORNERS, jnp.float32)
    # The window in A's pixel coordinates; bilinear sampling needs the preimages inside it.
    window_low = jnp.array([-origin_x, -origin_y], jnp.float32)
    window_high = jnp.array([window[1] - 1 - origin_x, window[0] - 1 - origin_y], jnp.float32)

    corners, scale = _candidate_patches(key_perspective, key_scale, half, config)
    corners = scale * corners
    # One angle for all candidates: rejection then shapes only scale, keystone and translation, and
    # the angles follow their distribution exactly (per-candidate angles thin out the diagonals,
    # whose rotated patches are the widest).
    rotation = _rotations(_rotation_angles(key_angle, (), config))
    # The margin of the unrotated patch: measured after rotation, it would shrink to nothing at
    # 45-135 degrees and let B drift off A at others, so overlap would depend on the angle.
    margin = config.translation * jnp.maximum(half - jnp.abs(corners).max(axis=1), 0.0)  # [n, 2]
    shift = jax.random.uniform(key_translation, (n, 2), minval=-1.0, maxval=1.0) * margin
    patches = corners @ rotation.T + (half + shift)[:, None]
    inside = jnp.all((patches >= window_low) & (patches <= window_high), axis=(1, 2))
    fits = inside & _is_convex(patches)

    upright = config.patch_ratio * unit * half + half
    turned = (config.patch_ratio * unit * half) @ rotation.T + half
    turned_fits = jnp.all((turned >= window_low) & (turned <= window_high))
    fallback = jnp.where(turned_fits, turned, upright)
    patch = jnp.where(jnp.any(fits), patches[jnp.argmax(fits)], fallback)
    return _showing(patch, height, width)


def translation(x: float, y: float) -> jax.Array:
    """float32 [3, 3] homography adding (x, y) to every point."""
    return jnp.array([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], jnp.float32)
