"""Figures in the style of the paper: detections on two views (Figure 7), matches with the true
and estimated image borders (Figure 8), and histograms (Figures 4-5: point-pair distances,
scores, relative x positions with and without the uniform loss).

Figures are drawn on matplotlib's Agg canvas without pyplot, so importing this module changes
no global backend and works on machines without a display. Every function writes one PNG of
``figsize * dpi`` pixels and returns its path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import LogFormatter

from usp_jax.evaluation.metrics import corner_error, image_corners, project_points, shared_view_mask

DPI = 120
# Colours of the paper's figures: image-1 evidence green, image-2 / estimated evidence blue.
GREEN = "#2ca02c"
BLUE = "#1f77b4"
MATCH = "#ffbf00"
#: Width of one image panel, and size of a histogram figure, in inches.
PANEL_INCHES = 5.0
HISTOGRAM_INCHES = (7.0, 4.5)


def figure_path(path: str | Path) -> Path:
    """The file a figure saved as ``path`` lands in: matplotlib adds ``.png`` to a name without
    a suffix. Raises ValueError, before any work, for a suffix matplotlib cannot write."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(path)
    if not path.suffix:
        return path.with_name(path.name + ".png")
    if path.suffix[1:].lower() not in FigureCanvasAgg.get_supported_filetypes():
        raise ValueError(f"{path}: figures cannot be written as {path.suffix}; use .png or .pdf")
    return path


def _save(figure: Figure, path: str | Path) -> Path:
    """Saves ``figure``; returns the path written (:func:`figure_path`)."""
    path = figure_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=DPI)
    return path


def _show(axes, image: np.ndarray, title: str) -> None:
    axes.imshow(image, cmap="gray" if image.ndim == 2 else None, interpolation="nearest")
    axes.set_title(title)
    axes.set_axis_off()


def _keep_view(axes, shape: tuple[int, ...]) -> None:
    """Axis limits back on the image extent: points on the far pixel edge (x up to W) or warped
    borders outside it would otherwise widen the limits and shrink that panel."""
    axes.set_xlim(-0.5, shape[1] - 0.5)
    axes.set_ylim(shape[0] - 0.5, -0.5)


def _border(homography: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Image border (corners in drawing order, closed) warped by ``homography``, [5, 2]."""
    corners = image_corners(shape)[[0, 2, 3, 1, 0]]
    return project_points(corners, homography)


def plot_keypoints(
    image1: np.ndarray,
    keypoints1: np.ndarray,
    image2: np.ndarray,
    keypoints2: np.ndarray,
    path: str | Path,
    homography: np.ndarray | None = None,
    title: str = "Interest points",
) -> Path:
    """Detections on a reference and a target image side by side, as the paper's Figure 7:
    image-1 points are green crosses in image 1 and, warped by ``homography`` (image 1 -> 2),
    in image 2; image-2 points are blue squares in image 2 only.

    Images are uint8 ``[H, W, 3]`` (or ``[H, W]``); keypoints ``[N, 2]`` (x, y).
    """
    height = max(image1.shape[0], image2.shape[0])
    aspect = (image1.shape[1] + image2.shape[1]) / height
    figure = Figure(
        figsize=(2 * PANEL_INCHES, 2 * PANEL_INCHES / aspect + 1.0), layout="constrained"
    )
    left, right = figure.subplots(1, 2)
    cross = dict(marker="x", color=GREEN, s=18, linewidths=1.0)
    _show(left, image1, f"reference: {len(keypoints1)} points")
    left.scatter(*np.asarray(keypoints1).T, **cross)
    _show(right, image2, f"target: {len(keypoints2)} points")
    handles = [Line2D([], [], linestyle="", marker="x", color=GREEN, label="reference points")]
    if homography is not None:
        inside = shared_view_mask(keypoints1, homography, image2.shape[:2])
        right.scatter(*project_points(np.asarray(keypoints1)[inside], homography).T, **cross)
        handles[0].set_label("reference points (warped by H)")
    right.scatter(
        *np.asarray(keypoints2).T,
        marker="s",
        facecolors="none",
        edgecolors=BLUE,
        s=30,
        linewidths=1.0,
    )
    _keep_view(left, image1.shape)
    _keep_view(right, image2.shape)
    handles.append(
        Line2D(
            [],
            [],
            linestyle="",
            marker="s",
            markerfacecolor="none",
            color=BLUE,
            label="target points",
        )
    )
    figure.legend(handles=handles, loc="lower center", ncols=2, frameon=False)
    figure.suptitle(title)
    return _save(figure, path)


def plot_detections(image: np.ndarray, keypoints: np.ndarray, path: str | Path) -> Path:
    """The detections of one image (``usp-jax detect --out``): one panel, a green cross per
    keypoint, the count in the title. ``image`` uint8 ``[H, W, 3]`` or ``[H, W]``; ``keypoints``
    ``[N, 2]`` (x, y) in its pixels."""
    aspect = image.shape[1] / image.shape[0]
    figure = Figure(figsize=(PANEL_INCHES, PANEL_INCHES / aspect + 0.5), layout="constrained")
    axes = figure.subplots()
    _show(axes, image, f"{len(keypoints)} keypoints")
    axes.scatter(
        *np.asarray(keypoints, dtype=np.float64).reshape(-1, 2).T,
        marker="x",
        color=GREEN,
        s=18,
        linewidths=1.0,
    )
    _keep_view(axes, image.shape)
    return _save(figure, path)


def plot_matches(
    image1: np.ndarray,
    image2: np.ndarray,
    keypoints1: np.ndarray,
    keypoints2: np.ndarray,
    matches: np.ndarray,
    inliers: np.ndarray,
    true_homography: np.ndarray | None,
    estimated_homography: np.ndarray | None,
    path: str | Path,
    title: str = "Matches",
) -> Path:
    """RANSAC-filtered matches as the paper's Figure 8: the two images side by side, a line per
    inlier match, and image 1's border warped into image 2 by the true homography (green) and
    by the estimate (blue). ``matches`` [K, 2] and ``inliers`` [K] are what
    :func:`usp_jax.evaluation.match_and_estimate` returns. A None estimate draws no blue border;
    a None true homography (a pair with no ground truth) no green one, and the title gives the
    inlier count instead of the corner error.
    """
    (h1, w1), (h2, w2) = image1.shape[:2], image2.shape[:2]
    gap = max(w1, w2) // 40
    offset = w1 + gap
    canvas = np.full((max(h1, h2), offset + w2, 3), 255, dtype=np.uint8)
    canvas[:h1, :w1] = image1[..., None] if image1.ndim == 2 else image1
    canvas[:h2, offset:] = image2[..., None] if image2.ndim == 2 else image2
    aspect = canvas.shape[1] / canvas.shape[0]
    figure = Figure(
        figsize=(2 * PANEL_INCHES, 2 * PANEL_INCHES / aspect + 1.0), layout="constrained"
    )
    axes = figure.subplots()
    axes.imshow(canvas, interpolation="nearest")
    axes.set_axis_off()
    shift = np.array([offset, 0.0])
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)[np.asarray(inliers, dtype=bool)]
    starts = np.asarray(keypoints1, dtype=np.float64)[matches[:, 0]]
    ends = np.asarray(keypoints2, dtype=np.float64)[matches[:, 1]] + shift
    axes.add_collection(
        LineCollection(np.stack([starts, ends], axis=1), colors=MATCH, linewidths=0.7, alpha=0.8)
    )
    axes.scatter(*np.concatenate([starts, ends]).T, s=6, color=MATCH)
    handles = [Line2D([], [], color=MATCH, label=f"{len(matches)} inlier matches")]
    if true_homography is not None:
        true_border = _border(true_homography, (h1, w1)) + shift
        axes.plot(*true_border.T, color=GREEN, linewidth=2)
        handles.append(Line2D([], [], color=GREEN, linewidth=2, label="border, true H"))
    if estimated_homography is None:
        subtitle = "no homography estimated"
    else:
        axes.plot(
            *(_border(estimated_homography, (h1, w1)) + shift).T,
            color=BLUE,
            linewidth=2,
            linestyle="--",
        )
        handles.append(
            Line2D([], [], color=BLUE, linewidth=2, linestyle="--", label="border, estimated H")
        )
        if true_homography is None:
            subtitle = f"{len(matches)} of {len(inliers)} matches are inliers"
        else:
            error = corner_error(true_homography, estimated_homography, (h1, w1))
            subtitle = f"corner error {error:.2f} px"
    _keep_view(axes, canvas.shape)
    figure.legend(handles=handles, loc="lower center", ncols=len(handles), frameon=False)
    figure.suptitle(f"{title} ({subtitle})")
    return _save(figure, path)


def plot_histograms(
    values: dict[str, np.ndarray],
    path: str | Path,
    bins: int | np.ndarray = 50,
    xlabel: str = "",
    title: str = "",
    density: bool = False,
) -> Path:
    """Overlaid histograms, one per labelled array, as the paper's Figures 4-5 (e.g. point-pair
    distances d_k, scores, or relative x positions with and without the uniform loss).

    With an int ``bins`` every series shares the same edges over the joint range, so the bars
    line up. ``density`` normalises each series to unit area (compare series of unequal size).
    """
    arrays = {label: np.asarray(v, dtype=np.float64).ravel() for label, v in values.items()}
    finite = np.concatenate([a[np.isfinite(a)] for a in arrays.values()] or [np.zeros(0)])
    if np.ndim(bins) == 0 and finite.size:
        bins = np.histogram_bin_edges(finite, bins=bins)
    figure = Figure(figsize=HISTOGRAM_INCHES, layout="constrained")
    axes = figure.subplots()
    for i, (label, array) in enumerate(arrays.items()):
        data = array[np.isfinite(array)]
        style = dict(bins=bins, density=density, color=f"C{i}")
        axes.hist(
            data, histtype="stepfilled", alpha=0.35, label=f"{label} (n={data.size})", **style
        )
        axes.hist(data, histtype="step", linewidth=1.2, **style)
    axes.set_xlabel(xlabel)
    axes.set_ylabel("density" if density else "count")
    axes.set_title(title)
    axes.grid(alpha=0.3)
    if arrays:
        axes.legend()
    return _save(figure, path)


#: Panels of :func:`plot_training_curves`: title and the metrics.jsonl keys drawn in it.
CURVE_PANELS = (
    ("weighted loss terms (log)", ("loss/usp", "loss/uni_xy", "loss/desc", "loss/decorr")),
    ("point-pairs: mean d_k (px)", ("usp/mean_d",)),
    ("descriptor similarity", ("desc/sim_positive", "desc/sim_negative")),
    ("scores", ("pred/score_mean", "pred/score_std", "pred/score_position_r2")),
)


def plot_training_curves(
    rows: list[dict],
    path: str | Path,
    panels=CURVE_PANELS,
    smooth: int = 10,
    stage_starts: Sequence[float] = (),
) -> Path:
    """Training statistics against step, one panel per group of metrics (``metrics.jsonl`` rows
    as written by ``train.fit``). Each curve is a running mean over ``smooth`` logged rows, so
    the trend shows through batch noise; keys missing from the rows are skipped. A dashed line
    marks each step in ``stage_starts`` (where a run continued by ``--init`` began)."""
    steps = np.array([row["step"] for row in rows], dtype=np.float64)
    figure = Figure(figsize=(11.0, 7.0), layout="constrained")
    for axes, (title, keys) in zip(figure.subplots(2, 2).ravel(), panels):
        for key in keys:
            values = np.array([row.get(key, np.nan) for row in rows], dtype=np.float64)
            if not np.any(np.isfinite(values)):
                continue
            window = max(1, min(smooth, values.size))
            kernel = np.ones(window) / window
            smoothed = np.convolve(values, kernel, mode="valid")
            axes.plot(steps[window - 1 :], smoothed, label=key)
        if title.endswith("(log)"):
            axes.set_yscale("log")
        axes.set_title(title)
        axes.set_xlabel("step")
        axes.grid(alpha=0.3)
        if axes.lines:
            axes.legend(fontsize="small")
        for start in stage_starts:  # after the legend, which lists metrics only
            axes.axvline(start, color="0.5", linestyle="--", linewidth=0.8)
    return _save(figure, path)


def plot_example_pair(
    method, root: str | Path, out_dir: str | Path, res: tuple[int, int], top_k: int, nms: float
) -> Path:
    """Keypoints and matches (paper Figures 7-8) of ``method`` on the last (hardest) pair of the
    first viewpoint scene under ``root``, or of the first scene when there is none: the points
    and matches its HA comes from (NMS, shared-view filter, top-k). Writes
    ``METHOD_SCENE_1_K_keypoints.png`` and ``..._matches.png`` into ``out_dir``; returns the
    matches PNG's path."""
    from usp_jax.evaluation import protocol, sequences
    from usp_jax.evaluation.metrics import homography_matching

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = sequences.scan_sequences(root)
    first = next((f for f in files if f.split == "v"), files[0]).scene
    pair = sequences.read_pair([f for f in files if f.scene == first][-1])
    im1, im2, h = sequences.resize_pair(pair.image1, pair.image2, pair.homography, *res)
    f1, f2 = protocol.detect_both(method, im1, im2, nms)
    f1, f2, matching = homography_matching(
        f1, f2, h, im1.shape[:2], im2.shape[:2], top_k, method.norm
    )
    stem = f"{method.name}_{pair.scene}_1_{pair.index}"
    plot_keypoints(
        im1, f1.keypoints, im2, f2.keypoints, out_dir / f"{stem}_keypoints.png", homography=h
    )
    return plot_matches(
        im1,
        im2,
        f1.keypoints,
        f2.keypoints,
        matching.matches,
        matching.inliers,
        h,
        matching.homography,
        out_dir / f"{stem}_matches.png",
    )


def plot_speed_quality(points: Sequence[dict], path: str | Path) -> Path:
    """The speed/quality trade-off: images/s (log) against HA@3 (top row) and MS (bottom row),
    one column per image size. Each point is a dict with ``label``, ``size`` ("240x320"),
    ``images_per_s``, ``ha3``, ``ms`` and ``ours`` (learned networks in blue, the OpenCV
    baselines in grey), so a reader sees which methods are faster *and* better than which."""
    if not points:
        raise ValueError("no points to plot")
    sizes = list(dict.fromkeys(p["size"] for p in points))
    figure = Figure(figsize=(5.5 * len(sizes), 8.0), layout="constrained")
    grid = np.asarray(figure.subplots(2, len(sizes), squeeze=False))
    for column, size in enumerate(sizes):
        for row, (metric, name) in enumerate((("ha3", "HA@3"), ("ms", "MS"))):
            axes = grid[row, column]
            here = [p for p in points if p["size"] == size]
            span = np.ptp([p[metric] for p in here]) or 1.0
            placed: list[dict] = []  # Labelled right of their point, where nothing crowds them.
            for point in sorted(here, key=lambda p: p[metric]):
                colour = BLUE if point["ours"] else "0.45"
                axes.scatter(point["images_per_s"], point[metric], color=colour, zorder=3)
                # One network's weights share a speed: a label right of a point that another
                # label already sits beside (within 4% of the range) goes to the left instead.
                crowded = any(
                    abs(math.log(q["images_per_s"] / point["images_per_s"])) < 0.1
                    and abs(q[metric] - point[metric]) < 0.04 * span
                    for q in placed
                )
                if not crowded:
                    placed.append(point)
                axes.annotate(
                    point["label"],
                    (point["images_per_s"], point[metric]),
                    textcoords="offset points",
                    xytext=(-5, 4) if crowded else (5, 4),
                    ha="right" if crowded else "left",
                    fontsize="small",
                    color=colour,
                )
            axes.set_xscale("log")
            # Plain numbers on the log axis (its default writes 3x10^0 on short decades).
            axes.xaxis.set_major_formatter(LogFormatter(labelOnlyBase=False))
            axes.xaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))
            axes.set_xlabel("images/s (log)")
            axes.set_ylabel(name)
            axes.set_title(f"{name} against speed, {size}")
            axes.grid(alpha=0.3, which="both")
    return _save(figure, path)
