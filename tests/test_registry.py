"""The registry helper every registry of uniros_async holds its entries in: entry points, no-ops, refusals, misses."""

from __future__ import annotations

import sys

import pytest

from uniros_async.errors import ConfigError
from uniros_async.registry import Registry, closest_name, load_entry_point, split_entry_point

CONSTANT = {"answer": 42}


def _only_dicts(name: str, value: object) -> dict[str, int]:
    if not isinstance(value, dict):
        raise ConfigError(f"{name}: expected a dict, got {type(value).__name__}")
    return value


def test_an_entry_point_is_imported_on_the_first_lookup_and_checked() -> None:
    reg = Registry[dict[str, int]]("table", entry_points="attribute", check=_only_dicts, note="register adds one")
    reg.register("t", f"{__name__}:CONSTANT")
    assert reg.entries["t"] == f"{__name__}:CONSTANT"  # nothing imported yet
    assert reg.get("t") is CONSTANT
    assert reg.entries["t"] is CONSTANT  # type: ignore[comparison-overlap]  # loaded once, kept
    assert reg.register("t", f"{__name__}:CONSTANT") is CONSTANT  # the entry point of the same value: a no-op
    reg.register("bad", f"{__name__}:closest_name")
    with pytest.raises(ConfigError, match="bad: expected a dict, got function"):
        reg.get("bad")
    reg.register("gone", "no_such_module_here:X")
    with pytest.raises(ConfigError, match=r"table 'gone': cannot load 'no_such_module_here:X' \(cannot import"):
        reg.get("gone")
    assert reg.names() == ("bad", "gone", "t") and "t" in reg and len(reg) == 3


def test_the_same_value_again_is_a_no_op_and_another_is_refused_unless_overridden() -> None:
    reg = Registry[tuple[int, ...]]("pair")
    first = (1, 2)
    assert reg.register("p", first) is first
    assert reg.register("p", (1, 2)) is first  # equal: the entry already there stays
    with pytest.raises(ConfigError, match=r"pair 'p' is already registered \(a tuple\); pass override=True"):
        reg.register("p", (2, 1))
    assert reg.register("p", (2, 1), override=True) == (2, 1) and reg.get("p") == (2, 1)
    fixed = Registry[int]("id", overridable=False, describe=lambda e: f"<{e}>")
    fixed.register("x", 1)
    with pytest.raises(ConfigError, match=r"^id 'x' is already registered \(<1>\)$"):
        fixed.register("x", 2)


def test_a_miss_names_the_closest_and_the_registered() -> None:
    reg = Registry[int]("robot", note="register_robot adds one")
    for name, value in (("rx200", 1), ("ned2", 2)):
        reg.register(name, value)
    with pytest.raises(ConfigError) as info:
        reg.get("ned")
    assert (
        str(info.value)
        == "unknown robot 'ned' (did you mean 'ned2'?); registered: ['ned2', 'rx200'] (register_robot adds one)"
    )
    with pytest.raises(ConfigError, match=r"unknown robot 42; registered"):
        reg.get(42)  # type: ignore[arg-type]
    error = reg.unknown("rx20", message="no arm 'rx20' here", among=["ned2"])
    assert str(error).startswith("no arm 'rx20' here; registered: ['ned2']")  # nothing close among those
    assert closest_name("tpc", ["tcp", "shm"]) == "tcp" and closest_name("zzz", ["tcp"]) is None


def test_a_registry_of_modules() -> None:
    reg = Registry[object]("transport scheme", entry_points="module")
    reg.register("json", "json")
    assert reg.get("json") is sys.modules["json"]
    assert reg.register("json", "json") is sys.modules["json"]  # the module that name imports: a no-op


@pytest.mark.parametrize(
    ("entry_point", "attribute", "match"),
    [
        ("no_colon", True, "'module:attribute', got 'no_colon'"),
        (":X", True, "got ':X'"),
        ("m:", False, "'module' or 'module:attribute', got 'm:'"),
        ("a:b:c", True, "got 'a:b:c'"),
        (42, True, "got int"),
    ],
)
def test_malformed_entry_points_are_refused(entry_point: object, attribute: bool, match: str) -> None:
    with pytest.raises(ConfigError, match=f"^thing: expected an entry point .*{match}"):
        split_entry_point(entry_point, "thing", attribute=attribute)
    reg = Registry[int]("thing", entry_points="attribute" if attribute else "module")
    if isinstance(entry_point, str):
        with pytest.raises(ConfigError, match=match):
            reg.register("x", entry_point)
        assert "x" not in reg


def test_dotted_attributes_load_and_missing_ones_are_named() -> None:
    assert load_entry_point("os:path.join", "join") is __import__("os").path.join
    with pytest.raises(ConfigError, match=r"cannot load 'os:no_such_thing' \('os' has no 'no_such_thing'\)"):
        load_entry_point("os:no_such_thing", "thing")


def test_the_modules_example_runs() -> None:
    import doctest

    import uniros_async.registry

    result = doctest.testmod(uniros_async.registry)
    assert result.attempted >= 3 and result.failed == 0
