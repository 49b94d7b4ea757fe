"""Structure from motion with the network's features: COLMAP's database, geometric verification,
incremental mapper and bundle adjustment through pycolmap (the optional ``sfm`` extra), with our
keypoints and mutual-nearest-neighbour matches in place of COLMAP's SIFT.

The steps, each a function (``usp-jax reconstruct`` runs them in order): ``detect_images`` ->
``match_pairs`` on ``image_pairs`` -> ``fundamental_inliers`` -> ``refine_keypoints``
(``sfm.tracks``: what COLMAP gets) -> ``write_database`` (with a ``Camera``) -> ``verify`` ->
``map_images`` from ``initial_pair`` (``sfm.colmap``), then ``model_summary`` and, where true
poses are known, ``pose_errors``. ``export_features`` and ``top_view`` (``sfm.outputs``) write
what other tools and people read. It lives beside the CLI: detection, training and evaluation
never load its heavy optional dependency.
"""

from usp_jax.sfm.colmap import (
    COLMAP_OFFSET,
    INSTALL,
    Camera,
    camera_params,
    check_camera,
    colmap_keypoints,
    initial_pair,
    load_pycolmap,
    map_images,
    model_summary,
    pose_errors,
    reader_options,
    registered_poses,
    verified_pairs,
    verify,
    write_database,
)
from usp_jax.sfm.outputs import export_features, top_view
from usp_jax.sfm.tracks import (
    AFFINE_STEPS,
    EPIPOLAR_THRESHOLD,
    RATIO,
    WINDOW,
    Refinement,
    check_sizes,
    descriptor_distances,
    detect_images,
    fundamental_inliers,
    image_pairs,
    keypoint_tracks,
    match_pairs,
    refine_keypoints,
    track_anchors,
)

__all__ = [
    "AFFINE_STEPS",
    "COLMAP_OFFSET",
    "EPIPOLAR_THRESHOLD",
    "INSTALL",
    "RATIO",
    "WINDOW",
    "Camera",
    "Refinement",
    "camera_params",
    "check_camera",
    "check_sizes",
    "colmap_keypoints",
    "descriptor_distances",
    "detect_images",
    "export_features",
    "fundamental_inliers",
    "image_pairs",
    "initial_pair",
    "keypoint_tracks",
    "load_pycolmap",
    "map_images",
    "match_pairs",
    "model_summary",
    "pose_errors",
    "reader_options",
    "refine_keypoints",
    "registered_poses",
    "top_view",
    "track_anchors",
    "verified_pairs",
    "verify",
    "write_database",
]
