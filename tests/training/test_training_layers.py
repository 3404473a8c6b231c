"""Training sits below the benchmarks: no module of ``uniros_async.training`` imports ``uniros_async.bench``."""

from __future__ import annotations

import ast
from pathlib import Path

import uniros_async.training

TRAINING = Path(uniros_async.training.__file__).parent


def _imported(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_training_imports_nothing_from_bench() -> None:
    modules = sorted(TRAINING.glob("*.py"))
    assert len(modules) > 5  # the package's modules were found
    offenders = {
        f"{p.name}: {name}"
        for p in modules
        for name in _imported(p)
        if name == "uniros_async.bench" or name.startswith("uniros_async.bench.")
    }
    assert not offenders, f"training imports bench (its statistics are uniros_async.stats): {sorted(offenders)}"
