import json

import jax
import pytest
from conftest import SMALL_FAST, SMALL_MODEL

from usp_jax.core.model import init_variables
from usp_jax.evaluation.benchmark import (
    OPENCV_DETECTORS,
    benchmark,
    format_benchmark,
    protocol_top_n,
    shipped_networks,
)
from usp_jax.inference import Detector, save_weights, weights


@pytest.fixture(scope="module")
def detector():
    # Jitted, the initialisation is one compile that the persistent cache (conftest) keeps.
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    return Detector(variables, SMALL_MODEL)


@pytest.fixture(scope="module")
def tiny_run(detector):
    return benchmark(
        detector, resolutions=((32, 48), (40, 56)), batch_sizes=(1, 2), repeats=1, warmup=0
    )


def test_benchmark_reports_every_method_resolution_and_batch(tiny_run):
    rows = {(r["method"], r["height"], r["width"], r["batch"]): r for r in tiny_run["rows"]}
    expected = {
        (method, h, w, b)
        for h, w in ((32, 48), (40, 56))
        for method, b in [("UnsuperPoint", 1), ("UnsuperPoint", 2)]
        + [(name, 1) for name in OPENCV_DETECTORS]
    }
    assert set(rows) == expected
    for row in rows.values():
        assert row["fps"] > 0 and row["first_call_s"] > 0
        assert row["fps"] == pytest.approx(row["batch"] / row["median_s"])
        assert row["top_n"] == protocol_top_n(row["height"], row["width"]) == 300
    assert tiny_run["device"] == jax.devices()[0].device_kind
    assert tiny_run["jax_version"] == jax.__version__
    assert tiny_run["models"]["UnsuperPoint"]["descriptor_dim"] == 16


def test_benchmark_result_is_json_serialisable(tiny_run):
    assert json.loads(json.dumps(tiny_run))["rows"] == tiny_run["rows"]


def test_benchmark_reports_progress_per_timed_row_on_stderr(detector, capsys):
    """Minutes of timing at the defaults: a bar on stderr names each row and counts them all."""
    benchmark(detector, resolutions=((32, 48),), batch_sizes=(1,), repeats=1, warmup=0)
    assert capsys.readouterr().err == ""  # progress is asked for, as the CLI does
    benchmark(
        detector, resolutions=((32, 48),), batch_sizes=(1,), repeats=1, warmup=0, progress=True
    )
    err = capsys.readouterr().err
    rows = 1 + len(OPENCV_DETECTORS)
    assert "benchmark" in err and f"{rows}/{rows}" in err
    assert "UnsuperPoint, 32x48, batch 1" in err and f"{OPENCV_DETECTORS[-1]}, 32x48" in err


def test_format_benchmark_is_the_papers_table_layout(tiny_run):
    table = format_benchmark(tiny_run)
    header = next(line for line in table.splitlines() if line.startswith("Detectors"))
    assert "FPS @ 32x48" in header and "FPS @ 40x56" in header
    labels = [line.split("|")[0].strip() for line in table.splitlines() if "|" in line]
    # Classical detectors first, then UnsuperPoint per batch size, as in Table 5.
    assert labels[1:7] == [*OPENCV_DETECTORS, "UnsuperPoint, b1", "UnsuperPoint, b2"]
    assert "First call (s)" in labels
    assert "enlarged" not in table


def test_an_upsampled_detector_is_recorded_and_named_in_the_table(detector):
    upsampled = Detector(detector.variables, SMALL_MODEL, upsample=2)
    result = benchmark(
        upsampled,
        resolutions=((32, 48),),
        batch_sizes=(1,),
        repeats=1,
        warmup=0,
        include_opencv=False,
    )
    assert result["upsample"] == 2
    assert "UnsuperPoint on 2x enlarged images" in format_benchmark(result)


def test_named_detectors_are_timed_side_by_side_in_one_table(detector):
    fast = Detector(init_variables(jax.random.PRNGKey(0), SMALL_FAST), SMALL_FAST)
    result = benchmark(
        {"paper": detector, "fast": fast},
        resolutions=((32, 48),),
        batch_sizes=(1,),
        repeats=1,
        warmup=0,
        include_opencv=False,
    )
    assert [r["method"] for r in result["rows"]] == ["UnsuperPoint paper", "UnsuperPoint fast"]
    assert result["models"]["UnsuperPoint fast"]["backbone"] == "fast"
    labels = [line.split("|")[0].strip() for line in format_benchmark(result).splitlines()]
    assert "UnsuperPoint paper, b1" in labels and "UnsuperPoint fast, b1" in labels


def test_shipped_networks_times_each_network_once_whatever_weights_it_ships_with(
    detector, tmp_path, monkeypatch
):
    files = {"paper": (detector.variables, SMALL_MODEL)}
    for seed, name in enumerate(("fast", "rotation")):  # one network, two weights
        files[name] = (init_variables(jax.random.PRNGKey(seed), SMALL_FAST), SMALL_FAST)
    registry = {}
    for name, (variables, config) in files.items():
        registry[name] = str(tmp_path / f"{name}.npz")
        save_weights(registry[name], variables, config)
    monkeypatch.setattr(weights, "PRETRAINED", registry)
    networks = shipped_networks(top_n=7)
    assert list(networks) == ["paper", "fast"]
    assert networks["fast"].model_config == SMALL_FAST and networks["fast"].top_n == 7


def test_protocol_top_n_follows_the_evaluation_settings():
    assert protocol_top_n(240, 320) == 300
    assert protocol_top_n(480, 640) == 1000


def test_benchmark_rejects_empty_settings(detector):
    with pytest.raises(ValueError, match="repeats"):
        benchmark(detector, repeats=0)
    with pytest.raises(ValueError, match="batch sizes"):
        benchmark(detector, batch_sizes=())
