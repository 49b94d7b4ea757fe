"""The quick-start job (``usp-jax demo``, ``usp_jax.demo()``): the shipped weights evaluated
against ORB and SIFT on HPatches-layout pairs made from bundled photos the model never saw,
offline, in about 20 s on 2 idle CPU cores (29 s of CPU time), with a keypoint and a matches PNG.

It sits above training and evaluation: without shipped weights it trains briefly instead.
"""

from __future__ import annotations

import pathlib
import sys
import time

from usp_jax.evaluation import plotting, protocol
from usp_jax.evaluation.pairs import make_pairs
from usp_jax.inference import weights
from usp_jax.inference.detector import Detector
from usp_jax.inference.images import sample_photos

#: Package photos held out of the shipped weights' training corpus (experiments/build_corpus.py).
DEMO_PHOTOS = ("coffee.png", "chelsea.png", "rocket.jpg")
#: Where the demo writes when no folder is given: under the current folder, the user's own.
DEFAULT_OUT = pathlib.Path("usp-jax-demo")
#: What the table's columns mean, one line each (docs: the evaluation protocol; paper section 5).
METRIC_LEGEND = (
    "RS: repeatability, the share of points found again within 3 px in the other image (higher"
    " is better)",
    "LE: localisation error, the mean distance in px of those repeated points (lower is better)",
    "HA e=1/3/5: homography accuracy, the share of pairs whose RANSAC homography from descriptor"
    " matches puts the image corners within e px of the truth on average (higher is better)",
    "MS: matching score, the share of nearest-neighbour descriptor matches that land within 3 px"
    " of the true position (higher is better)",
)


def demo(
    out: str | pathlib.Path = DEFAULT_OUT, weights_name: str | None = None
) -> protocol.Results:
    """Runs the demo into ``out`` (pairs, PNGs; ``out/train`` if it has to train) and prints the
    evaluation table; returns its results. ``weights_name``: shipped weights by name (None: the
    default); a named one that is missing is an error, not a reason to train."""
    start = time.perf_counter()
    if weights_name is not None:
        weights.pretrained_path(weights_name)  # an unknown name: one line, before any output
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    print("[1/3] loading the model", file=sys.stderr)
    try:
        detector = Detector.pretrained(weights_name)
        name = weights_name or weights.DEFAULT_PRETRAINED
        print(f"model: the {name!r} weights shipped with usp-jax")
        about = "photos the shipped model never saw"
    except FileNotFoundError:
        if weights_name:
            raise
        detector = _short_training(out / "train")
        about = "photos the short training saw too (no shipped weights)"
    photos = {
        path.name: path for distribution, path in sample_photos() if distribution == "scikit-image"
    }
    print("[2/3] building HPatches-layout pairs from the bundled photos", file=sys.stderr)
    make_pairs(
        [photos[name] for name in DEMO_PHOTOS],
        out / "pairs",
        seed=0,
        size=(480, 640),
        progress=True,
    )
    print("[3/3] evaluating against ORB and SIFT", file=sys.stderr)
    methods = protocol.methods(detector, ("orb", "sift"), top_k=300)
    results = protocol.evaluate(
        methods, out / "pairs", height=240, width=320, top_k=300, nms=0, progress=True
    )
    print(f"\npairs made from {about}")
    print(protocol.format_table(results))  # its first line: the size, points and NMS
    print("\n" + "\n".join(METRIC_LEGEND))
    matches = plotting.plot_example_pair(methods[0], out / "pairs", out, (240, 320), 300, 0)
    for path in example_pair_files(matches):
        print(f"wrote {path}")
    print(f"demo finished in {time.perf_counter() - start:.0f} s; outputs in {out}")
    return results


def example_pair_files(matches: pathlib.Path) -> list[pathlib.Path]:
    """The PNGs ``plotting.plot_example_pair`` writes, given the matches PNG it returns: the
    first image's keypoints beside it, then the matches."""
    keypoints = matches.with_name(matches.name.removesuffix("_matches.png") + "_keypoints.png")
    return [keypoints, matches]


def _short_training(workdir: pathlib.Path) -> Detector:
    from usp_jax.training import config as config_lib
    from usp_jax.training.train import fit

    print("no shipped weights: a short training on the bundled photos", file=sys.stderr)
    fit(config_lib.override(config_lib.cpu(), ["num_steps=150", "checkpoint_every=150"]), workdir)
    return Detector.from_checkpoint(workdir)
