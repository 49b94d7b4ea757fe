"""Matching across any in-plane rotation with upright weights.

The upright weights match well up to ~10-20 degrees of in-plane rotation and fail beyond; the
rotation-invariant weights (``Detector.pretrained("rotation")``) match at any angle, but far
less distinctively. Together they do better than either: the rotation-invariant network (the
*guide*) estimates how far image 2 is turned from image 1, image 2 is turned back by that angle,
and the upright network matches the pair (experiments/notes/choices.md, "--any-rotation": on rotated
viewpoint pairs MS 0.246 -> 0.517 and HA@3 0.31 -> 0.800, 0.530 and 0.850 with today's refined
points, and with ``upsample=2`` an MS above ORB's, AKAZE's, BRISK's and SIFT's at every angle,
at the cost of two guide detections and one detection on a larger canvas). Where the guide
cannot read the angle (repetitive patterns, little texture) the upright network searches for it
(:func:`search_turn`). For the moderate turns of hand-held photos, which the upright network's own
matches still read, :func:`turn_back_pair` needs no guide (``usp-jax match``'s default).

Angles are degrees, positive = counter-clockwise on screen (``cv2.getRotationMatrix2D``'s
sense); :func:`in_plane_rotation` reads the opposite, clockwise, sense from a homography, so
turning image 2 by ``in_plane_rotation(H)`` undoes H's rotation.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.core.model import CELL
from usp_jax.inference.detector import Detector
from usp_jax.inference.features import Features
from usp_jax.inference.matching import Matching, match_and_estimate
from usp_jax.inference.pyramid import candidates

#: Within this many degrees of a quarter turn (0, 90, 180 or -90) image 2 is turned by the quarter
#: turn alone: the upright weights hold up to there, and a quarter turn moves every pixel whole
#: (no resampling, no larger canvas); 0 detects image 2 as it is.
UPRIGHT_BELOW = 10.0
#: Turned-back points closer than this (px) to image 2's edges are dropped: on the canvas the
#: photo's edges meet its mirror image, whose seam is no real structure.
EDGE_MARGIN = 4.0
#: Points of each image the guide matches to estimate the turn (the evaluation's top-k).
GUIDE_POINTS = 300
#: Fewer RANSAC inliers than this leave the guide's angle in doubt: 4 points fit a homography,
#: and a handful more agree by chance on hard pairs (wrong angles came with 6-7 inliers on the
#: held-out rotated pairs; right ones with a median of 48).
GUIDE_MIN_INLIERS = 10
#: Degrees between the turns an unsure guide's pair is searched at with the upright weights:
#: every angle then lies within 15 degrees of one of them, inside the range they match over.
SEARCH_STEP = 30.0


def in_plane_rotation(homography: np.ndarray, shape: tuple[int, int]) -> float:
    """In-plane rotation in degrees of a [3, 3] homography at the centre of an image of ``shape``
    (H, W): the angle of the similarity closest to H's Jacobian there (its rotation part,
    ``atan2(J10 - J01, J00 + J11)``), positive = clockwise on screen (x right, y down)."""
    height, width = shape
    centre = np.array([(width - 1) / 2, (height - 1) / 2, 1.0])
    projected = homography @ centre
    # d(p / w) / dx = (H[:2, :2] w - p H[2, :2]) / w**2 for the homogeneous image p = H @ (x, y, 1).
    jacobian = (
        homography[:2, :2] * projected[2] - np.outer(projected[:2], homography[2, :2])
    ) / projected[2] ** 2
    return math.degrees(
        math.atan2(jacobian[1, 0] - jacobian[0, 1], jacobian[0, 0] + jacobian[1, 1])
    )


def _quarter_turns(angle: float) -> int | None:
    """``angle`` (degrees) in quarter turns when it is a whole number of them, else None."""
    quarters = round(angle / 90)
    return quarters if angle == 90 * quarters else None


def turn(image: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """``image`` [H, W(, 3)] turned by ``angle`` degrees about its centre, and the float64 [2, 3]
    affine taking the image's pixels (x, y) to the turned copy's. A quarter turn (a multiple of 90
    degrees) is exact: every pixel moves whole into an image of the same size (H and W swapped for
    an odd one). Any other angle turns onto a square canvas that holds all of the image (side: the
    diagonal, rounded up to whole cells); the rest of the canvas mirrors the image across its
    edges (``cv2.BORDER_REFLECT_101``). Black corners would put an artificial high-contrast edge
    along the photo's border that the network fires on and that bleeds into the descriptors of
    points near it: on the rotated held-out pairs mirroring lifted MS by 0.022 and HA@1 by 0.069
    (experiments/notes/choices.md, "--any-rotation")."""
    height, width = image.shape[:2]
    quarters = _quarter_turns(angle)
    if quarters is None:
        out_width = out_height = CELL * math.ceil(math.hypot(height, width) / CELL)
    else:
        out_width, out_height = (height, width) if quarters % 2 else (width, height)
    affine = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), angle, 1.0)
    affine[:, 2] += ((out_width - width) / 2, (out_height - height) / 2)
    if quarters is not None:
        # cos(90 degrees) is 6e-17 in floating point; the exact affine has whole entries.
        return np.ascontiguousarray(np.rot90(image, quarters % 4)), np.round(affine)
    canvas = cv2.warpAffine(
        image,
        affine,
        (out_width, out_height),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT_101,
    )
    return canvas, affine


def detectable_turn(angle: float) -> float:
    """The angle to turn image 2 back by for an estimated turn of ``angle`` degrees: the nearest
    quarter turn when it is within ``UPRIGHT_BELOW`` degrees, else ``angle`` itself."""
    quarter = 90.0 * round(angle / 90)
    return quarter if abs(angle - quarter) < UPRIGHT_BELOW else angle


def detect_turned(
    detector: Detector, image: np.ndarray, angle: float, top_n: int | None = None
) -> Features:
    """``detector``'s features of ``image`` turned by ``angle`` degrees, keypoints in ``image``'s
    own pixels, points within ``EDGE_MARGIN`` px of its edges dropped, at most ``top_n`` (by
    score; None: the detector's ``top_n``). Photos longer than the detector's ``max_side`` are shrunk before turning, as
    :meth:`Detector.detect` would shrink them, so both images of a pair meet the network at one
    scale."""
    height, width = image.shape[:2]
    small, factors = detector.shrink(image)
    canvas, affine = turn(small, angle)
    # Every point of the canvas (one per cell of the padded, enlarged canvas at most), so that the
    # cut below counts only points of the image itself (about half of a turned canvas is mirror).
    every_point = candidates(*canvas.shape[:2], detector.upsample, detector.any_scale)
    features = detector.detect_as_is(canvas, every_point)
    back = cv2.transform(
        np.asarray(features.keypoints, np.float64).reshape(-1, 1, 2),
        cv2.invertAffineTransform(affine),
    ).reshape(-1, 2)
    back = (back + 0.5) * factors - 0.5
    if _quarter_turns(angle) is not None:
        # The turned copy is the image itself: every point is the image's, as detect() finds it
        # (its last pixels' points lie up to half a pixel beyond W - 1 and H - 1).
        inside = np.ones(len(back), bool)
    else:
        inside = (
            (back[:, 0] >= EDGE_MARGIN)
            & (back[:, 0] <= width - 1 - EDGE_MARGIN)
            & (back[:, 1] >= EDGE_MARGIN)
            & (back[:, 1] <= height - 1 - EDGE_MARGIN)
        )
    top_n = detector.top_n if top_n is None else top_n
    keep = np.flatnonzero(inside)[:top_n]  # Scores come sorted, best first.
    scales = None if features.scales is None else features.scales[keep] * np.mean(factors)
    return Features(
        back[keep].astype(np.float32), features.scores[keep], features.descriptors[keep], scales
    )


class Turn(NamedTuple):
    """The guide's estimate: ``angle`` in degrees (:func:`in_plane_rotation` of its homography, 0
    without one) and the RANSAC ``inliers`` behind it."""

    angle: float
    inliers: int


def _matched(features1: Features, features2: Features) -> Matching:
    """:func:`match_and_estimate` on the ``GUIDE_POINTS`` best points of each (scores sorted)."""
    return match_and_estimate(
        *(
            Features(*(None if array is None else array[:GUIDE_POINTS] for array in f))
            for f in (features1, features2)
        )
    )


def estimate_turn(guide: Detector, image1: np.ndarray, image2: np.ndarray) -> Turn:
    """How far ``image2`` is turned from ``image1``, by the homography ``guide`` estimates between
    them from ``GUIDE_POINTS`` points each. ``guide`` should be rotation-invariant (the
    ``rotation`` weights)."""
    matching = _matched(*guide.detect_batch([image1, image2], top_n=GUIDE_POINTS))
    if matching.homography is None:
        return Turn(0.0, 0)
    return Turn(
        in_plane_rotation(matching.homography, image1.shape[:2]), int(matching.inliers.sum())
    )


def _detect_at(detector: Detector, image: np.ndarray, angle: float, top_n: int | None) -> Features:
    """``image``'s features turned by ``angle`` (0: as it is), in its own pixels."""
    return (
        detector.detect(image, top_n)
        if angle == 0
        else detect_turned(detector, image, angle, top_n)
    )


def search_turn(
    detector: Detector,
    features1: Features,
    shape1: tuple[int, int],
    image2: np.ndarray,
    guess: float = 0.0,
    top_n: int | None = None,
) -> tuple[Features, float]:
    """``image2``'s features turned back by the angle at which ``detector`` (upright weights)
    matches it best to ``features1`` (image 1's, of size ``shape1`` (H, W)), and that angle: for a
    pair the guide cannot read. Image 2 is detected at ``guess`` and every ``SEARCH_STEP``
    degrees; the turn with the most RANSAC inliers is within the upright weights' range of the
    truth, and the homography it finds reads the angle precisely (:func:`in_plane_rotation`), so
    image 2 is detected once more at that angle and the better of the two (by inliers) is kept.
    Costs up to ``360 / SEARCH_STEP + 2`` detections of image 2."""
    turns = [guess] + list(np.arange(-180.0 + SEARCH_STEP, 180.0 + SEARCH_STEP / 2, SEARCH_STEP))
    tried: dict[float, tuple[Features, Matching]] = {}

    def attempt(angle: float) -> float:
        angle = detectable_turn(float(angle))
        angle = angle + 360.0 if angle <= -180.0 else angle  # -180 and 180 are one turn
        if angle not in tried:
            features = _detect_at(detector, image2, angle, top_n)
            tried[angle] = features, _matched(features1, features)
        return angle

    for angle in turns:
        attempt(angle)
    best = max(tried, key=lambda angle: tried[angle][1].inliers.sum())
    homography = tried[best][1].homography
    if homography is not None:
        # The homography maps image 1 to image 2 in image 2's own pixels (the points were mapped
        # back), so it holds the whole turn, not only what is left after turning by ``best``.
        refined = attempt(in_plane_rotation(homography, shape1))
        if tried[refined][1].inliers.sum() >= tried[best][1].inliers.sum():
            best = refined
    return tried[best][0], best


def detect_pair(
    detector: Detector,
    guide: Detector,
    image1: np.ndarray,
    image2: np.ndarray,
    top_n: int | None = None,
) -> tuple[Features, Features, float]:
    """Features of both images for matching across any rotation: ``image1`` as it is, ``image2``
    turned back by :func:`estimate_turn`'s angle, both in their own pixels. Returns (features1,
    features2, the angle image 2 was turned back by).

    Within ``UPRIGHT_BELOW`` degrees of a quarter turn image 2 is turned by the quarter turn
    alone (:func:`detectable_turn`), so below it image 2 is detected as it is. When the guide's
    homography rests on fewer than ``GUIDE_MIN_INLIERS`` inliers (a hard pair, where its angle can
    be far off: repetitive patterns such as chessboards and printed grids, or little texture),
    the angle is searched for with ``detector`` itself (:func:`search_turn`), so an unsure guide
    costs more detections, not the pair."""
    turn = estimate_turn(guide, image1, image2)
    features1 = detector.detect(image1, top_n)
    if turn.inliers < GUIDE_MIN_INLIERS:
        return (
            features1,
            *search_turn(detector, features1, image1.shape[:2], image2, turn.angle, top_n),
        )
    angle = detectable_turn(turn.angle)
    return features1, _detect_at(detector, image2, angle, top_n), angle


def turn_back_pair(
    detector: Detector, image1: np.ndarray, image2: np.ndarray, top_n: int | None = None
) -> tuple[Features, Features, float]:
    """Features of both images with image 2 turned back by the turn the upright network's own
    matches read, no guide network: both images are detected as they are, and when the
    homography of their ``GUIDE_POINTS`` best points rests on at least ``GUIDE_MIN_INLIERS``
    inliers and turns by ``UPRIGHT_BELOW`` degrees or more (:func:`detectable_turn`), image 2 is
    detected once more turned back by that angle and kept so when that matches with as many
    inliers or more. Returns (features1, features2, the angle image 2 was turned back by; 0:
    upright).

    For the moderate turns two hand-held photos make, which the upright matches still read:
    on warped held-out pairs turned by 20-35 degrees the upright descriptor finds the partner of
    0.20 of the repeatable points, 0.54 with image 2 turned back by the true turn
    (experiments/RESULTS.md, "Turning image 2 back"). One more detection of image 2, on a larger
    canvas, when it turns; none otherwise."""
    features1 = detector.detect(image1, top_n)
    features2 = detector.detect(image2, top_n)
    upright = _matched(features1, features2)
    if upright.homography is None or upright.inliers.sum() < GUIDE_MIN_INLIERS:
        return features1, features2, 0.0
    angle = detectable_turn(in_plane_rotation(upright.homography, image1.shape[:2]))
    if angle == 0:
        return features1, features2, 0.0
    turned = _detect_at(detector, image2, angle, top_n)
    if _matched(features1, turned).inliers.sum() < upright.inliers.sum():
        return features1, features2, 0.0
    return features1, turned, angle


class TurnedMatching(NamedTuple):
    """:func:`match_any_rotation`'s result: the ``matching`` (indices into ``features1`` and
    ``features2``, homography from image 1 to image 2 in their own pixels), the ``angle`` in
    degrees image 2 was turned back by before detection (0: detected upright) and the features."""

    matching: Matching
    angle: float
    features1: Features
    features2: Features


def match_any_rotation(
    detector: Detector,
    image1: np.ndarray,
    image2: np.ndarray,
    guide: Detector | None = None,
    top_n: int | None = None,
) -> TurnedMatching:
    """Mutual nearest neighbours and the RANSAC homography (:func:`match_and_estimate`) of two
    images turned by any in-plane angle, with upright weights in ``detector``: :func:`detect_pair`
    with ``guide`` (default: the shipped ``rotation`` weights at ``detector``'s ``max_side``)."""
    if guide is None:
        guide = Detector.pretrained("rotation", max_side=detector.max_side)
    features1, features2, angle = detect_pair(detector, guide, image1, image2, top_n)
    return TurnedMatching(match_and_estimate(features1, features2), angle, features1, features2)
