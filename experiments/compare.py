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
the first file's, in percent, with the 95% paired-bootstrap interval over the pairs that Table 1
uses (``experiments/table1.py``). ``--intervals`` adds every method's mean with its 95% bootstrap
interval over the pairs (the ``--against`` model as one more row, labelled by its file's folder):

    python3 experiments/compare.py experiments/results/heldout_240x320.json \
        --against experiments/results/fast-v3/heldout_240x320.json --intervals
"""

from __future__ import annotations

import argparse
import json
import pathlib

from usp_jax.evaluation.analysis import by_rotation, by_view, markdown_by_view
from usp_jax.evaluation.protocol import METRICS
from usp_jax.evaluation.statistics import MODEL, mean_intervals, paired_change, per_pair


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
    if args.rotation:
        try:
            rotation_table = by_rotation(rows, args.rotation)
        except (OSError, ValueError) as error:
            parser.error(f"--rotation {args.rotation}: {error}")
        print("\n" + markdown_by_view(rotation_table, group="rotation (deg)"))
    if args.intervals:
        against = {} if new_rows is None else {pathlib.Path(args.against).parent.name: new_rows}
        print("\n" + intervals_markdown(rows, against, args.rounds))
    if new_rows is not None:
        try:
            changes = paired_change(rows, new_rows, args.rounds)
        except ValueError as error:
            parser.error(f"{args.against} against {args.results}: {error}")
        print(f"\n{MODEL} of {args.against} against {args.results}, % change (positive = better):")
        for metric, (change, (low, high)) in changes.items():
            print(f"  {metric:4s} {change:+6.1f}%  [{low:+.1f}, {high:+.1f}]")


def intervals_markdown(rows: list[dict], against: dict[str, list[dict]], rounds: int) -> str:
    """A markdown table of every method's mean and 95% bootstrap interval, per metric; the model
    rows of each ``against`` evaluation join as ``UnsuperPoint [label]``."""
    rows = list(rows)
    for label, other in against.items():
        rows += [{**r, "method": f"{MODEL} [{label}]"} for r in other if r["method"] == MODEL]
    # One pair order for every method, so the bootstrap draws the same pairs for all of them.
    rows.sort(key=lambda r: (r["scene"], r["k"]))
    table = mean_intervals(per_pair(rows), rounds)
    lines = ["| method | " + " | ".join(METRICS) + " |", "|---" * (len(METRICS) + 1) + "|"]
    for name, metrics in table.items():
        cells = [f"{mean:.3f} [{low:.3f}, {high:.3f}]" for mean, (low, high) in metrics.values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    pairs = len(next(iter(per_pair(rows).values()))[METRICS[0]])
    lines.append(f"\nmean [95% bootstrap interval over the {pairs} pairs, {rounds} resamples]")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
