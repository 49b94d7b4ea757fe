"""benchmarks/bench_video.py's network specs: what each --networks entry runs."""

import pathlib

import pytest

BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def bench_video(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the script imports its sibling `common`
    import bench_video

    return bench_video


@pytest.mark.parametrize(
    "spec, expected",
    [
        ("paper", ("paper", 0, None, "UnsuperPoint paper")),
        ("fast:480", ("fast", 480, None, "UnsuperPoint fast at 480 px")),
        ("fast:480+refine", ("fast", 480, True, "UnsuperPoint fast at 480 px +refine")),
        ("paper-refine", ("paper", 0, False, "UnsuperPoint paper -refine")),
    ],
)
def test_network_spec_reads_name_side_and_refinement(bench_video, spec, expected):
    assert bench_video.network_spec(spec) == expected


def test_network_spec_refuses_a_side_that_is_no_whole_number(bench_video):
    with pytest.raises(ValueError, match="whole number"):
        bench_video.network_spec("fast:abc")
