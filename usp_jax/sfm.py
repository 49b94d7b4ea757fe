"""Structure from motion with the network's features: COLMAP's database, geometric verification,
incremental mapper and bundle adjustment through pycolmap (the optional ``sfm`` extra), with our
keypoints and mutual-nearest-neighbour matches in place of COLMAP's SIFT.

The steps, each a function (``usp-jax reconstruct`` runs them in order):
:func:`detect_images` -> :func:`match_pairs` on :func:`image_pairs` -> :func:`fundamental_inliers`
-> :func:`refine_keypoints` -> :func:`write_database` -> :func:`verify` -> :func:`map_images`,
then :func:`model_summary` and, where true poses are known, :func:`pose_errors`. :func:`export_features` writes the features and raw matches for
users who run COLMAP or hloc themselves.

It lives beside the CLI rather than in ``inference`` or ``evaluation``: it is an application of
the detector with a heavy optional dependency that detection, training and evaluation must never
load, and ``benchmarks/bench_sfm.py`` uses it together with the evaluation's scenes.

COLMAP gets only the matches a 1 px fundamental matrix keeps (:func:`fundamental_inliers`), with
the keypoints of each track moved onto one anchor observation's patch, the simple form of
pixel-perfect SfM's featuremetric keypoint adjustment (:func:`refine_keypoints`): COLMAP keeps
one position per keypoint, shared by all its matches, so matches cannot be refined one by one.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); ours sits at (0, 0)
(``core.model``'s convention), so :func:`colmap_keypoints` is the one place that converts.
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

import numpy as np

from usp_jax.inference.features import Features
from usp_jax.inference.match_refinement import refine_matches
from usp_jax.inference.matching import mutual_nearest_neighbours

#: How to get pycolmap, quoted when it is missing.
INSTALL = "pip install 'usp-jax[sfm]'"
#: COLMAP's pixel-corner coordinates minus ours (pixel centres at integers, ``core.model``).
COLMAP_OFFSET = 0.5
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


def load_pycolmap():
    """The ``pycolmap`` module; ValueError naming the install command when it is missing."""
    try:
        import pycolmap
    except ImportError:
        raise ValueError(f"pycolmap is not installed: {INSTALL}") from None
    return pycolmap


def colmap_keypoints(keypoints: np.ndarray) -> np.ndarray:
    """Our (x, y) ``[N, 2]`` (pixel centres at integers) as COLMAP's float32 ``[N, 2]`` (the
    top-left pixel's centre at (0.5, 0.5))."""
    return (np.asarray(keypoints, np.float32).reshape(-1, 2) + COLMAP_OFFSET).astype(np.float32)


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
    """Mutual nearest neighbours in descriptor space (``inference.matching``, L2: what ``match`` pairs) of each pair:
    int ``[K, 2]`` (index into image i's keypoints, into image j's) per row of ``pairs``."""
    return [
        mutual_nearest_neighbours(features[i].descriptors, features[j].descriptors, ratio)
        for i, j in progress(pairs)
    ]


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
    epipolar line into the tracks. This leaves COLMAP few wrong matches to weed out."""
    import cv2

    if threshold is None:
        return [np.asarray(m, np.int64).reshape(-1, 2) for m in matches]
    kept = []
    for (i, j), pair_matches in zip(pairs, matches):
        pair_matches = np.asarray(pair_matches, np.int64).reshape(-1, 2)
        inliers = None
        if len(pair_matches) >= 8:
            try:
                _, inliers = cv2.findFundamentalMat(
                    features[i].keypoints[pair_matches[:, 0]].astype(np.float64),
                    features[j].keypoints[pair_matches[:, 1]].astype(np.float64),
                    cv2.USAC_MAGSAC,
                    threshold,
                    0.999,
                    10000,
                )
            except cv2.error:  # USAC asserts on some degenerate sets (all points on a line)
                inliers = None
        keep = np.zeros(len(pair_matches), bool) if inliers is None else inliers.ravel() > 0
        kept.append(pair_matches[keep])
    return kept


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
    onto their track anchor's patch, or that anchor. counts: ``tracks``, ``observations``
    (non-anchor keypoints in tracks), ``moved``, ``matches`` (given), ``settled_matches``.
    """

    features: list[Features]
    matches: list[np.ndarray]
    counts: dict


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
    anchor fixed; only matches between keypoints that settled so are kept.

    greys: each image's grey ``[H, W]`` (uint8, ``inference.images.grey``; any sequence that
    indexes, e.g. one reading from disk, as a video's frames would not all fit in memory);
    features: each image's detections; pairs: int ``[P, 2]``; matches: per pair int ``[K, 2]``,
    best :func:`fundamental_inliers` (tracks over raw mutual nearest neighbours are mostly
    wrong); ``progress`` wraps the loop over image pairs.
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
    refined = [np.array(f.keypoints, np.float32).reshape(-1, 2) for f in features]
    settled = [np.zeros(n, bool) for n in sizes]
    source, target = nodes[anchor[todo]], nodes[todo]
    # One (anchor image, image) pair at a time, as refine_matches takes two images: sorted so
    # each pair is one slice (a video's thousands of pairs never rescan every observation).
    order = np.lexsort((target[:, 0], source[:, 0]))
    source, target = source[order], target[order]
    key = source[:, 0] * len(features) + target[:, 0]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    moved = 0
    for lo, hi in progress(list(zip(starts, [*starts[1:], len(key)]))):
        a, b = source[lo, 0], target[lo, 0]
        points, ok = refine_matches(
            greys[a],
            greys[b],
            features[a].keypoints[source[lo:hi, 1]],
            features[b].keypoints[target[lo:hi, 1]],
            affine_steps=affine_steps,
        )
        refined[b][target[lo:hi, 1][ok]] = points[ok]
        settled[b][target[lo:hi, 1][ok]] = True
        settled[a][source[lo:hi, 1][ok]] = True
        moved += int(ok.sum())
    # A keypoint that did not move keeps the detector's error (about 1 px for `distilled`):
    # on rendered paths its matches cost more rotation accuracy than their points add.
    kept = [m[settled[i][m[:, 0]] & settled[j][m[:, 1]]] for (i, j), m in zip(pairs, matches)]
    counts = {
        "tracks": int(track.max(initial=-1) + 1),
        "observations": int(todo.sum()),
        "moved": moved,
        "matches": int(sum(len(m) for m in matches)),
        "settled_matches": int(sum(len(m) for m in kept)),
    }
    features = [f._replace(keypoints=k) for f, k in zip(features, refined)]
    return Refinement(features, kept, counts)


def write_database(
    database: str | pathlib.Path,
    image_dir: str | pathlib.Path,
    names: Sequence[str],
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
) -> list[int]:
    """A new COLMAP database holding the images (one shared SIMPLE_RADIAL camera, COLMAP's own
    import: rig, frame and image rows), their keypoints in COLMAP's convention and the raw
    matches. ``names`` are paths relative to ``image_dir``. Returns each name's image id."""
    pycolmap = load_pycolmap()
    pycolmap.Database.open(str(database)).close()  # import_images needs the file to exist
    pycolmap.import_images(
        str(database), str(image_dir), pycolmap.CameraMode.SINGLE, image_names=list(names)
    )
    with pycolmap.Database.open(str(database)) as db:
        by_name = {image.name: image.image_id for image in db.read_all_images()}
        ids = [by_name[name] for name in names]
        for image_id, found in zip(ids, features):
            db.write_keypoints(image_id, colmap_keypoints(found.keypoints))
        for (i, j), pair_matches in zip(pairs, matches):
            db.write_matches(ids[i], ids[j], np.asarray(pair_matches, np.uint32).reshape(-1, 2))
    return ids


def verify(database: str | pathlib.Path) -> None:
    """COLMAP's geometric verification of every matched pair (RANSAC E, F or H; the inliers
    become the database's two-view geometries, which the mapper uses)."""
    load_pycolmap().geometric_verification(str(database))


def verified_pairs(database: str | pathlib.Path) -> int:
    """How many image pairs passed the geometric verification."""
    with load_pycolmap().Database.open(str(database)) as db:
        return int(db.num_verified_image_pairs())


def map_images(
    database: str | pathlib.Path,
    image_dir: str | pathlib.Path,
    sparse_dir: str | pathlib.Path,
    on_image: Callable[[], object] | None = None,
) -> list:
    """COLMAP's incremental mapper: the models it finds, largest first, written as COLMAP
    writes them (``sparse_dir/0``, ``sparse_dir/1``, ...; none when no pair could start one).
    ``image_dir`` gives the points' colours; ``on_image`` is called at each image registered."""
    pycolmap = load_pycolmap()
    pathlib.Path(sparse_dir).mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(
        str(database), str(image_dir), str(sparse_dir), next_image_callback=on_image
    )
    return [models[k] for k in sorted(models)]


def model_summary(model) -> dict:
    """A model's registered images, 3-D points, mean track length (observations per point) and
    mean reprojection error in px."""
    return {
        "registered_images": int(model.num_reg_images()),
        "points": int(model.num_points3D()),
        "mean_track_length": float(model.compute_mean_track_length()),
        "mean_reprojection_error": float(model.compute_mean_reprojection_error()),
    }


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


def registered_poses(model) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Image name -> (world-to-camera rotation [3, 3], camera centre [3]) of every registered
    image of a pycolmap model."""
    poses = {}
    for image in model.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            poses[image.name] = (pose.rotation.matrix(), np.asarray(image.projection_center()))
    return poses


def pose_errors(model, true_poses: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
    """:func:`relative_pose_errors` over all pairs of the model's registered images with a true
    pose (name -> (rotation [3, 3], centre [3])): their count and the medians in degrees."""
    found = registered_poses(model)
    names = sorted(set(found) & set(true_poses))
    if len(names) < 2:
        return {"pairs": 0, "median_rotation_error": None, "median_translation_error": None}
    stack = lambda poses, k: np.stack([poses[n][k] for n in names])
    rotation, translation = relative_pose_errors(
        stack(found, 0), stack(found, 1), stack(true_poses, 0), stack(true_poses, 1)
    )
    return {
        "pairs": len(rotation),
        "median_rotation_error": float(np.median(rotation)),
        "median_translation_error": float(np.median(translation)),
    }


def export_features(
    path: str | pathlib.Path,
    names: Sequence[str],
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    kept: Sequence[np.ndarray] | None = None,
) -> None:
    """Features and raw matches in one ``.npz`` for other tools (COLMAP, hloc): per image
    ``NAME/keypoints`` float32 ``[N, 2]`` in COLMAP's convention, ``NAME/scores`` ``[N]``,
    ``NAME/descriptors`` ``[N, D]``; per pair ``NAME1//NAME2/matches`` int ``[K, 2]`` and, when
    ``kept`` is given, ``NAME1//NAME2/kept`` ``[K', 2]`` (those the database got)."""
    arrays = {}
    for name, found in zip(names, features):
        arrays[f"{name}/keypoints"] = colmap_keypoints(found.keypoints)
        arrays[f"{name}/scores"] = np.asarray(found.scores, np.float32)
        arrays[f"{name}/descriptors"] = np.asarray(found.descriptors)
    for (i, j), pair_matches in zip(pairs, matches):
        arrays[f"{names[i]}//{names[j]}/matches"] = np.asarray(pair_matches, np.int64)
    for (i, j), pair_kept in zip(pairs, kept if kept is not None else []):
        arrays[f"{names[i]}//{names[j]}/kept"] = np.asarray(pair_kept, np.int64).reshape(-1, 2)
    with open(path, "wb") as file:
        np.savez(file, **arrays)


def top_view(model, path: str | pathlib.Path, points: int = 20000) -> None:
    """A PNG of the model from above: its points (at most ``points``, in their colours) and
    camera centres with viewing directions on the world's x-z plane (COLMAP's world is the
    first camera's frame, y down, so x-z is the ground when that camera was level)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    xyz = np.array([p.xyz for p in model.points3D.values()]).reshape(-1, 3)
    rgb = np.array([p.color for p in model.points3D.values()]).reshape(-1, 3) / 255
    keep = np.random.default_rng(0).permutation(len(xyz))[:points]
    poses = registered_poses(model)
    centres = np.array([c for _, c in poses.values()]).reshape(-1, 3)
    views = np.array([r[2] for r, _ in poses.values()]).reshape(-1, 3)  # optical axes in world
    figure, axes = plt.subplots(figsize=(8, 8))
    axes.scatter(xyz[keep, 0], xyz[keep, 2], s=1, c=rgb[keep], linewidths=0)
    axes.quiver(centres[:, 0], centres[:, 2], views[:, 0], views[:, 2], color="red", width=0.003)
    axes.set(
        aspect="equal", xlabel="x", ylabel="z", title=f"{len(poses)} cameras, {len(xyz)} points"
    )
    figure.savefig(path, dpi=100)
    plt.close(figure)
