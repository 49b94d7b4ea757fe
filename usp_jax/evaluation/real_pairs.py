"""Pairs that two real exposures made, scored against their own ground truth.

The synthetic protocol (:mod:`usp_jax.evaluation.protocol`) warps one photo, the kind of pair the
network trains on. A real pair differs in everything a homography does not model: a second
exposure, sensor noise, parallax, occlusion. Each pair here is a folder with ``pair.json``::

    {"image1": "graf1.png", "image2": "graf3.png",
     "truth": "homography", "homography": "H1to3p.xml",   # or a plain-text 3x3 file
     "ransac": "homography"}
    {"image1": "aloeL.jpg", "image2": "aloeR.jpg",
     "truth": "disparity", "disparity": "aloeGT.png",      # or .npy / .pfm, float px
     "disparity_scale": 1.0, "ransac": "fundamental"}
    {"image1": "box.png", "image2": "box_in_scene.png", "truth": "none", "ransac": "homography"}

``truth`` says how an image-1 point (x, y) maps to image 2: through the homography (image 1 ->
2), to (x - d, y) with the left view's disparity d = stored value / ``disparity_scale`` (0 and
non-finite values are unknown), or not at all (score by RANSAC inliers alone). ``ransac`` is the
model every method's inliers are counted under: the protocol's homography
(``inference.matching.estimate_homography``: 3 px) or a fundamental matrix (1 px, the epipolar
constraint that holds across parallax).

Per pair and method, at native size, on the ``top_k`` strongest points of each image:

* ``matches``: mutual nearest neighbours in descriptor space; ``correct``: those whose image-2
  point lies within ``CORRECT_DISTANCE`` of where the truth puts their image-1 point;
  ``precision`` = correct / matches with a known truth;
* ``inliers``: the RANSAC model's inliers, median over ``orders`` random orders of the matches
  (with the 5th and 95th percentiles: OpenCV's RANSAC is a fixed function of the order);
* where the truth is known, the detector and the descriptor apart: ``repeatability``, the share
  of image-1 points mapped inside image 2 that have an image-2 point within ``CORRECT_DISTANCE``
  of their true place, and ``nn_correct``, the share of those repeatable points whose nearest
  neighbour in descriptor space among all image-2 points lies there too.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from usp_jax.evaluation.metrics import CORRECT_DISTANCE, project_points, top_k
from usp_jax.evaluation.protocol import Method, detect_both
from usp_jax.evaluation.sequences import check_homography, read_image
from usp_jax.inference.features import Features
from usp_jax.inference.matching import estimate_homography, matched_points, nearest_neighbours

TRUTHS = ("homography", "disparity", "none")
MODELS = ("homography", "fundamental")
#: The fundamental-matrix RANSAC: threshold on the epipolar distance, px.
FUNDAMENTAL_THRESHOLD = 1.0
#: Seed of the random orders of the matches given to RANSAC (the same for every method).
ORDER_SEED = 0
PAIR_FILE = "pair.json"


@dataclasses.dataclass(frozen=True)
class RealPair:
    """One real pair: uint8 RGB images ``[H1, W1, 3]`` and ``[H2, W2, 3]``; ``homography``
    float64 ``[3, 3]`` (image 1 -> 2) or ``disparity`` float64 ``[H1, W1]`` (px, NaN where
    unknown), as ``truth`` says; ``ransac`` the model inliers are counted under."""

    name: str
    image1: np.ndarray
    image2: np.ndarray
    truth: str
    ransac: str
    homography: np.ndarray | None = None
    disparity: np.ndarray | None = None


def _fail(folder: Path, message: str) -> ValueError:
    return ValueError(f"real pair {folder.name}: {message}")


def _read_homography(path: Path, folder: Path) -> np.ndarray:
    """A finite, invertible 3x3 matrix from OpenCV XML/YAML (its first matrix node, as graf's
    ``H1to3p.xml`` holds ``H13``) or plain text."""
    if path.suffix.lower() in (".xml", ".yml", ".yaml"):
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        root = storage.root() if storage.isOpened() else None
        nodes = [root.getNode(key) for key in root.keys()] if root is not None else []
        matrices = [node.mat() for node in nodes if node.isMap() or node.isSeq()]
        matrix = next((m for m in matrices if m is not None), None)
    else:
        try:
            matrix = np.loadtxt(path, dtype=np.float64)
        except ValueError:
            matrix = None
    if matrix is None:
        raise _fail(folder, f"{path.name} holds no 3x3 homography")
    try:
        return check_homography(matrix, path.name)
    except ValueError as err:
        raise _fail(folder, str(err)) from None


def _read_disparity(path: Path, scale: float, shape: tuple[int, int], folder: Path) -> np.ndarray:
    """Disparity in px, float64 ``[H1, W1]``, NaN where unknown (stored 0 or non-finite)."""
    if path.suffix.lower() == ".npy":
        try:
            stored = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise _fail(folder, f"{path.name} is not a readable .npy file ({error})") from None
    else:
        stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if stored is None:
            raise _fail(folder, f"{path.name} is not a readable disparity image")
    stored = np.asarray(stored, np.float64)
    if stored.shape != shape:
        raise _fail(
            folder,
            f"disparity {path.name} is {stored.shape[::-1]} (WxH), image1 is {shape[::-1]}",
        )
    with np.errstate(invalid="ignore"):
        known = np.isfinite(stored) & (stored != 0)
    return np.where(known, stored / scale, np.nan)


def read_real_pair(folder: str | Path) -> RealPair:
    """Read and check one pair folder; raises ValueError (one line naming the pair and the
    file) on a missing or unreadable file, an unknown ``truth`` or ``ransac``, a singular
    homography or a disparity map of another size than image 1."""
    folder = Path(folder)
    try:
        spec = json.loads((folder / PAIR_FILE).read_text())
    except FileNotFoundError:
        raise _fail(folder, f"no {PAIR_FILE} in {folder}") from None
    except (OSError, ValueError) as error:
        raise _fail(folder, f"{PAIR_FILE} is not readable JSON ({error})") from None
    if not isinstance(spec, dict):
        raise _fail(folder, f"{PAIR_FILE} must hold a JSON object")
    truth, ransac = spec.get("truth", "none"), spec.get("ransac", "homography")
    if truth not in TRUTHS or ransac not in MODELS:
        raise _fail(folder, f"truth must be one of {TRUTHS} and ransac one of {MODELS}")

    def path(key: str) -> Path:
        if not isinstance(spec.get(key), str):
            raise _fail(folder, f"{PAIR_FILE} names no {key!r} file")
        found = folder / spec[key]
        if not found.is_file():
            raise _fail(folder, f"{key} file {found.name} is missing")
        return found

    try:
        image1, image2 = read_image(path("image1")), read_image(path("image2"))
    except ValueError as error:
        raise _fail(folder, str(error).replace(str(folder) + "/", "")) from None
    homography = _read_homography(path("homography"), folder) if truth == "homography" else None
    disparity = None
    if truth == "disparity":
        scale = spec.get("disparity_scale", 1.0)
        if not isinstance(scale, int | float) or not scale > 0:
            raise _fail(folder, f"disparity_scale must be a positive number, got {scale!r}")
        disparity = _read_disparity(path("disparity"), float(scale), image1.shape[:2], folder)
    return RealPair(folder.name, image1, image2, truth, ransac, homography, disparity)


def scan_real_pairs(root: str | Path) -> list[Path]:
    """The pair folders (those holding ``pair.json``) under ``root``, sorted; ``root`` itself
    when it is one. Raises FileNotFoundError when there is none."""
    root = Path(root)
    if (root / PAIR_FILE).is_file():
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder of real pairs")
    found = sorted(path.parent for path in root.glob(f"*/{PAIR_FILE}"))
    if not found:
        raise FileNotFoundError(f"{root}: no real pair (a folder holding {PAIR_FILE})")
    return found


def true_positions(pair: RealPair, points1: np.ndarray) -> np.ndarray:
    """Where image-1 points ``[N, 2]`` (x, y, pixel centres at integers) are in image 2, float64
    ``[N, 2]``; NaN where the truth does not say (``none``, an unknown disparity, a point off
    the disparity map). The disparity is read at the nearest pixel: interpolating would mix in
    unknown neighbours and blur depth edges."""
    points1 = np.asarray(points1, np.float64).reshape(-1, 2)
    if pair.truth == "homography":
        return project_points(points1, pair.homography)
    found = np.full_like(points1, np.nan)
    if pair.truth == "disparity":
        height, width = pair.disparity.shape
        columns, rows = np.rint(points1[:, 0]).astype(int), np.rint(points1[:, 1]).astype(int)
        inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
        d = np.full(len(points1), np.nan)
        d[inside] = pair.disparity[rows[inside], columns[inside]]
        found = points1 - np.stack([d, np.zeros_like(d)], axis=1)
        found[np.isnan(d)] = np.nan  # the whole point is unknown, not only its x
    return found


def _distances(places: np.ndarray, points2: np.ndarray) -> np.ndarray:
    """``[N, M]`` distances from true places (NaN rows stay NaN) to image-2 points."""
    return np.linalg.norm(places[:, None, :] - points2[None, :, :], axis=2)


def detector_and_descriptor(
    pair: RealPair, features1: Features, features2: Features, norm: int
) -> tuple[int, int, int]:
    """(visible, repeatable, nn_correct) counts of image-1 points: mapped inside image 2; with an
    image-2 point within ``CORRECT_DISTANCE`` of that place; and, of those, whose nearest
    neighbour in descriptor space among all image-2 points is such a point."""
    places = true_positions(pair, features1.keypoints)
    height, width = pair.image2.shape[:2]
    with np.errstate(invalid="ignore"):
        visible = (
            np.all(np.isfinite(places), axis=1)
            & (places[:, 0] >= 0)
            & (places[:, 0] <= width - 1)
            & (places[:, 1] >= 0)
            & (places[:, 1] <= height - 1)
        )
    if not visible.any() or len(features2.scores) == 0:
        return int(visible.sum()), 0, 0
    near = _distances(places[visible], np.asarray(features2.keypoints, np.float64))
    near = near <= CORRECT_DISTANCE
    repeatable = near.any(axis=1)
    nearest = nearest_neighbours(
        features1.descriptors[visible], features2.descriptors, norm, cross_check=False
    )
    hit = np.zeros(len(near), dtype=bool)
    hit[nearest[:, 0]] = near[nearest[:, 0], nearest[:, 1]]
    return int(visible.sum()), int(repeatable.sum()), int((hit & repeatable).sum())


def count_inliers(points1: np.ndarray, points2: np.ndarray, model: str, orders: int) -> np.ndarray:
    """RANSAC inlier counts, int ``[orders]``, of ``model`` fitted to matched points ``[M, 2]``
    in ``orders`` random orders (``np.random.default_rng(ORDER_SEED)``'s permutations)."""
    rng = np.random.default_rng(ORDER_SEED)
    counts = []
    for _ in range(orders):
        order = rng.permutation(len(points1))
        first, second = points1[order], points2[order]
        if model == "homography":
            counts.append(int(estimate_homography(first, second)[1].sum()))
        elif len(first) < 8:
            counts.append(0)
        else:
            _, mask = cv2.findFundamentalMat(
                first, second, cv2.FM_RANSAC, FUNDAMENTAL_THRESHOLD, 0.999, 5000
            )
            counts.append(0 if mask is None else int(mask.sum()))
    return np.array(counts, dtype=np.int64)


@dataclasses.dataclass(frozen=True)
class RealPairResult:
    """One method on one real pair. Counts of the truth's metrics are None where the truth is
    ``none``; ``precision_interval`` is the 95% Wilson interval of ``precision``; ``inliers``
    the median over RANSAC orders with ``inliers_spread`` its 5th and 95th percentiles."""

    pair: str
    method: str
    truth: str
    ransac: str
    points: tuple[int, int]
    matches: int
    inliers: float
    inliers_spread: tuple[float, float]
    correct: int | None = None
    precision: float | None = None
    precision_interval: tuple[float, float] | None = None
    visible: int | None = None
    repeatable: int | None = None
    nn_correct: int | None = None

    @property
    def repeatability(self) -> float | None:
        return None if self.visible is None else self.repeatable / max(self.visible, 1)

    @property
    def nn_share(self) -> float | None:
        return None if self.repeatable is None else self.nn_correct / max(self.repeatable, 1)


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion; (0, 1) for no trials."""
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = (
        z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    )
    return max(0.0, centre - half), min(1.0, centre + half)


def score_pair(
    pair: RealPair,
    method: str,
    features1: Features,
    features2: Features,
    norm: int,
    orders: int = 1,
) -> RealPairResult:
    """Every metric of one method's (already top-k) points on ``pair`` (module docstring)."""
    matches = nearest_neighbours(features1.descriptors, features2.descriptors, norm, True)
    points1, points2 = matched_points(features1, features2, matches)
    inliers = count_inliers(points1, points2, pair.ransac, orders)
    low, median, high = np.percentile(inliers, [5, 50, 95]) if len(inliers) else (0, 0, 0)
    result = RealPairResult(
        pair.name,
        method,
        pair.truth,
        pair.ransac,
        (len(features1.scores), len(features2.scores)),
        len(matches),
        float(median),
        (float(low), float(high)),
    )
    if pair.truth == "none":
        return result
    error = np.linalg.norm(true_positions(pair, points1) - points2, axis=1)
    known = np.isfinite(error)
    correct = int(np.sum(error[known] <= CORRECT_DISTANCE))
    visible, repeatable, nn_correct = detector_and_descriptor(pair, features1, features2, norm)
    return dataclasses.replace(
        result,
        correct=correct,
        precision=correct / max(int(known.sum()), 1),
        precision_interval=wilson_interval(correct, int(known.sum())),
        visible=visible,
        repeatable=repeatable,
        nn_correct=nn_correct,
    )


def evaluate_real(
    methods: Sequence[Method],
    root: str | Path,
    *,
    top: int = 1000,
    nms: float = 0.0,
    ransac_orders: int = 20,
    progress: bool = True,
) -> list[RealPairResult]:
    """Every method on every real pair under ``root`` at native size: detect (with the uniform
    radius NMS when ``nms`` > 0), keep each image's ``top`` strongest points, then
    :func:`score_pair`. Every pair folder is read and checked before any method runs, so a bad
    one fails at once; an image where a method finds no point raises ValueError naming both."""
    pairs = [read_real_pair(folder) for folder in scan_real_pairs(root)]
    rows = []
    for pair in tqdm(pairs, desc="real pairs", unit="pair", disable=not progress):
        for method in methods:
            found = detect_both(method, pair.image1, pair.image2, nms)
            kept = [top_k(features, top) for features in found]
            for index, features in enumerate(kept, 1):
                if len(features.scores) == 0:
                    raise ValueError(
                        f"real pair {pair.name}: {method.name} found no point in image {index}"
                        " (a blank image?)"
                    )
            rows.append(score_pair(pair, method.name, *kept, method.norm, ransac_orders))
    return rows


def format_real_table(rows: Sequence[RealPairResult]) -> str:
    """One block per pair, one line per method: correct matches, precision with its interval,
    inliers with their spread over RANSAC orders, repeatability and the nearest-neighbour share
    (blank where the pair has no truth)."""
    width = max([len("method"), *(len(row.method) for row in rows)])
    header = (
        f"  {'method':<{width}} {'points':>11} {'matches':>8} {'correct':>8}"
        f" {'precision [95%]':>20} {'inliers [5-95%]':>18} {'RS':>6} {'NN ok':>6}"
    )
    lines, last = [], None
    for row in rows:
        if row.pair != last:
            lines += ["" if last else "", f"{row.pair} (truth: {row.truth}, {row.ransac} RANSAC)"]
            lines.append(header)
            last = row.pair
        low, high = row.inliers_spread
        cells = [
            f"  {row.method:<{width}} {f'{row.points[0]}/{row.points[1]}':>11} {row.matches:>8}",
            f"{row.correct if row.correct is not None else '-':>8}",
            f"{_precision(row):>20}",
            f"{f'{row.inliers:.0f} [{low:.0f}-{high:.0f}]':>18}",
            f"{_share(row.repeatability):>6} {_share(row.nn_share):>6}",
        ]
        lines.append(" ".join(cells))
    return "\n".join(lines).lstrip("\n")


def _share(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _precision(row: RealPairResult) -> str:
    if row.precision is None:
        return "-"
    low, high = row.precision_interval
    return f"{row.precision:.3f} [{low:.2f}, {high:.2f}]"


def real_to_json(rows: Sequence[RealPairResult], config: dict) -> dict:
    """A JSON-ready dict: the settings and one object per (pair, method) with the derived
    shares."""
    return {
        "config": config
        | {"correct_distance": CORRECT_DISTANCE, "fundamental_threshold": FUNDAMENTAL_THRESHOLD},
        "pairs": [
            dataclasses.asdict(row) | {"repeatability": row.repeatability, "nn_share": row.nn_share}
            for row in rows
        ],
    }
