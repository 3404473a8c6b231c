"""The one retry helper: delays double, stop at the cap, restart after reset, and refuse nonsense."""

from __future__ import annotations

import pytest

from uniros_async.backoff import Backoff
from uniros_async.errors import ConfigError


def test_delays_double_up_to_the_cap_and_reset_starts_again() -> None:
    b = Backoff(first_s=0.01, max_s=0.05)
    assert b.at_first
    assert [b.next_s() for _ in range(5)] == [0.01, 0.02, 0.04, 0.05, 0.05]
    assert not b.at_first
    b.reset()
    assert b.delay_s == 0.01 and b.at_first


async def test_sleep_is_limited_and_grows_the_next_delay() -> None:
    b = Backoff(first_s=10.0, max_s=20.0)
    await b.sleep(limit_s=0.0)  # would hang the test if the limit were ignored
    assert b.delay_s == 20.0


@pytest.mark.parametrize(("first_s", "max_s", "factor"), [(0.0, 1.0, 2.0), (2.0, 1.0, 2.0), (0.1, 1.0, 0.5)])
def test_nonsense_is_a_config_error(first_s: float, max_s: float, factor: float) -> None:
    with pytest.raises(ConfigError, match="first_s"):
        Backoff(first_s=first_s, max_s=max_s, factor=factor)
