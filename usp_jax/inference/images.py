"""Photos in: image files and bytes decoded as uint8 RGB the way ``cv2.imread`` shows them, and
the real photos that ship inside installed packages (the ``sample`` training source, the demo,
the benchmark), so that everything runs offline on a fresh install.
"""

from __future__ import annotations

import importlib.util
import pathlib

import cv2
import numpy as np

#: File suffixes read as images (any case) by folder sources and pair readers.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff", ".webp")

# Real photos inside PyPI wheels: PyPI distribution -> (import package, files inside it).
# scikit-image's other images are downloaded at run time, so only these are listed.
_SAMPLE_PHOTOS = {
    "scikit-image": (
        "skimage",
        tuple(
            f"data/{name}"
            for name in (
                "astronaut.png",
                "camera.png",
                "chelsea.png",
                "coffee.png",
                "rocket.jpg",
                "motorcycle_left.png",
                "motorcycle_right.png",
                "brick.png",
                "grass.png",
                "gravel.png",
                "coins.png",
                "text.png",
                "page.png",
            )
        ),
    ),
    "matplotlib": ("matplotlib", ("mpl-data/sample_data/grace_hopper.jpg",)),
    "scikit-learn": ("sklearn", ("datasets/images/china.jpg", "datasets/images/flower.jpg")),
}


def decode_image(data: bytes, name: str = "image") -> np.ndarray:
    """Encoded image bytes -> uint8 [H, W, 3] RGB, as ``cv2.imread`` would show the file.

    Grayscale is replicated to three channels, alpha is dropped, 16-bit is scaled to 8-bit
    (65535 -> 255), OpenCV's BGR order is turned into RGB, and the EXIF orientation is applied
    (like ``cv2.imread``), so a phone photo's keypoints land where a viewer shows its pixels.
    Raises ValueError naming ``name`` when OpenCV cannot decode the bytes.
    """
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        image = None  # OpenCV raises on some inputs (e.g. empty) and returns None on others.
    if image is None:
        raise ValueError(f"{name}: OpenCV cannot decode these {len(data)} bytes as an image")
    if image.dtype == np.uint16:
        image = cv2.convertScaleAbs(image, alpha=255 / 65535)
    elif image.dtype != np.uint8:
        raise ValueError(f"{name}: unsupported pixel type {image.dtype}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def grey(image: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W]`` grey levels (``cv2.COLOR_RGB2GRAY``'s BT.601 luma) of a uint8 RGB
    ``[H, W, 3]`` image; a grey ``[H, W]`` one as it is."""
    image = np.asarray(image)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def read_image(path: str | pathlib.Path) -> np.ndarray:
    """The image file at ``path`` as uint8 [H, W, 3] RGB (see ``decode_image``)."""
    return decode_image(pathlib.Path(path).read_bytes(), str(path))


def sample_photos() -> list[tuple[str, pathlib.Path]]:
    """(PyPI distribution, file) for each real photo inside an installed package.

    Paths come from the installed package directories, never from download helpers
    (``skimage.data`` fetches its other images from the internet).
    """
    photos = []
    for distribution, (package, files) in _SAMPLE_PHOTOS.items():
        spec = importlib.util.find_spec(package)
        if spec is None:  # scikit-learn is optional.
            continue
        root = pathlib.Path(spec.submodule_search_locations[0])
        photos += [(distribution, root / f) for f in files if (root / f).is_file()]
    return photos
