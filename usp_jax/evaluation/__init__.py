"""Judging detectors: the HPatches protocol and its metrics against the baselines
(``inference.methods``), pairs made from any photos, the speed benchmark, figures, and the
statistics that compare evaluations.

``usp_jax.evaluation.evaluate`` and the other names below are the protocol's public API.
"""

from usp_jax.evaluation.metrics import (
    CORRECT_DISTANCE,
    HA_TOLERANCES,
    corner_error,
    homography_accuracy,
    homography_matching,
    image_corners,
    matching_score,
    project_points,
    reordered_corner_errors,
    repeatability,
    shared_top_k,
    shared_view_mask,
    top_k,
)
from usp_jax.evaluation.protocol import (
    METRICS,
    SPLITS,
    EvalConfig,
    PairResult,
    Results,
    detect,
    detect_both,
    evaluate,
    evaluate_pair,
    format_table,
    methods,
    summarize,
    to_json,
)
from usp_jax.evaluation.sequences import (
    MIN_IMAGE_SIDE,
    Pair,
    PairFiles,
    load_sequences,
    read_image,
    read_pair,
    resize_pair,
    scan_sequences,
)
from usp_jax.inference.features import Features
from usp_jax.inference.matching import (
    RANSAC_MAX_ITERS,
    RANSAC_THRESHOLD,
    Matching,
    estimate_homography,
    match_and_estimate,
)
from usp_jax.inference.methods import Method, as_method, baseline_method

__all__ = [
    "CORRECT_DISTANCE",
    "HA_TOLERANCES",
    "METRICS",
    "MIN_IMAGE_SIDE",
    "RANSAC_MAX_ITERS",
    "RANSAC_THRESHOLD",
    "SPLITS",
    "EvalConfig",
    "Features",
    "Matching",
    "Method",
    "Pair",
    "PairFiles",
    "PairResult",
    "Results",
    "as_method",
    "baseline_method",
    "corner_error",
    "detect",
    "detect_both",
    "estimate_homography",
    "evaluate",
    "evaluate_pair",
    "format_table",
    "homography_accuracy",
    "homography_matching",
    "image_corners",
    "load_sequences",
    "match_and_estimate",
    "matching_score",
    "methods",
    "project_points",
    "read_image",
    "read_pair",
    "reordered_corner_errors",
    "repeatability",
    "resize_pair",
    "scan_sequences",
    "shared_top_k",
    "shared_view_mask",
    "summarize",
    "to_json",
    "top_k",
]
