"""Where a method loses accuracy: evaluation rows broken down by viewpoint strength (view k of
``usp-jax make-pairs``), by the pairs' in-plane rotation and by their zoom, and the precision of the RANSAC
inliers under the true homography.
"""

from __future__ import annotations

import collections
import math
import pathlib

import cv2
import jax
import numpy as np

from usp_jax.core import geometry
from usp_jax.evaluation import metrics, protocol, sequences
from usp_jax.evaluation.statistics import per_pair
from usp_jax.evaluation.zoom import ZOOM_EDGES, zoom_label, zoom_of
from usp_jax.inference.matching import Matching
from usp_jax.inference.turning import in_plane_rotation


def by_view(rows: list[dict]) -> dict[str, dict[int, dict[str, float]]]:
    """``{method: {k: statistics}}`` over the viewpoint ("v") pairs of evaluation rows.

    The metrics are the means of the rows' own per-pair values, undefined (null) LE skipped, as
    ``evaluation.summarize`` takes them; a failed estimate's corner error is null in the JSON
    and counts as infinite in the median."""
    return _statistics(rows, lambda row: row["k"])


# In-plane rotation ranges in degrees, (low, high), high None for open-ended: fine ones for upright
# pairs, 30-degree ones up to 180 for pairs that turn much further (``usp-jax make-pairs
# --rotation``). A pair falls in the last range whose low it reaches.
ROTATION_RANGES = ((0, 10), (10, 20), (20, None))
WIDE_ROTATION_RANGES = tuple((low, low + 30) for low in range(0, 180, 30))
# Below this largest rotation the wide ranges would be two, coarser than the fine ones; the
# held-out pairs reach 37 degrees (one pair; the rest stay under 24).
WIDE_FROM = 60


def rotation_ranges(angles) -> tuple[tuple[int, int | None], ...]:
    """:data:`WIDE_ROTATION_RANGES` if any of ``angles`` (degrees) turns by :data:`WIDE_FROM` or
    more, else :data:`ROTATION_RANGES`."""
    return WIDE_ROTATION_RANGES if any(abs(a) >= WIDE_FROM for a in angles) else ROTATION_RANGES


def _range_label(low: int, ranges) -> str:
    high = dict(ranges)[low]
    return f">={low}" if high is None else f"{low}-{high}"


def by_rotation(
    rows: list[dict], pairs_root: str | pathlib.Path, ranges=None
) -> dict[str, dict[str, dict]]:
    """``{method: {rotation range: statistics}}`` over the viewpoint pairs of evaluation rows, for
    every method in them, the ranges (default :func:`rotation_ranges` of the evaluated pairs)
    applied to :func:`in_plane_rotation` of each pair's homography at image 1's centre (read from
    ``pairs_root``, the folder that was evaluated). Ranges without pairs are left out."""
    angles = _pair_measure(rows, pairs_root, in_plane_rotation)
    evaluated = {(r["scene"], r["k"]) for r in rows if r["split"] == "v"}
    if ranges is None:
        ranges = rotation_ranges(angles[pair] for pair in evaluated)
    lows = [low for low, _ in ranges]

    def opening(row):  # The low of the range the pair falls in: numbers sort, labels would not.
        turn = abs(angles[row["scene"], row["k"]])
        return max((low for low in lows if turn >= low), default=lows[0])

    table = _statistics(rows, opening)
    return {
        m: {_range_label(low, ranges): s for low, s in groups.items()}
        for m, groups in table.items()
    }


def _pair_measure(rows: list[dict], pairs_root, measure) -> dict[tuple[str, int], float]:
    """``{(scene, k): measure(homography, image 1's (height, width))}`` of every pair under
    ``pairs_root``; raises ValueError when an evaluated viewpoint pair is not there."""
    values, sizes = {}, {}
    for files in sequences.scan_sequences(pairs_root):
        if files.path1 not in sizes:
            sizes[files.path1] = sequences.read_image(files.path1).shape[:2]
        values[files.scene, files.index] = measure(files.homography, sizes[files.path1])
    evaluated = {(r["scene"], r["k"]) for r in rows if r["split"] == "v"}
    missing = evaluated - values.keys()
    if missing:
        raise ValueError(f"{pairs_root} lacks {len(missing)} evaluated pairs, e.g. {min(missing)}")
    return values


def by_zoom(rows: list[dict], pairs_root: str | pathlib.Path, edges=ZOOM_EDGES) -> dict:
    """``{method: {zoom bin: statistics}}`` over the viewpoint pairs of evaluation rows, as
    :func:`by_rotation`, binned by :func:`zoom_of` of each pair's homography (read from
    ``pairs_root``, the folder that was evaluated); bins in increasing zoom, empty ones left
    out."""
    bins = zoom_bins(rows, pairs_root, edges)
    table = _statistics(rows, lambda row: bins[row["scene"], row["k"]])
    return {
        m: {zoom_bin_label(i, edges): s for i, s in groups.items()} for m, groups in table.items()
    }


def zoom_bins(
    rows: list[dict], pairs_root: str | pathlib.Path, edges=ZOOM_EDGES
) -> dict[tuple[str, int], int]:
    """``{(scene, k): bin}`` of the viewpoint pairs of evaluation rows: the index of the bin
    (0 below ``edges[0]``) that :func:`zoom_of` of the pair's homography falls in (read from
    ``pairs_root``, the folder that was evaluated)."""
    zooms = _pair_measure(rows, pairs_root, zoom_of)
    return {pair: int(np.searchsorted(edges, zoom, side="right")) for pair, zoom in zooms.items()}


def zoom_bin_label(index: int, edges=ZOOM_EDGES) -> str:
    """The label of bin ``index`` of :func:`zoom_bins` (``<0.71`` ... ``>=1.41``)."""
    return zoom_label((0.0, *edges)[index], edges)


def _statistics(rows: list[dict], group_of) -> dict[str, dict]:
    """Per method and per ``group_of(row)``, the viewpoint rows' mean metrics and median corner
    error (see :func:`by_view`)."""
    grouped: dict[str, dict] = {}
    for row in rows:
        if row["split"] == "v":
            grouped.setdefault(row["method"], {}).setdefault(group_of(row), []).append(row)
    table = {}
    for method, groups in grouped.items():
        table[method] = {}
        for key, group in sorted(groups.items()):
            values = per_pair(group)[method]
            error = [
                math.inf if row["corner_error"] is None else row["corner_error"] for row in group
            ]
            table[method][key] = {
                "pairs": len(group),
                **{
                    m: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
                    for m, v in values.items()
                },
                "median_corner_error": float(np.median(error)),
            }
    return table


def markdown_by_view(table: dict, group: str = "view k") -> str:
    lines = [
        f"| method | {group} | pairs | HA e=1 | HA e=3 | HA e=5 | median corner error (px) "
        "| LE | RS | MS |",
        "|" + "---|" * 10,
    ]
    for method, views in table.items():
        for k, s in views.items():
            lines.append(
                f"| {method} | {k} | {s['pairs']} | {s['ha1']:.2f} | {s['ha3']:.2f} | "
                f"{s['ha5']:.2f} | {s['median_corner_error']:.2f} | {s['le']:.2f} | "
                f"{s['rs']:.3f} | {s['ms']:.3f} |"
            )
    return "\n".join(lines)


def inlier_residuals(
    keypoints1: np.ndarray,
    keypoints2: np.ndarray,
    matching: Matching,
    homography: np.ndarray,
    shape1: tuple[int, int],
) -> dict[str, float]:
    """``{"inliers", "rms", "over_2px", "coverage", "offset_x", "offset_y"}`` of one pair's
    RANSAC inliers: their count, the RMS and share above 2 px of ``|p2 - H p1|`` under the TRUE
    homography ``H`` (image 1 -> 2), the area of their convex hull in image 1 over its area
    ``shape1`` (height, width), and the mean of ``p2 - H p1`` in image 2's pixels (x, y): a
    constant offset between the points and the truth, which cancels on upright pairs but not on
    turned ones (``sequences.resize_pair``).

    keypoints1 [N1, 2], keypoints2 [N2, 2] (x, y); ``matching`` as ``match_and_estimate``
    returns it for them. No inliers gives NaN for rms, over_2px and the offsets, coverage 0."""
    pairs = matching.matches[matching.inliers]
    inliers1 = keypoints1[pairs[:, 0]]
    residuals = keypoints2[pairs[:, 1]] - metrics.project_points(inliers1, homography)
    errors = np.linalg.norm(residuals, axis=1)
    if not len(errors):
        return {
            "inliers": 0.0,
            "rms": np.nan,
            "over_2px": np.nan,
            "coverage": 0.0,
            "offset_x": np.nan,
            "offset_y": np.nan,
        }
    hull = cv2.convexHull(np.asarray(inliers1, np.float32))
    offset_x, offset_y = residuals.mean(axis=0)
    return {
        "inliers": float(len(errors)),
        "rms": float(np.sqrt(np.mean(errors**2))),
        "over_2px": float(np.mean(errors > 2)),
        "coverage": float(cv2.contourArea(hull)) / (shape1[0] * shape1[1]),
        "offset_x": float(offset_x),
        "offset_y": float(offset_y),
    }


def inlier_residuals_by_view(
    methods: list[protocol.Method], root: str, height: int, width: int, top_k: int, nms: float
) -> dict[str, dict[int, dict[str, float]]]:
    """``{method: {k: mean inliers, rms, over_2px, coverage, offset_x and offset_y, median
    corner_error}}`` over the "v" pairs. A method with ``detect_pair`` (matching across any
    rotation) detects each pair through it, as the evaluation does."""
    rows: dict[tuple[str, int], list[dict]] = collections.defaultdict(list)
    for files in sequences.scan_sequences(root):
        if files.split != "v":
            continue
        pair = sequences.read_pair(files)
        image1, image2, homography = sequences.resize_pair(
            pair.image1, pair.image2, pair.homography, height, width
        )
        for method in methods:
            features1, features2 = protocol.detect_both(method, image1, image2, nms)
            kept1, kept2, matching = metrics.homography_matching(
                features1,
                features2,
                homography,
                image1.shape[:2],
                image2.shape[:2],
                top_k,
                method.norm,
            )
            row = inlier_residuals(
                kept1.keypoints, kept2.keypoints, matching, homography, image1.shape[:2]
            )
            row["corner_error"] = metrics.corner_error(
                homography, matching.homography, image1.shape[:2]
            )
            rows[(method.name, pair.index)].append(row)
    table: dict[str, dict[int, dict[str, float]]] = {method.name: {} for method in methods}
    for (name, k), group in sorted(rows.items()):
        table[name][k] = {
            **{
                key: float(np.nanmean([r[key] for r in group]))
                for key in ("inliers", "rms", "over_2px", "coverage", "offset_x", "offset_y")
            },
            "corner_error": float(np.median([r["corner_error"] for r in group])),
        }
    return table


def markdown_inlier_residuals(table: dict[str, dict[int, dict[str, float]]]) -> str:
    methods = list(table)
    lines = [
        "| view k | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for k in sorted(next(iter(table.values()))):
        cells = [
            f"{s['inliers']:.0f} / {s['rms']:.2f} / {100 * s['over_2px']:.1f}% / "
            f"{100 * s['coverage']:.0f}% / {s['corner_error']:.2f}"
            for s in (table[m][k] for m in methods)
        ]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def training_rotations(
    homography: geometry.HomographyConfig,
    height: int,
    width: int,
    draws: int,
    seed: int = 0,
    window: tuple[int, int] | None = None,
) -> np.ndarray:
    """In-plane rotations in degrees [draws] of random training homographies for a
    [height, width] crop; with ``window`` (a config's ``data.context_window``), those drawn for
    branch B rendered from a context window of that (height, width) around the crop."""
    keys = jax.random.split(jax.random.PRNGKey(seed), draws)
    if window is None:
        sample = jax.vmap(lambda key: geometry.sample_homography(key, height, width, homography))
    else:
        sample = jax.vmap(
            lambda key: geometry.sample_window_homography(key, height, width, window, homography)
        )
    return np.array(
        [in_plane_rotation(h, (height, width)) for h in np.asarray(sample(keys), np.float64)]
    )
