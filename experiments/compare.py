"""Three questions about evaluations written by ``usp-jax evaluate --json``: did a new model change
anything beyond the choice of pairs, and at which viewpoint strength and which in-plane rotation
each method loses its homography accuracy.

    python3 experiments/compare.py experiments/results/heldout_240x320.json \
        --against experiments/results/stage5/heldout_240x320.json --rotation data/heldout-pairs

prints, per view k of the viewpoint scenes (``usp-jax make-pairs`` draws view k = 2 ... 6 with
growing rotation, scale and keystone), every method's HA at eps 1/3/5, median corner error, LE,
RS and MS; with ``--zoom PAIRS`` the same per zoom bin (``usp-jax make-pairs --zoom``); with
``--rotation PAIRS`` the same per range of the pairs' in-plane rotation, read
from their homographies, for every method in the file (0-10, 10-20, >=20 degrees, or 30-degree
ranges up to 180 when some pair turns by 60 or more, as ``usp-jax make-pairs --rotation 180``
makes them); and with ``--against``, the change of that file's UnsuperPoint against
the first file's, in percent and as a difference, each with its 95% paired-bootstrap interval
over the pairs (as Table 1's, ``experiments/table1.py``); that model also joins the rotation
table and the intervals as the method ``UnsuperPoint [FOLDER]``, FOLDER its file's folder.
``--intervals`` adds every method's mean with its 95% bootstrap interval over the pairs:

    python3 experiments/compare.py experiments/results/heldout_240x320.json \
        --against experiments/results/fast-v3/heldout_240x320.json --intervals

Files evaluated with different ``--ransac-orders`` are not compared: a share of RANSAC orders
and the protocol's single estimate are different numbers.

``--versus-baselines`` prints, over the viewpoint pairs, the ``--against`` model's HA and MS
minus each other method's of the first file (the baselines), with 95% paired-bootstrap
intervals; each ``--pool RESULTS AGAINST`` adds one more draw of pairs (another
``usp-jax make-pairs --seed``) to that comparison:

    python3 experiments/compare.py A.json --against B.json --versus-baselines --pool A2.json B2.json

With ``--zoom`` naming one evaluated folder per draw (the first, then each ``--pool``'s), that
comparison is also printed for each zoom bin, over the bin's pairs of all draws:

    python3 experiments/compare.py A.json --against B.json --versus-baselines \
        --pool A2.json B2.json --zoom PAIRS PAIRS2
"""

from __future__ import annotations

import argparse
import json
import pathlib

from usp_jax.evaluation.analysis import (
    by_rotation,
    by_view,
    by_zoom,
    markdown_by_view,
    zoom_bin_label,
    zoom_bins,
)
from usp_jax.evaluation.protocol import METRICS
from usp_jax.evaluation.statistics import (
    MODEL,
    mean_intervals,
    paired_change,
    paired_difference,
    per_pair,
)


def _parser() -> argparse.ArgumentParser:
    """The command line (module docstring)."""
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
        "--zoom",
        metavar="PAIRS",
        nargs="+",
        help="also break the viewpoint pairs down by zoom (<0.71, 0.71-1, 1-1.41, >=1.41, from"
        " their homographies at image 1's centre), reading them from PAIRS, the evaluated folder;"
        " with --versus-baselines, one folder per draw (the first, then each --pool's) also"
        " breaks that comparison down by zoom",
    )
    parser.add_argument(
        "--intervals",
        action="store_true",
        help="every method's mean with its 95%% bootstrap interval over the pairs",
    )
    parser.add_argument(
        "--versus-baselines",
        action="store_true",
        help="the --against model against each other method of RESULTS on the viewpoint pairs",
    )
    parser.add_argument(
        "--pool",
        nargs=2,
        action="append",
        default=[],
        metavar=("RESULTS", "AGAINST"),
        help="with --versus-baselines: one more draw of pairs, pooled with the first",
    )
    parser.add_argument("--rounds", type=int, default=2000, help="bootstrap resamples")
    return parser


def main() -> None:
    parser = _parser()
    args = parser.parse_args()
    if (args.versus_baselines or args.pool) and not args.against:
        parser.error("--versus-baselines and --pool compare the --against model: give --against")
    if args.pool and not args.versus_baselines:
        parser.error("--pool pools draws for --versus-baselines: give --versus-baselines")
    count = 1 + len(args.pool)
    if args.zoom and len(args.zoom) > 1 and (not args.versus_baselines or len(args.zoom) != count):
        parser.error(
            f"--zoom takes one folder, or with --versus-baselines one per draw ({count}),"
            f" got {len(args.zoom)}"
        )
    files = [args.results, *([args.against] if args.against else []), *sum(args.pool, [])]
    try:
        evaluations = {path: read_evaluation(path) for path in files}
    except (OSError, ValueError, KeyError) as error:
        parser.error(f"cannot read the evaluation JSON: {error}")
    orders = {path: count for path, (_, count) in evaluations.items()}
    if len(set(orders.values())) > 1:
        # A share of RANSAC orders and the protocol's single draw are not the same number.
        listed = ", ".join(f"{path}: {count}" for path, count in orders.items())
        parser.error(f"the files estimate HA over different numbers of RANSAC orders ({listed})")
    rows = evaluations[args.results][0]
    new_rows = evaluations[args.against][0] if args.against else None
    pooled = [(evaluations[a][0], evaluations[b][0]) for a, b in args.pool]
    print(markdown_by_view(by_view(rows)))
    # The second file's model joins the first file's methods as one more, labelled, method.
    label = pathlib.Path(args.against).parent.name if args.against else ""
    joined = rows + ([] if new_rows is None else labelled(new_rows, label))
    breakdowns = (
        ("--rotation", args.rotation, by_rotation, "rotation (deg)"),
        ("--zoom", args.zoom[0] if args.zoom else None, by_zoom, "zoom"),
    )
    for flag, pairs, breakdown, group in breakdowns:
        if pairs:
            try:
                table = breakdown(joined, pairs)
            except (OSError, ValueError) as error:
                parser.error(f"{flag} {pairs}: {error}")
            print("\n" + markdown_by_view(table, group=group))
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
    if args.versus_baselines:
        draws = [(rows, new_rows), *pooled]
        try:
            table = versus_baselines(draws, args.rounds)
        except ValueError as error:
            parser.error(f"--versus-baselines: a draw's two files differ in their pairs: {error}")
        print("\n" + table)
        if args.zoom and len(args.zoom) == len(draws):
            try:
                print(versus_baselines_by_zoom(draws, args.zoom, args.rounds))
            except (OSError, ValueError) as error:
                parser.error(f"--zoom: {error}")


def read_evaluation(path: str) -> tuple[list[dict], int]:
    """The per-pair rows of a ``usp-jax evaluate --json`` file, and how many RANSAC orders its HA
    is over (1: the protocol's single estimate; files written before ``--ransac-orders`` existed
    are that)."""
    evaluation = json.loads(pathlib.Path(path).read_text())
    return evaluation["pairs"], int(evaluation.get("config", {}).get("ransac_orders", 1))


def versus_baselines(
    draws: list[tuple[list[dict], list[dict]]], rounds: int, keep=lambda draw, row: True
) -> str:
    """A markdown table: over the viewpoint pairs of every draw (rows, new rows) pooled, the new
    rows' model's HA at eps 1/3/5 and MS minus each other method's in the first rows, with the
    95% paired-bootstrap interval (``statistics.paired_difference``); only the pairs that
    ``keep(draw index, row)`` accepts (a zoom bin's, say)."""
    model, others = [], []
    for index, (rows, new_rows) in enumerate(draws):
        model += _viewpoint_rows(new_rows, index, lambda r: r["method"] == MODEL and keep(index, r))
        others += _viewpoint_rows(rows, index, lambda r: r["method"] != MODEL and keep(index, r))
    shown = ("ha1", "ha3", "ha5", "ms")
    lines = [
        f"{MODEL} of the --against file(s) minus each method, {len(model)} viewpoint pairs"
        f" of {len(draws)} draw(s) (difference [95% paired-bootstrap interval]):",
        "| method | " + " | ".join(shown) + " |",
        "|---" * (len(shown) + 1) + "|",
    ]
    for name in dict.fromkeys(r["method"] for r in others):
        # paired_difference compares the model's rows of two evaluations: the baseline's rows
        # stand in as the "base" evaluation's model.
        base = [{**r, "method": MODEL} for r in others if r["method"] == name]
        differences = paired_difference(base, model, rounds)
        cells = [
            f"{difference:+.3f} [{low:+.3f}, {high:+.3f}]"
            for difference, (low, high) in (differences[m] for m in shown)
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def versus_baselines_by_zoom(
    draws: list[tuple[list[dict], list[dict]]], folders: list[str], rounds: int
) -> str:
    """:func:`versus_baselines` once per zoom bin, over the bin's pairs of all draws, each
    draw's zooms read from its evaluated folder (``analysis.zoom_bins``)."""
    bins = [zoom_bins(new_rows, pairs) for (_, new_rows), pairs in zip(draws, folders)]
    tables = []
    for index in sorted(set().union(*(b.values() for b in bins))):
        table = versus_baselines(
            draws, rounds, keep=lambda draw, r: bins[draw][r["scene"], r["k"]] == index
        )
        tables.append(f"\nzoom {zoom_bin_label(index)}: {table}")
    return "\n".join(tables)


def _viewpoint_rows(rows: list[dict], draw: int, keep) -> list[dict]:
    """The viewpoint rows that ``keep(row)`` accepts, scenes prefixed by the draw: scene names
    repeat across draws of the same photos, and the draw keeps the pairs apart."""
    return [{**r, "scene": f"{draw}/{r['scene']}"} for r in rows if r["split"] == "v" and keep(r)]


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
