"""Table 1 of the paper: configurations C0-C4 on one fixed budget and seed.

| config | descriptor interpolation | uniform loss (xy) | decorrelation loss |
|---|---|---|---|
| C0 base | | | |
| C1 | x | | |
| C2 | | x | |
| C3 | | | x |
| C4 UnsuperPoint | x | x | x |

Every configuration is ``experiments/cpu_photos.py`` (128x160 crops of the photo corpus, seed 0,
the same data order) with the three switches set as above, trained from scratch for ``--steps``
steps with the learning rate decaying over those steps; the score-mean anchor
(``loss.alpha_score_mean``, not in the paper, see RESULTS.md) stays on in all five. Then all five
are evaluated together at 240x320 / 300 points on the held-out pairs, and the table prints C0 and
C4 as values and C1-C4 as changes relative to C0 (for LE lower is better, so its sign is flipped
as in the paper), each beside the paper's value. Under each change, a 95% interval from a paired
bootstrap over the evaluation pairs: how much of it the choice of pairs alone could explain (not
the seed's share, which one run per configuration cannot show). From the repository root::

    python3 experiments/table1.py --data data/corpus/train --pairs data/heldout-pairs \
        --workdir runs/table1 --steps 2000 --out experiments/results/table1

2,000 steps each is what fit in one session on a 2-core CPU (18 min per configuration); it compares
partly trained detectors (RESULTS.md). Give a longer ``--steps`` where the machine allows.

Re-running resumes or skips finished runs (checkpoints in ``WORKDIR/C0`` ... ``WORKDIR/C4``);
``--table OUT.json`` prints the table again from a finished run's per-pair results.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np

from usp_jax import config as config_lib
from usp_jax import evaluation, train
from usp_jax.inference import Detector, as_method

CONFIGS = {
    "C0": {"interpolate": False, "uniform": False, "decorrelation": False},
    "C1": {"interpolate": True, "uniform": False, "decorrelation": False},
    "C2": {"interpolate": False, "uniform": True, "decorrelation": False},
    "C3": {"interpolate": False, "uniform": False, "decorrelation": True},
    "C4": {"interpolate": True, "uniform": True, "decorrelation": True},
}
METRICS = evaluation.METRICS
# Logged training statistics that show what each module does (means over a run's last steps).
TRAINING_STATS = {
    "usp/mean_d": "d_k (px)",
    "usp/K": "K pairs",
    "pred/relative_at_edge": "positions in outer 5% of cell",
    "desc/sim_positive": "sim. positive",
    "desc/sim_negative": "sim. negative",
}
# The paper's Table 1 (HPatches, 240x320, 300 points): C0 and C4 as values, C1-C4 in percent of C0.
PAPER = {
    "C0": {"rs": 0.633, "le": 0.898, "ha1": 0.519, "ha3": 0.812, "ha5": 0.871, "ms": 0.458},
    "C1": {"rs": 1.1, "le": 1.0, "ha1": 0.0, "ha3": 1.9, "ha5": 2.0, "ms": 6.7},
    "C2": {"rs": 1.9, "le": 4.8, "ha1": 15.3, "ha3": 5.5, "ha5": 4.0, "ms": 3.2},
    "C3": {"rs": 0.2, "le": 4.4, "ha1": 8.3, "ha3": 0.6, "ha5": 2.6, "ms": 3.3},
    "C4": {"rs": 1.9, "le": 7.4, "ha1": 7.3, "ha3": 7.2, "ha5": 5.7, "ms": 9.4},
    "C4 values": {"rs": 0.612, "le": 0.991, "ha1": 0.521, "ha3": 0.831, "ha5": 0.902, "ms": 0.452},
}


def config_for(name: str, data_source: str, steps: int) -> config_lib.Config:
    base = config_lib.load(str(pathlib.Path(__file__).with_name("cpu_photos.py")))
    switches = CONFIGS[name]
    return config_lib.override(
        base,
        [
            f"data.source={data_source}",
            f"num_steps={steps}",
            # The learning rate decays over each run's own budget, as in the shipped run.
            f"optim.decay_steps={steps}",
            f"model.interpolate_descriptors={switches['interpolate']}",
            f"loss.alpha_uni_xy={base.loss.alpha_uni_xy if switches['uniform'] else 0.0}",
            f"loss.alpha_decorr={base.loss.alpha_decorr if switches['decorrelation'] else 0.0}",
        ],
    )


def relative_changes(summary: dict, base: str = "C0") -> dict[str, dict[str, float]]:
    """Per configuration and metric, the change relative to ``base`` in percent, positive =
    better; NaN where the base value is 0 (a metric none of the pairs scored on)."""
    reference = summary[base]
    changes = {}
    for name, values in summary.items():
        changes[name] = {}
        for metric in METRICS:
            with np.errstate(divide="ignore", invalid="ignore"):
                change = 100.0 * np.divide(
                    values[metric] - reference[metric], np.abs(reference[metric])
                )
            change = np.where(np.isfinite(change), change, np.nan)
            change = -change if metric == "le" else change
            changes[name][metric] = float(change) if change.ndim == 0 else change
    return changes


def per_pair(rows: list[dict]) -> dict[str, dict[str, np.ndarray]]:
    """``{config: {metric: [P]}}`` from evaluation rows (``evaluation.to_json``'s "pairs"), every
    configuration's pairs in the same order; null (undefined LE) becomes NaN."""
    table = {}
    for row in rows:
        values = table.setdefault(row["method"], {m: [] for m in METRICS})
        for metric in METRICS:
            values[metric].append(math.nan if row[metric] is None else row[metric])
    return {
        name: {m: np.asarray(v, np.float64) for m, v in values.items()}
        for name, values in table.items()
    }


def bootstrap_intervals(
    pairs: dict[str, dict[str, np.ndarray]], rounds: int = 2000, seed: int = 0, base: str = "C0"
) -> dict[str, dict[str, tuple[float, float]]]:
    """95% percentile intervals of :func:`relative_changes`, resampling the evaluation pairs with
    replacement, the same draw for every configuration (a paired bootstrap: each configuration met
    the same pairs). LE's mean skips its undefined (NaN) pairs, as ``evaluation.summarize`` does."""
    count = len(pairs[base][METRICS[0]])
    draws = np.random.default_rng(seed).integers(0, count, size=(rounds, count))
    means = {
        name: {m: np.nanmean(values[m][draws], axis=1) for m in METRICS}
        for name, values in pairs.items()
    }
    intervals = {}
    for name in pairs:
        changes = relative_changes({base: means[base], name: means[name]}, base)[name]
        intervals[name] = {
            m: tuple(float(q) for q in np.nanpercentile(changes[m], [2.5, 97.5])) for m in METRICS
        }
    return intervals


def markdown(summary: dict, changes: dict, intervals: dict, steps: int, pairs: int) -> str:
    """The paper's layout, ours (paper's) in every cell, the bootstrap interval under a change."""
    header = "| config | interp. | uniformXY | decorr. | RS | LE | HA e=1 | HA e=3 | HA e=5 | MS |"
    lines = [header, "|" + "---|" * 10]

    def flags(name):
        return " | ".join("x" if on else "" for on in CONFIGS[name].values())

    def values(name, paper):
        return " | ".join(f"{summary[name][m]:.3f} ({paper[m]:.3f})" for m in METRICS)

    lines.append(f"| C0 base | {flags('C0')} | {values('C0', PAPER['C0'])} |")
    for name in ("C1", "C2", "C3", "C4"):
        row = " | ".join(
            f"{changes[name][m]:+.1f}% ({PAPER[name][m]:+.1f}%)<br>"
            f"[{intervals[name][m][0]:+.1f}, {intervals[name][m][1]:+.1f}]"
            if math.isfinite(changes[name][m])
            else f"n/a ({PAPER[name][m]:+.1f}%)"
            for m in METRICS
        )
        lines.append(f"| {name} | {flags(name)} | {row} |")
    lines.append(f"| C4 UnsuperPoint | {flags('C4')} | {values('C4', PAPER['C4 values'])} |")
    lines.append("")
    lines.append(
        f"Ours (paper's, HPatches). {steps} steps each from scratch, seed 0; {pairs} held-out pairs"
        " at 240x320, top 300. [a, b]: 95% paired-bootstrap interval of the change over the pairs."
    )
    return "\n".join(lines)


def training_stats(rows: list[dict], last: int = 200) -> dict[str, float]:
    """Means of :data:`TRAINING_STATS` over the logged rows of a run's last ``last`` steps."""
    final = max(row["step"] for row in rows)
    tail = [row for row in rows if row["step"] > final - last]
    return {key: float(np.mean([row[key] for row in tail])) for key in TRAINING_STATS}


def training_markdown(stats: dict[str, dict[str, float]], last: int = 200) -> str:
    lines = [
        "| config | " + " | ".join(TRAINING_STATS.values()) + " |",
        "|---|" + "---|" * len(TRAINING_STATS),
    ]
    for name, values in stats.items():
        cells = (f"{values[k]:.0f}" if k == "usp/K" else f"{values[k]:.3f}" for k in TRAINING_STATS)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", f"Logged in training (128x160 crops), means over each run's last {last} steps."]
    return "\n".join(lines)


def report(evaluated: dict, steps: int, training: dict | None = None) -> tuple[dict, str]:
    """The JSON summary and the markdown tables of an evaluation (``evaluation.to_json``) and,
    given, each configuration's :func:`training_stats`."""
    summary = {name: evaluated["summary"][name]["all"] for name in CONFIGS}
    changes = relative_changes(summary)
    intervals = bootstrap_intervals(per_pair(evaluated["pairs"]))
    pairs = summary["C0"]["pairs"]
    table = markdown(summary, changes, intervals, steps, pairs)
    if training:
        table += "\n\n" + training_markdown(training)
    summary_json = {
        "steps": steps, "summary": summary, "relative": changes, "intervals": intervals,
        "paper": PAPER, "training": training, "evaluation": evaluated,
    }
    return summary_json, table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", help="training images (folder or tfds:NAME)")
    parser.add_argument("--pairs", help="HPatches-layout evaluation pairs")
    parser.add_argument("--workdir", help="one training run per configuration")
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--only", nargs="*", choices=sorted(CONFIGS), help="train only these")
    parser.add_argument("--out", help="write OUT.json and OUT.md")
    parser.add_argument("--table", help="only print the table of a finished run's OUT.json")
    args = parser.parse_args()
    if args.table:
        path = pathlib.Path(args.table)
        if not path.is_file():
            parser.error(f"--table {path}: no such file")
        written = json.loads(path.read_text())
        if "evaluation" not in written:
            parser.error(
                f"--table {path} has no per-pair results (an older table1.py wrote it): run the"
                " training command again, which skips the finished runs and evaluates them"
            )
        print(report(written["evaluation"], written["steps"], written.get("training"))[1])
        return
    if not (args.data and args.pairs and args.workdir):
        parser.error("--data, --pairs and --workdir are required unless --table is given")

    workdir = pathlib.Path(args.workdir)
    for name in args.only or CONFIGS:
        print(f"{name}: training {args.steps} steps into {workdir / name}")
        train.fit(config_for(name, args.data, args.steps), workdir / name)
    if args.only:
        return

    methods = [as_method(Detector.from_checkpoint(workdir / name), name) for name in CONFIGS]
    results = evaluation.evaluate(methods, args.pairs, height=240, width=320, top_k=300)
    training = {name: training_stats(train.read_metrics(workdir / name)) for name in CONFIGS}
    summary_json, table = report(evaluation.to_json(results), args.steps, training)
    print(table)
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(json.dumps(summary_json, indent=1))
        out.with_suffix(".md").write_text(table + "\n")
        print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
