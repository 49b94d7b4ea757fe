"""The files and folders the ``usp-jax`` commands write: each checked before any work (a folder
where a file should be, a missing or unwritable parent), and written whole or not at all."""

from __future__ import annotations

import os
import pathlib

from usp_jax.inference import video


def check_output_file(path: str | None, what: str) -> None:
    """Raises ValueError unless ``path`` can be written as a file (checked before any work)."""
    if not path:
        return
    target = pathlib.Path(path).expanduser()
    if target.is_dir():
        raise ValueError(f"{what} {path} is a folder, not a file")
    parent = target.absolute().parent
    if not parent.is_dir():
        raise ValueError(f"{what} {path}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or (
        target.exists() and not os.access(target, os.W_OK)
    ):
        raise ValueError(f"{what} {path} is not writable")


def figure_file(path: str | None, what: str) -> str | None:
    """The file a figure option writes, checked: a bare name gets ``.png``, as matplotlib adds it."""
    if not path:
        return path
    from usp_jax.evaluation.plotting import figure_path

    return suffixed_file(path, what, figure_path)


def suffixed_file(path: str | None, what: str, suffixed) -> str | None:
    """The file an option writes when ``suffixed`` may add a suffix to the name given, checked
    as given too: an existing folder is refused, not written beside as ``FOLDER.png``."""
    if not path:
        return path
    check_output_file(path, what)
    target = str(suffixed(path))
    check_output_file(target, what)
    return target


def check_output_folder(path: str | None, what: str) -> None:
    """Raises ValueError unless ``path`` is, or can be made as, a writable folder."""
    from usp_jax.training.workdir import folder_problem

    problem = folder_problem(path) if path else None
    if problem:
        raise ValueError(f"{what} {path}{problem}")


def write_text(path: str, text: str) -> None:
    """``text`` into ``path`` through a temporary name beside it, so it is never half-written."""
    write_atomic(path, lambda partial: partial.write_text(text))


def write_atomic(path: str | pathlib.Path, write) -> None:
    """``write(partial path)``, then the partial file renamed to ``path``; nothing is left at
    either name when ``write`` fails."""
    target = pathlib.Path(path).expanduser()
    partial = video.partial_path(target)
    try:
        write(partial)
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)
