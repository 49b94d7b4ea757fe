"""The folder ``make-pairs`` writes: it must be new, empty, or an earlier make-pairs output,
recognised by its manifest ``make-pairs.json`` (the settings, the source photos and the scenes it
holds), so nothing of the user's is overwritten or mixed into. A re-run over an earlier output
replaces it: its scenes are rewritten or removed, and any entry the manifest does not name, at
the top or inside a scene, makes the run refuse. Every scene is written into a temporary folder
and renamed into place once complete, so a failed or killed run leaves no half-made scene; the
manifest says ``"complete": false`` until the run ends.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

#: The manifest of a make-pairs output folder (module docstring).
MANIFEST = "make-pairs.json"
#: Suffix of a scene's folder while it is written; renamed to the scene's name once complete.
_PARTIAL = ".partial"


def write_scene(
    scene: Path, views: Sequence[np.ndarray], homographies: Sequence[np.ndarray]
) -> None:
    """Writes uint8 RGB views as 1.ppm.. (BGR on disk) and homographies[k] (image 1 -> k+2) as H_1_k,
    into a temporary folder renamed to ``scene`` once complete (replacing an earlier one)."""
    partial = scene.with_name("." + scene.name + _PARTIAL)  # hidden: never read as a scene
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        for index, view in enumerate(views, start=1):
            path = partial / f"{index}.ppm"
            if not cv2.imwrite(str(path), cv2.cvtColor(view, cv2.COLOR_RGB2BGR)):
                raise OSError(f"could not write {path}")
        for index, homography in enumerate(homographies, start=2):
            np.savetxt(partial / f"H_1_{index}", homography)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if scene.exists():
        shutil.rmtree(scene)
    partial.rename(scene)


def _own_name(name: object) -> bool:
    """Whether a manifest's scene name is one make-pairs writes (never a path elsewhere)."""
    return isinstance(name, str) and name[:2] in ("v_", "i_") and Path(name).name == name


def earlier_scenes(out_dir: str | Path) -> list[str]:
    """The scenes of an earlier make-pairs run in ``out_dir`` (none for a new or empty folder).

    Raises ValueError when the folder holds anything else: data without a manifest, or an entry
    its manifest does not name. Scenes' temporary folders (``.NAME.partial``) count as its own.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return []
    entries = sorted(p.name for p in out_dir.iterdir())
    if not entries:
        return []
    manifest = out_dir / MANIFEST
    if MANIFEST not in entries:
        raise ValueError(
            f"{out_dir} holds {len(entries)} entries (e.g. {entries[0]}) and is not a make-pairs"
            f" output (no {MANIFEST}); give a new or empty folder"
        )
    try:
        scenes = json.loads(manifest.read_text())["scenes"]
    except (OSError, ValueError, TypeError, KeyError) as error:
        raise ValueError(f"{manifest} is not a readable make-pairs manifest ({error})") from None
    if not isinstance(scenes, list) or not all(_own_name(name) for name in scenes):
        raise ValueError(f"{manifest}: its scenes are not a list of v_*/i_* folder names")
    own = {MANIFEST, *scenes, *("." + name + _PARTIAL for name in scenes)}
    foreign = [out_dir / name for name in entries if name not in own]
    foreign += [path for name in scenes for path in _foreign_in_scene(out_dir / name)]
    if foreign:
        raise ValueError(
            f"{foreign[0]} was not written by the make-pairs run of {manifest};"
            " make-pairs replaces only its own output: move it or give another folder"
        )
    return scenes


#: What make-pairs writes inside a scene: images 1.ppm ... 6.ppm and homographies H_1_2 ... H_1_6.
_SCENE_FILES = frozenset([f"{k}.ppm" for k in range(1, 7)] + [f"H_1_{k}" for k in range(2, 7)])


def _foreign_in_scene(scene: Path) -> list[Path]:
    """What a re-run would delete with ``scene`` that make-pairs never writes there: a file of
    another name, any folder, or the scene itself when it is no folder."""
    if not scene.exists() and not scene.is_symlink():
        return []
    if scene.is_symlink() or not scene.is_dir():
        return [scene]
    return sorted(
        path for path in scene.iterdir() if path.name not in _SCENE_FILES or not path.is_file()
    )


def write_manifest(out_dir: Path, settings: dict, scenes: Sequence[str], complete: bool) -> None:
    """The manifest (module docstring), replaced atomically."""
    partial = out_dir / ("." + MANIFEST + _PARTIAL)
    record = {"made_by": "usp-jax make-pairs", "complete": complete, **settings}
    partial.write_text(json.dumps({**record, "scenes": sorted(scenes)}, indent=1) + "\n")
    partial.replace(out_dir / MANIFEST)
