"""The fast network's figures, from files already in ``experiments/results/``:

* ``fast-v3/training_curves.png``: its two stages' logged statistics on one step axis;
* ``fast-v3/training_curves_beside_paper.png``: that figure beside the paper network's
  (``figures/training_curves.png``, drawn by ``experiments/figures.py`` from its stages);
* ``fast-v3/tradeoff.png``: images/s against HA@3 and MS on the held-out pairs at 240x320/300
  and 480x640/1000, for every network and checkpoint evaluated and the OpenCV baselines. Speeds
  are one side-by-side run (``benchmarks/bench_inference.py --json``, batch 1); checkpoints of
  one network share its speed.

From the repository root, after the evaluations and the benchmark that RESULTS.md lists::

    python3 experiments/fast_figures.py
"""

from __future__ import annotations

import argparse
import gzip
import json
import pathlib

from matplotlib.figure import Figure
from matplotlib.image import imread

from usp_jax.evaluation import plotting
from usp_jax.training import metrics as metrics_lib

RESULTS = pathlib.Path(__file__).with_name("results")
SIZES = ("240x320", "480x640")
#: label -> (benchmarked network, {size: evaluation JSON}); each file's UnsuperPoint rows.
NETWORKS = {
    "paper": ("paper", {s: f"heldout_{s}.json" for s in SIZES}),
    "fast": ("fast", {s: f"fast-v3/heldout_{s}.json" for s in SIZES}),
    "fast, step 4k": ("fast", {"240x320": "fast-v3/heldout_240x320_step4000.json"}),
    "fast, step 8k": ("fast", {"240x320": "fast-v3/heldout_240x320_step8000.json"}),
    "rotation": ("fast", {s: f"rotation/heldout_{s}.json" for s in SIZES}),
}
BASELINES = ("ORB", "AKAZE", "SIFT")


def summary(path: pathlib.Path, method: str) -> dict | None:
    """One method's summary over all pairs in an evaluation JSON, or None if not there."""
    if not path.is_file():
        return None
    result = json.loads(path.read_text())["summary"].get(method)
    return None if result is None else result["all"]


def speed_quality_points(bench: dict) -> list[dict]:
    """The trade-off plot's points: each evaluated network and baseline at each size."""
    rates = {
        (f"{r['height']}x{r['width']}", r["method"]): r["images_per_s"]
        for r in bench["rows"]
        if r["batch"] == 1
    }

    def point(label, size, rate, found, ours):
        return dict(
            label=label, size=size, images_per_s=rate, ha3=found["ha3"], ms=found["ms"], ours=ours
        )

    points = []
    for label, (network, files) in NETWORKS.items():
        for size, name in files.items():
            found = summary(RESULTS / name, "UnsuperPoint")
            if found is not None:
                points.append(
                    point(label, size, rates[size, f"UnsuperPoint {network}"], found, True)
                )
    for size in SIZES:
        for method in BASELINES:
            found = summary(RESULTS / f"heldout_{size}.json", method)
            points.append(point(method, size, rates[size, method], found, False))
    return points


def training_curves(out: pathlib.Path) -> None:
    stages = []
    for name in ("metrics_stage1", "metrics_finetune"):
        with gzip.open(RESULTS / "fast-v3" / f"{name}.jsonl.gz", "rt") as f:
            stages.append([json.loads(line) for line in f if line.strip()])
    rows, starts = metrics_lib.chain_stages(stages)
    ours = plotting.plot_training_curves(rows, out / "training_curves.png", stage_starts=starts)
    figure = Figure(figsize=(22.0, 7.6), layout="constrained")
    titles = (
        "paper network, its 128x160 stages 1-3 (32,500 of its 38,100 steps)",
        "fast network, both stages (18,000 at 128x160, then 1,500 at 240x320)",
    )
    for axes, path, title in zip(
        figure.subplots(1, 2), (RESULTS / "figures" / "training_curves.png", ours), titles
    ):
        axes.imshow(imread(path))
        axes.set_title(title, fontsize="x-large")
        axes.set_axis_off()
    figure.savefig(out / "training_curves_beside_paper.png", dpi=plotting.DPI)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", default=str(RESULTS / "fast-v3" / "bench_inference.json"))
    args = parser.parse_args()
    out = RESULTS / "fast-v3"
    training_curves(out)
    points = speed_quality_points(json.loads(pathlib.Path(args.bench).read_text()))
    plotting.plot_speed_quality(points, out / "tradeoff.png")
    for p in points:
        print(
            f"{p['size']} {p['label']:14s} {p['images_per_s']:6.1f} img/s"
            f"  HA@3 {p['ha3']:.3f}  MS {p['ms']:.3f}"
        )
    print(f"wrote {out}/training_curves.png, training_curves_beside_paper.png, tradeoff.png")


if __name__ == "__main__":
    main()
