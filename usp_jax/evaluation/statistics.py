"""How sure a change is: relative changes between evaluations and their 95% intervals from a
paired bootstrap over the evaluation pairs (how much of a change the choice of pairs alone
could explain). Rows are ``usp_jax.evaluation.to_json``'s "pairs".
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from usp_jax.evaluation.protocol import METRICS

#: The learned model's method name in evaluation rows.
MODEL = "UnsuperPoint"


def relative_changes(summary: dict, base: str = "C0") -> dict[str, dict[str, float]]:
    """Per configuration and metric, the change relative to ``base`` in percent, positive =
    better; NaN where the base value is 0 (a metric none of the pairs scored on)."""
    reference = summary[base]
    changes = {}
    for name, values in summary.items():
        changes[name] = {}
        for metric in METRICS:
            with np.errstate(divide="ignore", invalid="ignore"):
                change = 100.0 * np.divide(
                    values[metric] - reference[metric], np.abs(reference[metric])
                )
            change = np.where(np.isfinite(change), change, np.nan)
            change = -change if metric == "le" else change
            changes[name][metric] = float(change) if change.ndim == 0 else change
    return changes


def per_pair(rows: list[dict]) -> dict[str, dict[str, np.ndarray]]:
    """``{config: {metric: [P]}}`` from evaluation rows (``evaluation.to_json``'s "pairs"), every
    configuration's pairs in the same order; null (undefined LE) becomes NaN."""
    table = {}
    for row in rows:
        values = table.setdefault(row["method"], {m: [] for m in METRICS})
        for metric in METRICS:
            values[metric].append(math.nan if row[metric] is None else row[metric])
    return {
        name: {m: np.asarray(v, np.float64) for m, v in values.items()}
        for name, values in table.items()
    }


def _draws(count: int, rounds: int, seed: int) -> np.ndarray:
    """``[rounds, count]`` pair indices drawn with replacement: one bootstrap resample per row."""
    return np.random.default_rng(seed).integers(0, count, size=(rounds, count))


def _resampled_means(values: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """``[rounds]`` means of ``values`` [P] over each resample in ``draws``, skipping NaN (an
    undefined LE); a resample of only undefined values is NaN, which the percentiles skip."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(values[draws], axis=1)


def bootstrap_intervals(
    pairs: dict[str, dict[str, np.ndarray]], rounds: int = 2000, seed: int = 0, base: str = "C0"
) -> dict[str, dict[str, tuple[float, float]]]:
    """95% percentile intervals of :func:`relative_changes`, resampling the evaluation pairs with
    replacement, the same draw for every configuration (a paired bootstrap: each configuration met
    the same pairs). LE's mean skips its undefined (NaN) pairs, as ``evaluation.summarize`` does."""
    draws = _draws(len(pairs[base][METRICS[0]]), rounds, seed)
    means = {
        name: {m: _resampled_means(values[m], draws) for m in METRICS}
        for name, values in pairs.items()
    }
    intervals = {}
    for name in pairs:
        changes = relative_changes({base: means[base], name: means[name]}, base)[name]
        intervals[name] = {
            m: tuple(float(q) for q in np.nanpercentile(changes[m], [2.5, 97.5])) for m in METRICS
        }
    return intervals


def mean_intervals(
    pairs: dict[str, dict[str, np.ndarray]], rounds: int = 2000, seed: int = 0
) -> dict[str, dict[str, tuple[float, tuple[float, float]]]]:
    """``{method: {metric: (mean, (low, high))}}``: each method's mean over the pairs and its 95%
    percentile interval from a bootstrap over the pairs, the same draws for every method (all met
    the same pairs, so overlapping intervals still compare in order). ``pairs`` is
    :func:`per_pair`'s, ``{method: {metric: [P]}}``; LE skips its undefined (NaN) pairs."""
    draws = _draws(len(next(iter(pairs.values()))[METRICS[0]]), rounds, seed)
    table = {}
    for name, values in pairs.items():
        table[name] = {}
        for metric in METRICS:
            low, high = np.nanpercentile(_resampled_means(values[metric], draws), [2.5, 97.5])
            table[name][metric] = (float(np.nanmean(values[metric])), (float(low), float(high)))
    return table


def _model_pairs(base_rows: list[dict], new_rows: list[dict]) -> dict:
    """:func:`per_pair` of the model's rows in two evaluations, as configurations "base" and
    "new", matched by pair (scene, k) whatever order the files list them in."""

    def model_rows(rows, name):
        kept = sorted((r for r in rows if r["method"] == MODEL), key=lambda r: (r["scene"], r["k"]))
        return [{**r, "method": name} for r in kept]

    base, new = model_rows(base_rows, "base"), model_rows(new_rows, "new")
    if [(r["scene"], r["k"]) for r in base] != [(r["scene"], r["k"]) for r in new]:
        raise ValueError("the two evaluations did not score the same pairs")
    return per_pair(base + new)


def paired_change(base_rows: list[dict], new_rows: list[dict], rounds: int = 2000) -> dict:
    """``{metric: (change %, (low, high))}`` of the model in ``new_rows`` against ``base_rows``:
    positive = better (LE's sign flipped), interval from a paired bootstrap over the pairs."""
    pairs = _model_pairs(base_rows, new_rows)
    means = {
        name: {m: float(np.nanmean(v)) for m, v in metrics.items()}
        for name, metrics in pairs.items()
    }
    changes = relative_changes(means, base="base")["new"]
    intervals = bootstrap_intervals(pairs, rounds=rounds, base="base")["new"]
    return {m: (changes[m], intervals[m]) for m in METRICS}


def paired_difference(
    base_rows: list[dict], new_rows: list[dict], rounds: int = 2000, seed: int = 0
) -> dict:
    """``{metric: (difference, (low, high))}``: the model's mean in ``new_rows`` minus its mean
    in ``base_rows``, positive = better (LE's sign flipped), with the 95% interval of a paired
    bootstrap over the pairs (the same draw for both evaluations)."""
    pairs = _model_pairs(base_rows, new_rows)
    draws = _draws(len(pairs["base"][METRICS[0]]), rounds, seed)
    result = {}
    for metric in METRICS:
        sign = -1.0 if metric == "le" else 1.0
        base, new = pairs["base"][metric], pairs["new"][metric]
        resampled = sign * (_resampled_means(new, draws) - _resampled_means(base, draws))
        low, high = np.nanpercentile(resampled, [2.5, 97.5])
        difference = sign * (np.nanmean(new) - np.nanmean(base))
        result[metric] = (float(difference), (float(low), float(high)))
    return result
