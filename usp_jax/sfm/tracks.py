"""What COLMAP gets from the network: image pairs, mutual-nearest-neighbour matches, the
matches a fundamental matrix keeps (:func:`fundamental_inliers`), and the keypoints of each match
track moved onto one anchor observation's patch (:func:`refine_keypoints`), the simple form of
pixel-perfect SfM's featuremetric keypoint adjustment: COLMAP keeps one position per keypoint,
shared by all its matches, so matches cannot be refined one by one."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

import numpy as np

from usp_jax.inference.features import Features
from usp_jax.inference.match_refinement import cut_templates, match_templates
from usp_jax.inference.matching import mutual_nearest_neighbours
from usp_jax.inference.threads import one_blas_thread, threaded

#: Lowe's ratio test on the mutual nearest neighbours (1: none).
RATIO = 1.0
#: ``--window`` default: a video frame is matched to this many frames after it (COLMAP's own
#: sequential matcher overlaps 10 too).
WINDOW = 10
#: :func:`refine_keypoints`' affine Lucas-Kanade steps after each NCC peak: the translation-only
#: peak is biased by the view change (about 0.3 px on rendered rooms), the affine fit removes it.
AFFINE_STEPS = 5
#: :func:`fundamental_inliers`' epipolar distance, px (``reconstruct --epipolar``): the matches
#: COLMAP gets and the tracks are built of. On a rendered 12-frame path (seed 1, ``distilled``)
#: it took COLMAP's verification from 12-20 s to 0.5 s, and the keypoint refinement's usable
#: tracks from a third of the matched keypoints to all (experiments/results/sfm/README.md).
EPIPOLAR_THRESHOLD = 1.0
#: :func:`refine_keypoints` keeps only settled matches, except in an image where fewer than this
#: share of its matches settled: there it keeps them all, as the refinement could not check it.
MIN_SETTLED_SHARE = 1 / 3


def image_pairs(count: int, window: int | None = None) -> np.ndarray:
    """Pairs to match, int ``[P, 2]`` (i < j): every pair (``window`` None: photos), or each
    image with the ``window`` images after it (a video's frames)."""
    i, j = np.triu_indices(count, k=1)
    keep = slice(None) if window is None else (j - i) <= window
    return np.stack([i[keep], j[keep]], axis=1).astype(np.int64).reshape(-1, 2)


def check_sizes(names: Sequence[str], sizes: Sequence[tuple[int, int]]) -> tuple[int, int]:
    """The one (height, width) of all images; ValueError when there are fewer than two, or when
    sizes differ: all images share one COLMAP camera (one size, one focal length)."""
    if len(names) < 2:
        raise ValueError(f"structure from motion needs two images or more, got {len(names)}")
    first = tuple(sizes[0])
    for name, size in zip(names, sizes):
        if tuple(size) != first:
            raise ValueError(
                f"mixed image sizes: {names[0]} is {first[1]}x{first[0]} but {name} is"
                f" {size[1]}x{size[0]}; the images share one COLMAP camera (one size and focal"
                " length, COLMAP's SINGLE camera mode): resize them alike or reconstruct each"
                " size apart"
            )
    return first


def detect_images(
    detector, images: Iterable[np.ndarray], progress: Callable = iter
) -> list[Features]:
    """The detector's features of each uint8 ``[H, W, 3]`` RGB image, in order (``progress``
    wraps the iteration, e.g. a tqdm bar)."""
    return [detector.detect(image) for image in progress(images)]


def match_pairs(
    features: Sequence[Features], pairs: np.ndarray, progress: Callable = iter, ratio: float = RATIO
) -> list[np.ndarray]:
    """Mutual nearest neighbours in descriptor space (``inference.matching``, L2: what ``match``
    pairs) of each pair: int ``[K, 2]`` (index into image i's keypoints, into image j's) per row
    of ``pairs``. A pair per thread (``inference.threads``), each product on one BLAS thread:
    66 pairs of 12 frames, 0.97 -> 0.74 s (median of 63 runs)."""

    def matched(pair) -> np.ndarray:
        i, j = pair
        return mutual_nearest_neighbours(features[i].descriptors, features[j].descriptors, ratio)

    with one_blas_thread:  # for the whole stage, not per pair
        return threaded(matched, pairs, progress)


def _match_edges(counts: Sequence[int], pairs: np.ndarray, matches: Sequence[np.ndarray]):
    """(offsets int ``[I + 1]``, edges int ``[E, 2]``): node ``offsets[i] + k`` is keypoint k of
    image i (``counts`` ``[I]`` keypoints per image); each match of ``pairs`` ``[P, 2]`` joins
    two nodes."""
    offsets = np.concatenate([[0], np.cumsum(np.asarray(counts, np.int64))])
    edges = [
        np.stack([offsets[i] + m[:, 0], offsets[j] + m[:, 1]], axis=1)
        for (i, j), m in zip(pairs, (np.asarray(m, np.int64).reshape(-1, 2) for m in matches))
    ]
    return offsets, np.concatenate([np.zeros((0, 2), np.int64), *edges]).astype(np.int64)


def fundamental_inliers(
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    threshold: float | None = EPIPOLAR_THRESHOLD,
) -> list[np.ndarray]:
    """Each pair's matches (int ``[K, 2]``, per row of ``pairs`` ``[P, 2]``) that a RANSAC
    fundamental matrix (OpenCV's MAGSAC++) keeps within ``threshold`` px, int ``[K', 2]``; none
    for a pair of under 8 matches or without a model; all when ``threshold`` is None.

    Mutual nearest neighbours are a quarter right on rendered rooms: COLMAP's own RANSAC then
    runs to its trial cap on every pair, and its 4 px verification lets wrong matches near their
    epipolar line into the tracks. This leaves COLMAP few wrong matches to weed out. A pair per
    thread (OpenCV's RANSAC releases the GIL): 66 pairs, 0.96 -> 0.47 s on 2 cores."""
    matches = [np.asarray(m, np.int64).reshape(-1, 2) for m in matches]
    if threshold is None:
        return matches

    def kept(job) -> np.ndarray:
        (i, j), pair_matches = job
        return pair_matches[_epipolar_inliers(features[i], features[j], pair_matches, threshold)]

    return threaded(kept, list(zip(pairs, matches)))


def _epipolar_inliers(
    features1: Features, features2: Features, matches: np.ndarray, threshold: float
) -> np.ndarray:
    """bool ``[K]``: which of one pair's matches ``[K, 2]`` :func:`fundamental_inliers` keeps."""
    import cv2

    inliers = None
    if len(matches) >= 8:
        try:
            _, inliers = cv2.findFundamentalMat(
                features1.keypoints[matches[:, 0]].astype(np.float64),
                features2.keypoints[matches[:, 1]].astype(np.float64),
                cv2.USAC_MAGSAC,
                threshold,
                0.999,
                10000,
            )
        except cv2.error:  # USAC asserts on some degenerate sets (all points on a line)
            inliers = None
    return np.zeros(len(matches), bool) if inliers is None else inliers.ravel() > 0


def keypoint_tracks(
    counts: Sequence[int],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    distances: Sequence[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Tracks of (image, keypoint) nodes that never hold two keypoints of one image: union-find
    over the matches taken closest first in descriptor space, refusing a merge whose two tracks
    share an image. Plain connected components would let one wrong match join two tracks, and
    spoil both for every image they reach; here the match that would do so is left out, and it
    is usually the weaker one.

    counts: keypoints per image ``[I]``; pairs: int ``[P, 2]`` image indices; matches: per pair
    int ``[K, 2]`` (keypoint of image i, of image j); distances: per pair float ``[K]``, the
    order in which matches are taken (None: as given). Returns (nodes int ``[V, 2]`` (image,
    keypoint) of every keypoint in a track of two or more, ordered by track then image; track
    int ``[V]``, 0 to T - 1).
    """
    offsets, edges = _match_edges(counts, pairs, matches)
    if distances is not None:
        flat = np.concatenate([np.zeros(0), *(np.ravel(d) for d in distances)])
        edges = edges[np.argsort(flat, kind="stable")]
    image_of = np.repeat(np.arange(len(counts)), np.diff(offsets)).tolist()
    parent = list(range(int(offsets[-1])))
    images: dict[int, set] = {}  # root -> the images its track holds (absent: its own alone)

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]  # path halving
            x = parent[x]
        return x

    # A Python loop: each merge must see the merges before it (a video's 10^6 matches: seconds).
    for u, v in edges.tolist():
        ru, rv = find(u), find(v)
        if ru == rv:
            continue
        su, sv = images.get(ru) or {image_of[ru]}, images.get(rv) or {image_of[rv]}
        if not su.isdisjoint(sv):
            continue
        if len(su) < len(sv):
            ru, rv, su, sv = rv, ru, sv, su
        parent[rv] = ru
        images[ru] = su | sv
        images.pop(rv, None)
    node = np.unique(edges.ravel())
    root = np.array([find(x) for x in node.tolist()], np.int64).reshape(-1)
    roots, sizes = np.unique(root, return_counts=True)
    keep = np.isin(root, roots[sizes > 1])
    node, root = node[keep], root[keep]
    order = np.lexsort((node, root))
    node, root = node[order], root[order]
    _, track = np.unique(root, return_inverse=True)
    image = np.searchsorted(offsets, node, side="right") - 1
    nodes = np.stack([image, node - offsets[image]], axis=1)
    return nodes.astype(np.int64).reshape(-1, 2), track.astype(np.int64).reshape(-1)


def descriptor_distances(
    features: Sequence[Features], pairs: np.ndarray, matches: Sequence[np.ndarray]
) -> list[np.ndarray]:
    """Each match's L2 descriptor distance, float32 ``[K]`` per row of ``pairs``."""
    rows = [np.asarray(f.descriptors, np.float32).reshape(len(f.keypoints), -1) for f in features]
    return [
        np.linalg.norm(rows[i][m[:, 0]] - rows[j][m[:, 1]], axis=1)
        for (i, j), m in zip(pairs, (np.asarray(m, np.int64).reshape(-1, 2) for m in matches))
    ]


def _runs(values: np.ndarray) -> list[slice]:
    """The slices of sorted ``values`` [N] that each hold one value, in order."""
    if len(values) == 0:
        return []
    starts = np.flatnonzero(np.concatenate([[True], values[1:] != values[:-1]]))
    return [slice(lo, hi) for lo, hi in zip(starts, [*starts[1:], len(values)])]


def track_anchors(track: np.ndarray, degree: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """int ``[T]``: the index into the track's nodes (``track`` ``[V]``, ordered) of each track's
    anchor, the node with the most matches (``degree`` ``[V]``), then the highest score (``[V]``).
    Most matches: a view in the middle of the track, the least view change to the others."""
    order = np.lexsort((-np.asarray(scores), -np.asarray(degree), track))
    first = np.concatenate([[True], track[order][1:] != track[order][:-1]])
    return order[first]


class Refinement(NamedTuple):
    """What :func:`refine_keypoints` returns.

    features: each image's detections, keypoints ``[N_i, 2]`` moved where a move was found.
    matches: per pair int ``[K', 2]``, the given matches whose two keypoints both settled: moved
    onto their track anchor's patch, or that anchor; every given match of a pair with an image
    where fewer than :data:`MIN_SETTLED_SHARE` of the matches settled. counts: ``tracks``,
    ``observations`` (non-anchor keypoints in tracks), ``moved``, ``matches`` (given),
    ``settled_matches``, ``unchecked_images`` (those keeping every match), ``kept_matches``.
    """

    features: list[Features]
    matches: list[np.ndarray]
    counts: dict


def _settle(
    greys: Sequence[np.ndarray],
    features: Sequence[Features],
    source: np.ndarray,
    target: np.ndarray,
    affine_steps: int,
    progress: Callable,
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """(keypoints float32 ``[N_i, 2]`` per image, settled bool ``[N_i]`` per image, how many
    moved): each observation ``target`` int ``[V, 2]`` (image, keypoint) moved onto the patch
    of its anchor ``source`` ``[V, 2]`` (:func:`refine_keypoints`); settled marks both ends of
    each move."""
    refined = [np.array(f.keypoints, np.float32).reshape(-1, 2) for f in features]
    settled = [np.zeros(len(f.keypoints), bool) for f in features]
    # One image at a time, whichever anchors its observations follow: templates are cut from
    # each anchor image, then all are searched for in one call (a call per image pair spent most
    # of its time in NumPy's per-call overhead: 1.08 -> 0.65 s on 12 frames, on one thread).
    # Sorted so that each image is one slice, and each anchor image a slice of that (a video's
    # thousands of images never rescan every observation).
    order = np.lexsort((source[:, 0], target[:, 0]))
    source, target = source[order], target[order]

    def refined_image(block: slice) -> tuple[np.ndarray, np.ndarray]:
        b, ib, anchors = target[block.start, 0], target[block, 1], source[block]
        cut = [
            cut_templates(
                np.asarray(greys[anchors[part.start, 0]], np.float32),
                features[anchors[part.start, 0]].keypoints[anchors[part, 1]],
            )
            for part in _runs(anchors[:, 0])
        ]
        return match_templates(
            np.concatenate([template for template, _ in cut]),
            np.concatenate([usable for _, usable in cut]),
            greys[b],
            features[b].keypoints[ib],
            affine_steps=affine_steps,
        )

    blocks = _runs(target[:, 0])
    moved = 0
    for block, (points, ok) in zip(blocks, threaded(refined_image, blocks, progress)):
        b, ib, anchors = target[block.start, 0], target[block, 1], source[block]
        refined[b][ib[ok]] = points[ok]
        settled[b][ib[ok]] = True
        for part in _runs(anchors[:, 0]):
            settled[anchors[part.start, 0]][anchors[part, 1][ok[part]]] = True
        moved += int(ok.sum())
    return refined, settled, moved


def refine_keypoints(
    greys: Sequence[np.ndarray],
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    affine_steps: int = AFFINE_STEPS,
    progress: Callable = iter,
) -> Refinement:
    """Track-consistent refinement: the observations of each track (:func:`keypoint_tracks`)
    moved to the NCC peak and affine polish of its anchor's grey patch (``refine_matches``), the
    anchor fixed; only matches between keypoints that settled so are kept (:class:`Refinement`).

    greys: each image's grey ``[H, W]`` (uint8, ``inference.images.grey``; any sequence that
    indexes, e.g. one reading from disk, as a video's frames would not all fit in memory);
    features: each image's detections; pairs: int ``[P, 2]``; matches: per pair int ``[K, 2]``,
    best :func:`fundamental_inliers` (tracks over raw mutual nearest neighbours are mostly
    wrong); ``progress`` wraps the loop over images.
    """
    sizes = [len(f.keypoints) for f in features]
    matches = [np.asarray(m, np.int64).reshape(-1, 2) for m in matches]
    nodes, track = keypoint_tracks(
        sizes, pairs, matches, descriptor_distances(features, pairs, matches)
    )
    offsets, edges = _match_edges(sizes, pairs, matches)
    flat = offsets[nodes[:, 0]] + nodes[:, 1]
    degree = np.bincount(edges.ravel(), minlength=offsets[-1])[flat]
    scores = np.concatenate([np.asarray(f.scores, np.float64).reshape(-1) for f in features])
    anchor = track_anchors(track, degree, scores[flat])[track]  # each node's anchor node
    todo = anchor != np.arange(len(track))
    refined, settled, moved = _settle(
        greys, features, nodes[anchor[todo]], nodes[todo], affine_steps, progress
    )
    # A keypoint that did not move keeps the detector's error (about 1 px for `distilled`):
    # on rendered paths its matches cost more rotation accuracy than their points add. But an
    # image whose matches mostly did not settle (blur, flat texture) keeps them all: without
    # them COLMAP dropped such a frame (25% settled, against 43-81% on 59 other frames).
    both = [settled[i][m[:, 0]] & settled[j][m[:, 1]] for (i, j), m in zip(pairs, matches)]
    given, held = np.zeros(len(features)), np.zeros(len(features))
    for (i, j), ok in zip(pairs, both):
        given[[i, j]] += len(ok)
        held[[i, j]] += ok.sum()
    unchecked = held < MIN_SETTLED_SHARE * given
    kept = [m if unchecked[[i, j]].any() else m[ok] for (i, j), m, ok in zip(pairs, matches, both)]
    total = lambda found: int(sum(len(m) for m in found))
    counts = dict(tracks=int(track.max(initial=-1) + 1), observations=int(todo.sum()))
    counts.update(
        moved=moved, matches=total(matches), settled_matches=sum(int(ok.sum()) for ok in both)
    )
    counts.update(unchecked_images=int(unchecked.sum()), kept_matches=total(kept))
    features = [f._replace(keypoints=k) for f, k in zip(features, refined)]
    return Refinement(features, kept, counts)
