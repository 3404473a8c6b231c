"""``bench._environ.environ_set``: a variable set for a block and restored after it, as the benchmarks set what
the workers they start read (``UNIROS_LOOP_PRIORITY``, ``UNIROS_SHARED_CORES``)."""

from __future__ import annotations

import os

import pytest

from uniros_async.bench._environ import environ_set

NAME = "UNIROS_TEST_ENVIRON_SET"


def test_a_variable_set_for_the_block_is_unset_again_after_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(NAME, raising=False)
    with environ_set(NAME, "rt"):
        assert os.environ[NAME] == "rt"
    assert NAME not in os.environ


def test_a_variable_that_was_set_gets_its_value_back_even_after_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(NAME, "pin")
    with pytest.raises(RuntimeError, match="inside"), environ_set(NAME, "off"):
        assert os.environ[NAME] == "off"
        raise RuntimeError("inside")
    assert os.environ[NAME] == "pin"


def test_none_leaves_the_variable_as_it_is(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(NAME, "pin")
    with environ_set(NAME, None):
        assert os.environ[NAME] == "pin"
    assert os.environ[NAME] == "pin"
    monkeypatch.delenv(NAME)
    with environ_set(NAME, None):
        assert NAME not in os.environ
    assert NAME not in os.environ
