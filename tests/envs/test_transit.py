"""The env's estimate of a joint state's transit (``envs.transit.StateTransit``): bookkeeping, no network.

Following a subscription is tested on a real one, in an in-process memory domain. Otherwise a link is simulated on
paper: the arm's clock runs ``OFFSET_NS`` ahead of the env's, a command sent at env time ``t`` arrives after ``fwd``,
and a state stamped at env time ``ts`` arrives after ``back``, echoing the newest command received and how long
before its stamp that arrived, as ``ServoSimNode`` does.
"""

from __future__ import annotations

import asyncio
import re
import time

import numpy as np
import pytest

from uniros_async.bus import codec, open_domain, open_node
from uniros_async.bus.messages import Header, JointState
from uniros_async.envs.transit import SENT_RING, TRANSIT_WINDOW_S, StateTransit
from uniros_async.errors import CodecError

OFFSET_NS = 123_456_789_000  # the arm's clock minus the env's
MS = 1_000_000
S = 1_000_000_000


def _state(stamp_env_ns: int, echo: tuple[int, int] | None, *, echoes: bool = True) -> JointState:
    """A state stamped at env time ``stamp_env_ns`` (on the arm's clock), echoing (command stamp, its arrival in env
    time) or, when ``echo`` is None, no command yet."""
    if not echoes:
        stamp_stamp, age = None, None
    elif echo is None:
        stamp_stamp, age = None, -1
    else:
        stamp_stamp, age = echo[0], stamp_env_ns - echo[1]
    return JointState(
        header=Header(stamp_ns=stamp_env_ns + OFFSET_NS),
        name=("a",),
        position=[0.0],
        velocity=[0.0],
        effort=[0.0],
        command_stamp_ns=stamp_stamp,
        command_age_ns=age,
    )


class Link:
    """Commands every ``period`` and states every ``period`` over a link of ``fwd`` / ``back`` each way."""

    def __init__(self, transit: StateTransit, fwd_ns: int, back_ns: int, period_ns: int = 100 * MS) -> None:
        self.transit, self.fwd, self.back, self.period = transit, fwd_ns, back_ns, period_ns
        self.t = 10 * S
        self.sends: list[tuple[int, int]] = []  # (stamp, arrival at the arm), env time
        self.commanding = True

    def run(self, seconds: float) -> tuple[JointState, int]:
        """Advance ``seconds``: a command (while commanding) and a state each period; the newest state and its
        arrival."""
        last: tuple[JointState, int] | None = None
        for _ in range(round(seconds * S / self.period)):
            self.t += self.period
            if self.commanding:
                self.transit.sent(self.t)
                self.sends.append((self.t, self.t + self.fwd))
            arrived = [c for c in self.sends if c[1] <= self.t]
            js = _state(self.t, arrived[-1] if arrived else None)
            arrival = self.t + self.back
            self.transit.observe(js, arrival)
            last = (js, arrival)
        assert last is not None
        return last


def test_without_an_echo_a_fixed_delay_is_invisible_and_queueing_is_not() -> None:
    transit = StateTransit()
    for i in range(20):  # 1 s each way, every state
        transit.observe(_state(i * 100 * MS, None, echoes=False), i * 100 * MS + S)
    js = _state(2 * S, None, echoes=False)
    transit.observe(js, 2 * S + S)
    assert transit.transit_ns(js, 2 * S + S) == 0  # the offset of the clocks and the delay cancel out
    late = _state(2 * S + 100 * MS, None, echoes=False)
    transit.observe(late, 2 * S + 100 * MS + S + 300 * MS)  # queued 0.3 s more than the others
    assert transit.transit_ns(late, 2 * S + 100 * MS + S + 300 * MS) == 300 * MS
    assert not transit.echoes and not transit.awaiting_round_trip and transit.round_trip_ns is None


def test_the_echo_measures_the_round_trip_and_a_fixed_delay_counts() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=S, back_ns=S)
    js, arrival = link.run(0.5)  # no command echoed yet: the quickest state sees nothing, the missing echo does
    assert transit.echoes and transit.awaiting_round_trip
    # the first command went out at 10.1 s, the newest state arrived at 11.5 s still without an echo of any
    assert transit.transit_ns(js, arrival) == 700 * MS
    js, arrival = link.run(3.0)
    assert not transit.awaiting_round_trip
    assert transit.round_trip_ns == 2 * S and transit.offset_round_trip_ns == 2 * S
    assert transit.transit_ns(js, arrival) == S  # half the round trip, whatever the clocks' offset


def test_an_asymmetric_link_is_judged_by_half_its_round_trip() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=100 * MS, back_ns=500 * MS)
    js, arrival = link.run(3.0)
    assert transit.round_trip_ns == 600 * MS
    assert transit.transit_ns(js, arrival) == 300 * MS  # half the asymmetry (0.2 s) below the truth: the stated limit


def test_the_estimate_follows_the_delay_down_without_new_commands() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=S, back_ns=S)
    js, arrival = link.run(5.0)
    assert transit.transit_ns(js, arrival) == S
    # stale: the env stops commanding, so the arm echoes the same old command, older at every state
    link.commanding = False
    link.back = 20 * MS  # the delay goes away (the backward leg is what the states travel)
    js, arrival = link.run(1.0)
    assert transit.transit_ns(js, arrival) == 20 * MS
    # the commands in flight when it went came back quicker (a long way out, a short way back): passed over
    assert transit.round_trip_ns == S + 20 * MS and transit.offset_round_trip_ns == 2 * S


def test_a_delay_that_comes_later_is_seen_at_once() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=10 * MS, back_ns=10 * MS)
    link.run(3.0)
    link.fwd = link.back = S
    # no echo of a delayed command back yet: the offset is known already (the states stalled for the extra second
    # when it came, so the echo of the last quick command, sent before the stall, is no round trip)
    js, arrival = link.run(0.3)
    assert transit.transit_ns(js, arrival) == S


def test_only_an_echo_of_our_own_recent_commands_counts() -> None:
    transit = StateTransit(stall_s=1000.0)  # states seconds apart here: no stall
    js = _state(S, (5 * S, S - 10 * MS))  # a stamp we never sent (another commander, or garbage)
    transit.observe(js, S + 10 * MS)
    assert transit.echoes and transit.round_trips == 0 and transit.awaiting_round_trip
    for bad_stamp, bad_age in (("x", 1), (5 * S, "1"), (5 * S, -5), (5 * S, 10 * S)):
        transit.sent(5 * S)
        bogus = JointState(
            header=Header(stamp_ns=2 * S), name=("a",), position=[0.0], velocity=[0.0], effort=[0.0],
            command_stamp_ns=bad_stamp, command_age_ns=bad_age,  # type: ignore[arg-type]
        )  # fmt: skip
        transit.observe(bogus, 6 * S)  # (the last: an age longer than the round trip, rtt < 0)
    assert transit.round_trips == 0
    for i in range(SENT_RING + 1):
        transit.sent(100 * S + i)
    assert len(transit._sent) == SENT_RING
    transit.observe(_state(200 * S, (100 * S, 150 * S)), 201 * S)  # the oldest send, forgotten
    assert transit.round_trips == 0
    transit.observe(_state(200 * S, (100 * S + 1, 150 * S)), 201 * S)
    assert transit.round_trips == 1


def test_a_command_that_waited_through_a_stall_is_no_round_trip() -> None:
    transit = StateTransit(stall_s=0.5)
    t0 = 10 * S
    transit.sent(t0)  # the arm freezes before it takes this command
    transit.observe(_state(t0, None), t0 + MS)
    frozen = _state(t0 + 2 * S, (t0, t0 + 2 * S))  # 2 s later it runs again: the command arrives, is echoed at once
    transit.observe(frozen, t0 + 2 * S + MS)
    assert transit.round_trips == 0 and transit.awaiting_round_trip
    assert transit.transit_ns(frozen, t0 + 2 * S + MS) == 0  # the state after the stall is fresh
    transit.sent(t0 + 2100 * MS)  # a command after the stall: its echo is a round trip
    fresh = _state(t0 + 2200 * MS, (t0 + 2100 * MS, t0 + 2101 * MS))
    transit.observe(fresh, t0 + 2201 * MS)
    assert transit.round_trips == 1 and transit.round_trip_ns == 2 * MS
    assert transit.transit_ns(fresh, t0 + 2201 * MS) == MS


def test_the_windows_are_bounded_and_forget_after_a_minute() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=S, back_ns=S)
    link.run(5.0)
    # slower and slower round trips (each a sample the window keeps): bounded by the window's length
    for _ in range(round(TRANSIT_WINDOW_S) + 30):
        link.fwd += MS
        link.run(1.0)
    assert len(transit._trips) <= TRANSIT_WINDOW_S * S / link.period + 1
    used = transit.offset_round_trip_ns
    assert used is not None and used > 2 * S  # the 2 s ones left the window
    transit.clear()
    assert transit.round_trip_ns is None and not transit.echoes and transit.offset_round_trip_ns is None
    assert transit._sent, "the env's own send stamps outlive a new connection"


def test_without_commands_the_round_trips_expire_and_an_unechoed_command_bounds_the_age() -> None:
    transit = StateTransit()
    link = Link(transit, fwd_ns=S, back_ns=S)
    link.run(5.0)
    link.commanding = False  # the env stopped commanding; the arm echoes its last command ever after
    js, arrival = link.run(TRANSIT_WINDOW_S + 2)
    assert transit.awaiting_round_trip and transit.offset_round_trip_ns is None
    assert transit.transit_ns(js, arrival) == 0  # back to the quickest state alone: the fixed delay unseen
    link.commanding = True
    js, arrival = link.run(0.5)  # commands since 0.4 s before the newest state's stamp, none echoed a second later
    assert transit.transit_ns(js, arrival) == 700 * MS
    js, arrival = link.run(2.0)
    assert transit.transit_ns(js, arrival) == S


class CountingTransit(StateTransit):
    """A StateTransit that counts the states it observes."""

    def __init__(self, stall_s: float) -> None:
        super().__init__(stall_s)
        self.observed: list[JointState] = []

    def observe(self, js: JointState, arrival_ns: int) -> None:
        self.observed.append(js)
        super().observe(js, arrival_ns)


async def test_following_a_subscription_observes_each_state_once_and_a_new_one_afresh() -> None:
    transit = CountingTransit(stall_s=1000.0)  # the test's pauses are no stall
    async with open_domain("memory://") as domain, open_node("arm", domain=domain) as arm:
        async with open_node("env", domain=domain) as env:
            pub = await arm.create_publisher(JointState, "joint_states")
            sub = await env.create_subscription(JointState, "joint_states")
            transit.follow(sub)  # nothing received yet: nothing to observe
            assert transit.observed == [] and not transit.echoes
            sent = time.monotonic_ns()
            transit.sent(sent)
            first = _state(sent, (sent, sent))  # echoes the command at once (age 0): the round trip is its way
            pub.publish(first)
            async with asyncio.timeout(5):
                assert await sub.receive() is first
            transit.follow(sub)
            transit.follow(sub)  # no new state: not observed again
            assert transit.observed == [first]
            assert transit.round_trips == 1 and transit.echoes
            rtt = transit.round_trip_ns
            assert rtt is not None and 0 <= rtt <= time.monotonic_ns() - sent
            # another subscription (the arm's domain joined again) that has received as many states as the first
            # had when last followed: cleared, and its state observed all the same
            again = await env.create_subscription(JointState, "joint_states")
            second = _state(time.monotonic_ns(), None, echoes=False)
            pub.publish(second)
            async with asyncio.timeout(5):
                assert await again.receive() is second
            assert again.received == 1 and sub.received == 2
            transit.follow(again)
            assert transit.observed == [first, second]
            assert transit.round_trips == 0 and transit.round_trip_ns is None and not transit.echoes
            transit.follow(again)
            transit.follow(sub)  # back to the first: afresh again, its newest state observed once more
            assert transit.observed == [first, second, second] and transit.round_trips == 0


def test_describe_names_the_round_trips_or_the_unechoed_commands() -> None:
    transit = StateTransit()
    assert transit.describe(10 * S) == ""  # nothing sent, nothing echoed
    link = Link(transit, fwd_ns=S, back_ns=S)
    _, arrival = link.run(0.5)  # the first command went out at 10.1 s, none echoed by 11.5 s
    assert transit.describe(arrival) == (
        "the arm echoed none of our commands of the last 1.40 s: a round trip at least that long"
    )
    _, arrival = link.run(3.0)
    assert transit.describe(arrival) == (
        "the round trip to the arm measured 2.00 s by its echo of our commands (half of 2.00 s counted as a"
        " state's transit)"
    )
    link.commanding = False
    link.back = 20 * MS  # the delay goes: the newest round trip is shorter than the one counted
    _, arrival = link.run(1.0)
    text = transit.describe(arrival)
    assert re.fullmatch(r"the round trip to the arm measured 1\.02 s .* \(half of 2\.00 s counted .*\)", text), text
    transit.clear()
    assert transit.describe(arrival) == ""  # an arm not known to echo: no claim about unechoed commands


def test_a_joint_state_from_a_publisher_without_the_echo_decodes_without_one() -> None:
    import msgpack

    js = _state(S, (S - MS, S - MS))
    frame = b"".join(bytes(p) for p in codec.encode(js))
    (n,) = np.frombuffer(frame[:4], "<u4")
    name, values, table = msgpack.unpackb(frame[4 : 4 + n], raw=False, strict_map_key=False)
    assert len(values) == 7
    for kept in (5, 6):  # an older publisher's frame: without the trailing fields
        body = msgpack.packb([name, values[:kept], table], use_bin_type=True)
        head = len(body).to_bytes(4, "little") + body
        head += bytes(-len(head) % 8)
        old = codec.decode(head + frame[(4 + n + 7) // 8 * 8 :], JointState)
        assert old.command_age_ns is None and old.header.stamp_ns == js.header.stamp_ns
        np.testing.assert_array_equal(old.position, js.position)
    body = msgpack.packb([name, values[:4], table], use_bin_type=True)  # a required field missing: refused
    with pytest.raises(CodecError, match=r"JointState: expected 5 to 7 fields, got 4"):
        codec.decode(len(body).to_bytes(4, "little") + body + bytes(-(4 + len(body)) % 8), JointState)
