"""benchmarks/bench_pose.py: what each --networks entry runs, and bad pairs end in one line."""

import pathlib

import pytest

BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def bench_pose(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the script imports its siblings
    import bench_pose

    return bench_pose


def test_a_candidate_reads_side_refinement_nms_and_point_count(bench_pose):
    label, options = bench_pose.candidate("distilled:480+refine/nms0/top2000", 1000)
    assert label == "UnsuperPoint distilled at 480 px +refine NMS 0 top 2000"
    assert options == {
        "name": "distilled",
        "top_n": 2000,
        "nms_radius": 0.0,
        "max_side": 480,
        "refine": True,
    }
    assert bench_pose.candidate("paper", 1000) == (
        "UnsuperPoint paper",
        {"name": "paper", "top_n": 1000, "nms_radius": 4.0, "max_side": 0, "refine": None},
    )
    with pytest.raises(ValueError, match="nmsR or topN"):
        bench_pose.candidate("paper/fast", 1000)


def test_pairs_without_poses_are_one_line_and_exit_2(bench_pose, monkeypatch, capsys, tmp_path):
    (tmp_path / "pairs" / "p0").mkdir(parents=True)
    monkeypatch.setattr("sys.argv", ["bench_pose.py", "--pairs", str(tmp_path / "pairs")])
    with pytest.raises(SystemExit) as stop:
        bench_pose.main()
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and len(err) == 1 and "without its poses" in err[0]


def test_ncc_refines_a_network_or_a_baseline_row_with_default_or_given_settings(bench_pose):
    label, options = bench_pose.candidate("distilled:640/ncc", 1000)
    assert label == "UnsuperPoint distilled at 640 px +ncc" and options["match_refinement"] == {}
    label, options = bench_pose.candidate("paper/ncc=3,2,0.7,5", 1000)
    assert label == "UnsuperPoint paper +ncc 3,2,0.7,5"
    assert options["match_refinement"] == dict(radius=3, search=2, min_ncc=0.7, affine_steps=5)
    assert bench_pose.baseline_spec("SIFT/ncc") == ("SIFT", "SIFT +ncc", {})
    assert bench_pose.baseline_spec("SIFT") == ("SIFT", "SIFT", None)
    for bad in ("SIFT/nms2", "SIFT/ncc=5"):
        with pytest.raises(ValueError):
            bench_pose.baseline_spec(bad)
