"""HPatches and Oxford-affine sequences on disk: the image pairs (1, k), k = 2..6, of every scene,
with their ground-truth homographies, read lazily, and the protocol's resizing of a pair.

Coordinates follow the project's convention: homographies are 3x3 and map image 1's pixels
(x, y), centres at integers, to image k's. Image shapes are ``(height, width)``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.inference import images as image_files

#: Images smaller than this on a side cannot hold a meaningful pair.
MIN_IMAGE_SIDE = 8

_HPATCHES_IMAGE = re.compile(r"^([1-6])$")
_OXFORD_IMAGE = re.compile(r"^img([1-6])$")


class PairFiles(NamedTuple):
    """Where one image pair lives on disk; ``homography`` (float64 [3, 3]) is already read."""

    scene: str
    split: str
    index: int
    path1: Path
    path2: Path
    homography: np.ndarray


class Pair(NamedTuple):
    """One image pair: images are uint8 ``[H, W, 3]`` RGB, ``homography`` float64 [3, 3] maps
    pixels of ``image1`` to ``image2`` (HPatches' ``H_1_k``)."""

    scene: str
    split: str
    index: int
    image1: np.ndarray
    image2: np.ndarray
    homography: np.ndarray


def _split_of(scene: str) -> str:
    return scene[0] if scene[:2] in ("i_", "v_") else "other"


def _scene_images(folder: Path) -> tuple[dict[int, Path], str] | None:
    """Images 1..6 of a scene folder by index, and the layout ('hpatches' or 'oxford')."""
    for layout, pattern in (("hpatches", _HPATCHES_IMAGE), ("oxford", _OXFORD_IMAGE)):
        images = {}
        for path in sorted(folder.iterdir()):
            match = pattern.match(path.stem)
            if match and path.suffix.lower() in image_files.IMAGE_SUFFIXES and path.is_file():
                images.setdefault(int(match.group(1)), path)
        if 1 in images:
            return images, layout
    return None


def _read_homography(path: Path) -> np.ndarray:
    """The float64 [3, 3] homography in ``path``; raises ValueError naming the file unless it is
    a finite, invertible 3x3 matrix (every metric maps points both ways)."""
    try:
        homography = np.loadtxt(path, dtype=np.float64)
    except ValueError as error:
        raise ValueError(f"{path}: not a plain-text 3x3 homography ({error})") from None
    return check_homography(homography, str(path))


def check_homography(homography: np.ndarray, name: str) -> np.ndarray:
    """``homography`` as float64 [3, 3]; raises ValueError starting with ``name`` unless it is a
    finite, invertible 3x3 matrix."""
    homography = np.asarray(homography, np.float64)
    if homography.shape != (3, 3):
        raise ValueError(f"{name}: expected a 3x3 homography, got shape {homography.shape}")
    if not np.all(np.isfinite(homography)):
        raise ValueError(f"{name}: the homography holds NaN or infinite values")
    # Rank by SVD with numpy's default tolerance: all-zero and collapsing matrices fail alike.
    rank = np.linalg.matrix_rank(homography)
    if rank < 3:
        raise ValueError(f"{name}: the homography is singular (rank {rank}), not invertible")
    return homography


def _scene_pairs(folder: Path) -> list[PairFiles]:
    found = _scene_images(folder)
    if found is None:
        raise FileNotFoundError(f"scene {folder.name}: no image 1 (1.ppm or img1.ppm) in {folder}")
    images, layout = found
    if len(images) < 2:
        raise ValueError(f"scene {folder.name}: only image 1, no image 2..6 to pair it with")
    pairs = []
    for k in sorted(images)[1:]:
        h_name = f"H_1_{k}" if layout == "hpatches" else f"H1to{k}p"
        h_path = folder / h_name
        if not h_path.is_file():
            raise FileNotFoundError(
                f"scene {folder.name}: missing homography file {h_name} ({h_path})"
            )
        pairs.append(
            PairFiles(
                folder.name,
                _split_of(folder.name),
                k,
                images[1],
                images[k],
                _read_homography(h_path),
            )
        )
    return pairs


def scan_sequences(root: str | Path) -> list[PairFiles]:
    """List every pair (1, k), k = 2..6, of an HPatches or Oxford-affine folder, reading only the
    homographies (images are read lazily by :func:`read_pair`).

    ``root`` holds scene folders, or is one scene folder itself. HPatches scenes (``i_*``,
    ``v_*``) hold ``1.ppm``..``6.ppm`` and ``H_1_2``..``H_1_6``; Oxford scenes (graf, wall, ...)
    hold ``img1``..``img6`` (.ppm/.pgm/.png/.jpg) and ``H1to2p``..``H1to6p``. A scene's split is
    'i' or 'v' from its ``i_``/``v_`` prefix, else 'other'. Folders without an image 1 are
    skipped unless named like an HPatches scene.

    Raises FileNotFoundError for a missing root or a scene without image 1 or an H file,
    ValueError for a root without scenes or an H file that is unreadable, not finite or singular
    (naming the file), all before any image is read.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"evaluation data folder not found: {root}")
    if _scene_images(root) is not None:
        return _scene_pairs(root)
    pairs = []
    # Hidden folders are not scenes (make-pairs writes a scene as .NAME.partial first).
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if _split_of(folder.name) != "other" or _scene_images(folder) is not None:
            pairs.extend(_scene_pairs(folder))
    if not pairs:
        raise ValueError(
            f"{root}: no HPatches (i_*/v_* with 1.ppm, H_1_2..) "
            "or Oxford (img1.ppm, H1to2p..) scenes"
        )
    return pairs


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as uint8 ``[H, W, 3]`` RGB (``inference.images.read_image``), >= 8 px a side.

    Deviation: KP2D feeds OpenCV's BGR order to its network; RGB is this project's convention.
    Raises ValueError naming the file when OpenCV cannot decode it or a side is under 8 px.
    """
    image = image_files.read_image(path)
    height, width = image.shape[:2]
    if min(height, width) < MIN_IMAGE_SIDE:
        raise ValueError(
            f"{path}: image is {width}x{height} px, need at least {MIN_IMAGE_SIDE} px per side"
        )
    return image


def read_pair(files: PairFiles) -> Pair:
    """Load the images of one :class:`PairFiles`."""
    return Pair(
        files.scene,
        files.split,
        files.index,
        read_image(files.path1),
        read_image(files.path2),
        files.homography,
    )


def load_sequences(root: str | Path) -> Iterator[Pair]:
    """Iterate lazily over every pair of an HPatches or Oxford folder (see :func:`scan_sequences`).

    The folder structure is checked at once; each image is read only when its pair is reached,
    so the 580 HPatches pairs are never all in memory.
    """
    return map(read_pair, scan_sequences(root))


def resize_pair(
    image1: np.ndarray, image2: np.ndarray, homography: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resize both images straight to ``height x width`` (``cv2.resize``, aspect ratio not kept,
    no crop) and adapt the homography per image and per axis, as the protocol (and KP2D) do:

    ``H' = diag(sx_k, sy_k, 1) @ H @ inv(diag(sx_1, sy_1, 1))``,
    ``sx = width / W``, ``sy = height / H`` of each image.

    Note that this scales coordinates about pixel (0, 0); ``cv2.resize`` scales about the
    corner (-0.5, -0.5), so every point lands ``0.5 * (s - 1)`` px off where H' puts it (-0.25 px
    at half size), in both images. The protocol keeps that offset (KP2D's numbers have it). On
    upright pairs it nearly cancels; on a pair turned by an angle a it moves each method's
    homography by ``(I - R(a)) @ (0.25, 0.25)``, up to 0.7 px at 180 degrees, except OpenCV
    SIFT's, whose points carry an opposite +0.25 px offset of their own
    (experiments/notes/choices.md, "Resizing and turned pairs"). Pairs made at the evaluated size
    need no resizing and have no such offset.

    Returns the two resized uint8 images and H' (float64 [3, 3]).
    """

    def scale(image: np.ndarray) -> np.ndarray:
        return np.diag([width / image.shape[1], height / image.shape[0], 1.0])

    adapted = scale(image2) @ homography @ np.linalg.inv(scale(image1))
    return (
        cv2.resize(image1, (width, height)),
        cv2.resize(image2, (width, height)),
        adapted,
    )
