"""Fault tests need root, ``ip``, ``tc`` and ``nft``: without them they skip saying what is missing, unless
``UNIROS_REQUIRE_NETFAULT=1`` (set by ``.ci/run``) makes them fail instead."""

from __future__ import annotations

import os

import pytest

from uniros_async.testing.netfault import netfault_missing


@pytest.fixture(scope="session")
def netfault_ready() -> None:
    reason = netfault_missing()
    if reason is None:
        return
    if os.environ.get("UNIROS_REQUIRE_NETFAULT") == "1":
        pytest.fail(f"UNIROS_REQUIRE_NETFAULT=1 but {reason}")
    pytest.skip(reason)
