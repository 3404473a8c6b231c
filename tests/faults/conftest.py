"""Fault tests need root, ``ip``, ``tc`` and ``nft``: without them they skip saying what is missing, unless
``UNIROS_REQUIRE_NETFAULT=1`` (set by ``.ci/run``) makes them fail instead."""

from __future__ import annotations

import pytest
from rig.netfault import netfault_missing

from ._arm import skip_or_fail


@pytest.fixture(scope="session")
def netfault_ready() -> None:
    skip_or_fail(netfault_missing(), "UNIROS_REQUIRE_NETFAULT")
