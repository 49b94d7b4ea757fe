"""The paper's core as pure functions: the network, homography geometry, correspondences, the
four losses and photometric augmentation, plus the CPU backend's kernels and the settings checks.
Imports nothing else of the package."""
