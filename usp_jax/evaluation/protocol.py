"""The HPatches evaluation protocol over a data set: every method on every pair (1, k) through the
same code path (read, resize, detect, the same radius NMS, then the metrics of
:mod:`usp_jax.evaluation.metrics`), aggregated as the paper's tables.

A :class:`~usp_jax.inference.methods.Method` is any detector: a classical one or XFeat
(``methods.baseline_method``) or a ``Detector`` wrapped by ``methods.as_method``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from usp_jax.evaluation.metrics import (
    CORRECT_DISTANCE,
    HA_TOLERANCES,
    corner_error,
    homography_matching,
    matching_score,
    reordered_corner_errors,
    repeatability,
    take,
)
from usp_jax.evaluation.sequences import Pair, read_pair, resize_pair, scan_sequences
from usp_jax.inference.detector import Detector
from usp_jax.inference.features import Features
from usp_jax.inference.matching import matched_points
from usp_jax.inference.methods import Method, as_method, baseline_method
from usp_jax.inference.nms import radius_nms_host

# Section order of the tables: every pair, then HPatches' illumination and viewpoint splits.
SPLITS = ("i", "v", "other")
METRICS = ("rs", "le", "ha1", "ha3", "ha5", "ms")
_HEADERS = ("RS", "LE", "HA e=1", "HA e=3", "HA e=5", "MS")


def methods(
    detector: Detector | None,
    baselines: Sequence[str],
    top_k: int,
    guide: Detector | None = None,
    turn_back: bool = False,
) -> list[Method]:
    """The methods of one evaluation: ``detector`` (if any, :func:`as_method`, with ``guide`` or
    ``turn_back``) and the named ``baselines`` (OpenCV's, or "xfeat":
    ``methods.baseline_method``), in that order, for a protocol keeping ``top_k`` points.

    The evaluation applies NMS and the shared-view filter before its own top-k, to
    UnsuperPoint's full candidate set; a baseline cut at exactly top-k before them would be left
    with fewer points than the model on every viewpoint pair, so each keeps 4 ``top_k``.
    """
    found = [as_method(detector, guide=guide, turn_back=turn_back)] if detector is not None else []
    return found + [baseline_method(name, 4 * top_k) for name in baselines]


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Settings of one evaluation run (the paper's two: 240x320 / 300 and 480x640 / 1000).

    ``height``/``width`` None keeps every image at its own size. ``nms`` is the suppression
    radius in pixels (0 = none), applied to every method's points before any top-k.
    ``ransac_orders`` 1 is the protocol's HA: one RANSAC estimate per pair, from the matches in
    the matcher's order. N > 1 makes each pair's HA at eps the share of N random orders of the
    same matches whose estimate is within eps (``metrics.reordered_corner_errors``): the chance
    that RANSAC finds the homography, free of the one draw's luck; ``corner_error`` stays the
    protocol's.
    """

    height: int | None = 240
    width: int | None = 320
    top_k: int = 300
    nms: float = 0.0
    ransac_orders: int = 1


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
    return take(checked, radius_nms_host(keypoints, scores, nms)) if nms > 0 else checked


def detect(method: Method, image: np.ndarray, nms: float = 0.0) -> Features:
    """``method.detect(image)`` with its output validated and the protocol's radius NMS applied:
    the points every metric starts from."""
    return _checked(method.detect(image), method, nms)


def detect_both(
    method: Method, image1: np.ndarray, image2: np.ndarray, nms: float = 0.0
) -> tuple[Features, Features]:
    """:func:`detect` of both images of a pair, through ``method.detect_pair`` when it has one."""
    if method.detect_pair is None:
        return detect(method, image1, nms), detect(method, image2, nms)
    found = method.detect_pair(image1, image2)
    return tuple(_checked(features, method, nms) for features in found)


def evaluate_pair(method: Method, pair: Pair, config: EvalConfig) -> PairResult:
    """Run one method on one (already resized) pair and compute every metric."""
    features1, features2 = detect_both(method, pair.image1, pair.image2, config.nms)
    shape1, shape2 = pair.image1.shape[:2], pair.image2.shape[:2]
    args = (features1, features2, pair.homography, shape1, shape2, config.top_k)
    rs, le = repeatability(*args)
    # metrics.homography_accuracy, keeping the matches for the re-ordered estimates.
    kept1, kept2, matching = homography_matching(*args, norm=method.norm)
    error = corner_error(pair.homography, matching.homography, shape1)
    errors = np.array([error])
    if config.ransac_orders > 1:
        points = matched_points(kept1, kept2, matching.matches)
        errors = reordered_corner_errors(*points, pair.homography, shape1, config.ransac_orders)
    ha1, ha3, ha5 = (float(np.mean(errors <= eps)) for eps in HA_TOLERANCES)
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
    ransac_orders: int = 1,
    progress: bool = True,
) -> Results:
    """Evaluate every method on every pair (1, k) of an HPatches/Oxford folder, all through the
    same code path: read, :func:`resize_pair`, detect, radius NMS (if ``nms > 0``), then
    :func:`repeatability`, :func:`homography_accuracy` and :func:`matching_score` with ``top_k``.

    Pass ``height=width=None`` to keep the native sizes; ``ransac_orders`` > 1 estimates HA over
    that many orders of each pair's matches (:class:`EvalConfig`). Aggregate with :func:`summarize`,
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
    if ransac_orders < 1:
        raise ValueError(f"ransac_orders must be at least 1, got {ransac_orders}")
    config = EvalConfig(height, width, top_k, float(nms), int(ransac_orders))
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
    orders = config.ransac_orders
    lines = [f"{size}, top {config.top_k} points, NMS = {config.nms:g}"]
    if orders > 1:
        lines[0] += f", HA: share of {orders} random orders of the matches given to RANSAC"

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
