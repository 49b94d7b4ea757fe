"""The paper's Figures 4 and 5 for a trained model: histograms of point-pair distances d_k and of
scores (Fig. 4), and of x-coordinate predictions inside the cell (Fig. 5), with and without the
uniform loss when a second checkpoint trained without it is given; and, for a training workdir,
the logged statistics against step (``training_curves.png``), over all stages of a run that was
continued with ``--init`` when the earlier workdirs are given.

The statistics come from the training framework itself (section 3): held-out photos, a random
homography T per photo, both branches through the model in inference mode, point-pairs as in
section 4. From the repository root::

    python3 experiments/figures.py --checkpoint runs/corpus-cpu-stage3 --photos data/corpus/heldout \
        --out experiments/results/figures --earlier-stages runs/corpus-cpu runs/corpus-cpu-stage2 \
        [--without-uniform runs/no-uniform]

About a minute on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from usp_jax.core import geometry, losses
from usp_jax.core.model import UnsuperPoint
from usp_jax.evaluation import plotting
from usp_jax.inference import weights
from usp_jax.training import checkpoint, crops, data
from usp_jax.training import metrics as metrics_lib


def pair_statistics(checkpoint_dir, photos, height=240, width=320, seed=0):
    """d_k of point-pairs, scores and relative x of every point over the photos' random pairs."""
    cfg = checkpoint.load_config(checkpoint_dir)
    _, variables = weights.load_checkpoint(checkpoint_dir)
    model = UnsuperPoint(cfg.model)
    source = data.open_source(str(photos))
    rng = np.random.default_rng(seed)

    @jax.jit
    def run(image, key):
        h = geometry.sample_homography(key, height, width, cfg.homography)
        warped, _ = geometry.warp_image(image, h, (height, width))
        pred = model.apply(variables, jnp.stack([image, warped]))
        a, b = jax.tree.map(lambda x: x[0], pred), jax.tree.map(lambda x: x[1], pred)
        corr = losses.branch_correspondences(a, b, h, height, width, cfg.loss.eps_correspond)
        return corr.d, corr.paired, pred.scores, pred.relative[..., 0]

    d, scores, rel_x = [], [], []
    for i in range(len(source)):
        for repeat in range(4):
            crop = crops.random_crop(rng, source[i], height, width, (0.5, 1.0))
            key = jax.random.PRNGKey(seed * 1000 + i * 10 + repeat)
            dk, paired, s, x = jax.device_get(run(jnp.asarray(crop, jnp.float32) / 255, key))
            d.append(dk[paired])
            scores.append(s.ravel())
            rel_x.append(x.ravel())
    return np.concatenate(d), np.concatenate(scores), np.concatenate(rel_x)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--photos", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--without-uniform", help="checkpoint of a run with loss.alpha_uni_xy=0")
    parser.add_argument(
        "--earlier-stages",
        nargs="*",
        default=[],
        metavar="WORKDIR",
        help="workdirs of the stages before --checkpoint, in training order",
    )
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    d, scores, rel_x = pair_statistics(args.checkpoint, args.photos)
    fig4 = {  # file: (values by label, x label, title)
        "fig4a_pair_distances.png": (
            {"point-pairs": d},
            "d_k (px)",
            "Point-pair distances d_k (paper Fig. 4a)",
        ),
        "fig4b_scores.png": ({"all points": scores}, "score", "Scores (paper Fig. 4b)"),
    }
    for file, (values, xlabel, title) in fig4.items():
        plotting.plot_histograms(values, out / file, bins=40, xlabel=xlabel, title=title)
    series = {"with uniform loss": 8 * rel_x}
    if args.without_uniform:
        series["without uniform loss"] = 8 * pair_statistics(args.without_uniform, args.photos)[2]
    plotting.plot_histograms(
        series,
        out / "fig5_x_in_cell.png",
        bins=np.linspace(0, 8, 33),
        xlabel="x inside the 8 px cell",
        density=True,
        title="x-coordinate predictions (paper Fig. 5)",
    )
    stages = [
        metrics_lib.read_metrics(workdir) for workdir in [*args.earlier_stages, args.checkpoint]
    ]
    if stages[-1]:  # a training workdir: also its logged statistics over the run
        rows, starts = metrics_lib.chain_stages(stages)
        plotting.plot_training_curves(rows, out / "training_curves.png", stage_starts=starts)
    print(
        f"median d_k {np.median(d):.2f} px over {d.size} pairs; score mean {scores.mean():.3f} "
        f"std {scores.std():.3f}; share of x within 0.4 px of a cell edge "
        f"{np.mean((rel_x < 0.05) | (rel_x > 0.95)):.3f}"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
