"""``usp-jax track SOURCE``: keypoint tracks through a video file, a folder of frames or a camera
(``inference.tracking``), with the shipped network or, through the same tracker, OpenCV's ORB,
AKAZE and SIFT or XFeat (``--method``).

Every output is checked before the first frame and written only when the run is complete
(``--out`` under a temporary name, renamed at the end; ``--json``, the ``.npz`` of descriptors and
scores beside it, and ``--tracks`` at the end); a failure on the way leaves none of them. Fewer
than two tracked frames is an error; a camera that does not move is a warning (its fundamental
matrix verifies nothing). Ctrl-C ends the run as the end of the video would.

``--any-rotation`` is not offered: the tracker matches each frame to the previous frame and to a
recent keyframe, between which a camera turns a few degrees at most, within what the upright
network matches; turning every frame back would add two detections per frame for no gain. A
camera that rolls fast is better served by ``--weights rotation``.

The network's defaults are the video ones (``tracking.default_detector``): ``--weights
distilled``, detecting on a copy of each frame at most ``--network-side 480`` px long, its
matches to the previous frame refined (``--refine-matches``: NCC peak and affine Lucas-Kanade
polish, ``tracking.TrackingConfig``): the most accurate relative poses within SIFT's time per
frame on rendered rooms and on footage (``tracking.VIDEO_SIDE``), because the package default, ``paper`` at
full size, takes ~6x SIFT's time per frame. The peers (``--method``) run as they are unless
``--refine-matches`` is given. The network's own sub-pixel keypoint refinement stays off,
whatever the weights: on footage it adds time and no inliers.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import pathlib
import statistics
import sys

import numpy as np

from usp_jax.cli import arguments, outputs
from usp_jax.inference import tracking, video
from usp_jax.inference.detector import MAX_SIDE
from usp_jax.inference.tracking import VIDEO_SIDE, VIDEO_WEIGHTS

#: ``--method`` names: the network, then the peers that run through the same tracker.
METHODS = ("usp", "orb", "akaze", "sift", "xfeat")


def add_parser(subparsers) -> None:
    """The ``track`` subcommand's options (``cli.parser`` calls this)."""
    p = subparsers.add_parser("track", help="keypoint tracks through a video, folder or camera")
    p.add_argument("source", help="a video file, a folder of frames (name order) or a camera index")
    arguments.add_checkpoint(
        p, default=VIDEO_WEIGHTS, why="the fast network taught by paper: real time on a CPU"
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        default="usp",
        help="the detector: usp (the network, default), or orb, akaze, sift or xfeat (where its"
        " package is installed) through the same tracker, for comparison",
    )
    p.add_argument(
        "--top", type=arguments.positive, default=1000, help="points per frame (default 1000)"
    )
    arguments.add_nms_radius(p, 4.0, "the network's NMS radius in px (default 4: spread points)")
    arguments.add_max_side(
        p,
        f"shrink frames longer than this first, every method alike (default {MAX_SIDE}; 0: never)",
    )
    arguments.add_max_side(
        p,
        f"the network detects on a copy of each frame at most this long, its points mapped"
        f" back to the frame's pixels (default {VIDEO_SIDE}; 0: the frame itself)",
        flag="--network-side",
        default=None,
    )
    p.add_argument(
        "--every", type=arguments.positive, default=1, metavar="N", help="track every N-th frame"
    )
    p.add_argument(
        "--max-frames",
        type=arguments.positive,
        metavar="N",
        help="stop after N tracked frames (Ctrl-C also ends a run, keeping its outputs)",
    )
    p.add_argument(
        "--planar",
        action="store_true",
        help="verify matches with a homography (a planar scene, a camera that only turns)"
        " instead of the fundamental matrix",
    )
    p.add_argument(
        "--refine-matches",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="move each match's point to the NCC peak of the previous frame's patch, polished by"
        f" {tracking.AFFINE_STEPS} affine Lucas-Kanade steps, before verification (default: on"
        " for --method usp, off for the peers)",
    )
    p.add_argument(
        "--json",
        help="one record per frame: index, points, track ids, matches, inliers, ms; beside it,"
        " NAME.npz holds every frame's points, scores, descriptors and track ids"
        " (tracking.load_features reads it)",
    )
    p.add_argument(
        "--tracks", metavar="FILE", help="CSV track,frame,x,y of every track seen in 2+ frames"
    )
    p.add_argument(
        "--out", help="annotated video (.avi: MJPG, .mp4: mp4v) or, ending in .png, a frame strip"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    arguments.add_upsample(p)
    arguments.add_any_scale(p)


def _method(args):
    """The detector ``--method`` names, with ``--top`` points per frame."""
    if args.method != "usp":
        used = [f"--{n}" for n in ("weights", "checkpoint") if getattr(args, n, None)]
        used += ["--any-scale"] if getattr(args, "any_scale", False) else []
        used += ["--network-side"] if getattr(args, "network_side", None) is not None else []
        if used:
            raise ValueError(f"{' and '.join(used)} only apply to --method usp")
        # XFeat without its packages raises a ValueError saying so.
        from usp_jax.inference.methods import baseline_method

        return baseline_method(args.method, args.top)
    side = getattr(args, "network_side", None)
    options = {
        "top_n": args.top,
        "nms_radius": args.nms,
        "max_side": VIDEO_SIDE if side is None else side,
        # As the video default (tracking.default_detector): on footage it adds time, no inliers.
        "refine": False,
    }
    if not (getattr(args, "weights", None) or getattr(args, "checkpoint", None)):
        args = argparse.Namespace(**{**vars(args), "weights": VIDEO_WEIGHTS})
    if getattr(args, "any_scale", False):
        options["any_scale"] = True
    return arguments.load_detector(args, **options)


def _config(args) -> tracking.TrackingConfig:
    """The tracker's settings: ``--planar``, ``--every``, and ``--refine-matches`` (unset: on
    for the network, off for the peers)."""
    refine = getattr(args, "refine_matches", None)
    return tracking.TrackingConfig(
        planar=args.planar,
        every=args.every,
        refine_matches=args.method == "usp" if refine is None else refine,
    )


def features_path(json_path: str) -> pathlib.Path:
    """The ``.npz`` of descriptors and scores beside ``--json`` (same name, suffix ``.npz``)."""
    path = pathlib.Path(json_path).expanduser()
    if path.suffix.lower() == ".npz":
        raise ValueError(
            f"--json {json_path}: the descriptors go to the .npz beside it; name the"
            " JSON file .json"
        )
    return path.with_suffix(".npz")


def _save_features(path: pathlib.Path, results: list[tracking.TrackedFrame]) -> None:
    def write(partial: pathlib.Path) -> None:
        with open(partial, "wb") as file:
            tracking.save_features(file, results)

    outputs.write_atomic(path, write)


def _record(result: tracking.TrackedFrame) -> dict:
    """One frame's ``--json`` record."""
    return {
        "index": result.index,
        "points": np.round(result.points, 2).tolist(),
        "track_ids": result.track_ids.tolist(),
        "matches": result.matches.tolist(),
        "inliers": result.inliers.tolist(),
        "keyframe": result.keyframe,
        "keyframe_inliers": result.keyframe_inliers,
        "is_keyframe": result.is_keyframe,
        "ms": round(result.ms, 2),
    }


def _tracks_csv(results: list[tracking.TrackedFrame]) -> str:
    """``--tracks``: ``track,frame,x,y`` rows of every track seen in two frames or more."""
    lengths = tracking.track_lengths(results)
    ids = np.unique(np.concatenate([r.track_ids for r in results]))
    kept = set(ids[lengths >= 2].tolist())
    rows = sorted(
        (track, r.index, x, y)
        for r in results
        for track, (x, y) in zip(r.track_ids.tolist(), r.points.tolist())
        if track in kept
    )
    return "track,frame,x,y\n" + "".join(f"{t},{i},{x:.2f},{y:.2f}\n" for t, i, x, y in rows)


def summary(results: list[tracking.TrackedFrame]) -> dict:
    """The run's numbers: frames, mean inliers to the previous frame, keyframes, median length
    of the tracks seen in two frames or more, mean ms per frame (the first frame, which compiles
    the network, left out when there are others) and frames/s."""
    lengths = tracking.track_lengths(results)
    times = [r.ms for r in results[1:]] or [r.ms for r in results]
    inliers = [int(r.inliers.sum()) for r in results[1:]]
    return {
        "frames": len(results),
        "mean_inliers": statistics.fmean(inliers) if inliers else 0.0,
        "keyframes": sum(r.is_keyframe for r in results),
        "tracks": int(np.sum(lengths >= 2)),
        "median_track_length": float(np.median(lengths[lengths >= 2])) if any(lengths >= 2) else 0,
        "ms_per_frame": statistics.fmean(times) if times else 0.0,
        "frames_per_s": 1e3 / statistics.fmean(times) if times else 0.0,
        "camera_motion_px": tracking.camera_motion(results),
    }


def _print_summary(args, numbers: dict, width: int, height: int) -> None:
    """The run's one line of numbers (:func:`summary`'s)."""
    print(
        f"{args.source}: {numbers['frames']} frames tracked with {args.method} at"
        f" {width}x{height}; {numbers['mean_inliers']:.0f} inliers per frame to the previous"
        f" ({'homography' if args.planar else 'fundamental matrix'}),"
        f" {numbers['keyframes']} keyframes, {numbers['tracks']} tracks seen twice or more"
        f" (median {numbers['median_track_length']:g} frames),"
        f" {numbers['ms_per_frame']:.0f} ms per frame ({numbers['frames_per_s']:.1f} frames/s)"
    )


def _warn_if_static(numbers: dict, planar: bool) -> None:
    """One line on stderr when the camera did not move: every still point then fits a
    fundamental matrix, so its inliers count still points, not verified matches."""
    motion = numbers["camera_motion_px"]
    if not planar and motion is not None and motion < tracking.STATIC_MOTION:
        print(
            f"usp-jax track: warning: the camera does not move (inliers move {motion:.2f} px per"
            " frame, median): on a static view any point fits a fundamental matrix, so the"
            " inliers do not verify the matches; --planar verifies with a homography instead",
            file=sys.stderr,
        )


def run(args) -> int:
    """The command: every output checked, the frames tracked, the outputs written at the end."""
    from tqdm import tqdm

    for path, what in ((args.out, "--out"), (args.json, "--json"), (args.tracks, "--tracks")):
        outputs.check_output_file(path, what)
    # libav's complaints about a stream it decodes anyway (AV_LOG_QUIET), unless the user asks.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    if args.out:
        video.check_output(args.out)
    features = features_path(args.json) if args.json else None
    method = _method(args)
    source = video.open_source(args.source, args.max_side)
    config = _config(args)
    current = {}

    def remember(frames):
        # The tracker takes the frames lazily, so the last one taken is the one it yields for.
        for frame in frames:
            current["frame"] = frame
            yield frame

    frames = remember(source.frames)
    total = None if source.count is None else -(-source.count // args.every)
    if args.max_frames:
        total = args.max_frames if total is None else min(total, args.max_frames)
    results, annotate = [], video.Annotator()
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(video.AnnotatedOutput(args.out, source.fps)) if args.out else None
        tracked = itertools.islice(tracking.track(frames, method, config), args.max_frames or None)
        bar = stack.enter_context(
            tqdm(
                tracked,
                total=total,
                desc=f"tracking {pathlib.Path(str(args.source)).name} ({args.method})",
                unit="frame",
                disable=args.no_progress,
                leave=False,
            )
        )
        try:
            for result in bar:
                results.append(result)
                bar.set_postfix(inliers=int(result.inliers.sum()), refresh=False)
                if out is not None:
                    out.write(annotate(current["frame"], result))
        except KeyboardInterrupt:
            pass  # the end of the run, as the end of the video would be
        if len(results) < 2:
            raise ValueError(
                f"{args.source}: {len(results) or 'no'} frame{'s' * (len(results) != 1)} tracked;"
                " tracking needs two or more (a video of one frame, or --every or --max-frames"
                " leaving one)"
            )
        numbers = summary(results)
    height, width = current["frame"].shape[:2]
    _print_summary(args, numbers, width, height)
    _warn_if_static(numbers, args.planar)
    if args.out:
        print(f"wrote {args.out}")
    if args.json:
        document = {
            "source": args.source,
            "method": args.method,
            "size": [width, height],
            "geometry": "homography" if args.planar else "fundamental",
            "summary": numbers,
            "frames": [_record(r) for r in results],
        }
        _save_features(features, results)
        outputs.write_text(args.json, json.dumps({**document, "features": features.name}))
        print(f"wrote {args.json}\nwrote {features}")
    if args.tracks:
        outputs.write_text(args.tracks, _tracks_csv(results))
        print(f"wrote {args.tracks}")
    return 0
