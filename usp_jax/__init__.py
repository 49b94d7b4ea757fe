"""usp-jax: UnsuperPoint (Christiansen et al., 2019) in JAX/Flax.

Importing the package loads the core and inference layers only (JAX, Flax, NumPy, OpenCV);
training and evaluation load when used (``usp_jax.training``, ``usp_jax.evaluation``).
"""

from usp_jax.core.augment import PhotometricConfig, photometric_augment
from usp_jax.core.correspondence import Correspondences, find_correspondences
from usp_jax.core.geometry import (
    HomographyConfig,
    compose_homographies,
    invert_homography,
    sample_homography,
    warp_image,
    warp_points,
)
from usp_jax.core.losses import (
    LossConfig,
    decorrelation_loss,
    descriptor_loss,
    total_loss,
    uniform_loss,
    usp_loss,
)
from usp_jax.core.model import ModelConfig, Predictions, UnsuperPoint, fast_config, init_variables
from usp_jax.inference import Detector, TrackedFrame, TrackingConfig, to_cv2, track

__version__ = "0.1.0"


def __getattr__(name: str):
    # ``usp_jax.demo`` (the quick-start job) needs the evaluation stack: loaded on first use.
    if name == "demo":
        from usp_jax.quickstart import demo

        return demo
    raise AttributeError(f"module 'usp_jax' has no attribute {name!r}")


__all__ = [
    "Correspondences",
    "Detector",
    "HomographyConfig",
    "LossConfig",
    "ModelConfig",
    "PhotometricConfig",
    "Predictions",
    "TrackedFrame",
    "TrackingConfig",
    "UnsuperPoint",
    "compose_homographies",
    "decorrelation_loss",
    "demo",
    "descriptor_loss",
    "fast_config",
    "find_correspondences",
    "init_variables",
    "invert_homography",
    "photometric_augment",
    "sample_homography",
    "to_cv2",
    "total_loss",
    "track",
    "uniform_loss",
    "usp_loss",
    "warp_image",
    "warp_points",
]
