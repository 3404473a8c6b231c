"""Every ``module.name`` a docstring or comment of uniros_async names in double backticks still resolves.

Every line of the package is read (docstrings, comments, and message text, which names modules the same way).
What counts as a reference to a module (the rest is left alone):

- a dotted name in double backticks, with an optional trailing ``()``: ``uniros_async.bus.codec``,
  ``protocol.pack_step_request()``, ``SimClock.advance`` (a class's attribute: it is not a module reference
  unless its first part is a module);
- absolute (``uniros_async.x.y``), or relative: its first part names a module of the package root
  (``bus.codec``) or of the package the text is in (``worker.pack_step_request`` in ``runtime/``);
- not file names (``worker.py``, ``rx200.xml``), not other packages (``np.float32``, ``gymnasium.Env``), and not
  attribute access on an object whose variable is named like a module: ``config.robot`` reads as a local when
  ``robot`` is no name of the module ``config`` but an attribute of some class of the package.

A name resolves when the longest module prefix is a module (a file or a package folder), the next part is bound at
its top level (defined, assigned, imported or lazily exported; imports inside uniros_async are followed), and a
part after a class is defined in that class or in one of its bases inside the package (a base from outside is not
checked). Everything is read as source, so no module is imported.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import uniros_async

PACKAGE = Path(uniros_async.__file__).parent
ROOT = PACKAGE.parent
_SPAN = re.compile(r"``([^`\s]+?)``")
_DOTTED = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+")
_NO_ATTRIBUTES = {"object", "Generic", "Protocol", "ABC", "NamedTuple", "Enum", "Exception", "TypedDict"}
"""Bases that give a class none of the attributes a docstring names."""
_FILE_SUFFIXES = {"py", "pyi", "c", "so", "xml", "md", "json", "yaml", "yml", "toml", "txt", "csv", "png", "zip"}


def _module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@functools.cache
def _source(module: str) -> Path | None:
    """The file (or the folder of a namespace package) of a module of uniros_async, or None."""
    base = ROOT.joinpath(*module.split("."))
    for path in (base / "__init__.py", base.with_suffix(".py")):
        if path.is_file():
            return path
    return base if base.is_dir() and module.startswith("uniros_async") else None


@functools.cache
def _parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _tree(module: str) -> ast.Module:
    path = _source(module)
    return _parse(path) if path is not None and path.is_file() else ast.Module(body=[], type_ignores=[])


def _statements(body: list[ast.stmt]) -> list[ast.stmt]:
    """A module's top-level statements, with those inside top-level ``if`` and ``try`` blocks."""
    out: list[ast.stmt] = []
    for st in body:
        if isinstance(st, ast.If):
            out += _statements(st.body + st.orelse)
        elif isinstance(st, ast.Try):
            out += _statements(st.body + [s for h in st.handlers for s in h.body] + st.orelse + st.finalbody)
        else:
            out.append(st)
    return out


Binding = ast.stmt | tuple[str, str] | None
"""What a top-level name is bound to: its statement, ``(module, name)`` of a from-import, or None (unknown)."""


@functools.cache
def _top_names(module: str) -> dict[str, Binding]:
    names: dict[str, Binding] = {}
    listed: set[str] = set()  # names in __all__ or a lazy-export table: bound, maybe nowhere to follow
    source = _source(module)
    is_package = source is not None and (source.name == "__init__.py" or source.is_dir())
    for st in _statements(_tree(module).body):
        if isinstance(st, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.setdefault(st.name, st)
        elif isinstance(st, ast.Assign | ast.AnnAssign | ast.AugAssign):
            targets = st.targets if isinstance(st, ast.Assign) else [st.target]
            for target in targets:
                for node in ast.walk(target):
                    if isinstance(node, ast.Name):
                        names.setdefault(node.id, st)
            if isinstance(st.value, ast.List | ast.Tuple | ast.Dict):  # __all__ and lazy-export tables
                keys = st.value.keys if isinstance(st.value, ast.Dict) else st.value.elts
                for key in keys:
                    if isinstance(key, ast.Constant) and isinstance(key.value, str) and key.value.isidentifier():
                        listed.add(key.value)
        elif isinstance(st, ast.ImportFrom):
            base = st.module or ""
            if st.level:
                parts = module.split(".") if is_package else module.split(".")[:-1]
                base = ".".join(parts[: len(parts) - st.level + 1] + ([st.module] if st.module else []))
            for alias in st.names:
                names.setdefault(alias.asname or alias.name, (base, alias.name))
        elif isinstance(st, ast.Import):
            for alias in st.names:
                names.setdefault(alias.asname or alias.name.split(".")[0], (alias.name, ""))
    return names | {name: None for name in listed - set(names)}


def _lookup(module: str, name: str, depth: int = 0) -> tuple[str, ast.stmt | None] | bool:
    """Where ``module.name`` is defined: ``(module, its statement or None for a module)``; True when it is bound but
    cannot be followed (outside uniros_async, or lazily); False when it is not bound at all."""
    if _source(f"{module}.{name}") is not None:
        return f"{module}.{name}", None
    names = _top_names(module)
    if name not in names:
        return False
    binding = names[name]
    if isinstance(binding, tuple):
        source, attr = binding
        if not source.startswith("uniros_async") or depth > 8:
            return True
        if not attr:
            return (source, None) if _source(source) is not None else False
        return _lookup(source, attr, depth + 1) if _source(source) is not None else False
    return (module, binding) if binding is not None else True


def _class_defines(module: str, cls: ast.ClassDef, attr: str, depth: int = 0) -> bool:
    for node in ast.walk(cls):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) and node.name == attr:
            return True
        if isinstance(node, ast.Name | ast.Attribute) and isinstance(node.ctx, ast.Store):
            if (node.id if isinstance(node, ast.Name) else node.attr) == attr:
                return True
    for base in cls.bases:
        base = base.value if isinstance(base, ast.Subscript) else base  # Generic[T], Mapping[str, int]
        if isinstance(base, ast.Name) and base.id in _NO_ATTRIBUTES:
            continue
        found = _lookup(module, base.id) if isinstance(base, ast.Name) and depth < 8 else True
        if not isinstance(found, tuple) or not isinstance(found[1], ast.ClassDef):
            return True  # a base from outside the package: its attributes are not checked
        if _class_defines(found[0], found[1], attr, depth + 1):
            return True
    return False


def _resolves(parts: list[str]) -> bool:
    i = len(parts)
    while i and _source(".".join(parts[:i])) is None:
        i -= 1
    if i == 0:
        return False
    module, rest = ".".join(parts[:i]), parts[i:]
    if not rest:
        return True
    found = _lookup(module, rest[0])
    if not isinstance(found, tuple) or len(rest) == 1:
        return bool(found)
    where, statement = found
    if statement is None:
        return _resolves([*where.split("."), *rest[1:]])
    return _class_defines(where, statement, rest[1]) if isinstance(statement, ast.ClassDef) else True


_ATTRIBUTE = re.compile(
    r"^[ \t]+(?:async[ \t]+)?def[ \t]+(\w+)"  # a method (or a nested function)
    r"|^[ \t]+(\w+)[ \t]*:[ \t]*[\w\"'\[]"  # a class-body field (``robot: str``)
    r"|\.(\w+)[ \t]*(?::[^=\n]*)?=(?!=)",  # an attribute assigned (``self.stats = ...``)
    re.MULTILINE,
)


@functools.cache
def _attribute_names() -> frozenset[str]:
    """Every name an object of a class of the package may have: its methods, its fields and every attribute
    assigned anywhere, read with a regular expression (parsing every file would take seconds)."""
    names: set[str] = set()
    for path in PACKAGE.rglob("*.py"):
        for match in _ATTRIBUTE.finditer(path.read_text()):
            names.add(next(g for g in match.groups() if g))
    return frozenset(names)


def _texts(path: Path) -> list[tuple[int, str]]:
    """The file's lines: its docstrings and comments, and any message text (double backticks are not code)."""
    return list(enumerate(path.read_text().splitlines(), start=1))


def _check(text: str, package: str) -> bool | None:
    """Whether ``text`` (what stood in double backticks) resolves, read in ``package``; None: no module reference."""
    name = text.removesuffix("()")
    if not _DOTTED.fullmatch(name) or name.rpartition(".")[2] in _FILE_SUFFIXES:
        return None
    parts = name.split(".")
    if parts[0] == "uniros_async":
        return _resolves(parts)
    bases = [m for m in (f"{package}.{parts[0]}", f"uniros_async.{parts[0]}") if _source(m)]
    if not bases:
        return None  # not a module of the package: another package, a class, a local
    if all(not _lookup(m, parts[1]) for m in bases) and parts[1] in _attribute_names():
        return None  # obj.attribute on a variable named like a module (``config.robot``)
    return any(_resolves([*m.split("."), *parts[1:]]) for m in bases)


def _offenders() -> tuple[list[str], int]:
    offenders, checked = [], 0
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_of(path)
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for line, text in _texts(path):
            for match in _SPAN.finditer(text):
                found = _check(match.group(1), package)
                checked += found is not None
                if found is False:
                    offenders.append(f"{path.relative_to(ROOT)}:{line}: ``{match.group(1)}``")
    return offenders, checked


def test_every_module_name_a_docstring_names_resolves() -> None:
    offenders, checked = _offenders()
    assert checked > 50, checked  # the scan found the package's references
    assert not offenders, "names that no longer resolve:\n" + "\n".join(offenders)


def test_what_counts_as_a_module_reference() -> None:
    runtime = "uniros_async.runtime"
    assert _check("worker.unpack_step_reply_into", runtime) is False  # moved to protocol: caught
    assert _check("protocol.unpack_step_reply_into()", runtime) is True
    assert _check("runtime.worker.no_such_name", "uniros_async.envs") is False  # envs/runtime.py tried too
    assert _check("bus.codec", runtime) is True  # relative to the package root
    for text in ("config.robot", "np.float32", "worker.py", "rx200.xml", "SimClock.advance", "gymnasium.Env"):
        assert _check(text, runtime) is None, text


def test_the_resolver_tells_a_moved_name_from_a_present_one() -> None:
    assert _resolves("uniros_async.errors.ConfigError".split("."))
    assert _resolves("uniros_async.registry.Registry.register".split("."))
    assert _resolves("uniros_async.transports.base.register_scheme".split("."))  # a package without __init__
    assert _resolves("uniros_async.robots.RobotSpec.name".split("."))  # re-exported, then a dataclass field
    assert not _resolves("uniros_async.errors.NoSuchError".split("."))
    assert not _resolves("uniros_async.registry.Registry.no_such_method".split("."))
    assert not _resolves("uniros_async.no_such_module.x".split("."))
