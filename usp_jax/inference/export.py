"""Ahead-of-time export: a whole detector (weights, padding, network, NMS, top-N) as one
serialised ``jax.export`` artifact that runs with JAX alone, without this package's model code.
"""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.inference.detector import Detector, check_size, padding, unbatch
from usp_jax.inference.features import Features


def export(
    detector: Detector,
    path: str | pathlib.Path,
    height: int,
    width: int,
    batch: str | int = "b",
) -> None:
    """Serialise the whole detector (weights included) for uint8 images [batch, height, width, 3].

    ``batch`` is a symbolic dimension name (any batch size at run time) or a fixed int. The file
    holds a ``jax.export`` artifact for the current platform computing ``(keypoints [B, K, 2],
    scores [B, K], descriptors [B, K, F], counts [B])`` with the detector's top_n, NMS and border,
    and with ``any_scale`` the points' sizes [B, K] too; padding to whole cells happens inside. Read it back with :func:`load_exported`.
    """
    check_size((height, width, 3), height, width)
    (batch_dim,) = (batch,) if isinstance(batch, int) else jax.export.symbolic_shape(batch)
    pad_h, pad_w = padding(height, width)

    def detect(images):
        if detector.any_scale:  # the pyramid pads each level itself
            return detector._function(detector.variables, images, top_n=detector.top_n)
        padded = jnp.pad(images, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        sizes = jnp.broadcast_to(jnp.array([height, width], jnp.int32), (images.shape[0], 2))
        return detector._function(detector.variables, padded, sizes, top_n=detector.top_n)

    spec = jax.ShapeDtypeStruct((batch_dim, height, width, 3), jnp.uint8)
    exported = jax.export.export(jax.jit(detect))(spec)
    pathlib.Path(path).write_bytes(exported.serialize())


def load_exported(path: str | pathlib.Path):
    """A file written by :func:`export` as ``uint8 [B, H, W, 3] -> list[Features]``; needs only
    JAX (``jax.export.deserialize``), not the model code."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"exported detector {path} does not exist")
    exported = jax.export.deserialize(bytearray(path.read_bytes()))

    def detect_batch(images: np.ndarray) -> list[Features]:
        return unbatch(exported.call(images))

    return detect_batch
