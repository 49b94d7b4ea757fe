"""benchmarks/bench_sfm.py: the camera each ``--intrinsics`` mode gives both pipelines."""

import pathlib

import pytest

from usp_jax import sfm

BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def bench_sfm(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import bench_sfm

    return bench_sfm


def test_the_true_camera_is_held_fixed_known_refined_from_as_exif_prior_or_unused(bench_sfm):
    true = sfm.Camera("PINHOLE", (500.0, 502.0, 320.0, 240.0))
    assert bench_sfm.intrinsics(true, "known") == (true, True)
    # COLMAP's camera for a photo with an EXIF focal length: SIMPLE_RADIAL, no distortion yet.
    prior = sfm.Camera("SIMPLE_RADIAL", (501.0, 320.0, 240.0, 0.0))
    assert bench_sfm.intrinsics(true, "prior") == (prior, False)
    assert bench_sfm.intrinsics(true, "estimated") == (sfm.Camera(), False)
    assert set(bench_sfm.INTRINSICS) == {"known", "prior", "estimated"}
