"""bfloat16 compute (``model.dtype=bfloat16``) against float32: the same tiny run, both loss curves.

Accelerators run convolutions in bfloat16 at several times the float32 rate; the parameters,
the optimizer state and the losses stay float32 (``model.ModelConfig.dtype``). This checks on
the CPU that training in bfloat16 follows the float32 run. The paper's network on 64x80 crops of
the photos bundled with the installed packages, batch 4, 300 steps, the learning rate decaying
on a cosine; the descriptor terms are rescaled to the 80 cells of such a crop as
``cpu_photos.py`` rescales them to 320 (lambda_d x 80 / 1200, alpha_desc x 1200 / 80). From the
repository root::

    usp-jax train --config experiments/mixed_precision.py --data sample --workdir runs/mp-f32
    usp-jax train --config experiments/mixed_precision.py --data sample --workdir runs/mp-bf16 \\
        model.dtype=bfloat16
    usp-jax train --config experiments/mixed_precision.py --data sample --workdir runs/mp-f32-seed1 \\
        seed=1
    python3 experiments/mixed_precision.py float32=runs/mp-f32 bfloat16=runs/mp-bf16 \\
        "float32, seed 1=runs/mp-f32-seed1" --out experiments/results/mixed_precision.png

The second float32 run (another initialisation and order of crops) measures how far two runs
drift apart without any change of precision. The last command draws the runs' loss terms
against step and prints the means of their first and last 50 steps (experiments/RESULTS.md,
"Mixed precision").
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from usp_jax import config as config_lib

#: Steps averaged for the start and the end of a run in the printed summary.
WINDOW = 50
#: Logged terms drawn, one panel each.
TERMS = ("loss", "loss/usp", "loss/uni_xy", "loss/desc", "loss/decorr", "usp/mean_d")


def get_config() -> config_lib.Config:
    return config_lib.override(
        config_lib.paper(),
        [
            "data.height=64",
            "data.width=80",
            "data.scale_range=(0.25, 0.5)",
            "batch_size=4",
            "loss.lambda_d=16.7",
            "loss.alpha_desc=0.015",
            "num_steps=300",
            "optim.decay_steps=300",
            "checkpoint_every=300",
            "log_every=1",
            "keep_checkpoints=1",
        ],
    )


def smooth(values: np.ndarray, width: int = 10) -> np.ndarray:
    """Running mean over ``width`` steps ([N] -> [N - width + 1]): one step's loss is mostly the
    noise of its random homographies."""
    return np.convolve(values, np.ones(width) / width, mode="valid")


def curves(workdir: str | pathlib.Path) -> dict[str, np.ndarray]:
    """{term: [steps]} of a workdir's metrics, plus "step"; a step logged twice keeps its last row."""
    from usp_jax.training.metrics import read_metrics

    rows = {row["step"]: row for row in read_metrics(workdir)}
    steps = sorted(rows)
    return {
        name: np.array([rows[s].get(name, np.nan) for s in steps], float)
        for name in ("step", *TERMS)
    }


def summary(runs: dict[str, dict[str, np.ndarray]]) -> str:
    """One line per run and term: mean of the first and of the last ``WINDOW`` steps."""
    lines = []
    for name, run in runs.items():
        parts = [
            f"{term} {np.mean(run[term][:WINDOW]):.4g} -> {np.mean(run[term][-WINDOW:]):.4g}"
            for term in TERMS
        ]
        lines.append(f"{name} ({len(run['step'])} steps): " + ", ".join(parts))
    return "\n".join(lines)


def plot(runs: dict[str, dict[str, np.ndarray]], out: str | pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, 3, figsize=(12, 6), constrained_layout=True)
    for axis, term in zip(axes.flat, TERMS):
        for name, run in runs.items():
            values = smooth(run[term])
            axis.plot(run["step"][len(run["step"]) - len(values) :], values, label=name)
        axis.set_title(f"{term} (10-step mean)")
        axis.set_xlabel("step")
    axes.flat[0].legend()
    figure.savefig(out, dpi=100)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="NAME=WORKDIR", help="runs to compare")
    parser.add_argument("--out", required=True, help="PNG to write")
    args = parser.parse_args()
    runs = {name: curves(workdir) for name, workdir in (r.rsplit("=", 1) for r in args.runs)}
    print(summary(runs))
    plot(runs, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
