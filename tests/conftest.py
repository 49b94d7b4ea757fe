"""Shared test set-up: a persistent compilation cache so repeated shapes compile once per run."""

import os
import tempfile

import jax
import pytest

jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("USP_JAX_TEST_CACHE", os.path.join(tempfile.gettempdir(), "usp_jax_jit_cache")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.fixture(scope="session")
def photo():
    """A real photo (uint8 [512, 512, 3]) that ships inside scikit-image."""
    import skimage.data

    return skimage.data.astronaut()
