"""Experiment configuration: one frozen dataclass tree, overridable as ``section.field=value``.

Each module owns the dataclass of its concept (``ModelConfig`` in model, ``LossConfig`` in losses,
...); ``Config`` only composes them with the optimisation settings. ``experiments/*.py`` each
define ``get_config()`` for one reproducible run.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import json
import os
import pathlib
import typing
from collections.abc import Sequence
from typing import Any

from usp_jax.core import settings
from usp_jax.core.augment import PhotometricConfig
from usp_jax.core.distillation import DistillConfig
from usp_jax.core.geometry import HomographyConfig
from usp_jax.core.losses import LossConfig
from usp_jax.core.model import ModelConfig
from usp_jax.core.settings import from_dict
from usp_jax.training.data import DataConfig


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """Adam with its default betas (paper section 5: "ADAM optimizer with a default setting")."""

    learning_rate: float = 1e-3
    # Steps of linear warm-up from 0; 0 keeps the paper's constant rate.
    warmup_steps: int = 0
    # Global-norm clipping, 0 = off (the paper does not clip).
    clip_norm: float = 0.0
    # Cosine decay of the rate to 0 over this many steps after the warm-up (it then stays 0);
    # 0 keeps the paper's constant rate. A short run ending at a low rate averages out the last
    # steps' gradient noise, which a constant rate leaves in the final weights.
    decay_steps: int = 0

    def __post_init__(self):
        for name in ("learning_rate", "warmup_steps", "clip_norm", "decay_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"optim.{name} must be >= 0, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything a training run depends on. ``batch_size`` is global and per branch."""

    model: ModelConfig = ModelConfig()
    loss: LossConfig = LossConfig()
    homography: HomographyConfig = HomographyConfig()
    photometric: PhotometricConfig = PhotometricConfig()
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    distill: DistillConfig = DistillConfig()
    batch_size: int = 5
    num_steps: int = 236_574  # 10 epochs of COCO train2017 (118,287 images) at batch 5.
    seed: int = 0
    checkpoint_every: int = 2000
    keep_checkpoints: int = 3
    log_every: int = 50
    # A weights file (``usp-jax export --save-weights``) to start from instead of a random init, to
    # fine-tune on new data; the optimiser starts fresh. "" = random init.
    init_weights: str = ""


def paper() -> Config:
    """The paper's run (section 5): 240x320 colour crops, batch 5 per branch, Adam, 10 epochs."""
    return Config()


def cpu() -> Config:
    """A run that learns something in minutes on a laptop CPU: small crops, short schedule."""
    return Config(
        data=DataConfig(height=120, width=160),
        batch_size=4,
        num_steps=2000,
        checkpoint_every=250,
        log_every=10,
    )


PRESETS = {"paper": paper, "cpu": cpu}


def load(spec: str) -> Config:
    """A preset name (``paper``, ``cpu``), a Python file defining ``get_config()``, or
    ``FILE.py:NAME`` for another function of that file (a recipe's later stages).

    Raises ValueError in one line for a file that does not run (syntax error, failing import,
    an exception in the function) or whose function does not return a valid :class:`Config`.
    """
    if spec in PRESETS:
        return PRESETS[spec]()
    file, _, function = spec.partition(".py:")
    file = file + ".py" if function else spec
    function = function or "get_config"
    path = pathlib.Path(file)
    if not path.is_file():
        raise FileNotFoundError(
            f"config {spec!r} is neither a preset ({', '.join(PRESETS)}) nor an existing file"
        )
    try:
        module_spec = importlib.util.spec_from_file_location(path.stem, path)
        if module_spec is None or module_spec.loader is None:
            raise ValueError(f"config file {file} is not a Python file (it must end in .py)")
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
    except SyntaxError as error:
        raise ValueError(
            f"config file {file} has a syntax error at line {error.lineno}: {error.msg}"
        ) from error
    except ValueError:
        raise
    except Exception as error:  # the user's file failed: an import, a typo, anything it runs
        raise ValueError(f"config file {file} failed to run: {_one_line(error)}") from error
    if not callable(getattr(module, function, None)):
        raise ValueError(f"config file {file} defines no {function}()")
    try:
        config = getattr(module, function)()
    except Exception as error:
        raise ValueError(f"config file {file}: {function}() failed: {_one_line(error)}") from error
    if not isinstance(config, Config):
        raise ValueError(
            f"config file {file}: {function}() returned {type(config).__name__}, not a"
            " usp_jax.config.Config"
        )
    try:
        return validate(config)
    except ValueError as error:
        raise ValueError(f"config file {file}: {error}") from None


def _one_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


def validate(config: Config) -> Config:
    """Checks every field's type and range (``RANGES``; floats finite, crops whole 8x8 cells)
    and returns ``config``; raises ValueError naming the first bad key."""
    if not isinstance(config, Config):
        raise ValueError(f"expected a usp_jax.config.Config, got {type(config).__name__}")
    settings.check_fields(config, "")
    return config


def flatten(config: Config) -> dict[str, Any]:
    """``{"model.descriptor_dim": 256, ...}``: every leaf field by its override key."""

    def walk(node: dict, prefix: str):
        for name, value in node.items():
            if isinstance(value, dict):
                yield from walk(value, f"{prefix}{name}.")
            else:
                yield prefix + name, tuple(value) if isinstance(value, list) else value

    return dict(walk(to_dict(config), ""))


def differences(old: Config, new: Config) -> dict[str, tuple[Any, Any]]:
    """``{key: (old value, new value)}`` for every field that differs, by override key."""
    before, after = flatten(old), flatten(new)
    return {
        key: (before.get(key), after.get(key)) for key in after if before.get(key) != after.get(key)
    }


def _coerce(text: str, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    try:
        if annotation is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if annotation in (int, float, str):
            return annotation(text)
        if origin in (tuple, list) or annotation in (tuple, list):
            value = ast.literal_eval(text)
            return tuple(value) if not isinstance(value, (int, float)) else (value,)
        return ast.literal_eval(text)
    except (ValueError, SyntaxError, RecursionError, MemoryError):  # nesting too deep to parse
        raise ValueError(f"cannot read {_short(text)!r} as {annotation} for {where}") from None


def _short(text: str, length: int = 60) -> str:
    """``text`` cut to ``length`` characters for a one-line message (a value may be huge)."""
    return text if len(text) <= length else text[: length - 3] + "..."


def override(config: Config, assignments: list[str]) -> Config:
    """Applies ``["loss.alpha_uni_xy=50", "batch_size=10", ...]`` and returns a new Config."""
    for assignment in assignments:
        if "=" not in assignment:
            raise ValueError(f"override {assignment!r} is not of the form key=value")
        key, text = assignment.split("=", 1)
        config = _set(config, key.strip().split("."), text.strip(), key.strip())
    return validate(config)


def assemble(
    spec: str,
    data: str | None = None,
    init: str | None = None,
    overrides: Sequence[str] = (),
    steps: int | None = None,
    teacher: str | None = None,
) -> Config:
    """The config of one ``usp-jax train`` command: :func:`load` ``spec``, then ``init_weights=init``,
    ``distill.teacher=teacher`` and ``data.source=data`` (when given), then ``overrides`` in order (a later key wins, so an
    explicit ``data.source=`` beats ``data``), then ``num_steps=steps`` (when given).

    ``steps`` is ``num_steps``: giving both, they must agree, so that neither silently beats the
    other. Raises ValueError in one line for a bad override, or naming both values when ``steps``
    and a ``num_steps=`` override disagree; FileNotFoundError for a ``spec`` that is no preset
    and no file.
    """
    config = load(spec)
    options = [f"init_weights={init}"] if init else []
    options += [f"distill.teacher={teacher}"] if teacher else []
    options += [f"data.source={data}"] if data else []
    config = override(config, [*options, *overrides])
    if steps is not None:
        explicit = [
            o.split("=", 1)[1].strip()
            for o in overrides
            if o.split("=", 1)[0].strip() == "num_steps"
        ]
        if explicit and config.num_steps != steps:
            raise ValueError(
                f"--steps {steps} and num_steps={explicit[-1]} disagree; give one of them"
            )
        config = override(config, [f"num_steps={steps}"])
    return config


def _set(node: Any, path: list[str], text: str, key: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(node)}
    if path[0] not in fields:
        raise ValueError(
            f"unknown config key {key!r}; {type(node).__name__} has {', '.join(fields)}"
        )
    hints = typing.get_type_hints(type(node))
    current = getattr(node, path[0])
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise ValueError(f"config key {key!r}: {path[0]} has no sub-fields")
        return dataclasses.replace(node, **{path[0]: _set(current, path[1:], text, key)})
    if dataclasses.is_dataclass(current):
        names = ", ".join(f.name for f in dataclasses.fields(current))
        raise ValueError(
            f"config key {key!r} is a section, not a value; set one of its fields ({names}),"
            f" e.g. {key}.{dataclasses.fields(current)[0].name}=..."
        )
    value = _coerce(text, hints[path[0]], key)
    try:
        return dataclasses.replace(node, **{path[0]: value})
    except (ValueError, TypeError) as error:  # a section's own check, which may not name it
        wanted = str(hints[path[0]]).replace("typing.", "")
        raise ValueError(f"config key {key}={_short(text)} (a {wanted}): {error}") from None


def to_dict(config: Config) -> dict:
    return dataclasses.asdict(config)


def save(config: Config, path: pathlib.Path) -> None:
    """Writes ``path`` atomically: a crash or a full disk leaves the old file or the new one,
    never a part of either."""
    path = pathlib.Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "w") as file:
            file.write(json.dumps(to_dict(config), indent=2) + "\n")
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def read(path: pathlib.Path) -> Config:
    return from_dict(json.loads(pathlib.Path(path).read_text()), Config)


__all__ = [
    "Config",
    "DistillConfig",
    "OptimConfig",
    "assemble",
    "cpu",
    "differences",
    "load",
    "override",
    "paper",
    "read",
    "save",
    "to_dict",
    "validate",
]
