"""WallClock's precise sleeps: never early, and the bounded spin only where asked for."""

from __future__ import annotations

import time

import pytest

from uniros_async.clock import WallClock


@pytest.mark.parametrize("spin", [True, False])
async def test_sleep_until_never_returns_early_and_spins_only_when_asked(spin: bool) -> None:
    clock = WallClock(spin_lead_ns=20_000_000)  # a 20 ms lead: a spin shows as CPU time, whatever the load
    try:
        cpu0 = time.thread_time_ns()
        deadline = clock.now_ns() + 40_000_000
        await clock.sleep_until(deadline, spin=spin)
        assert clock.now_ns() >= deadline
        cpu_ms = (time.thread_time_ns() - cpu0) / 1e6
        if spin:
            assert cpu_ms > 5.0, f"the spin should burn most of its 20 ms lead, burnt {cpu_ms:.2f} ms"
        else:
            assert cpu_ms < 5.0, f"spin=False must sleep through, burnt {cpu_ms:.2f} ms of CPU"
    finally:
        clock.close()
