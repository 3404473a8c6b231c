"""The error tree: errors.py defines every UnirosError, its docstring draws each one under its parent, and
``uniros_async`` exports them all."""

from __future__ import annotations

import ast
import inspect
import re
import subprocess
import sys
from pathlib import Path

import uniros_async
from uniros_async import errors
from uniros_async.errors import UnirosError

PACKAGE = Path(uniros_async.__file__).parent
_CLASS = re.compile(r"^[ \t]*class[ \t]+(?P<name>\w+)[ \t]*\((?P<bases>[^)]*)\)", re.MULTILINE)
_TREE_LINE = re.compile(r"^[ │]*(?:[├└]── )?(?P<name>[A-Z]\w+)\b")


def _error_classes() -> dict[str, type[BaseException]]:
    """Every UnirosError subclass errors.py makes (InvalidActionsError is built on first access)."""
    found = {name: getattr(errors, name) for name in errors.__all__}
    found.update({n: v for n, v in vars(errors).items() if isinstance(v, type) and issubclass(v, UnirosError)})
    return {n: c for n, c in found.items() if isinstance(c, type) and issubclass(c, UnirosError)}


def _tree() -> dict[str, str | None]:
    """The docstring's tree as ``name -> parent name`` (None for the root), read from the indentation."""
    doc = inspect.getdoc(errors) or ""
    block = doc.split("::", 1)[1].split("\n\n", 2)[1]  # the indented block after "::"
    parents: dict[str, str | None] = {}
    stack: list[tuple[int, str]] = []
    for line in block.splitlines():
        m = _TREE_LINE.match(line.removeprefix("    "))
        assert m, f"not a tree line: {line!r}"
        depth = m.start("name")
        while stack and stack[-1][0] >= depth:
            stack.pop()
        parents[m["name"]] = stack[-1][1] if stack else None
        stack.append((depth, m["name"]))
    return parents


def test_the_docstring_draws_every_error_under_its_parent() -> None:
    classes, tree = _error_classes(), _tree()
    assert set(classes) == set(tree), (
        f"in errors.py but not drawn: {sorted(set(classes) - set(tree))}; drawn but not defined: "
        f"{sorted(set(tree) - set(classes))}"
    )
    assert tree["UnirosError"] is None
    for name, parent in tree.items():
        if parent is not None:
            assert classes[parent] in classes[name].__bases__, f"{name} is drawn under {parent}, not derived from it"


def test_every_error_is_exported_from_errors_and_from_the_package() -> None:
    names = set(_error_classes())
    assert names <= set(errors.__all__), sorted(names - set(errors.__all__))
    assert names <= set(uniros_async.__all__), sorted(names - set(uniros_async.__all__))
    for name in names:
        assert getattr(uniros_async, name) is getattr(errors, name)
    assert {"RobotError", "StepTimeoutError", "InvalidActionsError", "CheckpointError"} <= names
    assert issubclass(errors.StepTimeoutError, TimeoutError) and issubclass(errors.StepTimeoutError, errors.WorkerError)


def test_no_module_outside_errors_defines_a_uniros_error() -> None:
    """Read as text (importing every module would import ROS, Ray, MuJoCo): a class whose base is a class of the
    tree, or a class found deriving from one (to any depth), is a UnirosError defined outside errors.py."""
    classes: list[tuple[str, int, str, set[str]]] = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == PACKAGE / "errors.py":
            continue
        text = path.read_text()
        for match in _CLASS.finditer(text):
            bases = {base.split("[")[0].strip().rpartition(".")[2] for base in match["bases"].split(",")}
            line = text.count("\n", 0, match.start()) + 1
            classes.append((str(path.relative_to(PACKAGE.parent)), line, match["name"], bases))
    assert len(classes) > 100  # the scan read the package's classes
    errors_ = set(_error_classes())
    outside: list[str] = []
    grew = True
    while grew:
        grew = False
        for where, line, name, bases in classes:
            entry = f"{where}:{line}: {name}({', '.join(sorted(bases))})"
            if bases & errors_ and entry not in outside:
                outside.append(entry)
                errors_.add(name)
                grew = True
    assert not outside, f"UnirosErrors defined outside uniros_async/errors.py (move them there): {outside}"


def test_the_old_places_import_them_from_errors() -> None:
    """Read as source (training imports torch): each module that defined one of them imports it from errors.py, so
    an old ``from uniros_async.training.checkpoint import CheckpointError`` gives the same class."""
    for module, name in [
        ("runtime/vector.py", "InvalidActionsError"),
        ("training/checkpoint.py", "CheckpointError"),
        ("training/evaluate.py", "EvaluationStopped"),
        ("training/recipes.py", "TrainingInterrupted"),
        ("sim/render.py", "RenderError"),
        ("camera/capture.py", "CameraError"),
        ("camera/topic.py", "FrameError"),
        ("bag/errors.py", "BagDamagedError"),
        ("view/__init__.py", "ViewError"),
    ]:
        tree = ast.parse((PACKAGE / module).read_text())
        imported = {
            alias.name
            for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.module == "uniros_async.errors"
            for alias in node.names
        }
        assert name in imported, f"{module} does not import {name} from uniros_async.errors"
    import gymnasium

    cls = errors.InvalidActionsError
    assert issubclass(cls, gymnasium.error.InvalidAction) and issubclass(cls, ValueError)


def test_importing_the_errors_imports_no_gymnasium() -> None:
    code = (
        "import sys, uniros_async, uniros_async.errors as e\n"
        "assert 'gymnasium' not in sys.modules\n"
        "cls = uniros_async.InvalidActionsError\n"
        "assert 'gymnasium' in sys.modules and cls is e.InvalidActionsError and cls.__module__ == e.__name__\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
