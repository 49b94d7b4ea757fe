"""Structure from motion, COLMAP's own SIFT pipeline against ours, on the same images in one run.

SIFT: ``pycolmap.extract_features`` -> ``match_exhaustive`` (photos) or ``match_sequential``
(a video, ``--window`` frames overlap) -> ``incremental_mapping``, COLMAP's defaults.
Ours (``usp_jax.sfm``, what ``usp-jax reconstruct`` runs): the network's keypoints, mutual
nearest neighbours on the same pairs, COLMAP's geometric verification and the same mapper.
Both share one camera (COLMAP's SINGLE camera mode): a SIMPLE_RADIAL that COLMAP estimates, or
on a rendered path the true one (``--intrinsics``). ``--pipelines`` picks which of
ours run, each a row: ``raw`` gives COLMAP every mutual nearest neighbour; ``filtered`` the
matches a 1 px fundamental matrix keeps (``sfm.fundamental_inliers``, ``--epipolar``); ``refined``
those, with each track's keypoints moved onto its anchor's patch and only the matches of
keypoints that settled so (``sfm.refine_keypoints``: reconstruct's default). All rows share one
detection. ``--repeats K`` runs each of our rows K times on that detection
(rows with ``repeat`` 0 to K - 1): COLMAP's RANSAC and mapper are random, and the rotation error
of one run can differ several-fold from the next's. ``--no-detector-refine`` drops the
network's learned sub-pixel refinement of its points (reconstruct keeps it).

Reported per pipeline: registered images, 3-D points, mean track length, mean reprojection
error, wall time per stage (ours after one warm-up detection; its compile time beside; the
refined row's ``refine`` stage and its counts of tracks and moved keypoints), the shared
camera's focal length, and,
where the true poses are known, the median relative-rotation and translation-direction errors
over all pairs of registered images (``sfm.pose_errors``).

Inputs: ``--scene N`` renders a camera path of N frames through a room of photos
(``evaluation.scenes``: ``room`` and ``camera_path``, true poses known); ``--images`` takes a
folder of photos or a video (frames every ``--every``-th), no poses, or with ``--rectified`` a
rectified stereo pair (the relative rotation the identity, the baseline along x)::

    python3 benchmarks/bench_sfm.py --scene 24 --photos data/corpus/train \\
        --json experiments/results/sfm/room.json
    python3 benchmarks/bench_sfm.py --images box.mp4 --every 15 \\
        --json experiments/results/sfm/box.json
    python3 benchmarks/bench_sfm.py --images aloe --rectified --json .../aloe.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import tempfile
import time

import cv2
import numpy as np
import pycolmap

from usp_jax import sfm
from usp_jax.inference.detector import Detector
from usp_jax.inference.images import IMAGE_SUFFIXES, grey, read_image

RATIO = sfm.RATIO
EPIPOLAR = sfm.EPIPOLAR_THRESHOLD
PIPELINES = ("raw", "filtered", "refined")
INTRINSICS = ("estimated", "prior", "known")
#: ``--intrinsics``' camera, given to SIFT's pipeline and ours, and whether it is held fixed.
CAMERA, FIXED = sfm.Camera(), False
#: ``--colmap-start``'s opposite: ours start the mapper from ``sfm.initial_pair``.
START = True


def rendered_path(folder: pathlib.Path, photos: str, count: int, size, seed: int):
    """Renders a camera path into ``folder``; its true poses, name -> (R, centre), and its
    camera (COLMAP's PINHOLE: COLMAP's principal point is ours plus half a pixel)."""
    from usp_jax.evaluation import scenes

    scene = scenes.room(scenes.load_photos(photos), seed=seed)
    poses = {}
    for index, camera in enumerate(scenes.camera_path(scene, count, *size, seed=seed)):
        name = f"{index:04d}.png"
        image = scenes.render(scene, camera)[0]
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        poses[name] = (camera.R, camera.centre)
    (fx, _, cx), (_, fy, cy) = camera.K[:2]
    offset = sfm.COLMAP_OFFSET
    return poses, sfm.Camera("PINHOLE", (fx, fy, cx + offset, cy + offset))


def intrinsics(true: sfm.Camera, mode: str) -> tuple[sfm.Camera, bool]:
    """``--intrinsics``' camera (a true PINHOLE ``true``) and whether the mapper holds it."""
    if mode == "known":
        return true, True
    if mode == "prior":  # COLMAP's camera for a photo with EXIF: its focal length, refined
        fx, fy, cx, cy = true.params
        return sfm.Camera("SIMPLE_RADIAL", ((fx + fy) / 2, cx, cy, 0.0)), False
    return sfm.Camera(), False


def video_frames(video: str, folder: pathlib.Path, every: int) -> None:
    capture = cv2.VideoCapture(video)
    index = 0
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        if index % every == 0:
            cv2.imwrite(str(folder / f"{index:06d}.png"), frame)
        index += 1


def _mapped(database, images, work, seconds, general_start=True) -> list:
    start = time.perf_counter()
    sparse = work / "sparse"
    models = sfm.map_images(database, images, sparse, None, FIXED, general_start and START)
    seconds["map"] = time.perf_counter() - start
    return models


def run_sift(images: pathlib.Path, names, work: pathlib.Path, window) -> tuple[list, dict]:
    seconds, database = {}, work / "database.db"
    start = time.perf_counter()
    pycolmap.extract_features(
        database,
        images,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=sfm.reader_options(CAMERA),
    )
    seconds["detect"] = time.perf_counter() - start
    start = time.perf_counter()
    if window is None:
        pycolmap.match_exhaustive(database)
    else:
        pycolmap.match_sequential(
            database,
            pairing_options=pycolmap.SequentialPairingOptions(
                overlap=window, quadratic_overlap=False
            ),
        )
    seconds["match + verify"] = time.perf_counter() - start
    return _mapped(database, images, work, seconds, general_start=False), seconds


def detect_ours(images, names, detector) -> tuple[list, float]:
    """Our features of every image and the seconds they took (shared by both of our rows)."""
    start = time.perf_counter()
    features = sfm.detect_images(detector, (read_image(images / n) for n in names))
    return features, time.perf_counter() - start


def run_ours(images, names, work, window, detected, pipeline) -> tuple[list, dict, dict]:
    features, detect_s = detected
    seconds, database, counts = {"detect": detect_s}, work / "database.db", {}
    start = time.perf_counter()
    pairs = sfm.image_pairs(len(names), window)
    matches = sfm.match_pairs(features, pairs, ratio=RATIO)
    seconds["match"] = time.perf_counter() - start
    if pipeline != "raw":
        start = time.perf_counter()
        matches = sfm.fundamental_inliers(features, pairs, matches, EPIPOLAR)
        seconds["filter"] = time.perf_counter() - start
    if pipeline == "refined":
        start = time.perf_counter()
        greys = [grey(read_image(images / n)) for n in names]
        features, matches, counts = sfm.refine_keypoints(greys, features, pairs, matches)
        seconds["refine"] = time.perf_counter() - start
    start = time.perf_counter()
    sfm.write_database(database, images, names, features, pairs, matches, CAMERA)
    sfm.verify(database)
    seconds["verify"] = time.perf_counter() - start
    return _mapped(database, images, work, seconds), seconds, counts


def report(name, models, seconds, poses) -> dict:
    row = {"method": name, "models": len(models), "seconds": seconds}
    row["seconds"]["total"] = sum(seconds.values())
    if models:
        row.update(sfm.model_summary(models[0]))
        # The shared camera's focal length as bundle adjustment left it (true: 554.3 px).
        row["focal_px"] = sfm.camera_params(models[0])[0]
        if poses:
            row.update(sfm.pose_errors(models[0], poses))
    return row


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", type=int, metavar="N", help="render a path of N frames")
    source.add_argument("--images", help="a folder of photos or a video")
    p.add_argument(
        "--rectified",
        action="store_true",
        help="--images is a rectified stereo pair (Middlebury's): true relative rotation the"
        " identity, the second camera to the right of the first",
    )
    p.add_argument("--photos", default="data/corpus/train", help="--scene's textures")
    p.add_argument("--size", type=int, nargs=2, default=(480, 640), metavar=("H", "W"))
    p.add_argument("--seed", type=int, default=0, help="--scene's room and path")
    p.add_argument("--every", type=int, default=1, help="a video's every N-th frame")
    p.add_argument("--window", type=int, help="match each image to the N after it (a video)")
    p.add_argument("--weights", default="distilled")
    p.add_argument("--top", type=int, default=2000)
    p.add_argument("--max-side", type=int, default=1280)
    p.add_argument("--ratio", type=float, default=sfm.RATIO, help="ours: Lowe's ratio test")
    p.add_argument(
        "--pipelines",
        nargs="+",
        choices=PIPELINES,
        default=["raw", "refined"],
        help="ours: every mutual nearest neighbour to COLMAP (raw), those a fundamental matrix"
        " keeps (filtered), those with their keypoints refined along tracks (refined:"
        " reconstruct's default)",
    )
    p.add_argument(
        "--epipolar",
        type=float,
        default=sfm.EPIPOLAR_THRESHOLD,
        help="filtered and refined: the fundamental matrix's threshold, px",
    )
    p.add_argument(
        "--intrinsics",
        choices=INTRINSICS,
        default="estimated",
        help="--scene: COLMAP estimates the shared camera from its guess of the focal length"
        " (estimated), from the true one as a photo's EXIF gives it (prior), or gets the true"
        " camera and holds it fixed (known)",
    )
    p.add_argument(
        "--colmap-start",
        action="store_true",
        help="ours: COLMAP's mapper chooses its own first pair (reconstruct's choice before"
        " sfm.initial_pair; SIFT's rows always do)",
    )
    p.add_argument(
        "--detector-refine",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="ours: the network's learned sub-pixel refinement of its points (on in reconstruct)",
    )
    p.add_argument("--repeats", type=int, default=1, help="runs of each of our rows")
    p.add_argument("--json", help="write the rows here")
    return p


def main() -> None:
    global RATIO, EPIPOLAR, CAMERA, FIXED, START
    args = _parser().parse_args()
    RATIO, EPIPOLAR, START = args.ratio, args.epipolar, not args.colmap_start
    root = pathlib.Path(tempfile.mkdtemp(prefix="bench-sfm-"))
    images, poses = root / "images", None
    images.mkdir()
    if args.scene:
        poses, camera = rendered_path(images, args.photos, args.scene, args.size, args.seed)
        CAMERA, FIXED = intrinsics(camera, args.intrinsics)
    elif pathlib.Path(args.images).is_dir():
        for path in sorted(pathlib.Path(args.images).iterdir()):
            if path.suffix.lower() in IMAGE_SUFFIXES:
                shutil.copy(path, images / path.name)
    else:
        video_frames(args.images, images, args.every)
    names = sorted(p.name for p in images.iterdir())
    if args.rectified:
        poses = {names[0]: (np.eye(3), np.zeros(3)), names[1]: (np.eye(3), np.array([1.0, 0, 0]))}
    start = time.perf_counter()
    detector = Detector.pretrained(
        args.weights, top_n=args.top, max_side=args.max_side, refine=args.detector_refine
    )
    detector.detect(read_image(images / names[0]))  # compiles, outside the timed stages
    compile_s = time.perf_counter() - start
    work = root / "sift"
    work.mkdir()
    rows = [report("sift", *run_sift(images, names, work, args.window), poses)]
    detected = detect_ours(images, names, detector)
    for repeat in range(args.repeats):
        for pipeline in args.pipelines:
            work = root / f"usp-{pipeline}-{repeat}"
            work.mkdir()
            models, seconds, counts = run_ours(images, names, work, args.window, detected, pipeline)
            rows.append(report(f"usp {pipeline}", models, seconds, poses))
            rows[-1].update({"repeat": repeat, **({"refinement": counts} if counts else {})})
    for row in rows[1:]:
        row["compile_s"] = compile_s
    document = {
        "source": f"scene {args.scene} seed {args.seed}" if args.scene else args.images,
        "images": len(names),
        "size": list(read_image(images / names[0]).shape[:2]),
        "settings": vars(args),
        "rows": rows,
    }
    print(json.dumps(document, indent=1))
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps(document, indent=1) + "\n")
    shutil.rmtree(root)


if __name__ == "__main__":
    main()
