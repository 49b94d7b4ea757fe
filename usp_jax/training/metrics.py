"""What a training run records and watches: ``metrics.jsonl`` and TensorBoard rows, the warnings
of the collapses peers reported, and the stop on a non-finite loss.
"""

from __future__ import annotations

import json
import logging
import pathlib

log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """The loss or the gradients became NaN or inf."""


class MetricsWriter:
    """Appends metrics to ``metrics.jsonl`` and TensorBoard event files (first process only)."""

    def __init__(self, workdir: pathlib.Path, enabled: bool = True):
        self.enabled = enabled
        if not enabled:
            return
        from tensorboardX import SummaryWriter

        path = workdir / "metrics.jsonl"
        _drop_torn_line(path)
        self._jsonl = open(path, "a")
        self._tb = SummaryWriter(str(workdir / "tensorboard"))

    def write(self, step: int, metrics: dict[str, float]) -> None:
        if not self.enabled:
            return
        self._jsonl.write(json.dumps({"step": step, **metrics}) + "\n")
        self._jsonl.flush()
        for name, value in metrics.items():
            self._tb.add_scalar(name, value, step)

    def close(self) -> None:
        if self.enabled:
            self._jsonl.close()
            self._tb.close()


def _drop_torn_line(path: pathlib.Path) -> None:
    """Cuts a last line that a kill or a full disk left without its newline."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    text = path.read_bytes()
    if not text.endswith(b"\n"):
        with open(path, "r+b") as file:
            file.truncate(text.rfind(b"\n") + 1)


def read_metrics(workdir: str | pathlib.Path) -> list[dict]:
    """The rows :class:`MetricsWriter` appended to ``WORKDIR/metrics.jsonl``, in the order written
    (``[]`` before the first log). A run resumed after a kill logs the steps after its last
    checkpoint a second time; the later row of a step is the one its kept weights went through.
    A line that is not a row (cut short by a kill or a full disk, or damaged anywhere in the
    file) is skipped, and the count of skipped lines is logged as a warning."""
    path = pathlib.Path(workdir) / "metrics.jsonl"
    if not path.is_file():
        return []
    rows, bad = [], []
    for number, line in enumerate(path.read_text(errors="replace").split("\n"), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except (ValueError, RecursionError):
            row = None
        if isinstance(row, dict) and isinstance(row.get("step"), int):
            rows.append(row)
        else:
            bad.append(number)
    if bad:
        log.warning(
            "%s: skipped %d line(s) that are not metrics rows (line %s)",
            path,
            len(bad),
            ", ".join(map(str, bad[:5])) + (", ..." if len(bad) > 5 else ""),
        )
    return rows


def progress_postfix(metrics: dict[str, float], steps_per_s: float, batch_size: int) -> dict:
    return {
        "steps/s": f"{steps_per_s:.2f}",
        "img/s": f"{2 * batch_size * steps_per_s:.1f}",
        "loss": f"{metrics['loss']:.4g}",
        "usp": f"{metrics['loss/usp']:.4g}",
        "uni": f"{metrics['loss/uni_xy']:.3g}",
        "desc": f"{metrics['loss/desc']:.4g}",
        "K": f"{metrics['usp/K']:.0f}",
        "d": f"{metrics['usp/mean_d']:.2f}",
    }


def collapse_warnings(metrics: dict[str, float]) -> dict[str, str]:
    """The collapses peers reported, and the score ramp, read off one metrics row: {what: message}."""
    warnings = {}
    # Saturated and constant. A constant near 1/2 is the normal start under the mean anchor: the
    # scores spread once positions become repeatable (~2,000 steps in experiments/paper_network.py).
    saturated = abs(metrics.get("pred/score_mean", 0.5) - 0.5) > 0.4
    if metrics.get("pred/score_std", 1.0) < 0.02 and saturated:
        warnings["scores"] = (
            f"scores have collapsed to a constant (std {metrics['pred/score_std']:.3g}, mean "
            f"{metrics['pred/score_mean']:.3g}); loss.alpha_score_mean > 0 anchors their mean"
        )
    if metrics.get("pred/score_position_r2", 0.0) > 0.5:
        warnings["score ramp"] = (
            f"scores follow the position in the image, not its content (R^2 of a plane fit "
            f"{metrics['pred/score_position_r2']:.2f}); loss.alpha_uni_score > 0 rewards such a "
            f"ramp, loss.alpha_score_mean alone does not"
        )
    if metrics.get("desc/sim_negative", 0.0) > 0.9:
        warnings["descriptors"] = (
            f"descriptors have collapsed onto one vector (mean similarity of non-matching pairs "
            f"{metrics['desc/sim_negative']:.2f}): the hinge's positives outweigh its negatives; "
            f"lower loss.lambda_d in proportion to the cell count (250 suits 240x320)"
        )
    return warnings


def check_finite(metrics: dict | None, step: int, mngr) -> None:
    if metrics is not None and not float(metrics["finite"]):
        raise TrainingDiverged(
            f"loss became non-finite at step {step} (loss={float(metrics['loss'])}); stopped, "
            f"last good checkpoint: step {mngr.latest_step()} in {mngr.directory}"
        )


def chain_stages(stages: list[list[dict]]) -> tuple[list[dict], list[int]]:
    """One step axis over training stages that each count from step 1 (a run started with
    ``--init`` has a fresh step counter). Returns the rows with steps offset by the earlier
    stages' last steps, and the offset step at which each later stage begins.

    A run resumed after a kill logs the steps after its last checkpoint again; the later row of
    a step wins, as it is the one the kept weights went through."""
    rows, starts, offset = [], [], 0
    for index, stage in enumerate(stages):
        latest = {row["step"]: row for row in stage}
        if index:
            starts.append(offset)
        rows += [{**row, "step": step + offset} for step, row in sorted(latest.items())]
        offset += max(latest, default=0)
    return rows, starts
