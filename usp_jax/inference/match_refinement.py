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


def _template_blocks(
    grey: np.ndarray, points: np.ndarray, radius: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(blocks float32 [M, side + 1, side + 1], fx [M, 1, 1], fy [M, 1, 1]): the whole pixels
    around each point of ``points`` [M, 2] that the bilinear template of side ``2 radius + 1``
    reads (every point ``radius`` or more px inside the image), and the point's fractional
    offsets. The template's grid is whole-pixel spaced, so one (fx, fy) serves all its pixels."""
    size = 2 * radius + 2
    corner = np.floor(points)
    fraction = (points - corner).astype(np.float32)
    corner = corner.astype(np.int64) - radius
    view = np.lib.stride_tricks.sliding_window_view(grey, (size, size))
    return view[corner[:, 1], corner[:, 0]], fraction[:, 0, None, None], fraction[:, 1, None, None]


def templates(grey: np.ndarray, points: np.ndarray, radius: int) -> np.ndarray:
    """float32 [M, side, side]: the grey patches of side ``2 radius + 1`` centred on
    ``points`` [M, 2] (x, y; each at least ``radius`` px inside the image, ``grey`` float32),
    bilinearly sampled at whole-pixel offsets and made zero-mean."""
    blocks, fx, fy = _template_blocks(grey, points, radius)
    top = blocks[:, :-1, :-1] * (1 - fx) + blocks[:, :-1, 1:] * fx
    bottom = blocks[:, 1:, :-1] * (1 - fx) + blocks[:, 1:, 1:] * fx
    template = top * (1 - fy) + bottom * fy
    return template - template.mean(axis=(1, 2), keepdims=True)


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


def _box_sums(values: np.ndarray, side: int) -> np.ndarray:
    """float64 [..., U, U]: the sums of every ``side`` x ``side`` window of ``values``
    [..., S, S] (U = S - side + 1), as ``B V B^T`` with B [U, S] the band of ones: two small
    matrix products, 2.5x faster than summing shifted slices."""
    count = values.shape[-1] - side + 1
    offset = np.arange(values.shape[-1]) - np.arange(count)[:, None]
    band = ((offset >= 0) & (offset < side)).astype(np.float64)
    return band @ values.astype(np.float64) @ band.T


def ncc_scores(
    grey1: np.ndarray | None,
    grey2: np.ndarray,
    points1: np.ndarray | None,
    centres2: np.ndarray,
    radius: int,
    search: int,
    template: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(NCC float64 ``[M, 2 search + 1, 2 search + 1]`` indexed [match, dy, dx], template
    standard deviation [M]) of the templates of image 1 around ``points1`` [M, 2] against
    image 2's patches centred on the whole pixels ``centres2`` int [M, 2] plus each offset.
    Every template and window must lie inside its image. ``template``: :func:`templates` of
    ``points1``, when the caller has it already (grey1 and points1 are then not read)."""
    side, width = 2 * radius + 1, 2 * search + 1
    if template is None:
        template = templates(np.asarray(grey1, np.float32), points1, radius)
    template_norm = np.sqrt(np.einsum("mij,mij->m", template, template, dtype=np.float64))
    span = side + 2 * search
    corner = centres2 - (radius + search)
    view = np.lib.stride_tricks.sliding_window_view(np.asarray(grey2, np.float32), (span, span))
    region = view[corner[:, 1], corner[:, 0]]  # [M, span, span], whole pixels: no interpolation
    # Centred on its mean: the windows' variance from sums stays exact in float32 products.
    region = region - region.mean(axis=(1, 2), keepdims=True)
    sums, squares = _box_sums(np.stack([region, region * region]), side)
    window_var = np.maximum(squares - sums**2 / side**2, 0.0)
    product = np.empty((len(region), width, width), np.float64)
    for v in range(width):  # the template is zero-mean: its dot product with each window
        for u in range(width):
            product[:, v, u] = np.einsum(
                "mij,mij->m", template, region[:, v : v + side, u : u + side]
            )
    denominator = template_norm[:, None, None] * np.sqrt(window_var)
    # A window flat to rounding (its variance a millionth of a grey level's) correlates with
    # nothing: as an exactly flat one, or a flat template.
    flat = (window_var <= 1e-6 * side**2) | (template_norm[:, None, None] <= 0)
    ncc = np.where(flat, -1.0, product / np.where(flat, 1.0, denominator))
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


def _extrapolated(grey: np.ndarray) -> np.ndarray:
    """float32 [H + 2, W + 2]: ``grey`` framed by one pixel continuing each edge linearly
    (2 edge - next), so that a central difference on it is ``np.gradient``'s one-sided one
    at the edge (the frame's corners are never read)."""
    height, width = grey.shape
    framed = np.empty((height + 2, width + 2), np.float32)
    framed[1:-1, 1:-1] = grey
    framed[0, 1:-1] = 2 * grey[0] - grey[min(1, height - 1)]
    framed[-1, 1:-1] = 2 * grey[-1] - grey[max(height - 2, 0)]
    framed[1:-1, 0] = 2 * grey[:, 0] - grey[:, min(1, width - 1)]
    framed[1:-1, -1] = 2 * grey[:, -1] - grey[:, max(width - 2, 0)]
    framed[0, 0] = framed[0, -1] = framed[-1, 0] = framed[-1, -1] = 0.0
    return framed


def _sample_with_gradient(
    framed: np.ndarray, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values, d/dx, d/dy), each as ``x``: the image inside :func:`_extrapolated`'s frame
    ``framed`` and its ``np.gradient`` (central differences, one-sided at the edges), bilinearly
    interpolated at x, y (within [0, W-1] x [0, H-1]). Twelve whole pixels per point, read
    from the flat image: the gradient's bilinear sample is the bilinear weights times the
    central differences at the four pixels around the point."""
    height, width = framed.shape[0] - 2, framed.shape[1] - 2
    x0 = np.minimum(x.astype(np.int32), width - 2)  # x >= 0: truncation is the floor
    y0 = np.minimum(y.astype(np.int32), height - 2)
    fx, fy = x - x0, y - y0
    w11 = fx * fy
    w01, w10 = fx - w11, fy - w11
    w00 = 1 - fx - w10
    stride = width + 2
    index = y0 * stride + x0  # of the pixel (x0 - 1, y0 - 1), the frame's (x0, y0)
    flat = framed.ravel()

    def at(shift):  # the pixel ``shift`` flat steps from (x0, y0), read from a shifted view
        return flat[stride + 1 + shift :].take(index)

    v00, v01, v10, v11 = at(0), at(1), at(stride), at(stride + 1)
    value = w00 * v00 + w01 * v01 + w10 * v10 + w11 * v11
    dx = w00 * (v01 - at(-1)) + w01 * (at(2) - v00)
    dx += w10 * (v11 - at(stride - 1)) + w11 * (at(stride + 2) - v10)
    dy = w00 * (v10 - at(-stride)) + w01 * (v11 - at(1 - stride))
    dy += w10 * (at(2 * stride) - v00) + w11 * (at(2 * stride + 1) - v01)
    dx *= 0.5
    dy *= 0.5
    return value, dx, dy


def affine_polish(
    grey1: np.ndarray | None,
    grey2: np.ndarray,
    points1: np.ndarray | None,
    points2: np.ndarray,
    radius: int,
    steps: int,
    template: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(points float64 [K, 2], ok bool [K]): ``points2`` [K, 2] moved by ``steps`` Gauss-Newton
    steps of an affine Lucas-Kanade fit of image 1's template around ``points1`` [K, 2] (module
    docstring). Each step moves a point by at most half a pixel and its linear map by at most
    0.1 per entry; ok is False where a warped window left image 2 or a result is not finite.
    ``template``: :func:`templates` of ``points1``, when the caller has it already (grey1 and
    points1 are then not read).

    Image 2 and its gradient are read only where the warped windows fall (twelve whole pixels
    per sample, :func:`_sample_with_gradient`), in float32; the 6 x 6 systems are solved in
    float64."""
    if template is None:
        template = templates(np.asarray(grey1, np.float32), points1, radius)
    count, side = len(points2), 2 * radius + 1
    template = template.reshape(count, side * side)
    energy = np.maximum(np.einsum("mp,mp->m", template, template, dtype=np.float64), 1e-12)
    grid = np.arange(-radius, radius + 1, dtype=np.float32)
    ox, oy = (o.ravel() for o in np.meshgrid(grid, grid))  # [side^2], x along the row
    framed = _extrapolated(np.asarray(grey2, np.float32))
    height, width = grey2.shape
    points = np.array(points2, np.float64)
    linear = np.tile(np.eye(2), (count, 1, 1))
    ok = np.ones(count, bool)
    damping = 1e-6 * np.eye(6)
    columns = np.empty((count, 6, side * side), np.float32)
    for _ in range(steps):
        px, py = points[:, 0, None].astype(np.float32), points[:, 1, None].astype(np.float32)
        a = linear.astype(np.float32)
        x = px + a[:, 0, 0, None] * ox + a[:, 0, 1, None] * oy
        y = py + a[:, 1, 0, None] * ox + a[:, 1, 1, None] * oy
        # The window's extremes lie at the grid's corners.
        reach = radius * np.abs(a).sum(axis=2)  # [K, 2]: x and y
        ok &= (px[:, 0] - reach[:, 0] >= 0) & (px[:, 0] + reach[:, 0] <= width - 1)
        ok &= (py[:, 0] - reach[:, 1] >= 0) & (py[:, 0] + reach[:, 1] <= height - 1)
        np.clip(x, 0, width - 1, out=x)
        np.clip(y, 0, height - 1, out=y)
        window, ax, ay = _sample_with_gradient(framed, x, y)
        window -= window.mean(axis=1, keepdims=True)
        columns[:, 0], columns[:, 1] = ax, ay  # [K, 6, P]: the warp's Jacobian, per pixel
        np.multiply(ax, ox, out=columns[:, 2])
        np.multiply(ax, oy, out=columns[:, 3])
        np.multiply(ay, ox, out=columns[:, 4])
        np.multiply(ay, oy, out=columns[:, 5])
        columns -= columns.mean(axis=2, keepdims=True)
        gain = (np.einsum("mp,mp->m", window, template, dtype=np.float64) / energy).astype(
            np.float32
        )
        residual = gain[:, None] * template - window
        normal = np.matmul(columns, columns.transpose(0, 2, 1), dtype=np.float32)
        rhs = np.matmul(columns, residual[:, :, None])
        step = np.linalg.solve(normal.astype(np.float64) + damping, rhs.astype(np.float64))
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
    grey1 = np.asarray(grey1, np.float32)
    points1 = np.asarray(points1, np.float64).reshape(-1, 2)
    if grey1.ndim != 2 or len(points1) != len(np.asarray(points2).reshape(-1, 2)):
        raise ValueError(
            f"need grey images [H, W] and points [M, 2] of equal M, got images {grey1.shape},"
            f" {np.shape(grey2)} and points {points1.shape}, {np.shape(points2)}"
        )
    if radius < 1:
        raise ValueError(f"radius must be at least 1, got {radius}")
    template, usable = cut_templates(grey1, points1, radius)
    return match_templates(template, usable, grey2, points2, search, min_ncc, affine_steps)


def cut_templates(
    grey: np.ndarray, points: np.ndarray, radius: int = RADIUS
) -> tuple[np.ndarray, np.ndarray]:
    """(template float32 [M, side, side], usable bool [M]): :func:`templates` of image 1's
    points [M, 2] (``grey`` float32 [H, W]) where they lie ``radius`` px inside it (usable),
    zeros elsewhere."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    usable = _inside(points, grey.shape, radius + 1e-9)
    template = np.zeros((len(points), 2 * radius + 1, 2 * radius + 1), np.float32)
    if usable.any():  # an image smaller than a template has none
        template[usable] = templates(grey, points[usable], radius)
    return template, usable


def match_templates(
    template: np.ndarray,
    usable: np.ndarray,
    grey2: np.ndarray,
    points2: np.ndarray,
    search: int = SEARCH,
    min_ncc: float = MIN_NCC,
    affine_steps: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_matches` once image 1's side is cut (:func:`cut_templates`: ``template``
    [M, side, side], ``usable`` [M]), so that the matches of several images into one image 2
    are refined in one call (``sfm.refine_keypoints``: a call per image pair spent most of its
    time in NumPy's per-call overhead). The rest as :func:`refine_matches`."""
    grey2 = np.asarray(grey2, np.float32)
    points2 = np.asarray(points2, np.float64).reshape(-1, 2)
    radius = (template.shape[-1] - 1) // 2
    if grey2.ndim != 2 or len(template) != len(points2) or len(usable) != len(points2):
        raise ValueError(
            f"need a grey image [H, W] and templates, usable flags and points of equal M, got"
            f" image {grey2.shape}, {template.shape}, {np.shape(usable)} and {points2.shape}"
        )
    if search < 1 or affine_steps < 0:
        raise ValueError(
            f"search must be at least 1 and affine_steps at least 0, got {search}, {affine_steps}"
        )
    refined = points2.copy()
    moved = np.zeros(len(points2), bool)
    centres = np.round(np.where(np.isfinite(points2), points2, 0.0))
    usable = np.asarray(usable, bool) & _inside(
        np.where(np.isfinite(points2), centres, np.nan), grey2.shape, radius + search
    )
    index = np.flatnonzero(usable)
    if index.size == 0:
        return refined.astype(np.float32), moved
    template = template[index]
    ncc, spread = ncc_scores(
        None, grey2, None, centres[index].astype(np.int64), radius, search, template
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
            None, grey2, None, peaks, radius, affine_steps, template[accept]
        )
        ok &= np.linalg.norm(polished - peaks, axis=1) <= 1.0
        peaks[ok] = polished[ok]
    refined[index[accept]] = peaks
    moved[index[accept]] = True
    return refined.astype(np.float32), moved
