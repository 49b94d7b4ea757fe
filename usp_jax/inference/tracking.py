"""Keypoint tracking through a video, the front end of a VSLAM or AR system (the paper's future
work): each frame's features are matched to the previous frame and to the last keyframe, the
matches are checked against the scene's geometry, and the surviving points carry track ids from
frame to frame.

The keyframe rule: the first frame is a keyframe. Every later frame is matched to the previous
frame and, when that is not the keyframe, to the keyframe as well. A frame becomes the new
keyframe when its inliers to the keyframe fall below ``keyframe_ratio`` (default one half) of
its inliers to the previous frame: the view has moved far enough from the keyframe that half of
what a short step still matches no longer matches across the long one (or the shot was cut).
Matching to the keyframe bridges a point over frames where its detection or match was missed:
a point with no verified match in the previous frame takes the track id of its verified match
in the keyframe, unless another point of the frame already carries that id.

Any detector fits: a ``Detector`` or any object with ``detect(uint8 [H, W, 3] RGB) -> Features``
and, for binary descriptors, ``norm = cv2.NORM_HAMMING`` (``usp_jax.evaluation``'s methods).
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import Any, NamedTuple

import cv2
import numpy as np

from usp_jax.inference.detector import Detector
from usp_jax.inference.features import Features
from usp_jax.inference.images import grey
from usp_jax.inference.match_refinement import refine_matches
from usp_jax.inference.matching import (
    RANSAC_MAX_ITERS,
    RANSAC_THRESHOLD,
    estimate_homography,
    matched_points,
    nearest_neighbours,
)
from usp_jax.inference.threads import THREADS, threaded

#: Points per frame and NMS radius of the default detector: the protocol's count above 240x320,
#: and the radius that spreads points for a better-conditioned estimate (RESULTS.md).
TOP_N = 1000
NMS_RADIUS = 4.0
#: The video default: the distilled fast network on a copy of each frame at most 480 px long
#: (points in the frame's pixels), its matches to the previous frame refined
#: (``match_refinement.refine_matches``: NCC peak, then ``AFFINE_STEPS`` affine Lucas-Kanade
#: steps), chosen by relative pose accuracy at SIFT's time budget (benchmarks/bench_pose.py,
#: RESULTS.md "Pose"). On 48 design pairs of rendered rooms 480 px with 2 steps (AUC@10 0.594)
#: is as accurate as the best candidate within SIFT's time there (560 px, 5 steps: 0.612, at
#: 0.99x SIFT's time) at 0.68x; on real footage (box.mp4, ~900 matches per frame, where the
#: refinement costs more) it is the one of the two within SIFT's time (0.83-0.85x since the
#: refinement runs a thread per core; 560 px with 5 steps 1.15-1.20x).
#: The old default, 640 px unrefined: 0.435. ``paper`` at full size takes ~6x SIFT's time, too
#: slow for a live camera. The network's own sub-pixel refinement stays off: on video it adds
#: time and no inliers.
VIDEO_WEIGHTS = "distilled"
VIDEO_SIDE = 480
#: Gauss-Newton steps of the affine polish after the NCC peak in the default match refinement.
AFFINE_STEPS = 2
#: RANSAC confidence of the fundamental matrix (OpenCV's default, 0.99, stops too early for
#: hundreds of matches with many outliers).
CONFIDENCE = 0.999
#: Median motion (px per tracked frame) of the inliers under which the camera counts as still:
#: a detector's points jitter by a few tenths of a pixel on a static view, and a hand-held
#: camera moves by pixels. On a static view every point fits a fundamental matrix.
STATIC_MOTION = 0.5


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """``planar``: verify matches with a homography (a planar scene or a turning camera) instead
    of the fundamental matrix; either way RANSAC's inlier distance is the protocol's 3 px (to
    the epipolar line, or of the homography's reprojection). ``keyframe_ratio``: the keyframe
    rule's fraction (module docstring). ``every``: track every N-th input frame.
    ``refine_matches``: before verification, move each match's point in the later frame to the
    sub-pixel NCC peak of a grey patch around its point in the earlier one, polished by
    ``affine_steps`` affine Lucas-Kanade steps (``match_refinement.refine_matches``, its
    other defaults); the verified geometry uses the moved points, the frames' points stay as
    detected. Only the matches to the previous frame are refined: those to the keyframe are
    verified as matched (refining them too cost a second refinement per frame and changed
    nothing measurable on box.mp4, RESULTS.md "Video"). On by default."""

    planar: bool = False
    keyframe_ratio: float = 0.5
    every: int = 1
    refine_matches: bool = True
    affine_steps: int = AFFINE_STEPS

    def __post_init__(self):
        if not 0 <= self.keyframe_ratio <= 1:
            raise ValueError(f"keyframe_ratio must be in [0, 1], got {self.keyframe_ratio}")
        if not isinstance(self.every, int) or self.every < 1:
            raise ValueError(f"every must be a positive integer, got {self.every!r}")
        if not isinstance(self.affine_steps, int) or self.affine_steps < 0:
            raise ValueError(f"affine_steps must be a whole number >= 0, got {self.affine_steps!r}")


class TrackedFrame(NamedTuple):
    """One frame's result.

    index: the frame's position in the input (0-based, counting frames skipped by ``every``).
    points: float32 ``[N, 2]`` (x, y) keypoints. track_ids: int64 ``[N]``, a point's track; a
    new id is a point seen for the first time. matches: int64 ``[K, 2]`` mutual nearest
    neighbours (index into the previous tracked frame's points, index into ``points``);
    inliers: bool ``[K]``, those consistent with the geometry. keyframe: the index of the
    keyframe this frame was matched to; keyframe_inliers: its verified matches to it (equal to
    the inliers' count when the keyframe is the previous frame). is_keyframe: this frame is the
    keyframe of the frames after it. ms: milliseconds spent on the frame (detection, matching,
    verification, track ids). scores: float32 ``[N]`` and descriptors ``[N, D]`` of the points,
    as the detector returned them (float32, or uint8 packed bits for binary descriptors).
    """

    index: int
    points: np.ndarray
    track_ids: np.ndarray
    matches: np.ndarray
    inliers: np.ndarray
    keyframe: int
    keyframe_inliers: int
    is_keyframe: bool
    ms: float
    scores: np.ndarray | None = None
    descriptors: np.ndarray | None = None


def verify(points1: np.ndarray, points2: np.ndarray, config: TrackingConfig) -> np.ndarray:
    """bool ``[K]``: which matched points ``[K, 2]`` (frame 1, frame 2) fit one RANSAC
    fundamental matrix (``cv2.findFundamentalMat``, ``FM_RANSAC``; the 8-point minimum), or one
    homography with ``config.planar`` (``matching.estimate_homography``). All False when there
    are too few points or no estimate."""
    if config.planar:
        return estimate_homography(points1, points2)[1]
    none = np.zeros(len(points1), dtype=bool)
    if len(points1) < 8:
        return none
    estimate, mask = cv2.findFundamentalMat(
        np.asarray(points1, np.float64),
        np.asarray(points2, np.float64),
        cv2.FM_RANSAC,
        RANSAC_THRESHOLD,
        CONFIDENCE,
        RANSAC_MAX_ITERS,
    )
    if estimate is None or mask is None:
        return none
    return mask.ravel().astype(bool)


def match_frames(
    features1: Features,
    features2: Features,
    norm: int,
    config: TrackingConfig,
    greys: tuple[np.ndarray, np.ndarray] | None = None,
    pool: Executor | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of two frames' descriptors (``matching.nearest_neighbours``)
    and :func:`verify`: (int64 ``[K, 2]`` matches, bool ``[K]`` inliers). With
    ``config.refine_matches`` and the frames' grey images ``greys`` (float32 ``[H, W]`` each),
    the matched points of frame 2 are refined (``match_refinement``, ``config.affine_steps``)
    before verification, a share of them per thread (``inference.threads``; ``pool``: the
    executor to run them on, None: one for this call)."""
    matches = nearest_neighbours(features1.descriptors, features2.descriptors, norm, True)
    points1, points2 = matched_points(features1, features2, matches)
    if config.refine_matches and greys is not None:
        steps = config.affine_steps

        def refined(share: np.ndarray) -> np.ndarray:
            return refine_matches(*greys, points1[share], points2[share], affine_steps=steps)[0]

        shares = np.array_split(np.arange(len(matches)), THREADS)
        points2 = np.concatenate(threaded(refined, shares, pool=pool))
    return matches, verify(points1, points2, config)


def assign_track_ids(
    count: int,
    previous_ids: np.ndarray,
    previous: tuple[np.ndarray, np.ndarray],
    keyframe_ids: np.ndarray,
    keyframe: tuple[np.ndarray, np.ndarray],
    next_id: int,
) -> tuple[np.ndarray, int]:
    """Track ids of a frame's ``count`` points and the next unused id.

    ``previous`` and ``keyframe`` are (matches ``[K, 2]``, inliers ``[K]``) to the previous frame
    and to the keyframe, whose points carry ``previous_ids`` and ``keyframe_ids``. A point
    verified against the previous frame continues its track; otherwise one verified against the
    keyframe continues the keyframe point's track when no other point carries it yet; every
    other point starts a new track. Mutual nearest neighbours are one-to-one, so no id repeats.
    """
    ids = np.full(count, -1, np.int64)
    matches, inliers = previous
    ids[matches[inliers, 1]] = previous_ids[matches[inliers, 0]]
    matches, inliers = keyframe
    mine, theirs = matches[inliers, 1], keyframe_ids[matches[inliers, 0]]
    bridge = (ids[mine] < 0) & ~np.isin(theirs, ids)
    ids[mine[bridge]] = theirs[bridge]
    new = ids < 0
    ids[new] = np.arange(next_id, next_id + int(new.sum()))
    return ids, next_id + int(new.sum())


def default_detector() -> Detector:
    """The video default: the ``VIDEO_WEIGHTS`` on copies at most ``VIDEO_SIDE`` px long,
    ``TOP_N`` points, NMS radius ``NMS_RADIUS``."""
    return Detector.pretrained(
        VIDEO_WEIGHTS, top_n=TOP_N, nms_radius=NMS_RADIUS, max_side=VIDEO_SIDE, refine=False
    )


def track(
    frames: Iterable[np.ndarray],
    detector: Any = None,
    config: TrackingConfig = TrackingConfig(),
) -> Iterator[TrackedFrame]:
    """Tracks keypoints through ``frames`` (uint8 ``[H, W, 3]`` RGB, all one size), yielding one
    :class:`TrackedFrame` per tracked frame as it is done (module docstring: the keyframe rule).

    ``detector``: a ``Detector`` (compiled once, for the frames' size), any object with
    ``detect`` and ``norm`` (module docstring), or None for :func:`default_detector`. Raises
    ValueError naming the frame when a frame's size differs from the first's.
    """
    detector = default_detector() if detector is None else detector
    # One pool for the run: the match refinement's threads (match_frames).
    with ThreadPoolExecutor(THREADS) as pool:
        yield from _tracked(frames, detector, config, pool)


def _tracked(
    frames: Iterable[np.ndarray], detector: Any, config: TrackingConfig, pool: Executor
) -> Iterator[TrackedFrame]:
    """:func:`track`'s loop, the refinement's threads on ``pool``."""
    norm = getattr(detector, "norm", cv2.NORM_L2)
    no_matches = (np.zeros((0, 2), np.int64), np.zeros(0, bool))
    previous = keyframe = None  # (index, features, track ids, grey frame or None)
    next_id, shape = 0, None
    for index, frame in itertools.islice(enumerate(frames), 0, None, config.every):
        frame = np.asarray(frame)
        if shape is None:
            shape = frame.shape
        elif frame.shape != shape:
            raise ValueError(
                f"frame {index} has shape {frame.shape}, the first frame {shape}: every frame must"
                " be one size"
            )
        start = time.perf_counter()
        features = detector.detect(frame)
        # float32 once: the frame is refined against as image 2, then as image 1 of the next.
        image = grey(frame).astype(np.float32) if config.refine_matches else None
        count = len(features.keypoints)
        to_previous = to_keyframe = no_matches
        separate = previous is not None and keyframe[0] != previous[0]
        if previous is not None:
            to_previous = match_frames(
                previous[1], features, norm, config, (previous[3], image), pool
            )
            # Unrefined (TrackingConfig): one refinement per frame.
            to_keyframe = (
                match_frames(keyframe[1], features, norm, config) if separate else to_previous
            )
        ids, next_id = assign_track_ids(
            count,
            previous[2] if previous else np.zeros(0, np.int64),
            to_previous,
            keyframe[2] if separate else np.zeros(0, np.int64),
            to_keyframe if separate else no_matches,
            next_id,
        )
        inliers, keyframe_inliers = int(to_previous[1].sum()), int(to_keyframe[1].sum())
        is_keyframe = keyframe is None or keyframe_inliers < config.keyframe_ratio * inliers
        matched_to = index if keyframe is None else keyframe[0]
        previous = (index, features, ids, image)
        if is_keyframe:
            keyframe = previous
        yield TrackedFrame(
            index,
            np.asarray(features.keypoints, np.float32).reshape(-1, 2),
            ids,
            *to_previous,
            matched_to,
            keyframe_inliers,
            is_keyframe,
            1e3 * (time.perf_counter() - start),
            np.asarray(features.scores, np.float32).reshape(-1),
            np.asarray(features.descriptors),
        )


def track_lengths(results: Iterable[TrackedFrame]) -> np.ndarray:
    """int64 ``[T]``: in how many frames each track id appears, over every track (a point never
    matched is a track of length 1)."""
    ids = [result.track_ids for result in results]
    if not ids:
        return np.zeros(0, np.int64)
    return np.unique(np.concatenate(ids), return_counts=True)[1].astype(np.int64)


def camera_motion(results: list[TrackedFrame]) -> float | None:
    """The median over consecutive tracked frames of the median distance (px) its inliers moved
    from the previous frame; None with fewer than two frames or no inliers. Under
    ``STATIC_MOTION`` the camera does not move, and a fundamental matrix means nothing."""
    steps = []
    for before, after in zip(results[:-1], results[1:]):
        kept = after.matches[after.inliers]
        if len(kept):
            moved = after.points[kept[:, 1]] - before.points[kept[:, 0]]
            steps.append(float(np.median(np.linalg.norm(moved, axis=1))))
    return float(np.median(steps)) if steps else None


def save_features(file, results: list[TrackedFrame]) -> None:
    """Every frame's points, scores, descriptors and track ids in one compressed ``.npz``
    (``file``: a path or a binary file): ``index`` [F], ``offsets`` [F + 1] (frame f's rows are
    ``offsets[f]:offsets[f + 1]``), ``points`` float32 [P, 2], ``scores`` float32 [P],
    ``track_ids`` int64 [P], and ``descriptors`` [P, D]: float descriptors as float16 (half the
    size; unit-length entries keep 3 significant digits), binary ones as their uint8 bytes."""
    counts = [len(r.points) for r in results]
    descriptors = np.concatenate([np.asarray(r.descriptors) for r in results])
    if descriptors.dtype != np.uint8:
        descriptors = descriptors.astype(np.float16)
    np.savez_compressed(
        file,
        index=np.array([r.index for r in results], np.int64),
        offsets=np.r_[0, np.cumsum(counts)].astype(np.int64),
        points=np.concatenate([r.points for r in results]).astype(np.float32),
        scores=np.concatenate([r.scores for r in results]).astype(np.float32),
        track_ids=np.concatenate([r.track_ids for r in results]).astype(np.int64),
        descriptors=descriptors,
    )


def load_features(file) -> list[dict[str, np.ndarray]]:
    """:func:`save_features`' frames: one dict per frame with ``index`` and its ``points``,
    ``scores``, ``track_ids`` and ``descriptors`` (float16 or uint8, as saved)."""
    with np.load(file) as data:
        offsets = data["offsets"]
        arrays = {k: data[k] for k in ("points", "scores", "track_ids", "descriptors")}
        return [
            {"index": int(i), **{k: v[start:stop] for k, v in arrays.items()}}
            for i, start, stop in zip(data["index"], offsets[:-1], offsets[1:], strict=True)
        ]
