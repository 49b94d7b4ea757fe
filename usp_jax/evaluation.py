"""HPatches evaluation of any keypoint detector: repeatability, localization error, homography
accuracy and matching score, as the UnsuperPoint paper reports them (section "Experiments").

The paper reuses SuperPoint's metric names; public code computes them three ways. This module
follows the project's evaluation protocol, which is KP2D's computation (TRI-ML/KP2D,
``kp2d/evaluation``), the one that reproduces the numbers the paper compares against.
Deliberate deviations from KP2D are marked "Deviation" in the docstrings: a pair without points
scores RS 0 (not -1), a pair without correspondences has LE NaN and is left out of the mean,
images are RGB rather than BGR.

Only numpy and OpenCV are used, so any detector (a classical one from :mod:`usp_jax.baselines`
or the learned model wrapped by the caller) is judged by the same code.

Coordinates follow the project's convention: points are ``[N, 2]`` (x, y) with pixel centres at
integer coordinates (OpenCV's), homographies are 3x3 and map image 1 to image k. Image shapes
are ``(height, width)``.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from usp_jax import data

#: The correct distance rho of the paper, in pixels (RS, LE and MS).
CORRECT_DISTANCE = 3.0
#: The homography-accuracy tolerances epsilon of the paper, in pixels.
HA_TOLERANCES = (1, 3, 5)
#: RANSAC settings of the protocol for ``cv2.findHomography``.
RANSAC_THRESHOLD = 3.0
RANSAC_MAX_ITERS = 5000
#: Images smaller than this on a side cannot hold a meaningful pair.
MIN_IMAGE_SIDE = 8

_HPATCHES_IMAGE = re.compile(r"^([1-6])$")
_OXFORD_IMAGE = re.compile(r"^img([1-6])$")
# Section order of the tables: every pair, then HPatches' illumination and viewpoint splits.
SPLITS = ("i", "v", "other")
METRICS = ("rs", "le", "ha1", "ha3", "ha5", "ms")
_HEADERS = ("RS", "LE", "HA e=1", "HA e=3", "HA e=5", "MS")


class Features(NamedTuple):
    """What a detector returns for one image (any order; the evaluation sorts by score).

    keypoints: float32 ``[N, 2]`` (x, y), OpenCV pixel-centre convention.
    scores: float32 ``[N]``, higher is better.
    descriptors: ``[N, D]``, float32 (compared with L2) or uint8 packed bits (Hamming).
    """

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray


@dataclasses.dataclass(frozen=True)
class Method:
    """A detector under evaluation: ``detect(uint8 [H, W, 3] RGB) -> Features``.

    ``norm`` is the descriptor distance, ``cv2.NORM_L2`` for float descriptors or
    ``cv2.NORM_HAMMING`` for binary ones (ORB, AKAZE, BRISK).
    """

    name: str
    detect: Callable[[np.ndarray], Features]
    norm: int = cv2.NORM_L2


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


class Matching(NamedTuple):
    """Result of the homography estimation procedure.

    matches: int ``[K, 2]`` indices (into features 1, into features 2) of mutual nearest
    neighbours in descriptor space. inliers: bool ``[K]``, RANSAC's inlier mask.
    homography: float64 [3, 3] estimate mapping image 1 to image 2, or None when it failed.
    """

    matches: np.ndarray
    inliers: np.ndarray
    homography: np.ndarray | None


# ---------------------------------------------------------------------------------------------
# Reading HPatches / Oxford sequences


def _split_of(scene: str) -> str:
    return scene[0] if scene[:2] in ("i_", "v_") else "other"


def _scene_images(folder: Path) -> tuple[dict[int, Path], str] | None:
    """Images 1..6 of a scene folder by index, and the layout ('hpatches' or 'oxford')."""
    for layout, pattern in (("hpatches", _HPATCHES_IMAGE), ("oxford", _OXFORD_IMAGE)):
        images = {}
        for path in sorted(folder.iterdir()):
            match = pattern.match(path.stem)
            if match and path.suffix.lower() in data.IMAGE_SUFFIXES and path.is_file():
                images.setdefault(int(match.group(1)), path)
        if 1 in images:
            return images, layout
    return None


def _read_homography(path: Path) -> np.ndarray:
    try:
        homography = np.loadtxt(path, dtype=np.float64)
    except ValueError as error:
        raise ValueError(f"{path}: not a plain-text 3x3 homography ({error})") from None
    if homography.shape != (3, 3) or not np.all(np.isfinite(homography)):
        raise ValueError(f"{path}: expected a finite 3x3 homography, got shape {homography.shape}")
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
    ValueError for a root without scenes or an unreadable H file.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"evaluation data folder not found: {root}")
    if _scene_images(root) is not None:
        return _scene_pairs(root)
    pairs = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        if _split_of(folder.name) != "other" or _scene_images(folder) is not None:
            pairs.extend(_scene_pairs(folder))
    if not pairs:
        raise ValueError(
            f"{root}: no HPatches (i_*/v_* with 1.ppm, H_1_2..) "
            "or Oxford (img1.ppm, H1to2p..) scenes"
        )
    return pairs


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as uint8 ``[H, W, 3]`` RGB (``usp_jax.data.read_image``), >= 8 px a side.

    Deviation: KP2D feeds OpenCV's BGR order to its network; RGB is this project's convention.
    Raises ValueError naming the file when OpenCV cannot decode it or a side is under 8 px.
    """
    image = data.read_image(path)
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
    corner (-0.5, -0.5), so H' is off by ``0.5 * (s - 1)`` px. The protocol keeps that offset
    (KP2D's numbers have it); it is well below the 3 px correct distance.

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


# ---------------------------------------------------------------------------------------------
# Point selection


def project_points(points: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Apply a homography to ``[N, 2]`` (x, y) points: ``cv2.perspectiveTransform``'s argument
    order and, for finite points, its result, but float64 and defined for N = 0. Points sent to
    infinity come back non-finite, so the protocol's visibility tests reject them (OpenCV and
    ``geometry.warp_points(H, xy)``, the JAX version used in training, return (0, 0))."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    projected = (
        np.concatenate([points, np.ones((len(points), 1))], axis=1) @ np.asarray(homography).T
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        return projected[:, :2] / projected[:, 2:]


def shared_view_mask(
    keypoints: np.ndarray, homography: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """Shared-view filter: bool ``[N]``, True where ``homography`` sends the point inside an
    image of ``shape`` (height, width), i.e. ``0 <= x < W`` and ``0 <= y < H`` as in KP2D's
    ``keep_true_keypoints``. Used with H for image-1 points and inv(H) for image-2 points."""
    warped = project_points(keypoints, homography)
    height, width = shape
    return (
        (warped[:, 0] >= 0) & (warped[:, 0] < width) & (warped[:, 1] >= 0) & (warped[:, 1] < height)
    )


def _take(features: Features, index: np.ndarray) -> Features:
    return Features(features.keypoints[index], features.scores[index], features.descriptors[index])


def top_k(features: Features, k: int) -> Features:
    """The ``k`` highest-scoring points, sorted by decreasing score (ties keep input order)."""
    order = np.argsort(-features.scores, kind="stable")[:k]
    return _take(features, order)


def nms_radius(keypoints: np.ndarray, scores: np.ndarray, radius: float) -> np.ndarray:
    """Greedy radius non-maximum suppression ("NMS = 4" rows of the paper's tables).

    Visiting points by decreasing score, keep a point unless a kept point lies within
    ``radius`` px (Euclidean, inclusive). Returns the int indices of the kept points ``[K]``,
    highest score first. SuperPoint's ``nms_fast`` suppresses a square window on integer-rounded
    positions instead; a disc on the exact positions treats sub-pixel detectors fairly.
    """
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(-np.asarray(scores), kind="stable")
    candidates = keypoints[order]
    suppressed = np.zeros(len(order), dtype=bool)
    kept = []
    for i in range(len(order)):
        if suppressed[i]:
            continue
        kept.append(order[i])
        suppressed[i:] |= np.sum((candidates[i:] - candidates[i]) ** 2, axis=1) <= radius**2
    return np.asarray(kept, dtype=np.int64)


def shared_top_k(
    features1: Features,
    features2: Features,
    homography: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    k: int,
) -> tuple[Features, Features]:
    """The protocol's selection for RS, LE and HA: drop image-1 points that H sends outside
    image 2 and image-2 points that inv(H) sends outside image 1, THEN keep the top ``k`` of
    each by score."""
    keep1 = shared_view_mask(features1.keypoints, homography, shape2)
    keep2 = shared_view_mask(features2.keypoints, np.linalg.inv(homography), shape1)
    return top_k(_take(features1, keep1), k), top_k(_take(features2, keep2), k)


# ---------------------------------------------------------------------------------------------
# Metrics (per pair)


def repeatability(
    features1: Features,
    features2: Features,
    homography: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    k: int,
    threshold: float = CORRECT_DISTANCE,
) -> tuple[float, float]:
    """Repeatability score (RS) and localization error (LE) of one pair, protocol section
    "Metrics" (KP2D's ``compute_repeatability``).

    After :func:`shared_top_k`, image-1 points are warped by H into image 2 and the N1 x N2
    distance matrix is formed. count1 = rows whose minimum is <= ``threshold``, count2 = such
    columns. ``RS = (count1 + count2) / (N1 + N2)``; LE = the sum of those in-threshold minimum
    distances (both directions) / (count1 + count2).

    Deviations from KP2D: a pair with no points at all scores RS 0 (KP2D returns -1 and
    averages it in, a bug); LE of a pair without any correspondence is NaN (KP2D divides 0 by 0)
    and the aggregate skips it with ``nanmean``.

    Returns ``(rs, le)``.
    """
    kept1, kept2 = shared_top_k(features1, features2, homography, shape1, shape2, k)
    n1, n2 = len(kept1.keypoints), len(kept2.keypoints)
    if n1 == 0 or n2 == 0:
        return 0.0, math.nan
    warped1 = project_points(kept1.keypoints, homography)
    distances = np.linalg.norm(
        warped1[:, None, :] - np.asarray(kept2.keypoints, np.float64)[None], axis=2
    )
    nearest = np.concatenate([distances.min(axis=1), distances.min(axis=0)])
    correct = nearest[nearest <= threshold]
    rs = len(correct) / (n1 + n2)
    le = float(correct.mean()) if len(correct) else math.nan
    return float(rs), le


def _match(
    descriptors1: np.ndarray, descriptors2: np.ndarray, norm: int, cross_check: bool
) -> np.ndarray:
    """Brute-force nearest neighbours, int ``[K, 2]`` (index in 1, index in 2)."""
    if len(descriptors1) == 0 or len(descriptors2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dtype = np.uint8 if norm == cv2.NORM_HAMMING else np.float32
    matcher = cv2.BFMatcher(norm, crossCheck=cross_check)
    matches = matcher.match(
        np.ascontiguousarray(descriptors1, dtype), np.ascontiguousarray(descriptors2, dtype)
    )
    return np.array([(m.queryIdx, m.trainIdx) for m in matches], dtype=np.int64).reshape(-1, 2)


def match_and_estimate(
    features1: Features, features2: Features, norm: int = cv2.NORM_L2
) -> Matching:
    """The paper's homography estimation procedure: mutual nearest neighbours in descriptor
    space (``cv2.BFMatcher(norm, crossCheck=True)``), then
    ``cv2.findHomography(p1, p2, cv2.RANSAC, 3, maxIters=5000)``.

    Fewer than 4 matches, or no homography from OpenCV, gives ``homography=None`` and no inliers.
    """
    matches = _match(features1.descriptors, features2.descriptors, norm, cross_check=True)
    no_inliers = np.zeros(len(matches), dtype=bool)
    if len(matches) < 4:
        return Matching(matches, no_inliers, None)
    points1 = np.asarray(features1.keypoints, np.float64)[matches[:, 0]]
    points2 = np.asarray(features2.keypoints, np.float64)[matches[:, 1]]
    estimate, mask = cv2.findHomography(
        points1, points2, cv2.RANSAC, RANSAC_THRESHOLD, maxIters=RANSAC_MAX_ITERS
    )
    if estimate is None or estimate.shape != (3, 3):
        return Matching(matches, no_inliers, None)
    return Matching(matches, mask.ravel().astype(bool), estimate)


def image_corners(shape: tuple[int, int]) -> np.ndarray:
    """Corners (0, 0), (0, H-1), (W-1, 0), (W-1, H-1) of an image, float64 [4, 2] (x, y)."""
    height, width = shape
    return np.array(
        [[0, 0], [0, height - 1], [width - 1, 0], [width - 1, height - 1]], dtype=np.float64
    )


def corner_error(
    true_homography: np.ndarray, estimate: np.ndarray | None, shape1: tuple[int, int]
) -> float:
    """Homography error (HE) of the paper: mean distance between image 1's corners warped by the
    true and by the estimated homography; ``inf`` when there is no estimate."""
    if estimate is None:
        return math.inf
    corners = image_corners(shape1)
    distance = np.linalg.norm(
        project_points(corners, true_homography) - project_points(corners, estimate), axis=1
    )
    error = float(distance.mean())
    return error if math.isfinite(error) else math.inf


def homography_matching(
    features1: Features,
    features2: Features,
    homography: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    k: int,
    norm: int = cv2.NORM_L2,
) -> tuple[Features, Features, Matching]:
    """The points and matches the homography accuracy of one pair is estimated from:
    :func:`shared_top_k`, then :func:`match_and_estimate` on the kept points. Returns
    (kept1, kept2, matching); ``matching`` indexes into the kept points."""
    kept1, kept2 = shared_top_k(features1, features2, homography, shape1, shape2, k)
    return kept1, kept2, match_and_estimate(kept1, kept2, norm)


def homography_accuracy(
    features1: Features,
    features2: Features,
    homography: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    k: int,
    norm: int = cv2.NORM_L2,
) -> float:
    """Corner error behind the homography accuracy (HA) of one pair, protocol section "Metrics"
    (KP2D's ``compute_homography``): :func:`homography_matching`, then :func:`corner_error`.
    The pair is correct at tolerance eps when the returned error is ``<= eps``; a failed
    estimate returns ``inf`` (wrong at every eps)."""
    _, _, matching = homography_matching(
        features1, features2, homography, shape1, shape2, k, norm
    )
    return corner_error(homography, matching.homography, shape1)


def _directional_matching_score(
    query: Features,
    train: Features,
    train_to_query: np.ndarray,
    shape: tuple[int, int],
    norm: int,
    threshold: float,
) -> float:
    matches = _match(query.descriptors, train.descriptors, norm, cross_check=False)
    if len(matches) == 0:
        return 0.0
    projected = project_points(np.asarray(train.keypoints)[matches[:, 1]], train_to_query)
    height, width = shape
    visible = (
        (projected[:, 0] >= 0)
        & (projected[:, 0] <= width - 1)
        & (projected[:, 1] >= 0)
        & (projected[:, 1] <= height - 1)
    )
    distance = np.linalg.norm(
        projected - np.asarray(query.keypoints, np.float64)[matches[:, 0]], axis=1
    )
    correct = visible & (distance < threshold)
    return float(correct.sum() / max(visible.sum(), 1))


def matching_score(
    features1: Features,
    features2: Features,
    homography: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    k: int,
    norm: int = cv2.NORM_L2,
    threshold: float = CORRECT_DISTANCE,
) -> float:
    """Matching score (MS) of one pair, protocol section "Metrics" (KP2D's
    ``compute_matching_score``).

    Top ``k`` over all points (no shared-view filter), plain nearest neighbour in descriptor
    space from 1 to 2. The matched image-2 points are warped by inv(H) into image 1; visible =
    inside ``[0, W-1] x [0, H-1]``; correct = visible and ``< threshold`` px from its image-1
    point; score = #correct / max(#visible, 1). Likewise from 2 to 1 with H. MS is the mean of
    both directions; a side without points scores 0.
    """
    kept1, kept2 = top_k(features1, k), top_k(features2, k)
    forward = _directional_matching_score(
        kept1, kept2, np.linalg.inv(homography), shape1, norm, threshold
    )
    backward = _directional_matching_score(kept2, kept1, homography, shape2, norm, threshold)
    return (forward + backward) / 2


# ---------------------------------------------------------------------------------------------
# Running methods over a data set


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Settings of one evaluation run (the paper's two: 240x320 / 300 and 480x640 / 1000).

    ``height``/``width`` None keeps every image at its own size. ``nms`` is the suppression
    radius in pixels (0 = none), applied to every method's points before any top-k.
    """

    height: int | None = 240
    width: int | None = 320
    top_k: int = 300
    nms: float = 0.0


class PairResult(NamedTuple):
    """Metrics of one method on one pair. ``corner_error`` is inf and ``le`` NaN when undefined;
    ``num_points`` is the mean count over both images of the points RS, LE and HA use (after
    NMS, the shared-view filter and top-k): below top-k, the method ran short of points."""

    scene: str
    split: str
    k: int
    method: str
    rs: float
    le: float
    corner_error: float
    ha1: float
    ha3: float
    ha5: float
    ms: float
    num_points: float


@dataclasses.dataclass(frozen=True)
class Results:
    """Per-pair rows of :func:`evaluate`, in data-set order, methods in the order given."""

    config: EvalConfig
    methods: tuple[str, ...]
    rows: tuple[PairResult, ...]


def _checked(features: Features, method: Method, nms: float) -> Features:
    """Validate a detector's output and apply the uniform radius NMS."""
    keypoints = np.asarray(features.keypoints, dtype=np.float32)
    scores = np.asarray(features.scores, dtype=np.float32).reshape(-1)
    descriptors = np.asarray(features.descriptors)
    n = len(scores)
    if keypoints.shape != (n, 2) or descriptors.ndim != 2 or len(descriptors) != n:
        raise ValueError(
            f"method {method.name}: expected keypoints [N, 2], scores [N], descriptors [N, D], got "
            f"{keypoints.shape}, {scores.shape}, {descriptors.shape}"
        )
    if method.norm == cv2.NORM_HAMMING and descriptors.dtype != np.uint8:
        raise ValueError(
            f"method {method.name}: Hamming norm needs uint8 descriptors, got {descriptors.dtype}"
        )
    checked = Features(keypoints, scores, descriptors)
    return _take(checked, nms_radius(keypoints, scores, nms)) if nms > 0 else checked


def detect(method: Method, image: np.ndarray, nms: float = 0.0) -> Features:
    """``method.detect(image)`` with its output validated and the protocol's radius NMS applied:
    the points every metric starts from."""
    return _checked(method.detect(image), method, nms)


def evaluate_pair(method: Method, pair: Pair, config: EvalConfig) -> PairResult:
    """Run one method on one (already resized) pair and compute every metric."""
    features1 = detect(method, pair.image1, config.nms)
    features2 = detect(method, pair.image2, config.nms)
    shape1, shape2 = pair.image1.shape[:2], pair.image2.shape[:2]
    args = (features1, features2, pair.homography, shape1, shape2, config.top_k)
    rs, le = repeatability(*args)
    error = homography_accuracy(*args, norm=method.norm)
    ha1, ha3, ha5 = (float(error <= eps) for eps in HA_TOLERANCES)
    kept1, kept2 = shared_top_k(*args)
    num_points = (len(kept1.scores) + len(kept2.scores)) / 2
    return PairResult(
        scene=pair.scene,
        split=pair.split,
        k=pair.index,
        method=method.name,
        rs=rs,
        le=le,
        corner_error=error,
        ha1=ha1,
        ha3=ha3,
        ha5=ha5,
        ms=matching_score(*args, norm=method.norm),
        num_points=num_points,
    )


def evaluate(
    methods: Sequence[Method],
    root: str | Path,
    *,
    height: int | None = 240,
    width: int | None = 320,
    top_k: int = 300,
    nms: float = 0,
    progress: bool = True,
) -> Results:
    """Evaluate every method on every pair (1, k) of an HPatches/Oxford folder, all through the
    same code path: read, :func:`resize_pair`, detect, radius NMS (if ``nms > 0``), then
    :func:`repeatability`, :func:`homography_accuracy` and :func:`matching_score` with ``top_k``.

    Pass ``height=width=None`` to keep the native sizes. Aggregate with :func:`summarize`,
    print with :func:`format_table`, save with :func:`to_json`.
    """
    names = tuple(method.name for method in methods)
    if not names:
        raise ValueError("evaluate needs at least one method")
    if len(set(names)) != len(names):
        raise ValueError(f"method names must be unique, got {names}")
    if (height is None) != (width is None):
        raise ValueError(
            f"give both height and width or neither, got height={height}, width={width}"
        )
    config = EvalConfig(height, width, top_k, float(nms))
    files = scan_sequences(root)
    rows = []
    for pair in tqdm(
        map(read_pair, files), total=len(files), desc="evaluate", unit="pair", disable=not progress
    ):
        if height is not None:
            image1, image2, homography = resize_pair(
                pair.image1, pair.image2, pair.homography, height, width
            )
            pair = pair._replace(image1=image1, image2=image2, homography=homography)
        rows.extend(evaluate_pair(method, pair, config) for method in methods)
    return Results(config, names, tuple(rows))


def _mean(values: list[float]) -> float:
    """Mean skipping NaN (undefined LE); NaN when no value is defined."""
    values = np.asarray(values, dtype=np.float64)
    return float(np.nanmean(values)) if np.any(np.isfinite(values)) else math.nan


def summarize(results: Results) -> dict[str, dict[str, dict[str, float]]]:
    """Means over pairs: ``{method: {section: {metric: value, "pairs": count}}}``.

    Sections are "all" and each split present ('i', 'v', 'other'). Metrics: rs, le (NaN pairs
    skipped), ha1, ha3, ha5 (fraction of pairs with corner error <= eps), ms, num_points.
    """
    summary = {}
    for name in results.methods:
        sections = {"all": [row for row in results.rows if row.method == name]}
        for row in sections["all"]:
            sections.setdefault(row.split, []).append(row)
        summary[name] = {
            section: {
                "pairs": len(rows),
                **{m: _mean([getattr(r, m) for r in rows]) for m in (*METRICS, "num_points")},
            }
            for section, rows in sections.items()
        }
    return summary


def format_table(results: Results) -> str:
    """The paper's table layout: one row per method, columns RS, LE, HA at eps 1/3/5 and MS,
    one section for all pairs and one per split."""
    config = results.config
    size = "native size" if config.height is None else f"{config.height}x{config.width}"
    summary = summarize(results)
    width = max([len("method"), *map(len, results.methods)])
    header = f"  {'method':<{width}}" + "".join(f"{h:>8}" for h in _HEADERS)
    titles = {
        "all": "all pairs",
        "i": "i: illumination",
        "v": "v: viewpoint",
        "other": "other scenes",
    }
    lines = [f"{size}, top {config.top_k} points, NMS = {config.nms:g}"]
    for section in ("all", *SPLITS):
        if section not in summary[results.methods[0]]:
            continue
        pairs = summary[results.methods[0]][section]["pairs"]
        lines += ["", f"{titles[section]} ({pairs} pairs)", header]
        for name in results.methods:
            values = summary[name][section]
            lines.append(f"  {name:<{width}}" + "".join(f"{values[m]:>8.3f}" for m in METRICS))
    return "\n".join(lines)


def _json_number(value: float) -> float | None:
    # JSON has no NaN or Infinity: undefined LE and failed homographies become null.
    return value if math.isfinite(value) else None


def to_json(results: Results) -> dict:
    """A JSON-ready dict: settings, per-method aggregates (:func:`summarize`) and per-pair rows.
    Non-finite numbers (undefined LE, the inf corner error of a failed estimate) become null."""
    summary = summarize(results)
    return {
        "config": dataclasses.asdict(results.config)
        | {"correct_distance": CORRECT_DISTANCE, "ha_tolerances": list(HA_TOLERANCES)},
        "summary": {
            name: {
                section: {key: _json_number(value) for key, value in values.items()}
                for section, values in sections.items()
            }
            for name, sections in summary.items()
        },
        "pairs": [
            {
                key: _json_number(value) if isinstance(value, float) else value
                for key, value in row._asdict().items()
            }
            for row in results.rows
        ],
    }
