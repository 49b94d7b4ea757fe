"""Match-time sub-pixel refinement: each match's point in image 2 moved to where a grey patch of
image 1 around its point correlates best (template matching by normalised cross-correlation, the
classical step behind KLT-style trackers and photogrammetric least-squares matching).

For a match (p1, p2): the template is the ``(2 radius + 1)^2`` grey patch of image 1 centred on
p1, bilinearly sampled on the pixel grid (pixel centres at integers, ``core.model``'s
convention). Image 2 is searched at whole-pixel offsets ``-search..search`` in x and y around
``round(p2)`` (its patches read at whole pixels, so no interpolation there); the NCC of each
offset is the Pearson correlation of the template with that patch. A least-squares quadratic
over the 3 x 3 NCC values around the best offset gives its sub-pixel peak, and p2 moves there.
p1 anchors the template and stays where it is: its own localization error no longer enters the
match, only the correspondence of the two points does.

Optionally (``affine_steps`` > 0) the NCC peak is then polished by Gauss-Newton steps of an
affine Lucas-Kanade fit (:func:`affine_polish`): the template is matched under a translation and
a 2 x 2 linear map (the local view change between two views: a patch's scale, turn and shear),
its gain and bias normalised out. Translation-only NCC is biased by that distortion (about
0.3 px median on rendered rooms with views 10-30 degrees apart, benchmarks/bench_pose.py); the
affine fit removes most of it. A polish that fails (leaves the image, a singular system, a move
over a pixel from the NCC peak) keeps the NCC peak.

A match keeps its original p2 (``moved`` False) when: a point is not finite, the template or the
searched window leaves its image, the template is flat (no texture to correlate), the best NCC
is below ``min_ncc``, the best offset lies on the search border (the true peak may lie beyond
it), or the quadratic has no maximum within one pixel of the best offset.
"""

from __future__ import annotations

import numpy as np

#: Template half-size, pixels: an 11 x 11 patch.
RADIUS = 5
#: Search half-size, whole pixels around round(p2): 3 reaches points 2 px off.
SEARCH = 3
#: The least NCC of the best offset for a move.
MIN_NCC = 0.8
#: A template whose pixels' standard deviation is below this (grey levels) is flat.
FLAT_STD = 1e-3

# The least-squares quadratic a + b x + c y + d x^2 + e x y + f y^2 over the 3 x 3 grid
# (x, y in -1, 0, 1; row-major, y outer): coefficients = _QUADRATIC @ values.
_Y, _X = np.mgrid[-1:2, -1:2].reshape(2, 9).astype(np.float64)
_QUADRATIC = np.linalg.pinv(np.stack([np.ones(9), _X, _Y, _X**2, _X * _Y, _Y**2], axis=1))


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``image`` [H, W] at float positions x, y (any equal shape, all within [0, W-1] x
    [0, H-1]) by bilinear interpolation, float64."""
    height, width = image.shape
    x0 = np.clip(np.floor(x).astype(np.int64), 0, width - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, height - 2)
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _inside(points: np.ndarray, shape: tuple[int, int], margin: float) -> np.ndarray:
    """bool [M]: points [M, 2] finite and at least ``margin`` px from the outer pixel centres
    of an image of ``shape`` (H, W)."""
    finite = np.all(np.isfinite(points), axis=1)
    safe = np.where(finite[:, None], points, 0.0)
    x, y = safe[:, 0], safe[:, 1]
    height, width = shape
    return (
        finite
        & (x >= margin)
        & (y >= margin)
        & (x <= width - 1 - margin)
        & (y <= height - 1 - margin)
    )


def ncc_scores(
    grey1: np.ndarray,
    grey2: np.ndarray,
    points1: np.ndarray,
    centres2: np.ndarray,
    radius: int,
    search: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(NCC float64 ``[M, 2 search + 1, 2 search + 1]`` indexed [match, dy, dx], template
    standard deviation [M]) of the templates of image 1 around ``points1`` [M, 2] against
    image 2's patches centred on the whole pixels ``centres2`` int [M, 2] plus each offset.
    Every template and window must lie inside its image."""
    side = 2 * radius + 1
    grid = np.arange(-radius, radius + 1, dtype=np.float64)
    template = _bilinear(
        grey1,
        points1[:, 0, None, None] + grid[None, None, :],
        points1[:, 1, None, None] + grid[None, :, None],
    )  # [M, side, side]
    template -= template.mean(axis=(1, 2), keepdims=True)
    template_norm = np.sqrt(np.einsum("mij,mij->m", template, template))
    steps = np.arange(-(radius + search), radius + search + 1)
    region = _bilinear(
        grey2,
        centres2[:, 0, None, None] + steps[None, None, :],
        centres2[:, 1, None, None] + steps[None, :, None],
    )  # [M, span, span]
    windows = np.lib.stride_tricks.sliding_window_view(region, (side, side), axis=(1, 2))
    sums = np.einsum("muvij->muv", windows)
    squares = np.einsum("muvij,muvij->muv", windows, windows)
    window_var = np.maximum(squares - sums**2 / side**2, 0.0)
    product = np.einsum("mij,muvij->muv", template, windows)  # the template is zero-mean
    denominator = template_norm[:, None, None] * np.sqrt(window_var)
    ncc = np.where(denominator > 0, product / np.where(denominator > 0, denominator, 1.0), -1.0)
    return ncc, template_norm / side


def quadratic_peak(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(offset float64 [M, 2] (x, y), valid bool [M]): the maximum of the least-squares
    quadratic through 3 x 3 values [M, 3, 3] (indexed [y, x], centre at (0, 0)); valid where
    the quadratic has a maximum (negative definite) within one pixel in x and y."""
    a, b, c, d, e, f = _QUADRATIC @ values.reshape(-1, 9).T
    # Gradient zero: [2d e; e 2f] [x; y] = -[b; c].
    determinant = 4 * d * f - e * e
    safe = np.where(determinant > 0, determinant, 1.0)
    x = (-b * 2 * f + c * e) / safe
    y = (-c * 2 * d + b * e) / safe
    valid = (determinant > 0) & (d < 0) & (np.abs(x) <= 1) & (np.abs(y) <= 1)
    return np.stack([np.where(valid, x, 0.0), np.where(valid, y, 0.0)], axis=1), valid


def affine_polish(
    grey1: np.ndarray,
    grey2: np.ndarray,
    points1: np.ndarray,
    points2: np.ndarray,
    radius: int,
    steps: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(points float64 [K, 2], ok bool [K]): ``points2`` [K, 2] moved by ``steps`` Gauss-Newton
    steps of an affine Lucas-Kanade fit of image 1's template around ``points1`` [K, 2] (module
    docstring), grey images float64. Each step moves a point by at most half a pixel and its
    linear map by at most 0.1 per entry; ok is False where a warped window left image 2 or a
    result is not finite."""
    gy, gx = np.gradient(grey2)
    grid = np.arange(-radius, radius + 1, dtype=np.float64)
    ox, oy = np.meshgrid(grid, grid)  # [side, side], x along the row
    template = _bilinear(grey1, points1[:, 0, None, None] + ox, points1[:, 1, None, None] + oy)
    template -= template.mean(axis=(1, 2), keepdims=True)
    energy = np.maximum(np.einsum("mij,mij->m", template, template), 1e-12)
    points = np.array(points2, np.float64)
    linear = np.tile(np.eye(2), (len(points), 1, 1))
    height, width = grey2.shape
    ok = np.ones(len(points), bool)
    for _ in range(steps):
        x = points[:, 0, None, None] + linear[:, 0, 0, None, None] * ox
        x = x + linear[:, 0, 1, None, None] * oy
        y = points[:, 1, None, None] + linear[:, 1, 0, None, None] * ox
        y = y + linear[:, 1, 1, None, None] * oy
        ok &= (x.min(axis=(1, 2)) >= 0) & (x.max(axis=(1, 2)) <= width - 1)
        ok &= (y.min(axis=(1, 2)) >= 0) & (y.max(axis=(1, 2)) <= height - 1)
        x, y = np.clip(x, 0, width - 1), np.clip(y, 0, height - 1)
        window = _bilinear(grey2, x, y)
        window -= window.mean(axis=(1, 2), keepdims=True)
        ax, ay = _bilinear(gx, x, y), _bilinear(gy, x, y)
        columns = np.stack([ax, ay, ax * ox, ax * oy, ay * ox, ay * oy], axis=-1)
        columns = (columns - columns.mean(axis=(1, 2), keepdims=True)).reshape(len(points), -1, 6)
        gain = np.einsum("mij,mij->m", window, template) / energy
        residual = (gain[:, None, None] * template - window).reshape(len(points), -1)
        normal = np.einsum("mpi,mpj->mij", columns, columns) + 1e-6 * np.eye(6)
        step = np.linalg.solve(normal, np.einsum("mpi,mp->mi", columns, residual)[..., None])
        step = np.nan_to_num(step[..., 0], nan=0.0, posinf=0.0, neginf=0.0)
        points += np.clip(step[:, :2], -0.5, 0.5)
        linear += np.clip(step[:, 2:], -0.1, 0.1).reshape(-1, 2, 2)
    return points, ok & np.all(np.isfinite(points), axis=1)


def refine_matches(
    grey1: np.ndarray,
    grey2: np.ndarray,
    points1: np.ndarray,
    points2: np.ndarray,
    radius: int = RADIUS,
    search: int = SEARCH,
    min_ncc: float = MIN_NCC,
    affine_steps: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Matched points of image 2 moved to the sub-pixel NCC peak of image 1's patches (module
    docstring: the method and when a point stays).

    grey1: [H, W] and grey2: [H2, W2] grey images (float32, or any real dtype; e.g.
    ``cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)``). points1, points2: [M, 2] (x, y) pixel
    positions of the matches (row i of each is one match; M may be 0). radius: the template's
    half-size (a ``2 radius + 1`` square); search: whole pixels searched each way around p2;
    min_ncc: the least correlation for a move; affine_steps: Gauss-Newton steps of the affine
    polish after the NCC peak (0: none).

    Returns (points2_refined float32 [M, 2], moved bool [M]); rows not moved hold points2 as
    given.
    """
    grey1 = np.asarray(grey1, np.float64)
    grey2 = np.asarray(grey2, np.float64)
    points1 = np.asarray(points1, np.float64).reshape(-1, 2)
    points2 = np.asarray(points2, np.float64).reshape(-1, 2)
    if grey1.ndim != 2 or grey2.ndim != 2 or len(points1) != len(points2):
        raise ValueError(
            f"need grey images [H, W] and points [M, 2] of equal M, got images {grey1.shape},"
            f" {grey2.shape} and points {points1.shape}, {points2.shape}"
        )
    if radius < 1 or search < 1 or affine_steps < 0:
        raise ValueError(
            f"radius and search must be at least 1 and affine_steps at least 0, got {radius},"
            f" {search}, {affine_steps}"
        )
    refined = points2.copy()
    moved = np.zeros(len(points2), bool)
    centres = np.round(np.where(np.isfinite(points2), points2, 0.0))
    usable = _inside(points1, grey1.shape, radius + 1e-9) & _inside(
        np.where(np.isfinite(points2), centres, np.nan), grey2.shape, radius + search
    )
    index = np.flatnonzero(usable)
    if index.size == 0:
        return refined.astype(np.float32), moved
    ncc, spread = ncc_scores(
        grey1, grey2, points1[index], centres[index].astype(np.int64), radius, search
    )
    width = 2 * search + 1
    best = ncc.reshape(len(index), -1).argmax(axis=1)
    best_y, best_x = np.divmod(best, width)
    rows = np.arange(len(index))
    interior = (best_x > 0) & (best_x < width - 1) & (best_y > 0) & (best_y < width - 1)
    strong = (ncc[rows, best_y, best_x] >= min_ncc) & (spread > FLAT_STD) & interior
    ny = np.clip(best_y, 1, width - 2)[:, None, None] + np.arange(-1, 2)[None, :, None]
    nx = np.clip(best_x, 1, width - 2)[:, None, None] + np.arange(-1, 2)[None, None, :]
    offset, peaked = quadratic_peak(ncc[rows[:, None, None], ny, nx])
    accept = strong & peaked
    whole = np.stack([best_x, best_y], axis=1) - search
    peaks = centres[index[accept]] + whole[accept] + offset[accept]
    if affine_steps > 0 and len(peaks):
        polished, ok = affine_polish(
            grey1, grey2, points1[index[accept]], peaks, radius, affine_steps
        )
        ok &= np.linalg.norm(polished - peaks, axis=1) <= 1.0
        peaks[ok] = polished[ok]
    refined[index[accept]] = peaks
    moved[index[accept]] = True
    return refined.astype(np.float32), moved
