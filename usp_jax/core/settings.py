"""Settings as frozen-dataclass trees: the type and range check of every field, named by its
override key (``model.head_channels``), and the round trip through plain dicts (JSON).

The model's settings (``ModelConfig``, which a weights file carries) and a training run's
(``usp_jax.config.Config``, which composes them) are both checked here, so a weights file needs
no training code to be validated.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any

_POSITIVE, _NON_NEGATIVE, _FRACTION = (1, None), (0, None), (0, 1)
#: Ranges (inclusive; None: unbounded) of the fields whose type alone does not bound them. Floats
#: must be finite everywhere; tuples of numbers are checked element by element.
RANGES = {
    "batch_size": _POSITIVE,
    "num_steps": _POSITIVE,
    "seed": (0, 2**32 - 1),
    "checkpoint_every": _POSITIVE,
    "keep_checkpoints": _POSITIVE,
    "log_every": _POSITIVE,
    "model.backbone_channels": _POSITIVE,
    "model.head_channels": _POSITIVE,
    "model.descriptor_dim": _POSITIVE,
    "model.leaky_relu_slope": _NON_NEGATIVE,
    "model.position_init_scale": _NON_NEGATIVE,
    "model.batch_norm_momentum": _FRACTION,
    "data.height": (8, None),
    "data.width": (8, None),
    "data.num_workers": _POSITIVE,
    "data.prefetch": _POSITIVE,
    "data.shuffle_seed": (0, 2**32 - 1),
    "loss.lambda_d": _NON_NEGATIVE,
    "loss.eps_correspond": (1e-9, None),
    "loss.eps_descriptor": (1e-9, None),
    "loss.hard_safe_radius": _NON_NEGATIVE,
    "distill.temperature": (1e-3, None),
    **{
        f"distill.{name}": _NON_NEGATIVE
        for name in ("alpha_self", "beta_score", "beta_position", "beta_descriptor")
    },
    **{
        f"loss.{name}": _NON_NEGATIVE
        for name in (
            "alpha_usp",
            "alpha_position",
            "alpha_score",
            "alpha_uni_xy",
            "alpha_score_mean",
            "alpha_uni_score",
            "alpha_desc",
            "alpha_decorr",
            "alpha_hard",
            "margin_hard",
        )
    },
}
# The network maps each 8x8 cell to one point: crops must be whole cells.
_MULTIPLE_OF_CELL = ("data.height", "data.width")
_DTYPES = ("float32", "bfloat16", "float16")


def _type_name(annotation: Any) -> str:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return " or ".join("None" if a is type(None) else _type_name(a) for a in args)
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


def _fits(value: Any, annotation: Any) -> bool:
    """Whether ``value`` has the type ``annotation`` names (ints count as floats; bools as
    neither)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, arg) for arg in args)
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin is tuple or annotation is tuple:
        if not isinstance(value, tuple):
            return False
        if not args:
            return True
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0]) for v in value)
        return len(args) == len(value) and all(_fits(v, a) for v, a in zip(value, args))
    return True


def _numbers(value: Any) -> list:
    if isinstance(value, tuple):
        return [v for item in value for v in _numbers(item)]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [value]
    return []


def check_fields(node: Any, prefix: str) -> None:
    """Checks every field of the dataclass tree ``node`` (type, finiteness, ``RANGES``, whole 8x8
    cells, dtype names); raises ValueError naming the first bad key, ``prefix`` + field name.
    Where a config is made (``config.load``, ``config.override``), before a run starts
    (``train.check_config``) and when a weights file is read."""
    hints = typing.get_type_hints(type(node))
    for field in dataclasses.fields(node):
        key, value, annotation = prefix + field.name, getattr(node, field.name), hints[field.name]
        if dataclasses.is_dataclass(annotation):
            if not isinstance(value, annotation):
                raise ValueError(
                    f"config key {key!r} is a section ({annotation.__name__}), got {value!r};"
                    f" set its fields instead, e.g. {key}.{dataclasses.fields(annotation)[0].name}"
                    "=..."
                )
            check_fields(value, key + ".")
            continue
        if not _fits(value, annotation):
            raise ValueError(f"config key {key}={value!r} is not of type {_type_name(annotation)}")
        numbers = _numbers(value)
        if any(not math.isfinite(v) for v in numbers):
            raise ValueError(f"config key {key}={value!r} is not a finite number")
        low, high = RANGES.get(key, (None, None))
        for v in numbers:
            if (low is not None and v < low) or (high is not None and v > high):
                bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
                raise ValueError(f"config key {key}={value!r} must be {bound}")
        if key in _MULTIPLE_OF_CELL and value % 8:
            raise ValueError(
                f"config key {key}={value!r} must be a multiple of 8 (one point per 8x8 cell)"
            )
        if key == "model.dtype" and value not in _DTYPES:
            raise ValueError(f"config key {key}={value!r} must be one of {', '.join(_DTYPES)}")


def from_dict(data: dict, cls: type) -> Any:
    """The dataclass tree ``cls`` from its ``dataclasses.asdict`` (tuples restored from JSON
    lists); fields missing from ``data`` keep their defaults."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value, annotation = data[f.name], hints[f.name]
        if dataclasses.is_dataclass(annotation):
            value = from_dict(value, annotation)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)
