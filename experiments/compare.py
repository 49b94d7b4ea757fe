"""Three questions about evaluations written by ``usp-jax evaluate --json``: did a new model change
anything beyond the choice of pairs, and at which viewpoint strength and which in-plane rotation
each method loses its homography accuracy.

    python3 experiments/compare.py experiments/results/heldout_240x320.json \
        --against experiments/results/stage5/heldout_240x320.json --rotation data/heldout-pairs

prints, per view k of the viewpoint scenes (``usp-jax make-pairs`` draws view k = 2 ... 6 with
growing rotation, scale and keystone), every method's HA at eps 1/3/5, median corner error, LE,
RS and MS; with ``--rotation PAIRS`` the same per range of the pairs' in-plane rotation, read
from their homographies, for every method in the file (0-10, 10-20, >=20 degrees, or 30-degree
ranges up to 180 when some pair turns by 60 or more, as ``usp-jax make-pairs --rotation 180``
makes them); and with ``--against``, the change of that file's UnsuperPoint against
the first file's, in percent and as a difference, each with its 95% paired-bootstrap interval
over the pairs (as Table 1's, ``experiments/table1.py``); that model also joins the rotation
table and the intervals as the method ``UnsuperPoint [FOLDER]``, FOLDER its file's folder.
``--intervals`` adds every method's mean with its 95% bootstrap interval over the pairs:

    python3 experiments/compare.py experiments/results/heldout_240x320.json \
        --against experiments/results/fast-v3/heldout_240x320.json --intervals
"""

from __future__ import annotations

import argparse
import json
import pathlib

from usp_jax.evaluation.analysis import by_rotation, by_view, markdown_by_view
from usp_jax.evaluation.protocol import METRICS
from usp_jax.evaluation.statistics import (
    MODEL,
    mean_intervals,
    paired_change,
    paired_difference,
    per_pair,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", help="JSON from usp-jax evaluate --json")
    parser.add_argument("--against", help="a second evaluation of the same pairs (a new model)")
    parser.add_argument(
        "--rotation",
        metavar="PAIRS",
        help="also break the viewpoint pairs down by in-plane rotation, reading "
        "their homographies from PAIRS, the evaluated folder",
    )
    parser.add_argument(
        "--intervals",
        action="store_true",
        help="every method's mean with its 95%% bootstrap interval over the pairs",
    )
    parser.add_argument("--rounds", type=int, default=2000, help="bootstrap resamples")
    args = parser.parse_args()
    try:
        rows = json.loads(pathlib.Path(args.results).read_text())["pairs"]
        new_rows = (
            json.loads(pathlib.Path(args.against).read_text())["pairs"] if args.against else None
        )
    except (OSError, ValueError, KeyError) as error:
        parser.error(f"cannot read the evaluation JSON: {error}")
    print(markdown_by_view(by_view(rows)))
    # The second file's model joins the first file's methods as one more, labelled, method.
    label = pathlib.Path(args.against).parent.name if args.against else ""
    joined = rows + ([] if new_rows is None else labelled(new_rows, label))
    if args.rotation:
        try:
            rotation_table = by_rotation(joined, args.rotation)
        except (OSError, ValueError) as error:
            parser.error(f"--rotation {args.rotation}: {error}")
        print("\n" + markdown_by_view(rotation_table, group="rotation (deg)"))
    if args.intervals:
        print("\n" + intervals_markdown(joined, args.rounds))
    if new_rows is not None:
        try:
            changes = paired_change(rows, new_rows, args.rounds)
            differences = paired_difference(rows, new_rows, args.rounds)
        except ValueError as error:
            parser.error(f"{args.against} against {args.results}: {error}")
        print(f"\n{MODEL} of {args.against} against {args.results} (positive = better):")
        for metric, (change, (low, high)) in changes.items():
            difference, (d_low, d_high) = differences[metric]
            print(
                f"  {metric:4s} {change:+6.1f}%  [{low:+.1f}, {high:+.1f}]"
                f"   difference {difference:+.3f}  [{d_low:+.3f}, {d_high:+.3f}]"
            )


def labelled(rows: list[dict], label: str) -> list[dict]:
    """The model's rows of an evaluation, as the method ``UnsuperPoint [label]``."""
    return [{**r, "method": f"{MODEL} [{label}]"} for r in rows if r["method"] == MODEL]


def intervals_markdown(rows: list[dict], rounds: int) -> str:
    """A markdown table of every method's mean and 95% bootstrap interval, per metric."""
    # One pair order for every method, so the bootstrap draws the same pairs for all of them.
    pairs = per_pair(sorted(rows, key=lambda r: (r["scene"], r["k"])))
    table = mean_intervals(pairs, rounds)
    lines = ["| method | " + " | ".join(METRICS) + " |", "|---" * (len(METRICS) + 1) + "|"]
    for name, metrics in table.items():
        cells = [f"{mean:.3f} [{low:.3f}, {high:.3f}]" for mean, (low, high) in metrics.values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    count = len(next(iter(pairs.values()))[METRICS[0]])
    lines.append(f"\nmean [95% bootstrap interval over the {count} pairs, {rounds} resamples]")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
