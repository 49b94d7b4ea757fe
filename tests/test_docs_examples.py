"""The Python blocks of the README, docs/api.md and docs/cli.md run as pasted: every name
defined, every module imported, the shapes and dtypes they state what the code takes."""

import pathlib
import re
import subprocess
import sys

import jax
import numpy as np
import pytest
from conftest import SMALL_MODEL, child_env

from usp_jax.core.model import init_variables
from usp_jax.inference import Detector, export

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Run by the test only, before a block: photos come back at a quarter of their size, so the
# README's code runs as written in seconds rather than a minute.
SMALL_PHOTOS = """\
import cv2
_imread = cv2.imread
cv2.imread = lambda *args: cv2.resize(_imread(*args), None, fx=0.25, fy=0.25)
"""


def python_blocks(path: pathlib.Path) -> list[str]:
    """The fenced ```python blocks of a Markdown file, in order."""
    return re.findall(r"^```python\n(.*?)^```$", path.read_text(), flags=re.S | re.M)


def test_python_blocks_are_found():
    assert python_blocks(ROOT / "README.md")
    assert len(python_blocks(ROOT / "docs" / "api.md")) == 1
    assert len(python_blocks(ROOT / "docs" / "cli.md")) == 1


@pytest.mark.slow
@pytest.mark.parametrize("document", ["README.md", "docs/api.md"])
def test_python_blocks_run_as_pasted_in_a_fresh_interpreter(document, tmp_path):
    for block in python_blocks(ROOT / document):
        done = subprocess.run(
            [sys.executable, "-c", SMALL_PHOTOS + block],
            cwd=tmp_path,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"{document} block failed:\n{block}\n{done.stderr[-3000:]}"


def test_docs_artifact_example_loads_and_runs_an_exported_detector(tmp_path, monkeypatch):
    """docs/cli.md's load-and-run example on a real artifact gives the detector's own points."""
    (block,) = python_blocks(ROOT / "docs" / "cli.md")
    size = re.search(r"--res (\d+)x(\d+)", block)
    height, width = int(size[1]), int(size[2])
    variables = init_variables(jax.random.PRNGKey(0), SMALL_MODEL)
    detector = Detector(variables, SMALL_MODEL, top_n=20)
    export(detector, tmp_path / "detector.bin", height, width)
    monkeypatch.chdir(tmp_path)
    names: dict = {}
    exec(compile(block, "docs/cli.md", "exec"), names)
    expected = detector.detect_batch(names["images"])
    assert names["keypoints"].shape == (len(names["images"]), 20, 2)
    np.testing.assert_allclose(names["points"], expected[0].keypoints, atol=1e-4)
    np.testing.assert_array_equal(names["counts"], [len(f.keypoints) for f in expected])


def shell_lines(path: pathlib.Path) -> list[str]:
    """The commands of a Markdown file's fenced ```bash blocks, one per line, comments cut."""
    blocks = re.findall(r"^```bash\n(.*?)^```$", path.read_text(), flags=re.S | re.M)
    lines = [line.split("  #")[0].strip() for block in blocks for line in block.splitlines()]
    return [line for line in lines if line and not line.startswith("#")]


def test_readme_shell_blocks_hold_commands_not_usage_syntax():
    lines = shell_lines(ROOT / "README.md")
    assert any(line.startswith("usp-jax train") for line in lines)
    for line in lines:  # [optional] parts, a|b choices and CAPITAL placeholders do not run
        assert not re.search(r"\[--|\w\|\w|\b[A-Z]{3,}\b", line), line


@pytest.mark.slow
def test_readme_shell_blocks_run_as_pasted_in_an_empty_folder(tmp_path):
    """Every README shell line, in order, in one empty folder; `usp-jax` is this checkout's,
    installing is left to the environment and the demo to its own test. Small inputs: make-pairs' bundled photos are cut to
    two, so that the evaluation and tracking that follow take seconds."""
    import shutil

    from usp_jax.inference.images import sample_photos

    photos = tmp_path / "two-photos"
    photos.mkdir()
    for _, path in sample_photos():
        if path.name in ("coffee.png", "chelsea.png"):
            shutil.copy(path, photos)
    for line in shell_lines(ROOT / "README.md"):
        if "pip install" in line or line.endswith("usp_jax demo"):  # the demo: test_cli's own
            continue
        line = line.replace("--images sample", f"--images {photos}")
        command = re.sub(r"^(usp-jax|python3 -m usp_jax)\b", f"{sys.executable} -m usp_jax", line)
        done = subprocess.run(
            command,
            shell=True,
            cwd=tmp_path,
            env={**child_env(), "PYTHONPATH": str(ROOT)},
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert done.returncode == 0, f"README line failed: {line}\n{done.stderr[-3000:]}"
