"""The import rules of docs/architecture.md hold: import-linter's contracts in pyproject.toml;
and a process a test starts runs this checkout's code."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _layers() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (layers,) = [c["layers"] for c in config["contracts"] if c["type"] == "layers"]
    return [name.strip() for layer in layers for name in layer.replace("|", ":").split(":")]


def _is_module(path: Path) -> bool:
    if path.name in ("__init__.py", "__main__.py", "migrations"):
        return False
    return path.suffix == ".py" or (path / "__init__.py").exists()


def test_no_module_imports_against_the_layers_or_the_forbidden_imports():
    # In a process of its own: import-linter sets up logging with dictConfig, which
    # disables every logger already made, and a later test of this process would then see
    # no records from dncq's loggers.
    linted = subprocess.run(
        [sys.executable, "-c", "from importlinter.cli import lint_imports_command as c; c()",
         str(ROOT / "pyproject.toml"), "--no-cache"],
        capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert linted.returncode == 0, linted.stdout + linted.stderr


def test_every_package_and_module_has_a_place_in_the_layers():
    placed = _layers()
    top_level = [f"{package}.{p.stem}" for package in ("jobs", "worker")
                 for p in (ROOT / package).iterdir() if _is_module(p)]

    assert sorted(m for m in top_level if m not in placed) == []


def test_a_process_a_test_starts_elsewhere_runs_this_checkouts_code():
    # A worker or `dncq serve` a test starts runs in a folder of its own: without this,
    # it would run the code an editable install points at, maybe another checkout's.
    found = subprocess.run([sys.executable, "-c", "import jobs; print(jobs.__file__)"],
                           capture_output=True, text=True, cwd="/", check=True)

    assert Path(found.stdout.strip()) == ROOT / "jobs" / "__init__.py"
