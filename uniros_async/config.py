"""Configs a user writes (YAML files, env keyword arguments), validated with pydantic and reported in our words.

Every such config is a ``ConfigModel``: frozen, unknown keys rejected, and each field typed with the types below
(``Int``, ``Float``, ``Bool``, ``Str``, ``Vec3``), which take what a YAML file or a command line gives and
refuse what is plainly a mistake: ``batch_size: 128.5`` or ``batch_size: true`` is not an integer, ``1e4`` is
(PyYAML reads YAML 1.1, where ``3e-4`` and ``1e4`` are strings; ``load_yaml`` reads them as the numbers they are,
and the number types accept numeric strings as well, so a quoted ``"1e4"`` works too). A bad config raises
``ConfigError`` with one line per problem, each naming the key's path and what was expected::

    td3.batch_size: expected an integer, got 128.5
    envs[1].kwargs.reward_type: expected one of 'dense', 'sparse', got 'spars'; did you mean 'sparse'?
    td3.lr: unknown key; did you mean 'learning_rate'?

Validation runs once, when a config is built; the values are then plain attributes (the env loop reads them
without pydantic in the way). Hot-path records (bus messages, sim state) stay dataclasses.

To add a key, add a typed field with its default (and ``Field(gt=..., le=...)`` bounds, or a validator for a
rule that spans fields); the docs table (docs/configuration.md) is generated from the fields
(``markdown_table``), and a test checks that it matches.
"""

from __future__ import annotations

import ast
import difflib
import inspect
import math
import numbers
import re
import textwrap
import types
import typing
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import numpy as np
import pydantic
from pydantic import BeforeValidator, ConfigDict, Strict, ValidationError
from pydantic_core import PydanticCustomError

from uniros_async.errors import ConfigError

if TYPE_CHECKING:
    from uniros_async.yamlio import load_yaml

__all__ = [
    "Bool",
    "ConfigModel",
    "Float",
    "Int",
    "KeyProblem",
    "Str",
    "Vec3",
    "attribute_docs",
    "closest",
    "config_error",
    "key_error",
    "load_config",
    "load_yaml",
    "markdown_table",
    "prefixed",
    "problems_error",
]

M = TypeVar("M", bound="ConfigModel")


# ---- field types


def _problem(message: str, value: Any) -> PydanticCustomError:
    return PydanticCustomError("uniros", "{message}", {"message": message, "value": value})


def _int_input(v: Any) -> Any:
    if isinstance(v, bool | np.bool_):
        raise _problem("expected an integer", v)
    if isinstance(v, numbers.Integral):  # numpy integers too
        return int(v)
    number = v
    if isinstance(v, str):
        try:
            return int(v.strip())  # "10", "1_000"
        except ValueError:
            pass
        try:
            number = float(v.strip())  # "1e4"
        except ValueError:
            raise _problem("expected an integer", v) from None
    if isinstance(number, numbers.Real):
        f = float(number)
        if math.isfinite(f) and f.is_integer():
            return int(f)
        raise _problem("expected an integer", v)
    return v


def _float_input(v: Any) -> Any:
    if isinstance(v, bool | np.bool_):
        raise _problem("expected a number", v)
    number = float(v) if isinstance(v, numbers.Real) and not isinstance(v, int | float) else v  # numpy scalars
    if isinstance(v, str):
        try:
            number = float(v.strip())  # "3e-4", "1_000", "inf"
        except ValueError:
            raise _problem("expected a number", v) from None
    if isinstance(number, float) and math.isnan(number):  # NaN passes every bound check: refuse it here
        raise _problem("expected a number (not NaN)", v)
    return number


def _vec3_input(v: Any) -> Any:
    if isinstance(v, list | tuple) and len(v) == 3:
        return tuple(v)
    if isinstance(v, np.ndarray) and v.shape == (3,):
        return tuple(v.tolist())
    raise _problem("expected 3 numbers [x, y, z]", v)


Int = Annotated[int, BeforeValidator(_int_input), Strict()]
"""An integer; also an integral float or numeric string (``1e4``, ``"1_000"``); never a bool or ``128.5``."""
Float = Annotated[float, BeforeValidator(_float_input), Strict()]
"""A number; also a numeric string (``"3e-4"``); never a bool."""
Bool = Annotated[bool, Strict()]
"""``true`` or ``false``; never 0, 1 or a string."""
Str = Annotated[str, Strict()]
"""A string; never a number."""
Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(_vec3_input)]
"""Three numbers (a point, in m)."""


# ---- the base model


class ConfigModel(pydantic.BaseModel):
    """Base of every user-written config: frozen, unknown keys rejected, errors raised as ConfigError.

    ``Model(**kwargs)`` and ``Model.from_data(mapping)`` both validate; a problem raises ConfigError (see the
    module docstring), never pydantic's ValidationError.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    def __init__(self, **data: Any) -> None:
        """Validate ``data``; see the class docstring.

        Raises:
            ConfigError: one line per problem: the key's path, what was expected and what was given.
        """
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise config_error(exc, type(self)) from None

    @classmethod
    def from_data(cls: type[M], data: Any, *, where: str = "") -> M:
        """Build the config from plain data (a mapping, as read from YAML; None: all defaults).

        Args:
            data: the mapping.
            where: what the data came from (a file name), put in front of the error message.

        Raises:
            ConfigError: ``data`` is not a mapping, or one line per problem (see the module docstring).
        """
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(_where(where, f"expected a mapping of {cls.__name__} keys, got {_show(data)}"))
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise config_error(exc, cls, where=where) from None

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The config's keys, in declaration order."""
        return tuple(cls.model_fields)

    def to_data(self) -> dict[str, Any]:
        """Plain data (dicts, lists, scalars) that ``from_data`` turns back into an equal config."""
        out: dict[str, Any] = _plain(self)
        return out


def _plain(v: Any) -> Any:
    if isinstance(v, pydantic.BaseModel):
        return {k: _plain(getattr(v, k)) for k in type(v).model_fields}
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    return v


def load_config(path: str | Path, cls: type[M]) -> M:
    """Load ``cls`` from the YAML file at ``path``.

    Raises:
        ConfigError: the file cannot be read or parsed, or the data is not a valid ``cls`` (messages start with
            the path).
    """
    from uniros_async.yamlio import load_yaml

    return cls.from_data(load_yaml(path), where=str(path))


class KeyProblem(ValueError):
    """A validator's complaint about one key of its model (the key joins the error's path)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def key_error(key: str, message: str) -> KeyProblem:
    """An error for a model validator to raise about one of its keys: the key joins the reported path.

    ``raise key_error("batch_size", f"must be <= buffer_size ({self.buffer_size}), got {self.batch_size}")`` in
    TD3Config's validator reports ``td3.batch_size: must be <= buffer_size (1000), got 2000`` in a TrainConfig.
    """
    return KeyProblem(key, message)


# ---- errors in our words


def closest(name: str, valid: Iterable[str]) -> str | None:
    """The valid name closest to ``name`` (a typo's likely meaning), or None when none is close."""
    names = list(valid)
    match = difflib.get_close_matches(str(name), names, n=1, cutoff=0.6)
    if match:
        return match[0]
    initials = [n for n in names if "_" in n and "".join(w[:1] for w in n.split("_")) == name]  # lr: learning_rate
    return initials[0] if len(initials) == 1 else None


def config_error(exc: ValidationError, root: type[pydantic.BaseModel] | None = None, *, where: str = "") -> ConfigError:
    """ConfigError from pydantic's ValidationError: one line per problem, ``path: expectation, got value``.

    Args:
        exc: the validation error.
        root: the model validated (to name the valid keys at an unknown key's level).
        where: put in front of the message (a file name).

    The returned error has ``problems``: the (path, message) pairs, for callers that nest this config in a larger
    one and put their own prefix in front of the paths.
    """
    problems = [p for err in exc.errors() for p in _describe(err, root)]
    return problems_error(problems, where=where)


def problems_error(problems: Sequence[tuple[str, str]], *, where: str = "") -> ConfigError:
    """ConfigError listing ``problems`` ((path, message) pairs), one per line; ``.problems`` holds them."""
    lines = [f"{path}: {msg}" if path else msg for path, msg in problems]
    if len(lines) == 1:
        text = _where(where, lines[0])
    else:
        text = _where(where, f"{len(lines)} problems:\n  " + "\n  ".join(lines))
    err = ConfigError(text)
    err.problems = list(problems)  # type: ignore[attr-defined]
    return err


def prefixed(exc: ConfigError, prefix: str, *, where: str = "") -> ConfigError:
    """``exc`` again with ``prefix`` in front of every problem's path (``exc`` itself if it has no problems)."""
    problems = getattr(exc, "problems", None)
    if not problems:
        return ConfigError(_where(where, str(exc))) if where else exc
    return problems_error([(_join(prefix, p), m) for p, m in problems], where=where)


def _where(where: str, text: str) -> str:
    return f"{where}: {text}" if where else text


def _join(prefix: str, path: str) -> str:
    if not prefix:
        return path
    if not path:
        return prefix
    return prefix + path if path.startswith("[") else f"{prefix}.{path}"


def _path(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _show(v: Any) -> str:
    if isinstance(v, dict):
        return "a mapping"
    text = repr(list(v)) if isinstance(v, tuple) else repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


_EXPECTED = {
    "int_type": "expected an integer",
    "int_parsing": "expected an integer",
    "int_from_float": "expected an integer",
    "float_type": "expected a number",
    "float_parsing": "expected a number",
    "finite_number": "expected a finite number",
    "bool_type": "expected true or false",
    "bool_parsing": "expected true or false",
    "string_type": "expected a string",
    "dict_type": "expected a mapping",
    "model_type": "expected a mapping",
    "model_attributes_type": "expected a mapping",
    "tuple_type": "expected a list",
    "list_type": "expected a list",
    "iterable_type": "expected a list",
}
_BOUNDS = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _describe(err: Any, root: type[pydantic.BaseModel] | None) -> list[tuple[str, str]]:
    loc: tuple[int | str, ...] = tuple(err["loc"])
    kind: str = err["type"]
    value = err.get("input")
    ctx: dict[str, Any] = err.get("ctx") or {}
    if kind == "extra_forbidden":
        valid = _keys_at(root, loc[:-1])
        near = closest(str(loc[-1]), valid) if valid else None
        if near:
            return [(_path(loc), f"unknown key; did you mean {near!r}?")]
        return [(_path(loc), f"unknown key (valid keys: {', '.join(valid)})" if valid else "unknown key")]
    if kind == "missing":
        return [(_path(loc), "missing (required)")]
    if kind == "uniros":
        return [(_path(loc), f"{ctx['message']}, got {_show(ctx['value'])}")]
    if kind == "literal_error":
        choices = re.findall(r"'((?:[^'\\]|\\.)*)'", str(ctx.get("expected", "")))
        msg = f"expected one of {', '.join(repr(c) for c in choices)}, got {_show(value)}"
        near = closest(value, choices) if isinstance(value, str) else None
        return [(_path(loc), msg + (f"; did you mean {near!r}?" if near else ""))]
    if kind in _BOUNDS:
        bound = next(iter(ctx.values()))
        return [(_path(loc), f"must be {_BOUNDS[kind]} {bound:g}, got {_show(value)}")]
    if kind == "string_pattern_mismatch":
        return [(_path(loc), f"must match {ctx.get('pattern')}, got {_show(value)}")]
    if kind == "string_too_short":
        return [(_path(loc), f"expected a non-empty string, got {_show(value)}")]
    if kind in ("too_short", "too_long"):
        n = ctx.get("min_length") if kind == "too_short" else ctx.get("max_length")
        return [
            (_path(loc), f"expected {'at least' if kind == 'too_short' else 'at most'} {n} item(s), got {_show(value)}")
        ]
    if kind in ("value_error", "assertion_error"):
        cause = ctx.get("error")
        if isinstance(cause, KeyProblem):
            return [(_path((*loc, cause.key)), str(cause))]
        nested = getattr(cause, "problems", None)
        if nested:  # a nested ConfigModel's own __init__ (pydantic calls it) raised ConfigError
            return [(_join(_path(loc), p), m) for p, m in nested]
        return [(_path(loc), str(cause) if cause is not None else err["msg"])]
    if kind in _EXPECTED:
        return [(_path(loc), f"{_EXPECTED[kind]}, got {_show(value)}")]
    return [(_path(loc), f"{err['msg']}, got {_show(value)}")]


def _keys_at(root: type[pydantic.BaseModel] | None, loc: Sequence[int | str]) -> list[str]:
    """The keys of the model at ``loc`` inside ``root`` (empty if it cannot be told)."""
    hint: Any = root
    for part in loc:
        hint = _model_in(hint, index=isinstance(part, int))
        if hint is None:
            return []
        if isinstance(part, str):
            field = hint.model_fields.get(part)
            if field is None:
                return []
            hint = field.annotation
    hint = _model_in(hint, index=False)
    return list(hint.model_fields) if hint is not None else []


def _model_in(hint: Any, *, index: bool) -> Any:
    """The model class ``hint`` names (through Optional and Annotated; an element's, if ``index``)."""
    for _ in range(4):
        if isinstance(hint, type) and issubclass(hint, pydantic.BaseModel):
            return None if index else hint
        origin = typing.get_origin(hint)
        args = typing.get_args(hint)
        if origin is Annotated:
            hint = args[0]
        elif origin in (typing.Union, types.UnionType):
            models = [a for a in args if a is not type(None)]
            if len(models) != 1:
                return None
            hint = models[0]
        elif index and origin in (tuple, list):
            hint, index = args[0], False
        else:
            return None
    return None


# ---- docs


def markdown_table(cls: type[pydantic.BaseModel], *, prefix: str = "") -> str:
    """A Markdown table of ``cls``'s keys: key, type (with its bounds), default and description."""
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    docs = attribute_docs(cls)
    for name, field in cls.model_fields.items():
        default = None if field.is_required() else field.get_default(call_default_factory=True)
        if field.is_required():
            shown = "required"
        elif isinstance(default, pydantic.BaseModel):
            shown = "see below"
        else:
            import yaml

            dumped = yaml.safe_dump(_plain(default), default_flow_style=True, width=1000)
            shown = f"`{dumped.removesuffix(chr(10)).removesuffix('...').strip()}`"
        desc = " ".join((field.description or docs.get(name, "")).split()).replace("|", "\\|")
        rows.append(f"| `{prefix}{name}` | {_type_name(field.annotation, field.metadata)} | {shown} | {desc} |")
    return "\n".join(rows) + "\n"


def attribute_docs(cls: type) -> dict[str, str]:
    """The docstring under each annotated attribute of ``cls`` and its bases (read from the source, for docs).

    The models document each key this way rather than with pydantic's ``use_attribute_docstrings``, which parses
    the source whenever a model class is created, i.e. in every process that imports one (a noticeable start-up cost
    per process); the docs need it only when they are generated.
    """
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass in (object, pydantic.BaseModel, ConfigModel):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for stmt, nxt in zip(body, body[1:], strict=False):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                out[stmt.target.id] = inspect.cleandoc(nxt.value.value)
    return out


def _type_name(hint: Any, metadata: Sequence[Any] = ()) -> str:
    return _with_bounds(_hint_name(hint), metadata)


def _with_bounds(name: str, metadata: Sequence[Any]) -> str:
    bounds = []
    flat = [x for m in metadata for x in (m.metadata if isinstance(m, pydantic.fields.FieldInfo) else [m])]
    for m in flat:
        for attr, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            v = getattr(m, attr, None)
            if v is not None:
                bounds.append(f"{op} {v:g}")
        if getattr(m, "min_length", None):
            if m.min_length == 1 and (name == "string" or name.startswith("list of")):
                name = f"non-empty {name}"
            else:
                bounds.append(f"at least {m.min_length} item(s)")
    return name + (f" ({', '.join(bounds)})" if bounds else "")


def _hint_name(hint: Any) -> str:
    names = {int: "integer", float: "number", bool: "bool", str: "string"}
    if hint in names:
        return names[hint]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Annotated:
        return _with_bounds(_hint_name(args[0]), args[1:])
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join("null" if a is type(None) else _hint_name(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_hint_name(args[0])}"
        if len(args) == 3 and all(_hint_name(a) == "number" for a in args):
            return "3 numbers"
        return "list"
    if origin is dict:
        return "mapping"
    if isinstance(hint, type) and issubclass(hint, pydantic.BaseModel):
        return "mapping"
    return str(getattr(hint, "__name__", hint))


def __getattr__(name: str) -> Any:
    # PyYAML loads only where YAML is read or docs are generated: an env worker validates its keyword arguments
    # with these models and reads no YAML.
    if name == "load_yaml":
        from uniros_async.yamlio import load_yaml

        return load_yaml
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
