"""COLMAP through pycolmap (the optional ``sfm`` extra): the shared camera, the database,
geometric verification, the incremental mapper and its start, and what a model holds.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); ours sits at (0, 0)
(``core.model``'s convention), so :func:`colmap_keypoints` is the one place that converts.
"""

from __future__ import annotations

import itertools
import pathlib
import shutil
import tempfile
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from usp_jax.evaluation.pose import relative_pose_errors
from usp_jax.inference.features import Features

#: How to get pycolmap, quoted when it is missing.
INSTALL = "pip install 'usp-jax[sfm]'"
#: COLMAP's pixel-corner coordinates minus ours (pixel centres at integers, ``core.model``).
COLMAP_OFFSET = 0.5


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


class Camera(NamedTuple):
    """The camera every image shares: COLMAP's model name (``SIMPLE_RADIAL``, ``PINHOLE``,
    ``OPENCV``, ...) and, when known, its parameters in COLMAP's order and pixel convention (the
    top-left pixel's centre at (0.5, 0.5): OpenCV's principal point plus 0.5); ``()``: COLMAP
    guesses them (the photos' EXIF focal length, else 1.2 times the longest side)."""

    model: str = "SIMPLE_RADIAL"
    params: tuple[float, ...] = ()


def check_camera(model: str, params: Sequence[float] = ()) -> Camera:
    """A :class:`Camera`; ValueError naming the model's parameters when the model is unknown to
    COLMAP, or the parameters are given but their count is wrong, a value is not finite or a
    focal length not positive."""
    pycolmap = load_pycolmap()
    models = [name for name in pycolmap.CameraModelId.__members__ if name != "INVALID"]
    if model not in models:
        raise ValueError(f"camera model {model!r} is not COLMAP's; one of {', '.join(models)}")
    params = tuple(float(p) for p in params)
    if not params:
        return Camera(model)
    camera = pycolmap.Camera(model=model, width=1, height=1, params=list(params))
    positive = all(params[i] > 0 for i in camera.focal_length_idxs())
    if not (camera.verify_params() and np.isfinite(params).all() and positive):
        count = len(camera.params_info.split(","))
        raise ValueError(
            f"camera {model} takes {count} finite parameters ({camera.params_info}, focal"
            f" lengths positive), got {', '.join(map(str, params))}"
        )
    return Camera(model, params)


def reader_options(camera: Camera = Camera()):
    """COLMAP's image reader options giving every image ``camera``."""
    options = load_pycolmap().ImageReaderOptions()
    options.camera_model = camera.model
    options.camera_params = ",".join(repr(float(p)) for p in camera.params)
    return options


def write_database(
    database: str | pathlib.Path,
    image_dir: str | pathlib.Path,
    names: Sequence[str],
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    camera: Camera = Camera(),
) -> list[int]:
    """A new COLMAP database holding the images (one shared ``camera``, COLMAP's own import:
    rig, frame and image rows), their keypoints in COLMAP's convention and the raw matches.
    ``names`` are paths relative to ``image_dir``. Returns each name's image id."""
    pycolmap = load_pycolmap()
    pycolmap.Database.open(str(database)).close()  # import_images needs the file to exist
    pycolmap.import_images(
        str(database),
        str(image_dir),
        pycolmap.CameraMode.SINGLE,
        image_names=list(names),
        options=reader_options(camera),
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


def initial_pair(database: str | pathlib.Path) -> tuple[int, int] | None:
    """The image ids of the verified pair with the most inlier matches whose two-view geometry
    COLMAP found general (CALIBRATED or UNCALIBRATED), not planar or panoramic; None if none.

    Why: COLMAP may start from a PLANAR_OR_PANORAMIC pair, whose pose a homography fixes only up
    to a two-fold ambiguity. With our features, which lie on fewer surfaces than SIFT's, that
    start bent or broke the model on a rendered path whenever the focal length was known or a
    prior (experiments/results/sfm/README.md)."""
    pycolmap = load_pycolmap()
    general = {pycolmap.TwoViewGeometryConfiguration.CALIBRATED}
    general.add(pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED)
    best, pair = 0, None
    with pycolmap.Database.open(str(database)) as db:
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            if geometry.config in general and len(geometry.inlier_matches) > best:
                best, pair = len(geometry.inlier_matches), pycolmap.pair_id_to_image_pair(pair_id)
    return None if pair is None else (int(pair[0]), int(pair[1]))


def _largest_first(models: dict, folder: pathlib.Path) -> list:
    """COLMAP's models (``{k: Reconstruction}``, written to ``folder/k``), most registered images
    first, their folders renumbered so. COLMAP numbers them in the order it built them, and a
    later start can register more (rendered path 4: 3, 8, then 12 images)."""
    order = sorted(sorted(models), key=lambda k: -models[k].num_reg_images())
    written = [(folder / str(k), folder / f"{new}.sorting") for new, k in enumerate(order)]
    for old, temporary in written:
        if old.is_dir():
            old.rename(temporary)
    for new, (_, temporary) in enumerate(written):
        if temporary.is_dir():
            temporary.rename(folder / str(new))
    return [models[k] for k in order]


def _start_folder(sparse_dir: pathlib.Path, index: int) -> pathlib.Path:
    """A new empty hidden folder beside ``sparse_dir`` for the mapper's start ``index``: a call
    killed earlier may have left one behind, and the mapper would add its models to whatever a
    reused folder still holds."""
    prefix = f".{sparse_dir.name}.start{index}-"
    return pathlib.Path(tempfile.mkdtemp(prefix=prefix, dir=sparse_dir.parent))


def map_images(
    database: str | pathlib.Path,
    image_dir: str | pathlib.Path,
    sparse_dir: str | pathlib.Path,
    on_image: Callable[[int], object] | None = None,
    fixed_intrinsics: bool = False,
    general_start: bool = True,
) -> list:
    """COLMAP's incremental mapper: the models it finds, most registered images first, written
    as COLMAP writes them and numbered in that order (``sparse_dir/0`` the largest,
    ``sparse_dir/1``, ...; none when no pair could start one).
    ``image_dir`` gives the points' colours; ``on_image(count)`` is called at each image
    registered, with the count of the mapper's run so far (it starts over when a second run does).
    ``fixed_intrinsics`` holds the camera as the database has it (a calibrated camera): bundle
    adjustment refines poses and points only.

    With ``general_start`` the mapper starts from :func:`initial_pair`; when that start fails
    or leaves images out, COLMAP's own choice of start runs too, and the run whose largest
    model registers more images, then with the lower mean reprojection error, is kept.
    Without, COLMAP chooses alone (its default)."""
    pycolmap = load_pycolmap()
    sparse_dir = pathlib.Path(sparse_dir)

    def mapped(folder: pathlib.Path, pair: tuple[int, int] | None) -> list:
        options = pycolmap.IncrementalPipelineOptions()
        if fixed_intrinsics:
            options.ba_refine_focal_length = options.ba_refine_principal_point = False
            options.ba_refine_extra_params = False
        if pair is not None:  # one try: COLMAP would retry an unsuitable given pair 200 times
            options.init_image_id1, options.init_image_id2 = pair
            options.init_num_trials = 1
        registered = itertools.count(1)
        models = pycolmap.incremental_mapping(
            str(database),
            str(image_dir),
            str(folder),
            options,
            next_image_callback=on_image and (lambda: on_image(next(registered))),
        )
        return _largest_first(models, folder)

    def rank(models: list) -> tuple[int, float]:
        return (
            (models[0].num_reg_images(), -models[0].compute_mean_reprojection_error())
            if models
            else (0, 0.0)
        )

    if sparse_dir.exists() and any(sparse_dir.iterdir()):
        raise ValueError(f"{sparse_dir} holds something already: map into a new or empty folder")
    with pycolmap.Database.open(str(database)) as db:
        images = db.num_images()
    pair = initial_pair(database) if general_start else None
    starts = [pair, None] if pair is not None else [None]
    best, kept = [], None
    sparse_dir.parent.mkdir(parents=True, exist_ok=True)
    made = []  # this call's folders, removed if it fails (another call's are not ours)
    try:
        for index, pair in enumerate(starts):
            folder = _start_folder(sparse_dir, index)
            made.append(folder)
            models = mapped(folder, pair)
            if kept is None or rank(models) > rank(best):
                if kept is not None:
                    shutil.rmtree(kept)
                best, kept = models, folder
            else:
                shutil.rmtree(folder)
            if rank(best)[0] == images:
                break
        if sparse_dir.exists():
            sparse_dir.rmdir()
        kept.rename(sparse_dir)
    except BaseException:
        for folder in made:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    return best


def model_summary(model) -> dict:
    """A model's registered images, 3-D points, mean track length (observations per point) and
    mean reprojection error in px."""
    return {
        "registered_images": int(model.num_reg_images()),
        "points": int(model.num_points3D()),
        "mean_track_length": float(model.compute_mean_track_length()),
        "mean_reprojection_error": float(model.compute_mean_reprojection_error()),
    }


def camera_params(model) -> list[float]:
    """The parameters of the camera a model's images share (COLMAP's order and convention), as
    bundle adjustment left them."""
    return [float(p) for p in next(iter(model.cameras.values())).params]


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
    """The relative-pose errors (``evaluation.pose.relative_pose_errors``) over all pairs of the
    model's registered images with a true pose (name -> (rotation [3, 3], centre [3])): their
    count and the medians in degrees."""
    found = registered_poses(model)
    names = sorted(set(found) & set(true_poses))
    stack = lambda poses, k: np.stack([poses[n][k] for n in names])
    if len(names) < 2:
        return {"pairs": 0, "median_rotation_error": None, "median_translation_error": None}
    errors = relative_pose_errors(*(stack(p, k) for p in (found, true_poses) for k in (0, 1)))
    medians = [float(np.median(e)) for e in errors]
    keys = ("median_rotation_error", "median_translation_error")
    return {"pairs": len(errors[0]), **dict(zip(keys, medians))}
