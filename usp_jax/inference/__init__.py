"""Running a trained network: the compiled ``Detector``, its weights files, features and matching.

Imports only JAX, Flax, NumPy and OpenCV, never the training or evaluation stacks.
"""

from usp_jax.inference.detector import MAX_SIDE, Detector
from usp_jax.inference.export import export, load_exported
from usp_jax.inference.features import Features, to_cv2
from usp_jax.inference.matching import Matching, match_and_estimate
from usp_jax.inference.tracking import TrackedFrame, TrackingConfig, track
from usp_jax.inference.turning import TurnedMatching, match_any_rotation
from usp_jax.inference.weights import (
    DEFAULT_PRETRAINED,
    PRETRAINED,
    WEIGHTS_DIR,
    load_weights,
    save_weights,
)

__all__ = [
    "DEFAULT_PRETRAINED",
    "MAX_SIDE",
    "PRETRAINED",
    "WEIGHTS_DIR",
    "Detector",
    "Features",
    "Matching",
    "TrackedFrame",
    "TrackingConfig",
    "TurnedMatching",
    "export",
    "load_exported",
    "load_weights",
    "match_and_estimate",
    "match_any_rotation",
    "save_weights",
    "to_cv2",
    "track",
]
