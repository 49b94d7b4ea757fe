"""usp-jax: UnsuperPoint (Christiansen et al., 2019) in JAX/Flax."""

from usp_jax.augment import PhotometricConfig, photometric_augment
from usp_jax.correspondence import Correspondences, find_correspondences
from usp_jax.geometry import (
    HomographyConfig,
    compose_homographies,
    invert_homography,
    sample_homography,
    warp_image,
    warp_points,
)
from usp_jax.inference import Detector, to_cv2
from usp_jax.losses import (
    LossConfig,
    decorrelation_loss,
    descriptor_loss,
    total_loss,
    uniform_loss,
    usp_loss,
)
from usp_jax.model import ModelConfig, Predictions, UnsuperPoint, fast_config, init_variables

__version__ = "0.1.0"

__all__ = [
    "Correspondences",
    "Detector",
    "HomographyConfig",
    "LossConfig",
    "ModelConfig",
    "PhotometricConfig",
    "Predictions",
    "UnsuperPoint",
    "compose_homographies",
    "decorrelation_loss",
    "descriptor_loss",
    "fast_config",
    "find_correspondences",
    "init_variables",
    "invert_homography",
    "photometric_augment",
    "sample_homography",
    "to_cv2",
    "total_loss",
    "uniform_loss",
    "usp_loss",
    "warp_image",
    "warp_points",
]
