"""What ``reconstruct`` writes beside COLMAP's own files: features and matches for other tools,
and a top view of a model."""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import numpy as np

from usp_jax.inference.features import Features
from usp_jax.sfm.colmap import colmap_keypoints, registered_poses


def export_features(
    path: str | pathlib.Path,
    names: Sequence[str],
    features: Sequence[Features],
    pairs: np.ndarray,
    matches: Sequence[np.ndarray],
    kept: Sequence[np.ndarray] | None = None,
) -> None:
    """Features and raw matches in one ``.npz`` for other tools (COLMAP, hloc): per image
    ``NAME/keypoints`` float32 ``[N, 2]`` in COLMAP's convention, ``NAME/scores`` ``[N]``,
    ``NAME/descriptors`` ``[N, D]``; per pair ``NAME1//NAME2/matches`` int ``[K, 2]`` and, when
    ``kept`` is given, ``NAME1//NAME2/kept`` ``[K', 2]`` (those the database got)."""
    arrays = {}
    for name, found in zip(names, features):
        arrays[f"{name}/keypoints"] = colmap_keypoints(found.keypoints)
        arrays[f"{name}/scores"] = np.asarray(found.scores, np.float32)
        arrays[f"{name}/descriptors"] = np.asarray(found.descriptors)
    for (i, j), pair_matches in zip(pairs, matches):
        arrays[f"{names[i]}//{names[j]}/matches"] = np.asarray(pair_matches, np.int64)
    for (i, j), pair_kept in zip(pairs, kept if kept is not None else []):
        arrays[f"{names[i]}//{names[j]}/kept"] = np.asarray(pair_kept, np.int64).reshape(-1, 2)
    with open(path, "wb") as file:
        np.savez(file, **arrays)


def top_view(model, path: str | pathlib.Path, points: int = 20000) -> None:
    """A PNG of the model from above: its points (at most ``points``, in their colours) and
    camera centres with viewing directions on the world's x-z plane (COLMAP's world is the
    first camera's frame, y down, so x-z is the ground when that camera was level)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    xyz = np.array([p.xyz for p in model.points3D.values()]).reshape(-1, 3)
    rgb = np.array([p.color for p in model.points3D.values()]).reshape(-1, 3) / 255
    keep = np.random.default_rng(0).permutation(len(xyz))[:points]
    poses = registered_poses(model)
    centres = np.array([c for _, c in poses.values()]).reshape(-1, 3)
    views = np.array([r[2] for r, _ in poses.values()]).reshape(-1, 3)  # optical axes in world
    figure, axes = plt.subplots(figsize=(8, 8))
    axes.scatter(xyz[keep, 0], xyz[keep, 2], s=1, c=rgb[keep], linewidths=0)
    axes.quiver(centres[:, 0], centres[:, 2], views[:, 0], views[:, 2], color="red", width=0.003)
    axes.set(
        aspect="equal", xlabel="x", ylabel="z", title=f"{len(poses)} cameras, {len(xyz)} points"
    )
    figure.savefig(path, dpi=100)
    plt.close(figure)
