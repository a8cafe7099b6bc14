"""The import rules of docs/architecture.md hold: import-linter's contracts in pyproject.toml."""

from __future__ import annotations

import tomllib
from pathlib import Path

from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parents[1]


def _layers() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (layers,) = [c["layers"] for c in config["contracts"] if c["type"] == "layers"]
    return [name.strip() for layer in layers for name in layer.replace("|", ":").split(":")]


def test_no_module_imports_against_the_layers_or_the_forbidden_imports():
    assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True,
                        no_logo=True) == 0


def test_every_package_and_module_has_a_place_in_the_layers():
    placed = _layers()
    top_level = [f"jobs.{p.stem}" for p in (ROOT / "jobs").iterdir()
                 if p.name != "__init__.py" and p.name != "migrations"
                 and (p.suffix == ".py" or (p / "__init__.py").exists())]
    top_level += [f"worker.{p.stem}" for p in (ROOT / "worker").iterdir()
                  if p.name != "__init__.py"
                  and (p.suffix == ".py" or (p / "__init__.py").exists())]

    assert sorted(m for m in top_level if m not in placed) == []
