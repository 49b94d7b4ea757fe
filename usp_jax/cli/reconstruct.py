"""``usp-jax reconstruct IMAGES --out DIR``: structure from motion with the network's features
(``usp_jax.sfm``: our keypoints and mutual-nearest-neighbour matches, COLMAP's verification and
incremental mapper through pycolmap).

IMAGES is a folder of photos, matched exhaustively, or a video, whose frames (every ``--every``-th)
are written to ``DIR/images`` and matched each to the ``--window`` frames after it. DIR gets what
COLMAP writes (``database.db``, models under ``sparse/0``, ``sparse/1``, ...) and
``summary.json``, ``points.ply`` and ``cameras.png`` (the largest model from above).

COLMAP gets only the matches a 1 px RANSAC fundamental matrix keeps (``--epipolar``), with the
keypoints of each match track moved onto one anchor observation's grey patch
(``--refine-keypoints``, on by default: ``sfm.refine_keypoints``, one position per keypoint, as
COLMAP keeps, consistent across the track). The mapper starts from the general pair with most
inliers, not a planar one (``sfm.initial_pair``). All images share one camera: COLMAP's estimate,
or a calibrated one (``--camera-model``, ``--camera-params``).

Everything is written into a temporary folder beside DIR, renamed to DIR when the run ends, so a
failure leaves nothing half-written; DIR must be new, empty or an earlier reconstruct output.
A run that finds no model still writes its summary, then fails.

``--any-rotation`` is not offered: it turns image 2 back per pair, so one image would get other
keypoints in each pair, while COLMAP keeps one set per image. A rolling camera is better served
by ``--weights rotation``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pathlib
import shutil
import sys
import time
from functools import lru_cache

from usp_jax import sfm
from usp_jax.cli import arguments
from usp_jax.inference.images import IMAGE_SUFFIXES, grey, read_image

log = logging.getLogger(__name__)

#: The network's defaults here: the distilled weights (fast) at full size with the refinement,
#: and more points than a single match needs, as SIFT in COLMAP keeps thousands.
WEIGHTS = "distilled"
TOP = 2000
#: ``--refine-keypoints``' default: on. On rendered 12-frame paths (``distilled``, three runs
#: each) it took the median relative-rotation error from 0.075-0.099 deg (every match, unrefined)
#: to 0.047-0.082 on the design path, 0.18-0.24 to 0.12-0.13 and 0.23-0.31 to 0.065-0.087 on two
#: held-out ones, and registered every image where unrefined runs lost all but 3 in 2 of 9
#: (experiments/results/sfm/README.md), for about 1 s.
REFINE_KEYPOINTS = True
#: What a reconstruct run writes into DIR: a folder holding only these is its own earlier output.
OUTPUTS = frozenset(
    {"database.db", "sparse", "images", "summary.json", "points.ply", "cameras.png", "features.npz"}
)


def add_parser(subparsers) -> None:
    """The ``reconstruct`` subcommand's options (``cli.parser`` calls this)."""
    p = subparsers.add_parser(
        "reconstruct", help="structure from motion: cameras and 3-D points with COLMAP"
    )
    p.add_argument("images", help="a folder of photos (one size) or a video file")
    p.add_argument("--out", required=True, help="new folder for the database, models, summary")
    arguments.add_checkpoint(p, default=WEIGHTS, why="the fast network taught by paper")
    p.add_argument(
        "--top", type=arguments.positive, default=TOP, help=f"points per image (default {TOP})"
    )
    arguments.add_max_side(p, "the network sees images shrunk to this longest side (0: never)")
    p.add_argument(
        "--window",
        type=arguments.positive,
        default=sfm.WINDOW,
        metavar="N",
        help="a video frame is matched to the N frames after it",
    )
    p.add_argument(
        "--every", type=arguments.positive, default=1, metavar="N", help="every N-th video frame"
    )
    p.add_argument(
        "--epipolar",
        type=float,
        default=sfm.EPIPOLAR_THRESHOLD,
        metavar="PX",
        help="COLMAP gets only the matches a RANSAC fundamental matrix keeps within PX"
        f" (default {sfm.EPIPOLAR_THRESHOLD}; 0: every mutual nearest neighbour)",
    )
    p.add_argument(
        "--refine-keypoints",
        action=argparse.BooleanOptionalAction,
        default=REFINE_KEYPOINTS,
        help="move each match track's keypoints to the NCC and affine peak of one anchor"
        " observation's patch, and give COLMAP the matches of keypoints that moved so"
        " (default: on)",
    )
    p.add_argument(
        "--camera-model",
        default=sfm.Camera().model,
        metavar="MODEL",
        help="COLMAP's model of the camera all images share (PINHOLE, OPENCV, ...)",
    )
    p.add_argument(
        "--camera-params",
        type=_numbers,
        default=(),
        metavar="P1,P2,...",
        help="the known camera in COLMAP's order and pixel convention (PINHOLE: fx,fy,cx,cy,"
        " with cx, cy OpenCV's plus 0.5), held fixed unless --refine-intrinsics (default:"
        " COLMAP estimates it from the EXIF focal length or 1.2 x the longest side)",
    )
    p.add_argument(
        "--refine-intrinsics",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="bundle adjustment refines the focal length and distortion (default: on, off"
        " with --camera-params)",
    )
    p.add_argument(
        "--export-features",
        action="store_true",
        help="also write DIR/features.npz: keypoints (as the database holds them, refined with"
        " --refine-keypoints), scores, descriptors, raw matches and those the database got",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    arguments.add_upsample(p)
    arguments.add_any_scale(p)


def _numbers(text: str) -> tuple[float, ...]:
    """``P1,P2,...`` as floats (``--camera-params``)."""
    try:
        return tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}"
        ) from None


def check_out(out: pathlib.Path) -> None:
    """ValueError unless ``out`` is new, an empty folder or an earlier reconstruct output."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    entries = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    others = [name for name in entries if name not in OUTPUTS]
    if others or (entries and "summary.json" not in entries):
        example = (others or entries)[0]
        raise ValueError(
            f"--out {out} holds {len(entries)} entries (e.g. {example}) and is not a reconstruct"
            " output (no summary.json); give a new or empty folder"
        )


def _image_files(folder: pathlib.Path) -> list[pathlib.Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) < 2:
        raise ValueError(
            f"{folder}: structure from motion needs two images or more, found {len(files)}"
            f" ({'/'.join(IMAGE_SUFFIXES)} files)"
        )
    return files


def _photos(folder: pathlib.Path, skipped: list[str]):
    """(name, RGB image) of each readable photo; unreadable ones are skipped with a warning."""
    for path in _image_files(folder):
        try:
            yield path.name, read_image(path)
        except (ValueError, OSError) as err:
            skipped.append(str(err))
            log.warning("skipping %s", err)


def _frames(video_path: pathlib.Path, every: int, image_dir: pathlib.Path):
    """(name, RGB frame) of every ``every``-th frame, each written as a PNG into ``image_dir``."""
    import cv2

    from usp_jax.inference import video

    image_dir.mkdir()
    for index, frame in enumerate(video.open_source(str(video_path)).frames):
        if index % every == 0:
            name = f"frame{index:06d}.png"
            if not cv2.imwrite(str(image_dir / name), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)):
                raise OSError(f"cannot write {image_dir / name}")
            yield name, frame


def _detect(detector, named_images, bar) -> tuple[list[str], list, tuple[int, int]]:
    """Names and features of the images, detected one by one under ``bar``; ValueError at the
    first image whose size differs from the first's, or when fewer than two are left."""
    names, features, size = [], [], None
    for name, image in named_images:
        if names:
            sfm.check_sizes([names[0], name], [size, image.shape[:2]])
        names.append(name)
        size = size or image.shape[:2]
        features.append(detector.detect(image))
        bar.update()
    return names, features, sfm.check_sizes(names, [size] * len(names))


class _Greys:
    """The grey images ``[H, W]`` of ``names`` in ``folder``, read when indexed, the last 16
    kept: a video's frames would not all fit in memory, and refinement reads them pair by pair."""

    def __init__(self, folder: pathlib.Path, names: list[str]):
        self.folder, self.names = folder, names
        self.read = lru_cache(maxsize=16)(self._read)

    def _read(self, index: int):
        return grey(read_image(self.folder / self.names[index]))

    def __getitem__(self, index: int):
        return self.read(int(index))

    def __len__(self) -> int:
        return len(self.names)


def _refine(args, image_dir, names, features, pairs, matches, summary) -> tuple[list, list]:
    """(features, matches) for COLMAP: refined and settled (``--refine-keypoints``), timed and
    counted into ``summary``; as given without the option."""
    from tqdm import tqdm

    if not args.refine_keypoints:
        return features, matches
    start = time.perf_counter()
    bar = lambda p: tqdm(p, desc="refine", unit="image", disable=args.no_progress, leave=False)
    features, matches, summary["refinement"] = sfm.refine_keypoints(
        _Greys(image_dir, names), features, pairs, matches, progress=bar
    )
    summary["seconds"]["refine"] = time.perf_counter() - start
    return features, matches


def _detector(args):
    if not (getattr(args, "weights", None) or getattr(args, "checkpoint", None)):
        args.weights = WEIGHTS
    return arguments.load_detector(args, top_n=args.top, max_side=args.max_side, refine=True)


def _stages(args, detector, work: pathlib.Path, source: pathlib.Path, summary: dict) -> list:
    """Every stage into ``work``, timed into ``summary``; the models, largest first."""
    from tqdm import tqdm

    seconds, skipped = summary["seconds"], summary["skipped"]
    video = not source.is_dir()
    image_dir = work / "images" if video else source.absolute()
    named = _frames(source, args.every, image_dir) if video else _photos(source, skipped)
    quiet = args.no_progress
    start = time.perf_counter()
    with tqdm(desc="detect", unit="image", disable=quiet, leave=False) as bar:
        names, features, (height, width) = _detect(detector, named, bar)
    seconds["detect"] = time.perf_counter() - start
    pairs = sfm.image_pairs(len(names), args.window if video else None)
    start = time.perf_counter()
    matches = sfm.match_pairs(
        features, pairs, lambda p: tqdm(p, desc="match", unit="pair", disable=quiet, leave=False)
    )
    seconds["match"] = time.perf_counter() - start
    start = time.perf_counter()
    kept = sfm.fundamental_inliers(features, pairs, matches, args.epipolar or None)
    seconds["filter"] = time.perf_counter() - start
    summary.update(
        images=len(names),
        size=[width, height],
        pairs=len(pairs),
        keypoints=int(sum(len(f.keypoints) for f in features)),
        matches=int(sum(len(m) for m in matches)),
        epipolar_matches=int(sum(len(m) for m in kept)),
    )
    features, kept = _refine(args, image_dir, names, features, pairs, kept, summary)
    if args.export_features:
        sfm.export_features(work / "features.npz", names, features, pairs, matches, kept)
    start = time.perf_counter()
    database = work / "database.db"
    with tqdm(total=2, desc="database, verify", disable=quiet, leave=False) as bar:
        sfm.write_database(database, image_dir, names, features, pairs, kept, args.camera)
        bar.update()
        sfm.verify(database)
        bar.update()
    seconds["verify"] = time.perf_counter() - start
    summary["verified_pairs"] = sfm.verified_pairs(database)
    start = time.perf_counter()
    with tqdm(total=len(names), desc="map", unit="image", disable=quiet, leave=False) as bar:
        fixed = not args.refine_intrinsics
        # The count, not a step: a second mapper run (COLMAP's own start) counts again.
        shown = lambda count: bar.update(count - bar.n)
        models = sfm.map_images(database, image_dir, work / "sparse", shown, fixed)
    seconds["map"] = time.perf_counter() - start
    return models


def _finish(work: pathlib.Path, out: pathlib.Path, models: list, summary: dict) -> None:
    """The figures and summary into ``work``, then ``work`` renamed to ``out``."""
    summary["models"] = [sfm.model_summary(model) for model in models]
    if models:  # the camera as bundle adjustment left it (COLMAP's order and convention)
        summary["camera"]["found"] = sfm.camera_params(models[0])
    summary.update(summary["models"][0] if models else {})
    if models:
        models[0].export_PLY(str(work / "points.ply"))
        sfm.top_view(models[0], work / "cameras.png")
    (work / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    if out.exists():
        shutil.rmtree(out)  # empty, or an earlier reconstruct output (check_out)
    os.replace(work, out)


def run(args) -> int:
    """The command: checks, stages, outputs and the one-line result."""
    source = pathlib.Path(args.images).expanduser()
    out = pathlib.Path(args.out).expanduser().absolute()
    pycolmap = sfm.load_pycolmap()
    if not source.exists():
        raise FileNotFoundError(f"{args.images} does not exist (a folder of photos or a video)")
    check_out(out)
    args.camera = sfm.check_camera(args.camera_model, args.camera_params)
    if args.refine_intrinsics is None:  # a known camera is a calibrated one
        args.refine_intrinsics = not args.camera.params
    if not (args.refine_intrinsics or args.camera.params):
        raise ValueError("--no-refine-intrinsics needs the camera: give --camera-params")
    if not args.verbose:
        pycolmap.logging.minloglevel = 3  # its failures come back as our one line
    detector = _detector(args)
    summary = {"command": "reconstruct", "source": str(args.images), "seconds": {}, "skipped": []}
    summary["detector"] = {"weights": args.weights or args.checkpoint, "top": args.top}
    summary["refine_keypoints"] = args.refine_keypoints
    summary["epipolar"] = args.epipolar
    summary["camera"] = {"model": args.camera.model, "params": list(args.camera.params)}
    summary["camera"]["refined"] = args.refine_intrinsics
    out.parent.mkdir(parents=True, exist_ok=True)
    work = out.with_name(f".{out.name}.partial")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    try:
        start = time.perf_counter()
        models = _stages(args, detector, work, source, summary)
        summary["seconds"]["total"] = time.perf_counter() - start
        _finish(work, out, models, summary)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not models:
        raise ValueError(
            f"no model found: no image pair of {summary['images']} had enough verified matches"
            f" ({summary['verified_pairs']} verified pairs) to start one; wrote {out}/summary.json"
        )
    print(
        f"{args.images}: {summary['registered_images']} of {summary['images']} images registered,"
        f" {summary['points']} points (mean track {summary['mean_track_length']:.2f}, reprojection"
        f" error {summary['mean_reprojection_error']:.2f} px), {len(models)} model(s) in"
        f" {summary['seconds']['total']:.0f} s; wrote {out}",
        file=sys.stdout,
    )
    return 0
