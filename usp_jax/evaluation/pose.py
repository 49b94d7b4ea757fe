"""Relative pose accuracy: two views with known cameras, each method's matches, the essential
matrix, and the area under the curve of pose errors, as SuperGlue (Sarlin et al., CVPR 2020),
LightGlue and XFeat report on MegaDepth and ScanNet.

Per pair: mutual nearest neighbours of the two images' descriptors; the essential matrix by
RANSAC on the matches in normalised coordinates (``cv2.findEssentialMat``, inlier threshold
``RANSAC_PIXELS`` px divided by the mean focal length, confidence ``CONFIDENCE``, OpenCV's
5-point solver); ``cv2.recoverPose`` on each candidate matrix, keeping the one with most points
in front of both cameras. The pair's error is the larger of the rotation's angle error and the
angle between the true and estimated translation directions (the translation's scale is not
observable; its sign ambiguity is folded, ``min(e, 180 - e)``, as SuperGlue does); no estimate
(fewer than 5 matches, or none found) is an infinite error.

The AUC at a threshold T is the area under the recall curve (the share of pairs with error at
most e, against e) from 0 to T, divided by T, the curve linear between the sorted errors as in
SuperGlue's ``pose_auc``: 1 when every pair is exact, 0 when none is under T.
"""

from __future__ import annotations

import json
import math
import shutil
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.inference.images import grey, read_image
from usp_jax.inference.match_refinement import refine_matches
from usp_jax.inference.matching import nearest_neighbours

#: Error thresholds of the AUC, degrees.
THRESHOLDS = (5.0, 10.0, 20.0)
#: RANSAC's inlier distance, pixels (SuperGlue's 1 px), and its confidence.
RANSAC_PIXELS = 1.0
CONFIDENCE = 0.99999


class PosePair(NamedTuple):
    """Two views and their relative pose: images uint8 ``[H, W, 3]`` RGB, intrinsics ``K1``,
    ``K2`` [3, 3], and ``R`` [3, 3], ``t`` [3] taking camera 1's frame to camera 2's
    (``x2 = R x1 + t``)."""

    name: str
    image1: np.ndarray
    image2: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    t: np.ndarray


def check_pose(R, t) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` as float64 arrays after checking them: R a [3, 3] rotation (orthonormal, det
    +1, to 1e-4), t a [3] nonzero finite vector. Raises ValueError saying what is wrong."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    if R.shape != (3, 3) or t.shape not in ((3,), (3, 1)):
        raise ValueError(f"a pose is R [3, 3] and t [3], got R {R.shape} and t {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError("the pose holds values that are not finite")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise ValueError("R is not a rotation (orthonormal with determinant +1)")
    if not np.linalg.norm(t) > 0:
        raise ValueError("t is zero: a camera that does not move has no relative direction")
    return R, t.reshape(3)


def check_intrinsics(K) -> np.ndarray:
    """``K`` as a float64 [3, 3] pinhole matrix after checking it (finite, positive focal
    lengths, last row 0 0 1). Raises ValueError saying what is wrong."""
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"intrinsics are a finite [3, 3] K, got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])):
        raise ValueError("K needs positive focal lengths and a last row 0 0 1")
    return K


def write_pairs(folder: str | Path, pairs: Sequence[PosePair]) -> None:
    """Pairs on disk, one folder each: ``1.png``, ``2.png`` and ``pose.json`` (K1, K2, R, t).
    The folder must not exist; it is written under a temporary name and renamed when complete."""
    folder = Path(folder)
    if folder.exists():
        raise ValueError(f"{folder} exists: pose pairs are written into a new folder")
    partial = folder.with_name(folder.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    for pair in pairs:
        target = partial / pair.name
        target.mkdir(parents=True)
        for index, image in ((1, pair.image1), (2, pair.image2)):
            cv2.imwrite(str(target / f"{index}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        fields = {k: np.asarray(getattr(pair, k)).tolist() for k in ("K1", "K2", "R", "t")}
        (target / "pose.json").write_text(json.dumps(fields))
    partial.rename(folder)


def read_pairs(folder: str | Path) -> list[PosePair]:
    """The pairs of :func:`write_pairs`'s layout in ``folder`` (sorted by name), every pose and
    intrinsics checked before any image is read. Raises ValueError naming the first bad pair."""
    folders = (
        sorted(p for p in Path(folder).iterdir() if p.is_dir()) if Path(folder).is_dir() else []
    )
    if not folders:
        raise ValueError(f"{folder}: no pair folders (each holds 1.png, 2.png and pose.json)")
    poses = []
    for path in folders:
        try:
            fields = json.loads((path / "pose.json").read_text())
            R, t = check_pose(fields["R"], fields["t"])
            poses.append((check_intrinsics(fields["K1"]), check_intrinsics(fields["K2"]), R, t))
        except FileNotFoundError:
            raise ValueError(f"{path}: no pose.json (a pair without its poses)") from None
        except (KeyError, TypeError, json.JSONDecodeError) as error:
            raise ValueError(f"{path}/pose.json: needs K1, K2, R and t ({error})") from None
        except ValueError as error:
            raise ValueError(f"{path}/pose.json: {error}") from None
    return [
        PosePair(path.name, read_image(path / "1.png"), read_image(path / "2.png"), *found)
        for path, found in zip(folders, poses, strict=True)
    ]


def rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """Angle in degrees of rotation matrices ``[..., 3, 3]``: arccos((trace - 1) / 2)."""
    cosine = (np.trace(rotations, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def direction_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between vectors ``[..., 3]`` (0 to 180; a zero vector gives 90)."""
    norms = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    cosine = np.sum(a * b, axis=-1) / np.where(norms > 0, norms, np.inf)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def relative_pose_errors(
    rotations: np.ndarray, centres: np.ndarray, true_rotations: np.ndarray, true_centres: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Errors over every pair i < j of cameras: world-to-camera rotations ``[N, 3, 3]`` and
    camera centres ``[N, 3]``, estimated and true. Returns (relative-rotation errors, the angle
    between R_j R_i^T estimated and true; translation-direction errors, the angle between
    R_j (c_i - c_j) estimated and true), degrees ``[N (N - 1) / 2]`` each. Both ignore the
    model's gauge (its world frame and scale)."""
    i, j = np.triu_indices(len(rotations), k=1)

    def relative(r, c):
        turn = r[j] @ np.swapaxes(r[i], -1, -2)
        return turn, np.einsum("pab,pb->pa", r[j], c[i] - c[j])

    turn, direction = relative(np.asarray(rotations), np.asarray(centres))
    true_turn, true_direction = relative(np.asarray(true_rotations), np.asarray(true_centres))
    return (
        rotation_angle(np.swapaxes(turn, -1, -2) @ true_turn),
        direction_angle(direction, true_direction),
    )


def pose_errors(R_true, t_true, R, t) -> tuple[float, float]:
    """(rotation error, translation direction error), degrees: the angle of ``R_true^T R`` and
    the angle between ``t_true`` and ``t`` with the sign ambiguity folded (module docstring)."""
    direction = float(direction_angle(np.ravel(t_true), np.ravel(t)))
    return float(rotation_angle(np.asarray(R_true).T @ R)), min(direction, 180.0 - direction)


def estimate_pose(
    points1: np.ndarray, points2: np.ndarray, K1: np.ndarray, K2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R [3, 3], unit t [3], bool inliers [M]) from matched pixels ``[M, 2]`` of two views, or
    None (fewer than 5 matches, or no essential matrix). Module docstring: the settings."""
    if len(points1) < 5:
        return None

    def normalised(points, K):
        return (np.asarray(points, np.float64) - K[:2, 2]) / np.diag(K)[:2]

    focal = np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]])
    n1, n2 = normalised(points1, K1), normalised(points2, K2)
    E, mask = cv2.findEssentialMat(
        n1, n2, np.eye(3), method=cv2.RANSAC, prob=CONFIDENCE, threshold=RANSAC_PIXELS / focal
    )
    if E is None:
        return None
    best = None
    for candidate in np.split(E, len(E) // 3):  # the 5-point solver may return several
        count, R, t, inliers = cv2.recoverPose(candidate, n1, n2, np.eye(3), 1e9, mask=mask.copy())
        if best is None or count > best[0]:
            best = (count, R, t.ravel(), inliers.ravel() > 0)
    return best[1:]


def pose_auc(errors: Sequence[float], thresholds: Sequence[float] = THRESHOLDS) -> list[float]:
    """The AUC of the recall curve of ``errors`` (degrees, inf: failed) up to each threshold,
    normalised by it (module docstring; SuperGlue's computation)."""
    errors = np.sort(np.asarray(errors, np.float64))
    recall = np.arange(1, len(errors) + 1) / len(errors)
    errors, recall = np.r_[0.0, errors], np.r_[0.0, recall]
    aucs = []
    for threshold in thresholds:
        last = np.searchsorted(errors, threshold)
        curve = np.r_[recall[:last], recall[last - 1]]
        at = np.r_[errors[:last], threshold]
        aucs.append(float(np.trapezoid(curve, at) / threshold))
    return aucs


def pair_row(
    method_name: str, pair: PosePair, features1, features2, norm: int, refine: dict | None = None
) -> dict:
    """One method's result on one pair: matches, inliers and the pose errors (inf: none).

    ``refine``: None, or keyword arguments of ``match_refinement.refine_matches`` ({} for its
    defaults): the matched points of image 2 are moved to the NCC peak of image 1's patches
    before the pose is estimated; the row then also holds ``moved`` (how many were) and
    ``refine_ms`` (the refinement's wall time for the pair, grey conversion included)."""
    matches = nearest_neighbours(features1.descriptors, features2.descriptors, norm, True)
    points1 = features1.keypoints[matches[:, 0]]
    points2 = features2.keypoints[matches[:, 1]]
    extra = {}
    if refine is not None:
        start = time.perf_counter()
        points2, moved = refine_matches(
            grey(pair.image1), grey(pair.image2), points1, points2, **refine
        )
        extra = {"moved": int(moved.sum()), "refine_ms": 1e3 * (time.perf_counter() - start)}
    estimate = estimate_pose(points1, points2, pair.K1, pair.K2)
    rotation = translation = math.inf
    inliers = 0
    if estimate is not None:
        rotation, translation = pose_errors(pair.R, pair.t, estimate[0], estimate[1])
        inliers = int(estimate[2].sum())
    return {
        "method": method_name,
        "pair": pair.name,
        "points": [len(features1.keypoints), len(features2.keypoints)],
        "matches": len(matches),
        "inliers": inliers,
        "rotation_error": rotation,
        "translation_error": translation,
        "error": max(rotation, translation),
        **extra,
    }


def evaluate_pose(pairs: Sequence[PosePair], methods: dict, progress=None) -> list[dict]:
    """Every method on every pair: rows of :func:`pair_row` plus ``ms`` (the two detections'
    mean wall time per image). The methods take turns pair by pair, so a drift in the machine's
    load reaches all of them alike. ``methods``: name -> an object with ``detect(image) ->
    Features`` and optionally ``norm`` (cv2.NORM_L2 when absent) and ``match_refinement``
    (:func:`pair_row`'s ``refine``; None when absent); ``progress`` wraps the pairs (e.g.
    tqdm)."""
    rows = []
    for pair in pairs if progress is None else progress(pairs):
        for name, method in methods.items():
            start = time.perf_counter()
            features1 = method.detect(pair.image1)
            features2 = method.detect(pair.image2)
            ms = (time.perf_counter() - start) * 500  # per image
            norm = getattr(method, "norm", cv2.NORM_L2)
            refine = getattr(method, "match_refinement", None)
            row = pair_row(name, pair, features1, features2, norm, refine)
            rows.append({**row, "ms": ms})
    return rows


def summarize(
    rows: list[dict], rounds: int = 2000, seed: int = 0, thresholds=THRESHOLDS
) -> dict[str, dict]:
    """Per method: ``auc`` {threshold: (AUC, (low, high))} with 95% percentile intervals of a
    bootstrap over the pairs (the same draws for every method: all met the same pairs), the
    median ``ms`` per image, mean ``inliers`` and ``matches``, the pair count, and for a method
    with refined matches the median ``refine_ms`` per pair."""
    by_method: dict[str, list[dict]] = {}
    for row in rows:
        by_method.setdefault(row["method"], []).append(row)
    count = len(next(iter(by_method.values())))
    draws = np.random.default_rng(seed).integers(0, count, size=(rounds, count))
    table = {}
    for name, found in by_method.items():
        errors = np.array([r["error"] for r in found])
        resampled = np.array([pose_auc(errors[d], thresholds) for d in draws])
        lows, highs = np.percentile(resampled, [2.5, 97.5], axis=0)
        table[name] = {
            "auc": {
                t: (auc, (float(lo), float(hi)))
                for t, auc, lo, hi in zip(
                    thresholds, pose_auc(errors, thresholds), lows, highs, strict=True
                )
            },
            "ms": statistics.median(r["ms"] for r in found),
            "inliers": statistics.fmean(r["inliers"] for r in found),
            "matches": statistics.fmean(r["matches"] for r in found),
            "pairs": len(found),
        }
        if any("refine_ms" in r for r in found):
            table[name]["refine_ms"] = statistics.median(r.get("refine_ms", 0.0) for r in found)
    return table


def auc_difference(
    rows: list[dict], first: str, second: str, rounds: int = 2000, seed: int = 0, threshold=10.0
) -> tuple[float, tuple[float, float]]:
    """AUC at ``threshold`` of method ``first`` minus ``second``'s, with the 95% interval of a
    paired bootstrap over the pairs (each draw resamples both methods' same pairs)."""
    errors = {}
    for name in (first, second):
        found = sorted((r["pair"], r["error"]) for r in rows if r["method"] == name)
        errors[name] = np.array([e for _, e in found])
    if len(errors[first]) != len(errors[second]) or not len(errors[first]):
        raise ValueError(f"{first!r} and {second!r} were not scored on the same pairs")
    draws = np.random.default_rng(seed).integers(
        0, len(errors[first]), (rounds, len(errors[first]))
    )
    gap = [
        pose_auc(errors[first][d], [threshold])[0] - pose_auc(errors[second][d], [threshold])[0]
        for d in draws
    ]
    low, high = np.percentile(gap, [2.5, 97.5])
    difference = pose_auc(errors[first], [threshold])[0] - pose_auc(errors[second], [threshold])[0]
    return difference, (float(low), float(high))


def format_table(table: dict[str, dict]) -> str:
    """A Markdown table of :func:`summarize`'s: AUC with its 95% interval per threshold."""
    thresholds = list(next(iter(table.values()))["auc"])
    header = "| method | " + " | ".join(f"AUC@{t:g}" for t in thresholds)
    lines = [header + " | ms/image | inliers |", "|---" * (len(thresholds) + 3) + "|"]
    for name, row in table.items():
        cells = [f"{a:.3f} ({lo:.3f}-{hi:.3f})" for a, (lo, hi) in row["auc"].values()]
        lines.append(
            f"| {name} | " + " | ".join(cells) + f" | {row['ms']:.0f} | {row['inliers']:.0f} |"
        )
    return "\n".join(lines)
