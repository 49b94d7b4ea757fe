"""The scripts the docs name (experiments/*.py, benchmarks/*.py) run against the package as it is:
every name they reach in a usp_jax module exists, and the documented ones run end to end on
small inputs (slow), also where XFeat is not installed."""

import ast
import importlib
import pathlib
import subprocess
import sys

import pytest
from conftest import TINY_RUN, child_env

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPTS = sorted([*(ROOT / "experiments").glob("*.py"), *(ROOT / "benchmarks").glob("*.py")])


def package_names(tree: ast.AST) -> dict[str, str]:
    """{local name: usp_jax module} of a script's imports of usp_jax modules."""
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("usp_jax"):
            for alias in node.names:
                module = f"{node.module}.{alias.name}"
                if importlib.util.find_spec(node.module) and _is_module(module):
                    names[alias.asname or alias.name] = module
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("usp_jax") and alias.asname:
                    names[alias.asname] = alias.name
    return names


def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_package_name_a_script_uses_exists(script):
    """A script calling a function the package no longer has (``checkpoint.load_variables``)
    fails only when run, after minutes of work; this finds it at once."""
    tree = ast.parse(script.read_text())
    modules = package_names(tree)
    missing = [
        f"{node.module}.{alias.name} (line {node.lineno})"
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("usp_jax")
        for alias in node.names
        if not _is_module(f"{node.module}.{alias.name}")
        and not hasattr(importlib.import_module(node.module), alias.name)
    ]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            module = modules.get(node.value.id)
            if module and not hasattr(importlib.import_module(module), node.attr):
                missing.append(f"{node.value.id}.{node.attr} (line {node.lineno})")
    assert not missing, f"{script.name} uses names its usp_jax modules lack: {missing}"


def run(argv, cwd, env=None):
    done = subprocess.run(
        [sys.executable, *argv],
        cwd=cwd,
        env={**child_env(), "PYTHONPATH": str(ROOT), **(env or {})},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, f"{argv} failed:\n{done.stderr[-3000:]}"
    return done.stdout


@pytest.mark.slow
def test_figures_draws_a_tiny_runs_statistics_and_curves(tmp_path):
    from usp_jax.cli import main

    workdir = tmp_path / "run"
    args = ["train", "--data", "sample", "--workdir", str(workdir), "--steps", "2", *TINY_RUN]
    assert main([*args, "data.height=64", "data.width=96"]) == 0
    photos = tmp_path / "photos"
    photos.mkdir()
    from usp_jax.inference.images import sample_photos

    for _, path in sample_photos()[:1]:
        (photos / path.name).write_bytes(path.read_bytes())
    script = ROOT / "experiments" / "figures.py"
    run(
        [str(script), "--checkpoint", str(workdir), "--photos", str(photos), "--out", "f"], tmp_path
    )
    assert {"fig4a_pair_distances.png", "fig5_x_in_cell.png", "training_curves.png"} <= {
        p.name for p in (tmp_path / "f").iterdir()
    }


# Run before the script: torch cannot be imported, as on a fresh install without XFeat; the
# script's folder comes first on the path, as when Python runs it.
WITHOUT_TORCH = (
    "import os, sys, runpy; sys.modules['torch'] = None; sys.argv = sys.argv[1:];"
    " sys.path.insert(0, os.path.dirname(sys.argv[0]));"
)


@pytest.mark.slow
def test_bench_inference_runs_where_xfeat_is_not_installed(tmp_path):
    script = ROOT / "benchmarks" / "bench_inference.py"
    argv = [
        "--size",
        "64x96",
        "--batch",
        "1",
        "--rounds",
        "1",
        "--block",
        "1",
        "--ceiling-side",
        "512",
    ]
    code = WITHOUT_TORCH + f"runpy.run_path({str(script)!r}, run_name='__main__')"
    out = run(["-c", code, str(script), *argv], tmp_path)
    assert "XFeat: not timed, not installed" in out
