"""Shared test set-up: a persistent compilation cache so repeated shapes compile once per run, and
the small network, tiny training run and command lines that several test modules use (imported
from here as ``from conftest import ...``)."""

import gc
import os
import sys
import tempfile

import jax
import numpy as np
import pytest

from usp_jax import config as config_lib
from usp_jax.core.model import ModelConfig, fast_config
from usp_jax.training.data import DataConfig

jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("USP_JAX_TEST_CACHE", os.path.join(tempfile.gettempdir(), "usp_jax_jit_cache")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def pytest_sessionfinish(session):
    # xdist stops a worker by interrupting its main thread; a KeyboardInterrupt that lands in
    # JAX's garbage-collection callback printed an "Exception ignored" warning after every run.
    # The process ends right after the session, so it needs no more collections.
    gc.disable()


#: A network small enough to compile and run in seconds on a CPU: 16-dim descriptors.
SMALL_MODEL = ModelConfig(
    backbone_channels=(8, 8, 8, 8, 16, 16, 16, 16), head_channels=16, descriptor_dim=16
)
#: The fast backbone at test size (``core.model.fast_config``), 8-d descriptors.
SMALL_FAST = fast_config(
    backbone_channels=(4, 8, 8, 16), head_channels=8, descriptor_head_channels=8, descriptor_dim=8
)

#: ``KEY=VALUE`` overrides of a tiny ``usp-jax train`` run: SMALL_MODEL on 32x48 crops, batch 2,
#: every step logged, a checkpoint every 2 steps.
TINY = [
    f"model.backbone_channels={SMALL_MODEL.backbone_channels}",
    f"model.head_channels={SMALL_MODEL.head_channels}",
    f"model.descriptor_dim={SMALL_MODEL.descriptor_dim}",
    "data.height=32",
    "data.width=48",
    "batch_size=2",
    "checkpoint_every=2",
    "log_every=1",
]

#: Options of a tiny ``usp-jax train`` run without a progress bar: the cpu preset and TINY.
TINY_RUN = ["--config", "cpu", "--no-progress", *TINY]

#: The command in a fresh interpreter, as the ``usp-jax`` script runs it (PYTHONPATH is inherited).
USP_JAX = [sys.executable, "-m", "usp_jax"]


def tiny_config(
    model: ModelConfig = SMALL_MODEL, size: tuple[int, int] = (32, 48), steps: int = 2, /, **changes
) -> config_lib.Config:
    """The API's tiny run: ``model`` on ``size`` (height, width) crops of the bundled photos, batch
    2, ``steps`` steps, every step logged, a checkpoint every 2; then ``changes`` as overrides
    (``tiny_config(seed=7, **{"optim.learning_rate": 0.5})``)."""
    height, width = size
    base = config_lib.Config(
        model=model,
        data=DataConfig(source="sample", height=height, width=width, num_workers=2),
        batch_size=2,
        num_steps=steps,
        log_every=1,
        checkpoint_every=2,
    )
    return config_lib.override(base, [f"{k}={v}" for k, v in changes.items()])


def train_args(workdir, steps: int, *options: str) -> list[str]:
    """``usp-jax train`` arguments: the bundled photos into ``workdir`` up to ``steps``, then
    ``options`` (more options and overrides)."""
    return ["train", "--data", "sample", "--workdir", str(workdir), "--steps", str(steps), *options]


def compilation_cache_env() -> dict[str, str]:
    """Environment variables that give a child process this run's compilation cache, so that it
    compiles nothing the tests compiled before."""
    return {
        "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir or "",
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(
            jax.config.jax_persistent_cache_min_compile_time_secs
        ),
    }


def child_env() -> dict[str, str]:
    """This process's environment plus the tests' compilation cache, for a child ``usp-jax``."""
    return {**os.environ, **compilation_cache_env()}


def gaussian_blob(centre, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """uint8 [H, W, 3] image of one bright Gaussian blob centred at ``centre`` (x, y), in the
    pixel-centre convention: a feature whose true position is known to a fraction of a pixel."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    blob = np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * sigma**2))
    return np.dstack([np.round(255 * blob).astype(np.uint8)] * 3)


@pytest.fixture(scope="session")
def photo():
    """A real photo (uint8 [512, 512, 3]) that ships inside scikit-image."""
    import skimage.data

    return skimage.data.astronaut()


@pytest.fixture(scope="session")
def small_weights(tmp_path_factory):
    """A weights file of SMALL_MODEL at a fixed random init (what ``usp-jax export`` writes)."""
    from usp_jax import inference
    from usp_jax.core.model import init_variables

    path = tmp_path_factory.mktemp("weights") / "small.npz"
    inference.save_weights(path, init_variables(jax.random.PRNGKey(0), SMALL_MODEL), SMALL_MODEL)
    return path


def one_error_line(capsys, command: str) -> str:
    """The one line a command wrote to stderr, checked to be its error line."""
    err = [line for line in capsys.readouterr().err.splitlines() if "libpng warning" not in line]
    assert len(err) == 1, err
    assert err[0].startswith(f"usp-jax {command}: error: ")
    return err[0]


def snapshot(folder):
    """{relative path: bytes (None for a folder)} of everything under ``folder``."""
    return {
        p.relative_to(folder): p.read_bytes() if p.is_file() else None
        for p in sorted(folder.rglob("*"))
    }
