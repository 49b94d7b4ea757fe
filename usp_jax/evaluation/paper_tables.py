"""Tables 1-4 of the paper beside ours: reads the JSON files ``usp-jax evaluate --json`` and
``usp-jax benchmark --json`` wrote and prints markdown with the paper's values next to ours.

From the repository root, after the evaluation and benchmark commands of RESULTS.md::

    python3 experiments/paper_tables.py --results experiments/results > experiments/results/paper_tables.md

Our accuracy numbers come from synthetic homography pairs of held-out photos, the paper's from
HPatches: compare methods within a column, and our column with the paper's only for the ranking.
The paper's speeds are UnsuperPoint on a Titan X GPU and OpenCV on an i7-7700HQ; ours are
whatever device ``benchmark.json`` names.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np

from usp_jax.evaluation.protocol import METRICS
from usp_jax.evaluation.statistics import (
    bootstrap_intervals,
    per_pair,
    relative_changes,
)

# The metrics by key, in the order of the paper's columns, with their column titles.
TITLES = {"rs": "RS", "le": "LE", "ha1": "HA e=1", "ha3": "HA e=3", "ha5": "HA e=5", "ms": "MS"}
# The paper's columns with NMS 4: homography accuracy and matching score only.
NMS_METRICS = ("ha1", "ha3", "ha5", "ms")


def _row(*values: float, metrics: tuple[str, ...] = tuple(TITLES)) -> dict[str, float]:
    """One row of a paper's table, its values in the order of ``metrics``, by metric key."""
    return dict(zip(metrics, values, strict=True))


# The paper's Table 2 (RS, LE) and Table 3 (HA at eps 1/3/5, MS; NMS 0 unless noted), HPatches.
PAPER = {
    "240x320": {
        "ORB": _row(0.532, 1.429, 0.131, 0.422, 0.540, 0.218),
        "AKAZE": _row(0.599, 1.007, 0.378, 0.724, 0.791, 0.311),
        "BRISK": _row(0.566, 1.077, 0.414, 0.767, 0.826, 0.258),
        "SIFT": _row(0.451, 0.855, 0.622, 0.845, 0.878, 0.304),
        "UnsuperPoint": _row(0.645, 0.832, 0.579, 0.855, 0.903, 0.424),
    },
    "480x640": {
        "ORB": _row(0.525, 1.430, 0.286, 0.607, 0.710, 0.204),
        "AKAZE": _row(0.572, 1.126, 0.369, 0.743, 0.812, 0.289),
        "BRISK": _row(0.505, 1.207, 0.300, 0.653, 0.746, 0.211),
        "SIFT": _row(0.421, 1.011, 0.602, 0.833, 0.876, 0.265),
        "UnsuperPoint": _row(0.612, 0.991, 0.493, 0.843, 0.905, 0.383),
    },
    "240x320 NMS 4": {
        "SIFT": _row(0.636, 0.829, 0.871, 0.248, metrics=NMS_METRICS),
        "UnsuperPoint": _row(0.557, 0.871, 0.921, 0.501, metrics=NMS_METRICS),
    },
}
# The paper's speed table (frames per second at 240x320, 480x640).
PAPER_FPS = {
    "ORB": (91, 33),
    "SIFT": (47, 12),
    "AKAZE": (100, 18),
    "BRISK": (18, 5),
    "UnsuperPoint, b1": (119, 65),
    "UnsuperPoint, b10": (323, 90),
}
SPEED_FILE = "benchmark.json"
FILES = {
    "240x320": "heldout_240x320.json",
    "480x640": "heldout_480x640.json",
    "240x320 NMS 4": "heldout_240x320_nms4.json",
}
# The same weights run on 2x enlarged images (``--upsample 2``), shown under the paper's
# detector when the file exists; the paper has no such row.
UPSAMPLED = "UnsuperPoint, upsample 2"
UPSAMPLED_FILES = {setting: name.replace(".json", "_up2.json") for setting, name in FILES.items()}


# Table 1: the configurations C0-C4 (experiments/table1.py trains and evaluates them).
CONFIGS = {
    "C0": {"interpolate": False, "uniform": False, "decorrelation": False},
    "C1": {"interpolate": True, "uniform": False, "decorrelation": False},
    "C2": {"interpolate": False, "uniform": True, "decorrelation": False},
    "C3": {"interpolate": False, "uniform": False, "decorrelation": True},
    "C4": {"interpolate": True, "uniform": True, "decorrelation": True},
}
# Logged training statistics that show what each module does (means over a run's last steps).
TRAINING_STATS = {
    "usp/mean_d": "d_k (px)",
    "usp/K": "K pairs",
    "pred/relative_at_edge": "positions in outer 5% of cell",
    "desc/sim_positive": "sim. positive",
    "desc/sim_negative": "sim. negative",
}
# The paper's Table 1 (HPatches, 240x320, 300 points): C0 and C4 as values, C1-C4 in percent of C0.
PAPER_TABLE1 = {
    "C0": _row(0.633, 0.898, 0.519, 0.812, 0.871, 0.458),
    "C1": _row(1.1, 1.0, 0.0, 1.9, 2.0, 6.7),
    "C2": _row(1.9, 4.8, 15.3, 5.5, 4.0, 3.2),
    "C3": _row(0.2, 4.4, 8.3, 0.6, 2.6, 3.3),
    "C4": _row(1.9, 7.4, 7.3, 7.2, 5.7, 9.4),
    "C4 values": _row(0.612, 0.991, 0.521, 0.831, 0.902, 0.452),
}


def table1_markdown(summary: dict, changes: dict, intervals: dict, steps: int, pairs: int) -> str:
    """The paper's layout, ours (paper's) in every cell, the bootstrap interval under a change."""
    header = "| config | interp. | uniformXY | decorr. | RS | LE | HA e=1 | HA e=3 | HA e=5 | MS |"
    lines = [header, "|" + "---|" * 10]

    def flags(name):
        return " | ".join("x" if on else "" for on in CONFIGS[name].values())

    def values(name, paper):
        return " | ".join(f"{summary[name][m]:.3f} ({paper[m]:.3f})" for m in METRICS)

    lines.append(f"| C0 base | {flags('C0')} | {values('C0', PAPER_TABLE1['C0'])} |")
    for name in ("C1", "C2", "C3", "C4"):
        row = " | ".join(
            f"{changes[name][m]:+.1f}% ({PAPER_TABLE1[name][m]:+.1f}%)<br>"
            f"[{intervals[name][m][0]:+.1f}, {intervals[name][m][1]:+.1f}]"
            if math.isfinite(changes[name][m])
            else f"n/a ({PAPER_TABLE1[name][m]:+.1f}%)"
            for m in METRICS
        )
        lines.append(f"| {name} | {flags(name)} | {row} |")
    lines.append(f"| C4 UnsuperPoint | {flags('C4')} | {values('C4', PAPER_TABLE1['C4 values'])} |")
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
    table = table1_markdown(summary, changes, intervals, steps, pairs)
    if training:
        table += "\n\n" + training_markdown(training)
    summary_json = {
        "steps": steps,
        "summary": summary,
        "relative": changes,
        "intervals": intervals,
        "paper": PAPER_TABLE1,
        "training": training,
        "evaluation": evaluated,
    }
    return summary_json, table


def table(ours: dict, paper: dict, metrics: tuple[str, ...]) -> list[str]:
    """Rows 'method | ours (paper) | ...' for every method we evaluated."""
    lines = [
        "| method | " + " | ".join(f"{TITLES[m]} ours (paper)" for m in metrics) + " |",
        "|---|" + "---|" * len(metrics),
    ]
    for method, values in ours.items():
        cells = []
        for metric in metrics:
            theirs = paper.get(method, {}).get(metric)
            value = values["all"][metric]
            ours_text = "-" if value is None else f"{value:.3f}"
            cells.append(ours_text + (f" ({theirs:.3f})" if theirs is not None else ""))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def with_upsampled(ours: dict, path: pathlib.Path) -> dict:
    """``ours`` with the upsampled model's summary inserted after UnsuperPoint, if ``path`` is a
    file (an ``evaluate --upsample 2 --json`` of the same setting)."""
    if not path.is_file():
        return ours
    upsampled = json.loads(path.read_text())["summary"]["UnsuperPoint"]
    merged = {}
    for method, values in ours.items():
        merged[method] = values
        if method == "UnsuperPoint":
            merged[UPSAMPLED] = upsampled
    return merged


def speed_table(benchmark: dict) -> list[str]:
    """Rows 'detector | fps ours (paper) at 240x320 | ... at 480x640' from a benchmark JSON."""
    resolutions = ((240, 320), (480, 640))
    fps = {}
    for row in benchmark["rows"]:
        label = row["method"]
        if label == "UnsuperPoint":
            label = f"UnsuperPoint, b{row['batch']}"
        fps[label, row["height"], row["width"]] = row["fps"]
    lines = [
        "| detector | " + " | ".join(f"FPS @ {h}x{w} ours (paper)" for h, w in resolutions) + " |",
        "|---|" + "---|" * len(resolutions),
    ]
    for label in dict.fromkeys(key[0] for key in fps):
        cells = []
        for column, (h, w) in enumerate(resolutions):
            value = fps.get((label, h, w))
            theirs = PAPER_FPS.get(label, (None, None))[column]
            text = "-" if value is None else f"{value:.1f}"
            cells.append(text + (f" ({theirs})" if theirs is not None else ""))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", required=True, help="folder with the evaluate --json files")
    args = parser.parse_args()
    folder = pathlib.Path(args.results)
    out = []
    for setting, name in FILES.items():
        path = folder / name
        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: run the evaluation commands of RESULTS.md")
        ours = with_upsampled(
            json.loads(path.read_text())["summary"], folder / UPSAMPLED_FILES[setting]
        )
        out += [f"### {setting}, {'300' if setting.startswith('240') else '1000'} points", ""]
        metrics = NMS_METRICS if "NMS" in setting else tuple(TITLES)
        out += table(ours, PAPER[setting], metrics) + [""]
    speed = folder / SPEED_FILE
    if speed.is_file():
        benchmark = json.loads(speed.read_text())
        out += [
            f"### Speed: UnsuperPoint on {benchmark['device']} ({benchmark['platform']}), "
            f"OpenCV on {benchmark['host']}",
            "",
        ]
        out += speed_table(benchmark) + [""]
    print("\n".join(out).rstrip())


if __name__ == "__main__":
    main()
