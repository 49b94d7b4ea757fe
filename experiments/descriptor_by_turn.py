"""Where the descriptor breaks: warped pairs of held-out photos at the changes two real exposures
make (graf, box), scored by the real-pair metrics and broken down by the pair's in-plane turn
and scale.

Each photo, shrunk to 640 px on its longer side, is warped by random homographies: a scale
log-uniform in [0.5, 1.6], a turn uniform in [-35, 35] degrees and a keystone, all about the
centre (graf1 -> 3 scales by about 0.9 and turns by about 20 degrees; box_in_scene shrinks the
box to about 0.6 and turns it). Every method then runs as in ``usp-jax evaluate --real``
(``evaluation.real_pairs.score_pair``: native size, its 1000 strongest points, mutual nearest
neighbours) and the table gives, per range of turn and of scale, the mean over pairs of the
repeatability and of the descriptor's share (repeatable image-1 points whose nearest neighbour
is their true partner), each with a 95% bootstrap interval over the pairs::

    PYTHONPATH=. python3 experiments/descriptor_by_turn.py --images data/corpus/heldout \\
        --weights paper --baselines SIFT --json experiments/results/real/descriptor_by_turn_paper.json

``--any-rotation`` turns image 2 back by the angle the shipped rotation guide estimates, as
``usp-jax match --any-rotation`` does; ``--true-turn`` by the pair's true turn, as a perfect
guide would; ``--turn-back`` by the turn the upright matches read (``usp-jax match
--turn-back``). ``--weights`` takes shipped names, weights files and
training checkpoints (several: one method each); ``--any-scale`` runs them on their pyramid. ``--compare A.json METHOD_A B.json METHOD_B``
prints B's method minus A's per range, paired over the pairs both files hold, with 95%
paired-bootstrap intervals (the same ``--seed`` and ``--per-photo`` draw the same pairs)::

    PYTHONPATH=. python3 experiments/descriptor_by_turn.py --compare \\
        experiments/results/real/descriptor_by_turn_paper.json paper \\
        experiments/results/real/descriptor_by_turn_turned.json runs/turned/checkpoints/900
"""

from __future__ import annotations

import argparse
import json
import pathlib

import cv2
import numpy as np

from usp_jax.evaluation.metrics import top_k
from usp_jax.evaluation.protocol import detect_both
from usp_jax.evaluation.real_pairs import RealPair, score_pair
from usp_jax.evaluation.zoom import zoom_of
from usp_jax.inference.detector import Detector
from usp_jax.inference.images import read_image
from usp_jax.inference.methods import as_method, baseline_method
from usp_jax.inference.turning import detect_turned, in_plane_rotation
from usp_jax.inference.weights import PRETRAINED

SIDE = 640
#: The ways to turn image 2 before detecting it: a guide network's angle, the true one, the
#: upright matches' own.
TURNS = ("any_rotation", "true_turn", "turn_back")
TOP = 1000
TURN_BINS = (0.0, 10.0, 20.0, 35.0)
SCALE_BINS = (0.5, 0.7, 0.9, 1.1, 1.6)


def random_homography(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """``[3, 3]``: a keystone, then a turn and a scale, all about the image centre."""
    scale = np.exp(rng.uniform(np.log(0.5), np.log(1.6)))
    angle = np.deg2rad(rng.uniform(-35.0, 35.0))
    centre = np.array([width / 2, height / 2])
    similarity = np.eye(3)
    similarity[:2, :2] = scale * np.array(
        [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    )
    keystone = np.eye(3)
    keystone[2, :2] = rng.uniform(-0.6, 0.6, 2) / np.array([width, height])
    to_centre, back = np.eye(3), np.eye(3)
    to_centre[:2, 2], back[:2, 2] = -centre, centre
    homography = back @ similarity @ keystone @ to_centre
    return homography / homography[2, 2]


def pairs(folder: pathlib.Path, per_photo: int, seed: int):
    """Yields (name, RealPair, turn in degrees, scale) for every photo under ``folder``; turning
    image 2 by the turn undoes the homography's (``turning.in_plane_rotation``)."""
    rng = np.random.default_rng(seed)
    for path in sorted(p for p in folder.iterdir() if p.is_file()):
        image = read_image(path)
        factor = SIDE / max(image.shape[:2])
        image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
        height, width = image.shape[:2]
        for index in range(per_photo):
            homography = random_homography(rng, height, width)
            warped = cv2.warpPerspective(image, homography, (width, height))
            name = f"{path.stem}-{index}"
            pair = RealPair(name, image, warped, "homography", "homography", homography)
            turn = in_plane_rotation(homography, (height, width))
            yield name, pair, turn, zoom_of(homography, (height, width))


def bootstrap(values: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = rng.choice(values, (draws, len(values))).mean(axis=1)
    return tuple(float(v) for v in np.percentile(means, [2.5, 97.5]))


def _cell(values: list[float], signed: bool = False) -> str:
    """``mean [low, high]`` of ``values`` with its 95% bootstrap interval over the pairs."""
    values = np.array(values)
    low, high = bootstrap(values)
    form = "+.3f" if signed else ".3f"
    return f"{values.mean():{form}} [{low:{form}}, {high:{form}}]"


def _ranges():
    for key, edges, unit in (("turn", TURN_BINS, " deg"), ("scale", SCALE_BINS, "x")):
        for low, high in zip(edges[:-1], edges[1:]):
            yield key, low, high, f"{key} {low:g}-{high:g}{unit}"


def compare(first: list[dict], second: list[dict]) -> str:
    """Second minus first, per range, over the pairs both hold (rows of one method each)."""
    before = {row["pair"]: row for row in first}
    both = [(before[row["pair"]], row) for row in second if row["pair"] in before]
    lines = ["| range | pairs | repeatability | descriptor's share |", "|---|---|---|---|"]
    for key, low, high, label in _ranges():
        inside = [(a, b) for a, b in both if low <= a[key] < high]
        if not inside:
            continue
        cells = [
            _cell([b[metric] - a[metric] for a, b in inside], signed=True)
            for metric in ("repeatability", "nn_share")
        ]
        lines.append(f"| {label} | {len(inside)} | {' | '.join(cells)} |")
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    methods = sorted({row["method"] for row in rows})
    lines = [
        "| method | range | pairs | repeatability | descriptor's share |",
        "|---|---|---|---|---|",
    ]
    for method in methods:
        mine = [row for row in rows if row["method"] == method]
        for key, low, high, label in _ranges():
            inside = [row for row in mine if low <= row[key] < high]
            if not inside:
                continue
            cells = [
                _cell([row[metric] for row in inside]) for metric in ("repeatability", "nn_share")
            ]
            lines.append(f"| {method} | {label} | {len(inside)} | {' | '.join(cells)} |")
    return "\n".join(lines)


def _detector(weights: str) -> Detector:
    """Shipped weights by name, else a weights file or a training workdir or checkpoint."""
    return Detector.pretrained(weights) if weights in PRETRAINED else Detector.load(weights)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=pathlib.Path)
    parser.add_argument("--compare", nargs=4, metavar=("A_JSON", "A_METHOD", "B_JSON", "B_METHOD"))
    parser.add_argument("--weights", nargs="*", default=["paper"])
    parser.add_argument("--baselines", nargs="*", default=["SIFT"])
    parser.add_argument(
        "--any-rotation",
        action="store_true",
        help="turn image 2 back by the rotation guide's angle",
    )
    parser.add_argument(
        "--true-turn",
        action="store_true",
        help="turn image 2 back by the pair's true turn (what a perfect guide would do)",
    )
    parser.add_argument(
        "--turn-back",
        action="store_true",
        help="turn image 2 back by the angle the upright matches read (turning.turn_back_pair)",
    )
    parser.add_argument("--any-scale", action="store_true", help="our detector on its pyramid")
    parser.add_argument("--per-photo", type=int, default=4)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args()
    if args.compare:
        first, second = (
            [r for r in json.loads(pathlib.Path(f).read_text())["rows"] if r["method"] == m]
            for f, m in (args.compare[:2], args.compare[2:])
        )
        print(compare(first, second))
        return
    if args.images is None:
        parser.error("--images is required (or --compare)")
    guide = Detector.pretrained("rotation") if args.any_rotation else None
    label = next((f" --{flag.replace('_', '-')}" for flag in TURNS if getattr(args, flag)), "")
    label += " --any-scale" if args.any_scale else ""
    ours = {
        w + label: _detector(w).replace(top_n=None, max_side=0, any_scale=args.any_scale)
        for w in args.weights
    }
    methods = [as_method(d, name, guide, args.turn_back) for name, d in ours.items()]
    methods += [baseline_method(name, TOP) for name in args.baselines]
    rows = []
    for name, pair, turn, scale in pairs(args.images, args.per_photo, args.seed):
        for method in methods:
            if args.true_turn and method.name in ours:
                detector = ours[method.name]
                found = detector.detect(pair.image1), detect_turned(detector, pair.image2, turn)
            else:
                found = detect_both(method, pair.image1, pair.image2)
            found = [top_k(f, TOP) for f in found]
            result = score_pair(pair, method.name, *found, method.norm)
            rows.append(
                dict(
                    pair=name,
                    method=method.name,
                    turn=abs(turn),
                    scale=scale,
                    correct=result.correct,
                    repeatability=result.repeatability,
                    nn_share=result.nn_share,
                )
            )
        print(name, f"turn {turn:.0f} scale {scale:.2f}", flush=True)
    print(table(rows))
    if args.json:
        config = {key: str(value) for key, value in vars(args).items()}
        args.json.write_text(json.dumps(dict(config=config, rows=rows), indent=1))


if __name__ == "__main__":
    main()
