"""``usp-jax train``: self-supervised training on a folder of photos or a TFDS dataset
(``training.train.fit``), resumed from its workdir when re-run, alone or as one process of a
multi-process run."""

from __future__ import annotations

import pathlib
import signal

from usp_jax.cli import arguments
from usp_jax.cli.errors import user_error
from usp_jax.inference.weights import PRETRAINED


def add_parser(subparsers) -> None:
    """The ``train`` subcommand: data, workdir, config, distributed run and overrides."""
    p = subparsers.add_parser(
        "train", help="self-supervised training (resumes an existing workdir)"
    )
    p.add_argument(
        "--data",
        help="an image folder, tfds:NAME[:SPLIT], 'sample' (the photos bundled with the installed"
        " packages) or pairs:FOLDER (views with depth and pose); required unless --config sets it",
    )
    p.add_argument(
        "--workdir", required=True, help="checkpoints, config.json, metrics, TensorBoard"
    )
    p.add_argument("--config", default="paper", help="preset (paper, cpu) or experiments/*.py file")
    p.add_argument(
        "--steps",
        type=arguments.positive,
        help="train up to this step (num_steps=N; giving both, they must agree)",
    )
    p.add_argument("--init", help="start from these weights (.npz from `usp-jax export`)")
    p.add_argument(
        "--teacher",
        metavar="NAME|PATH",
        help="distil a frozen teacher into the trained network (sets distill.teacher): shipped"
        f" weights by name ({', '.join(PRETRAINED)}), a .npz weights file or a training workdir;"
        " its scores, positions and descriptors on both branches become targets beside the"
        " paper's losses (weights: distill.alpha_self, distill.beta_*; see experiments/distill.py)",
    )
    p.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-process run (one process per host or accelerator); the"
        " cluster is detected as JAX does (SLURM, Open MPI, Cloud TPU,"
        " Kubernetes) unless the three options below are given",
    )
    p.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="address of process 0, which runs the coordination service (implies --distributed)",
    )
    p.add_argument(
        "--num-processes",
        type=arguments.positive,
        metavar="N",
        help="processes in the run (implies --distributed)",
    )
    p.add_argument(
        "--process-id",
        type=arguments.non_negative,
        metavar="I",
        help="this process's index, 0 to N-1 (implies --distributed)",
    )
    p.add_argument(
        "--init-timeout",
        type=arguments.positive,
        default=300,
        metavar="S",
        help="seconds to wait for every process to join before giving up (default 300)",
    )
    p.add_argument(
        "--heartbeat-timeout",
        type=arguments.positive,
        default=100,
        metavar="S",
        help="seconds of silence after which a process counts as dead (default 100)",
    )
    p.add_argument(
        "--allow-config-change",
        action="store_true",
        help="resume a workdir although settings differ from its config.json (the"
        " change is logged to config_changes.jsonl); without it such a resume"
        " is refused, naming the keys",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="KEY=VALUE",
        help="config overrides, e.g. loss.alpha_uni_xy=50 data.height=120",
    )


def run(args) -> int | None:
    """Trains or resumes into ``--workdir``; a run that SIGTERM stopped exits with 143."""
    from usp_jax.training import config as config_lib
    from usp_jax.training import distributed, train

    cfg = config_lib.assemble(
        args.config,
        data=args.data,
        init=args.init,
        teacher=args.teacher,
        overrides=args.overrides,
        steps=args.steps,
    )
    _check_data_given(args, cfg)
    who = ""
    if _distributed(args):
        launch = distributed.Launch(
            args.coordinator,
            args.num_processes,
            args.process_id,
            args.init_timeout,
            args.heartbeat_timeout,
        )
        who = distributed.join(launch, cfg, report=lambda line: user_error("train", line))
    print(
        f"{who}training {args.config} config on {cfg.data.source} into {args.workdir},"
        f" up to step {cfg.num_steps:,} at batch {cfg.batch_size}"
    )
    state = train.fit(
        cfg,
        args.workdir,
        progress=not args.no_progress,
        allow_config_change=args.allow_config_change,
    )
    step, checkpoints = int(state.step), pathlib.Path(args.workdir) / "checkpoints"
    if step < cfg.num_steps:  # a multi-process run stopped together on SIGTERM
        print(
            f"{who}stopped at step {step} of {cfg.num_steps} on SIGTERM, checkpoint saved in"
            f" {checkpoints}; rerun the same command to resume"
        )
        return 128 + signal.SIGTERM  # as if SIGTERM had ended it: the run is not finished
    print(f"{who}done: step {step}; checkpoints in {checkpoints}")
    return 0


def _check_data_given(args, cfg) -> None:
    """Raises ValueError when nothing chose the photos: no ``--data``, no ``data.source=`` and
    a config that leaves the default, so that a forgotten flag does not start a long run on
    the few bundled photos."""
    from usp_jax.training.data import DataConfig

    chosen = args.data is not None or any(
        o.split("=", 1)[0].strip() == "data.source" for o in args.overrides
    )
    if not chosen and cfg.data.source == DataConfig().source:
        raise ValueError(
            "--data is required: an image folder, tfds:NAME[:SPLIT], 'sample' for the few"
            " photos bundled with the installed packages, or pairs:FOLDER"
        )


def _distributed(args) -> bool:
    """Whether `train` joins a multi-process run: --distributed, or any of its explicit parts."""
    return args.distributed or any(
        value is not None for value in (args.coordinator, args.num_processes, args.process_id)
    )
