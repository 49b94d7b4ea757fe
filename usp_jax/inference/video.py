"""Video in and out for the tracker: frames from a video file, a folder of frames or a camera, and
tracked frames drawn into an annotated video or a PNG strip.

Every source is checked when it is opened (its first frame is read at once), so a source with
no frame fails before any output exists; an output is written under a temporary name beside its
path and renamed only when it is complete, so a failed run leaves nothing half-made.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Iterator
from typing import NamedTuple

import cv2
import numpy as np

from usp_jax.inference.images import IMAGE_SUFFIXES, read_image

#: Frames per second of an output when the source does not say (a folder, some cameras).
DEFAULT_FPS = 25.0
#: A PNG strip shows at most this many frames, spread over the run, each this many px high.
STRIP_FRAMES, STRIP_HEIGHT = 8, 240
#: Video containers ``--out`` writes, with their codec (MJPG plays everywhere; mp4v in .mp4).
CODECS = {".avi": "MJPG", ".mp4": "mp4v"}


class Source(NamedTuple):
    """frames: uint8 ``[H, W, 3]`` RGB, read as they are consumed; fps: the source's rate;
    count: its number of frames where known (None for a camera)."""

    frames: Iterator[np.ndarray]
    fps: float
    count: int | None


def open_source(source: str, max_side: int = 0) -> Source:
    """A video file, a folder of frames (image files in name order) or a camera index ("0").

    ``max_side`` > 0 shrinks frames longer than that on their longer side (``INTER_AREA``).
    Raises FileNotFoundError for a missing path and ValueError for a camera that does not open,
    a folder with no image files or a video with no readable frame.
    """
    from usp_jax.inference.detector import check_max_side

    max_side = check_max_side(max_side)
    path = pathlib.Path(source).expanduser()
    if source.isdigit() and not path.exists():
        # OpenCV warns on stderr for each backend that fails; the error below says it once.
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            capture = cv2.VideoCapture(int(source))
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not capture.isOpened():
            raise ValueError(f"camera {source} cannot be opened (no such camera, or it is busy)")
        return _from_capture(capture, f"camera {source}", None, max_side)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ValueError(
                f"{source}: folder has no frames (no {'/'.join(IMAGE_SUFFIXES)} files)"
            )
        frames = (_shrink(read_image(p), max_side) for p in files)
        return Source(frames, DEFAULT_FPS, len(files))
    if not path.is_file():
        raise FileNotFoundError(
            f"{source} does not exist (a video file, a folder or a camera index)"
        )
    capture = cv2.VideoCapture(str(path))
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    return _from_capture(capture, str(source), max(count, 1), max_side)


def _from_capture(capture: cv2.VideoCapture, name: str, count: int | None, max_side: int):
    ok, first = capture.read() if capture.isOpened() else (False, None)
    if not ok or first is None:
        capture.release()
        raise ValueError(f"{name}: no frame can be read (empty, or not a video OpenCV decodes)")
    fps = capture.get(cv2.CAP_PROP_FPS)

    def frames() -> Iterator[np.ndarray]:
        frame = first
        try:
            while frame is not None:
                yield _shrink(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB), max_side)
                ok, frame = capture.read()
                frame = frame if ok else None
        finally:
            capture.release()

    return Source(frames(), fps if 0 < fps < 1000 else DEFAULT_FPS, count)


def _shrink(frame: np.ndarray, max_side: int) -> np.ndarray:
    height, width = frame.shape[:2]
    if max_side <= 0 or max(height, width) <= max_side:
        return frame
    scale = max_side / max(height, width)
    size = (max(round(width * scale), 8), max(round(height * scale), 8))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


def check_output(path: str | pathlib.Path) -> None:
    """Raises ValueError unless ``path`` names a video container of ``CODECS`` or a ``.png``."""
    suffix = pathlib.Path(path).suffix.lower()
    if suffix not in (*CODECS, ".png"):
        raise ValueError(
            f"--out {path}: give a {', '.join(CODECS)} video or a .png strip, not {suffix!r}"
        )


def partial_path(path: pathlib.Path) -> pathlib.Path:
    """Where ``path`` is written until it is complete: a hidden name beside it, same suffix."""
    return path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")


class Annotator:
    """Draws tracked frames: each track's last ``trail`` positions as a line in the track's
    colour, a point seen for the first time as a grey dot, and the frame's numbers on top."""

    def __init__(self, trail: int = 10):
        self.trail = trail
        self.history: dict[int, list[tuple[int, int]]] = {}
        hues = np.arange(0, 180, 180 / 64, dtype=np.float32).astype(np.uint8)
        hsv = np.stack([hues, np.full(64, 255, np.uint8), np.full(64, 255, np.uint8)], -1)
        self.palette = cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0].tolist()

    def __call__(self, frame: np.ndarray, result) -> np.ndarray:
        """``frame`` (uint8 [H, W, 3] RGB) with ``result`` (a ``TrackedFrame``) drawn on a copy."""
        image = np.ascontiguousarray(frame).copy()
        history = {}
        for (x, y), track in zip(result.points.tolist(), result.track_ids.tolist()):
            trail = self.history.get(track, []) + [(round(x), round(y))]
            history[track] = trail[-self.trail :]
            if len(trail) == 1:
                cv2.circle(image, trail[0], 1, (160, 160, 160), -1)
                continue
            colour = self.palette[track % len(self.palette)]
            cv2.polylines(image, [np.array(history[track], np.int32)], False, colour, 1)
            cv2.circle(image, trail[-1], 2, colour, -1)
        self.history = history
        text = (
            f"frame {result.index}: {int(result.inliers.sum())} inliers,"
            f" {result.keyframe_inliers} to keyframe {result.keyframe}, {result.ms:.0f} ms"
            + (", keyframe" if result.is_keyframe else "")
        )
        for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(image, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, width)
        return image


class AnnotatedOutput:
    """``--out``: annotated frames into a video (``CODECS``) or a PNG strip of up to
    ``STRIP_FRAMES`` frames spread over the run. A context manager: the file appears under its
    name only when the block ends without an error; otherwise the partial file is removed."""

    def __init__(self, path: str | pathlib.Path, fps: float):
        check_output(path)
        self.path = pathlib.Path(path).expanduser()
        self.partial = partial_path(self.path)
        self.fps = fps
        self.writer: cv2.VideoWriter | None = None
        self.strip: list[np.ndarray] = []
        self.stride, self.seen = 1, 0

    def write(self, image: np.ndarray) -> None:
        """Adds one annotated uint8 [H, W, 3] RGB frame."""
        if self.path.suffix.lower() == ".png":
            # Keep every stride-th frame; when twice the strip's frames are kept, keep every
            # other one and double the stride: the strip spans the run without knowing its length.
            if self.seen % self.stride == 0:
                self.strip.append(image)
                if len(self.strip) == 2 * STRIP_FRAMES:
                    self.strip, self.stride = self.strip[::2], 2 * self.stride
            self.seen += 1
            return
        if self.writer is None:
            fourcc = cv2.VideoWriter_fourcc(*CODECS[self.path.suffix.lower()])
            size = (image.shape[1], image.shape[0])
            self.writer = cv2.VideoWriter(str(self.partial), fourcc, self.fps, size)
            if not self.writer.isOpened():
                raise ValueError(f"--out {self.path}: OpenCV cannot write this video")
        self.writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))

    def _finish(self) -> None:
        if self.writer is not None:
            self.writer.release()
        elif self.strip:
            step = -(-len(self.strip) // STRIP_FRAMES)
            height = min(STRIP_HEIGHT, self.strip[0].shape[0])
            width = round(self.strip[0].shape[1] * height / self.strip[0].shape[0])
            row = np.hstack(
                [
                    cv2.resize(f, (width, height), interpolation=cv2.INTER_AREA)
                    for f in self.strip[::step]
                ]
            )
            if not cv2.imwrite(str(self.partial), cv2.cvtColor(row, cv2.COLOR_RGB2BGR)):
                raise ValueError(f"--out {self.path}: OpenCV cannot write this PNG")
        else:
            raise ValueError(f"--out {self.path}: no frame was tracked")
        os.replace(self.partial, self.path)

    def __enter__(self) -> AnnotatedOutput:
        return self

    def __exit__(self, kind, error, trace) -> None:
        try:
            if kind is None:
                self._finish()
        finally:
            if self.writer is not None:
                self.writer.release()
            self.partial.unlink(missing_ok=True)
