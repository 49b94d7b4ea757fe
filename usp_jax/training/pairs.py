"""Training pairs of two views of a 3-D scene, with depth and relative pose (``data.source =
"pairs:FOLDER"``): parallax and occlusion, which one photo under a homography never shows.

The layout is the pose pairs' (``evaluation.pose.write_pairs``) plus each view's depth, one
folder per pair::

    FOLDER/NAME/1.png, 2.png       the two views (any size; both are resized to the crop size)
    FOLDER/NAME/pose.json          {"K1": 3x3, "K2": 3x3, "R": 3x3, "t": 3}, x2 = R x1 + t
    FOLDER/NAME/depth1.npy, depth2.npy
                                   float [H, W] per view, its z in the units of t (inf, NaN or
                                   <= 0 where unknown)

The losses need only where each point of one view lies in the other (``core.point_maps``); here
the host computes both maps from the depths, at the training size, and a batch carries them
beside the two images. ``experiments/render_pairs.py`` renders such folders from rooms of photos
(``evaluation.scenes``); a depth sensor's or an MVS reconstruction's output fits as well.
"""

from __future__ import annotations

import json
import pathlib
from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.core import point_maps
from usp_jax.inference.images import read_image

PREFIX = "pairs:"
_FILES = ("1.png", "2.png", "pose.json", "depth1.npy", "depth2.npy")


class ViewPair(NamedTuple):
    """Two views: uint8 RGB images, float64 depths [H, W] (NaN where unknown), K1, K2 [3, 3] and
    the relative pose R [3, 3], t [3]."""

    image1: np.ndarray
    image2: np.ndarray
    depth1: np.ndarray
    depth2: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    t: np.ndarray


def pair_folders(spec: str) -> list[pathlib.Path]:
    """The pair folders of ``pairs:FOLDER``, sorted; raises naming what is missing."""
    root = pathlib.Path(spec.removeprefix(PREFIX)).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"pair folder {root} does not exist")
    folders = sorted(p.parent for p in root.glob("*/pose.json"))
    if not folders:
        raise ValueError(f"pair folder {root} holds no NAME/pose.json (layout: training.pairs)")
    return folders


def read_pair(folder: pathlib.Path) -> ViewPair:
    """One pair folder; ValueError or OSError naming the file when something is missing or
    inconsistent (a depth not the size of its image, a pose of the wrong shape)."""
    for name in _FILES:
        if not (folder / name).is_file():
            raise ValueError(f"{folder}: {name} is missing")
    try:
        pose = json.loads((folder / "pose.json").read_text())
        K1, K2, R = (np.asarray(pose[k], np.float64) for k in ("K1", "K2", "R"))
        t = np.asarray(pose["t"], np.float64).ravel()
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{folder}/pose.json: {error}") from None
    if K1.shape != (3, 3) or K2.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"{folder}/pose.json: K1, K2 and R are 3x3 and t has 3 entries")
    images = [read_image(folder / f"{i}.png") for i in (1, 2)]
    depths = []
    for i, image in zip((1, 2), images, strict=True):
        depth = np.load(folder / f"depth{i}.npy", allow_pickle=False).astype(np.float64)
        if depth.shape != image.shape[:2]:
            raise ValueError(f"{folder}/depth{i}.npy is {depth.shape}, its image {image.shape[:2]}")
        depths.append(np.where(np.isfinite(depth) & (depth > 0), depth, np.nan))
    return ViewPair(*images, *depths, K1, K2, R, t)


def resized(image: np.ndarray, depth: np.ndarray, K: np.ndarray, height: int, width: int):
    """A view at ``height`` x ``width``: the image (area-averaged), its depth (nearest pixel, so no
    depth between two surfaces is made up) and K for the new pixel grid (centres at integers)."""
    sx, sy = width / image.shape[1], height / image.shape[0]
    scale = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])
    if (sx, sy) == (1.0, 1.0):
        return image, depth, K
    image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    return image, depth, scale @ K


def example(pair: ViewPair, height: int, width: int, rng: np.random.Generator) -> dict:
    """One training example: ``image_a``, ``image_b`` uint8 [height, width, 3] and the point maps
    ``a_to_b``, ``b_to_a`` float32 [height, width, 2] (NaN: not seen). Which view is A is drawn
    from ``rng``, so each pair serves both ways."""
    image1, depth1, K1 = resized(pair.image1, pair.depth1, pair.K1, height, width)
    image2, depth2, K2 = resized(pair.image2, pair.depth2, pair.K2, height, width)
    map12, map21 = point_maps.from_depth(depth1, depth2, K1, K2, pair.R, pair.t)
    if rng.random() < 0.5:
        return {"image_a": image1, "image_b": image2, "a_to_b": map12, "b_to_a": map21}
    return {"image_a": image2, "image_b": image1, "a_to_b": map21, "b_to_a": map12}
