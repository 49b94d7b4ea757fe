"""Zoom between the two images of a pair: zoomed views for ``usp-jax make-pairs --zoom`` and the
zoom of a pair read back from its homography, binned for the evaluation's breakdown
(``analysis.by_zoom``).

A view zoomed by z shows the content magnified z times about its centre (0.5: twice the extent
at half the pixel scale). Zoomed-out views are rendered 1 / z times larger and shrunk with
INTER_AREA, as a camera would see them, not aliased.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

# Seeds the zoom factors' generator together with (seed, photo index): a stream of its own
# (make-pairs' rotation angles use stream 1), so the other draws stay what they were.
_ZOOM_STREAM = 2
#: Widest zoom range make-pairs accepts: beyond, the photo would be enlarged past any sense.
ZOOM_LIMITS = (0.25, 4.0)


def pair_zooms(
    index: int, num_views: int, zoom: tuple[float, float] | None, *, seed: int = 0
) -> list[float]:
    """The zoom factors of the viewpoint pairs (1, 2) .. (1, num_views) of source photo `index`:
    log-uniform in [zoom[0], zoom[1]] (so that 0.5 and 2 are equally likely), 1 without zoom."""
    if zoom is None:
        return [1.0] * (num_views - 1)
    rng = np.random.default_rng([seed, index, _ZOOM_STREAM])
    low, high = np.log(zoom)
    return [float(z) for z in np.exp(rng.uniform(low, high, size=num_views - 1))]


def check_zoom(zoom: Sequence[float] | None) -> tuple[float, float] | None:
    if zoom is None:
        return None
    try:
        low, high = (float(z) for z in zoom)
    except (TypeError, ValueError):
        raise ValueError(f"zoom must be (min, max), got {zoom!r}") from None
    if not ZOOM_LIMITS[0] <= low <= high <= ZOOM_LIMITS[1]:
        raise ValueError(
            f"zoom must satisfy {ZOOM_LIMITS[0]} <= min <= max <= {ZOOM_LIMITS[1]}, got {zoom}"
        )
    return low, high


def zoomed(frame: np.ndarray, zoom: float, height: int, width: int) -> np.ndarray:
    """``frame`` (photo frame -> view pixels) followed by a magnification ``zoom`` about the
    view's centre."""
    centre = np.array([[1.0, 0.0, (width - 1) / 2], [0.0, 1.0, (height - 1) / 2], [0, 0, 1]])
    return centre @ np.diag([zoom, zoom, 1.0]) @ np.linalg.inv(centre) @ frame


def fitting_zoom(frame: np.ndarray, zoom: float, height: int, width: int, photo_shape) -> float:
    """``zoom``, raised towards 1 in steps of 2 % until the zoomed view of ``frame`` (photo pixels
    -> view pixels) lies inside the photo: a view never shows the black border."""
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], float)
    limit = np.array([photo_shape[1] - 1, photo_shape[0] - 1])
    while zoom < 1:
        inverse = np.linalg.inv(zoomed(frame, zoom, height, width))
        quad = cv2.perspectiveTransform(corners[None], inverse)[0]
        if np.all(quad >= 0) and np.all(quad <= limit):
            break
        zoom = min(1.0, zoom * 1.02)
    return zoom


def render(photo: np.ndarray, frame: np.ndarray, zoom: float, height: int, width: int):
    """The [height, width] view of ``photo`` through ``frame`` (its pixels -> the view's); a
    zoomed-out view (``zoom`` < 1) is rendered 1 / zoom times larger and shrunk with INTER_AREA."""
    if zoom >= 1:
        big, size = frame, (width, height)
    else:
        # cv2.resize maps pixel corners: small = (big + 0.5) zoom - 0.5.
        shift = (zoom - 1) / 2
        to_small = np.array([[zoom, 0.0, shift], [0.0, zoom, shift], [0.0, 0.0, 1.0]])
        big = np.linalg.inv(to_small) @ frame
        size = (math.ceil(width / zoom), math.ceil(height / zoom))
    view = cv2.warpPerspective(
        photo, big, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    if zoom < 1:
        view = cv2.resize(view, (width, height), interpolation=cv2.INTER_AREA)
    return view


#: Zoom bins, steps of sqrt 2 from 0.5 to 2 (``usp-jax make-pairs --zoom 0.5,2``); the outer
#: bins also take the few pairs that the views' own scale change pushes beyond.
ZOOM_EDGES = (0.71, 1.0, 1.41)


def zoom_of(homography: np.ndarray, shape: tuple[int, int]) -> float:
    """How much larger image 2 shows image 1's content at image 1's centre: the square root of
    the area ratio (Jacobian determinant) of the homography [3, 3] (image 1 -> 2) there.
    ``shape``: image 1's (height, width)."""
    h = np.asarray(homography, np.float64)
    x, y = (shape[1] - 1) / 2, (shape[0] - 1) / 2
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    u, v = (h[:2] @ [x, y, 1.0]) / w
    jacobian = (h[:2, :2] - np.outer([u, v], h[2, :2])) / w
    return float(np.sqrt(abs(np.linalg.det(jacobian))))


def zoom_label(zoom: float, edges=ZOOM_EDGES) -> str:
    """The bin of a zoom: ``<0.71``, ``0.71-1``, ``1-1.41`` or ``>=1.41`` for the default edges."""
    index = int(np.searchsorted(edges, zoom, side="right"))
    if index == 0:
        return f"<{edges[0]:g}"
    if index == len(edges):
        return f">={edges[-1]:g}"
    return f"{edges[index - 1]:g}-{edges[index]:g}"
