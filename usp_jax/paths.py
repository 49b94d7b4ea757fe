"""Checks of the folders a command will write, made before it writes anything."""

from __future__ import annotations

import os
import pathlib


def folder_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be used, or be made, as a writable folder; None when it can.

    The text continues a sentence that names the path, e.g. ``f"--out {path}{problem}"``: the
    path exists as a file, or the nearest existing ancestor is a file or not writable.
    """
    target = pathlib.Path(path).expanduser().absolute()
    if target.exists() and not target.is_dir():
        return " exists and is not a folder"
    existing = target
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f": {existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f": {existing} is not writable"
    return None
