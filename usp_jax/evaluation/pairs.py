"""Builds an HPatches-layout evaluation set from any folder of photos.

Every source photo gives up to two scenes, laid out like HPatches (`<scene>/1.ppm .. N.ppm` and plain-text
3x3 `<scene>/H_1_2 .. H_1_N`, each mapping pixels of image 1 to image k):

- `v_<stem>`: viewpoint changes. Image 1 is a frontal view of a sub-region of the photo, images 2..N are
  rendered through random homographies of growing strength (rotation, scale and a strong perspective
  keystone). Every rendered image shows real content only: each view is a patch inside the photo, drawn
  by geometry.sample_homography, so there are no black borders.
- `i_<stem>`: illumination changes. The same frontal image 1, identity homographies, and images 2..N
  with gamma, brightness, contrast, colour temperature and noise changes of growing strength.

With `rotation` or `rotation_angles`, every viewpoint pair (1, k) also turns by an in-plane angle, drawn
uniformly or taken from a list: views 2..N are then drawn by geometry.sample_window_homography inside a
square region of the photo around image 1 that holds a turned view at any angle, so rotated views
show real content too, and H_1_k stays exact.

With `zoom` (min, max), every viewpoint pair (1, k) also zooms: image k's content is magnified about its
centre by a factor drawn log-uniformly from [min, max] (0.5: image k shows twice the extent, at half the
pixel scale). Views are then cut from a window of the photo 1.5 / min times the output's sides around
image 1, so zoomed-out views show real content too; they are rendered at 1 / zoom times the output size
and shrunk with INTER_AREA, as a camera would see them, not aliased. The few strongly keystoned views
that would still reach past the photo zoom out less, just enough to fit (`zoom.fitting_zoom`).

Output is deterministic for a seed (and a given order of the source list).

Nothing of the user's is overwritten or mixed into (``evaluation.pairs_folder``).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import jax
import numpy as np
from tqdm import tqdm

from usp_jax.core.geometry import (
    HomographyConfig,
    sample_homography,
    sample_window_homography,
    window_origin,
)
from usp_jax.evaluation.pairs_folder import earlier_scenes, write_manifest, write_scene
from usp_jax.evaluation.zoom import check_zoom, fitting_zoom, pair_zooms, render, zoomed
from usp_jax.inference.images import IMAGE_SUFFIXES, read_image

# Image 1 of every scene: an upright, undistorted crop, like the frontal reference shots of HPatches.
REFERENCE_VIEW = HomographyConfig(patch_ratio=0.75, scaling=0.0, max_angle=0.0, perspective=0.0)
# The hardest view (image N). A keystone of 0.3 on both axes makes the local scale of H_1_N vary across
# image 1 by a factor of ~3.5 (median), which with the scale and rotation ranges resembles the hardest
# HPatches "v" images (whose rotations are moderate, hence pi/6), while image N still overlaps image 1
# by ~85 % (median). Strong draws are rejected often, so draw many candidates.
HARDEST_VIEW = HomographyConfig(
    patch_ratio=0.75, scaling=0.2, max_angle=math.pi / 6, perspective=0.3, num_candidates=256
)


#: Seeds are 32-bit: jax.random.PRNGKey and numpy's generators take them alike.
MAX_SEED = 2**32 - 1

# Seeds the drawn rotation angles' generator together with (seed, photo index): a stream of its own, so
# the illumination scenes' generator, seeded by (seed, photo index), draws what it drew before.
_ROTATION_STREAM = 1


def _view_config(strength: float) -> HomographyConfig:
    """HARDEST_VIEW with its rotation, scale and perspective ranges scaled by strength in (0, 1]."""
    return dataclasses.replace(
        HARDEST_VIEW,
        scaling=HARDEST_VIEW.scaling * strength,
        max_angle=HARDEST_VIEW.max_angle * strength,
        perspective=HARDEST_VIEW.perspective * strength,
    )


def _check_rotation(
    rotation: float | None, rotation_angles: Sequence[float] | None
) -> tuple[float, ...] | None:
    """The fixed angles as a tuple (None when not given), after checking both rotation arguments."""
    if rotation is not None and rotation_angles is not None:
        raise ValueError(
            "give rotation (a range to draw from) or rotation_angles (a list), not both"
        )
    if rotation is not None and not 0.0 <= rotation <= 180.0:
        raise ValueError(f"rotation must lie in [0, 180] degrees, got {rotation}")
    if rotation_angles is None:
        return None
    angles = tuple(float(a) for a in rotation_angles)
    if not angles or not all(-180.0 <= a <= 180.0 for a in angles):
        raise ValueError(
            f"rotation_angles must be one or more angles in [-180, 180] degrees, got "
            f"{list(rotation_angles)}"
        )
    return angles


def pair_rotations(
    index: int,
    num_views: int,
    *,
    seed: int = 0,
    rotation: float | None = None,
    rotation_angles: Sequence[float] | None = None,
) -> list[float]:
    """The extra in-plane angles in degrees of the viewpoint pairs (1, 2) .. (1, num_views) of source photo
    `index` (its position in the source list): drawn uniformly from [-rotation, rotation], or
    rotation_angles[(index + k - 2) % len(rotation_angles)] for pair (1, k), so that every angle of the list
    serves every view strength alike over len(rotation_angles) consecutive photos. Positive = image k's
    content turned counter-clockwise on screen against image 1's (cv2.getRotationMatrix2D's sign)."""
    angles = _check_rotation(rotation, rotation_angles)
    if angles is not None:
        return [angles[(index + k - 2) % len(angles)] for k in range(2, num_views + 1)]
    if rotation is None:
        return [0.0] * (num_views - 1)
    rng = np.random.default_rng([seed, index, _ROTATION_STREAM])
    return [float(a) for a in rng.uniform(-rotation, rotation, size=num_views - 1)]


def _list_sources(images: str | Path | Iterable[str | Path]) -> list[Path]:
    """Source photo paths: the image files of a folder (sorted), or the given paths (order kept)."""
    if isinstance(images, (str, Path)):
        folder = Path(images)
        if not folder.is_dir():
            raise FileNotFoundError(f"image folder not found: {folder}")
        paths = sorted(
            p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not paths:
            raise FileNotFoundError(
                f"no image files ({', '.join(sorted(IMAGE_SUFFIXES))}) in {folder}"
            )
    else:
        paths = [Path(p) for p in images]
        if not paths:
            raise FileNotFoundError("the list of source images is empty")
        for path in paths:
            if not path.is_file():
                raise FileNotFoundError(f"source image not found: {path}")
    stems: dict[str, Path] = {}
    for path in paths:
        if path.stem in stems:
            raise ValueError(
                f"source images {stems[path.stem]} and {path} share the scene name {path.stem!r}"
            )
        stems[path.stem] = path
    return paths


def _fit_to_cover(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resizes (keeping the aspect ratio) and centre-crops a uint8 [h, w, 3] image to [height, width, 3]."""
    factor = max(height / image.shape[0], width / image.shape[1])
    size = (max(width, round(image.shape[1] * factor)), max(height, round(image.shape[0] * factor)))
    # INTER_AREA averages when shrinking (no aliasing); cubic keeps edges sharper when enlarging.
    resized = cv2.resize(
        image, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC
    )
    top, left = (resized.shape[0] - height) // 2, (resized.shape[1] - width) // 2
    return resized[top : top + height, left : left + width]


def _illumination_change(
    image: np.ndarray, strength: float, rng: np.random.Generator
) -> np.ndarray:
    """Gamma, contrast, brightness, colour temperature and noise on a float [H, W, 3] RGB image in [0, 1].

    Directions are random, magnitudes grow with strength in (0, 1]: at strength 1 gamma and brightness
    change by a factor 2, contrast by 40 %, the red/blue balance by 30 %, plus noise of std 0.02.
    """
    gamma_sign, contrast_sign, brightness_sign, warmth_sign = rng.choice((-1.0, 1.0), size=4)
    gamma = 2.0 ** (gamma_sign * strength)
    contrast = 1.0 + contrast_sign * 0.4 * strength
    brightness = 2.0 ** (brightness_sign * strength)
    warmth = warmth_sign * 0.3 * strength
    gains = brightness * np.array([1.0 + warmth, 1.0, 1.0 - warmth])
    changed = image**gamma
    changed = (changed - changed.mean()) * contrast + changed.mean()
    changed = changed * gains + rng.normal(0.0, 0.02 * strength, image.shape)
    return np.clip(changed, 0.0, 1.0)


def _view_window(
    height: int, width: int, rotated: bool, zoom: tuple[float, float] | None
) -> tuple[int, int]:
    """The region of the photo views are cut from, in the [height, width] frame in which
    sample_homography works: the frame itself, or with rotation a window around it that holds
    REFERENCE_VIEW's patch, enlarged to the middle of the views' scale range, turned by any angle
    (a larger window would make rejection depend even less on the angle, at the price of
    enlarging the photo further); with zoom out, room for the largest zoomed-out patch."""
    if rotated:
        middle_scale = 1 + HARDEST_VIEW.scaling / 2
        side = math.ceil(REFERENCE_VIEW.patch_ratio * middle_scale * math.hypot(height, width))
        window = (max(height, side), max(width, side))
    else:
        window = (height, width)
    if zoom is not None and zoom[0] < 1:
        # About the frame's size / zoom around image 1.
        reach = 1.5 / zoom[0]
        window = (
            max(window[0], math.ceil(height * reach)),
            max(window[1], math.ceil(width * reach)),
        )
    return window


def _sample_frames(
    key: jax.Array,
    configs: Sequence[HomographyConfig],
    turns: Sequence[float] | None,
    height: int,
    width: int,
    window: tuple[int, int],
) -> list[np.ndarray]:
    """One scene's homographies [3, 3] (float64), image k's from ``fold_in(key, k)`` and
    ``configs[k - 1]``; with ``turns`` (degrees, images 2..N) each view past the first is also
    turned by its angle and cut from ``window``.

    Called eagerly on purpose: under jit every strength would be a separate compilation, while
    op-by-op dispatch compiles each primitive once and then takes milliseconds per view."""
    if turns is None:
        return [
            np.asarray(
                sample_homography(jax.random.fold_in(key, k), height, width, config), np.float64
            )
            for k, config in enumerate(configs, start=1)
        ]
    frames = [
        np.asarray(
            sample_homography(jax.random.fold_in(key, 1), height, width, configs[0]), np.float64
        )
    ]
    for k, (config, turn) in enumerate(zip(configs[1:], turns), start=2):
        # The pair's own rotation range, centred on the extra angle: the two compose.
        own = math.degrees(config.max_angle)
        config = dataclasses.replace(config, rotation_range=(turn - own, turn + own))
        frames.append(
            np.asarray(
                sample_window_homography(jax.random.fold_in(key, k), height, width, window, config),
                np.float64,
            )
        )
    return frames


def make_pairs(
    images: str | Path | Iterable[str | Path],
    out_dir: str | Path,
    *,
    seed: int = 0,
    size: tuple[int, int] = (480, 640),
    num_views: int = 6,
    kinds: Sequence[str] = ("v", "i"),
    rotation: float | None = None,
    rotation_angles: Sequence[float] | None = None,
    zoom: tuple[float, float] | None = None,
    progress: bool = False,
) -> list[Path]:
    """Writes `v_<stem>` / `i_<stem>` HPatches-style scenes for every readable source photo.

    Args:
      images: a folder (its image files, sorted by name) or a list of image paths.
      out_dir: where the scene folders go: a new or empty folder, or an earlier output of
        make_pairs, which is replaced (module docstring; anything else is refused).
      seed: 0 to 2**32 - 1; the output is a deterministic function of seed, the photos and their
        order.
      size: (H, W) of every generated image. Photos are resized to cover (H, W) / patch_ratio first
        (enlarged when smaller, so every view is a crop at roughly the photo's own scale; with rotation,
        the larger square below).
      num_views: images per scene, 2 to 6 (HPatches has 6).
      kinds: which scene kinds to write, a subset of ("v", "i").
      rotation: degrees in [0, 180]: every viewpoint pair (1, k) also turns by an angle drawn uniformly
        from [-rotation, rotation], on top of its own random rotation (up to +-30 degrees at the hardest
        view). Views are then cut from a square region of the photo that holds a view turned by any
        angle, so the photo is enlarged about 1.4 times more than without rotation.
      rotation_angles: instead of `rotation`, fixed angles in [-180, 180] degrees, used in turn
        (`pair_rotations`).
      zoom: (min, max) in [0.25, 4]: every viewpoint pair (1, k) also zooms by a factor drawn
        log-uniformly from the range (`zoom.pair_zooms`, module docstring).
      progress: show a tqdm progress bar over the photos.
    Returns:
      The scene folders written, in order.
    Raises:
      FileNotFoundError: the folder (or a listed file) does not exist, holds no image, or none is readable.
      ValueError: bad seed/num_views/kinds/size/rotation, two photos with the same stem (their scenes
        would collide), or an output folder holding other data. All of them are checked before
        anything is written.
    Unreadable photos are skipped with a warning naming them.
    """
    _check_settings(size, num_views, kinds, seed)
    _check_rotation(rotation, rotation_angles)
    plan = _ScenePlan.of(*size, num_views, seed, rotation, rotation_angles, check_zoom(zoom))
    sources = _list_sources(images)
    out_dir = Path(out_dir)
    earlier = earlier_scenes(out_dir)
    settings = plan.settings(kinds, sources)
    planned = [f"{kind}_{path.stem}" for path in sources for kind in ("v", "i") if kind in kinds]
    scenes: list[Path] = []
    for index, path in enumerate(
        tqdm(sources, desc="make-pairs", unit="photo", disable=not progress)
    ):
        try:
            photo = _fit_to_cover(read_image(path), *plan.source_size)
        except ValueError:
            warnings.warn(f"skipping unreadable image {path}", stacklevel=2)
            continue
        frames, views = plan.render(photo, index)
        if not scenes:  # the first scene: only now is anything written
            out_dir.mkdir(parents=True, exist_ok=True)
            # Until the run ends the manifest names every scene it may leave, so that a re-run
            # after a failure recognises them all.
            write_manifest(out_dir, settings, set(earlier) | set(planned), complete=False)
        scenes += _write_scenes(
            out_dir, path.stem, frames, views, kinds, plan.strengths, [seed, index]
        )
    if not scenes:
        raise FileNotFoundError(f"none of the {len(sources)} source images could be read")
    written = {scene.name for scene in scenes}
    for name in set(earlier) - written:  # an earlier run's scene this run does not make
        shutil.rmtree(out_dir / name, ignore_errors=True)
    write_manifest(out_dir, settings, written, complete=True)
    return scenes


def _check_settings(size: tuple[int, int], num_views: int, kinds: Sequence[str], seed) -> None:
    """Raises ValueError for a size, view count, kinds or seed :func:`make_pairs` cannot use."""
    height, width = size
    if height < 2 or width < 2:
        raise ValueError(f"size must be at least (2, 2), got {size}")
    if not 2 <= num_views <= 6:  # the HPatches layout names images 1.ppm ... 6.ppm
        raise ValueError(f"num_views must be 2 to 6 (HPatches layout), got {num_views}")
    if not kinds or set(kinds) - {"v", "i"}:
        raise ValueError(f"kinds must be a non-empty subset of ('v', 'i'), got {tuple(kinds)}")
    integer = isinstance(seed, (int, np.integer)) and not isinstance(seed, bool)
    if not integer or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be an integer from 0 to {MAX_SEED}, got {seed!r}")


@dataclasses.dataclass(frozen=True)
class _ScenePlan:
    """How every scene of one run is drawn: the output size, the window views are cut from, the
    size the photo is prepared at, the map from its pixels into the window's frame, and the
    homography settings of images 1..N with the strengths of images 2..N."""

    height: int
    width: int
    num_views: int
    seed: int
    rotation: float | None
    rotation_angles: tuple[float, ...] | None
    zoom: tuple[float, float] | None
    window: tuple[int, int]
    source_size: tuple[int, int]
    to_frame: np.ndarray
    configs: tuple[HomographyConfig, ...]
    strengths: tuple[float, ...]

    @classmethod
    def of(
        cls, height: int, width: int, num_views: int, seed: int, rotation, rotation_angles, zoom
    ) -> _ScenePlan:
        """The plan of a run of :func:`make_pairs`' settings (checked already)."""
        rotated = rotation is not None or rotation_angles is not None
        window = _view_window(height, width, rotated, zoom)
        # The photo is prepared at the size whose REFERENCE_VIEW crop has the output size: views
        # are then resampled about 1:1 instead of enlarged. Its pixel frame is mapped onto the
        # window, and the window onto the frame; that mapping cancels in H_1_k = Hk @ inv(H1).
        source_height = math.ceil(window[0] / REFERENCE_VIEW.patch_ratio)
        source_width = math.ceil(window[1] / REFERENCE_VIEW.patch_ratio)
        to_frame = np.diag(
            [(window[1] - 1) / (source_width - 1), (window[0] - 1) / (source_height - 1), 1.0]
        )
        if window != (height, width):
            origin_x, origin_y = window_origin(height, width, window)
            shift = np.array([[1.0, 0.0, -origin_x], [0.0, 1.0, -origin_y], [0.0, 0.0, 1.0]])
            to_frame = shift @ to_frame
        strengths = tuple((k - 1) / (num_views - 1) for k in range(2, num_views + 1))
        configs = (REFERENCE_VIEW, *(_view_config(strength) for strength in strengths))
        angles = None if rotation_angles is None else tuple(rotation_angles)
        source_size = (source_height, source_width)
        settings = (height, width, num_views, int(seed), rotation, angles, zoom)
        return cls(*settings, window, source_size, to_frame, configs, strengths)

    def settings(self, kinds: Sequence[str], sources: Sequence[Path]) -> dict:
        """The settings a manifest records, with the scene ``kinds`` and source photos."""
        angles = self.rotation_angles
        return {
            "seed": self.seed,
            "size": [self.height, self.width],
            "num_views": self.num_views,
            "kinds": list(kinds),
            "rotation": self.rotation,
            "rotation_angles": None if angles is None else list(angles),
            "zoom": None if self.zoom is None else list(self.zoom),
            "sources": [str(path) for path in sources],
        }

    def render(self, photo: np.ndarray, index: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Source photo ``index``'s (homographies [3, 3] of images 1..N in the frame, uint8
        views); its pair zooms are lowered where a view would reach past the photo."""
        height, width, seed = self.height, self.width, self.seed
        turns = None
        if self.rotation is not None or self.rotation_angles is not None:
            turns = pair_rotations(
                index,
                self.num_views,
                seed=seed,
                rotation=self.rotation,
                rotation_angles=self.rotation_angles,
            )
        zooms = pair_zooms(index, self.num_views, self.zoom, seed=seed)
        key = jax.random.fold_in(jax.random.PRNGKey(seed), index)
        frames = _sample_frames(key, self.configs, turns, height, width, self.window)
        zooms = [1.0] + [
            fitting_zoom(frame @ self.to_frame, z, height, width, photo.shape)
            for frame, z in zip(frames[1:], zooms)
        ]
        frames = [zoomed(frame, z, height, width) for frame, z in zip(frames, zooms)]
        # Every view lies inside the photo, so the black constant border never shows (a test
        # checks it).
        views = [
            render(photo, frame @ self.to_frame, z, height, width)
            for frame, z in zip(frames, zooms)
        ]
        return frames, views


def _write_scenes(
    out_dir: Path,
    stem: str,
    frames: Sequence[np.ndarray],
    views: Sequence[np.ndarray],
    kinds: Sequence[str],
    strengths: Sequence[float],
    seed: list[int],
) -> list[Path]:
    """Writes one photo's ``v_STEM`` scene (``views``, H_1_k from ``frames``) and ``i_STEM``
    scene (image 1 under lighting changes of ``strengths``, drawn from ``seed``), as ``kinds``
    asks; returns the scene folders written."""
    written = []
    if "v" in kinds:
        reference_inverse = np.linalg.inv(frames[0])
        homographies = [frame @ reference_inverse for frame in frames[1:]]
        write_scene(out_dir / f"v_{stem}", views, [h / h[2, 2] for h in homographies])
        written.append(out_dir / f"v_{stem}")
    if "i" in kinds:
        rng = np.random.default_rng(seed)
        reference = views[0].astype(np.float64) / 255.0
        changed = [_illumination_change(reference, strength, rng) for strength in strengths]
        lit = [views[0]] + [np.round(255.0 * image).astype(np.uint8) for image in changed]
        write_scene(out_dir / f"i_{stem}", lit, [np.eye(3)] * len(strengths))
        written.append(out_dir / f"i_{stem}")
    return written
