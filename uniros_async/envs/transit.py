"""How long a joint state spent on its way from the arm to the env, when the arm's clock is not the env's.

A state's stamp is on the arm's clock and its arrival on the env's, so ``D = arrival - stamp`` is the state's
transit plus the offset ``c`` between the two clocks. A state's transit is ``D - c``, with ``c`` estimated two ways,
over a sliding window of ``TRANSIT_WINDOW_S`` (a restarted arm, with a new clock, is judged afresh after one window):

- **the quickest state**: ``c`` at most the smallest ``D`` of the window (no transit is negative). Against it a
  state's transit is how much longer than the quickest it took: time spent queued (a starved link, a socket buffer).
  Any delay every state has, a fixed delay of the link, cancels out with the offset.
- **the round trip**: an arm that echoes, in each state, the stamp of the newest command it had received
  (``JointState.command_stamp_ns``: the env's own send time) and how long before its stamp that command arrived
  (``command_age_ns``, the arm's clock) gives a round trip of the link on the env's clock alone::

      round_trip = (arrival - command sent) - command_age   # = forward transit + backward transit

  and, with the link taken as symmetric (the state's way back as long as the command's way out, as NTP assumes), an
  offset ``c = D - round_trip / 2``: that state is counted ``round_trip / 2`` in transit. Half, not the whole round
  trip: the whole would count the forward leg, which the state never travelled, and an arm 0.2 s away each way (its
  states 0.3 s old with a 0.1 s tick) would be judged 0.5 s old and stopped.

The offset used is the smaller of the quickest state's ``D`` and the largest round-trip offset of the window, so a
state's transit is the larger of the two estimates, and never less than the quickest-state one. Of the round trips
the one most favourable to the states counts: a round trip whose legs differ makes its offset off by half the
difference, and only a way back longer than the way out (jitter) errs toward younger states, by at most half the
jitter; a way out longer than the way back (a command that went out before a delay dropped, or queued behind others)
errs toward older states and is passed over. Only the first state that echoes a command is a round trip: later ones
echo the same command with the same way out, which, once the env stopped commanding (as it does on stale states),
belongs to an older link than their way back. So the estimate follows the link back down when a delay goes away,
without a command crossing it. Nor is a round trip taken whose command went out before a stall of the states (no
state for longer than ``stall_s``: a partition, a frozen arm) and was echoed after it: it waited through the stall
on its way out, while the states after the stall are fresh.

Before any round trip of the window (the arm echoes, but none of our commands yet): a command sent at ``t0`` and not
echoed by a state that arrived at ``t`` gives a round trip longer than ``t - t0``, so such a state's transit is at
least half of it; an env that keeps commanding a link whose round trip exceeds twice its robot timeout sees its
states turn stale without an echo. A stall of the states starts that count afresh, at the next command.

Bounded: the windows hold at most one sample per state of ``TRANSIT_WINDOW_S`` (monotonic deques, O(1) per state),
and the send stamps an echo is matched against are the env's last ``SENT_RING`` commands (an echo of anything else,
another sender's command or a stamp too old, measures nothing). An arm that does not echo (``command_age_ns`` None:
an adapter's arm, an older ``uniros robot serve``) leaves the quickest-state estimate alone.

The env feeds it from its joint-state subscription (``follow``): each new state is observed once, and a new
subscription (the arm's domain joined again: perhaps a new arm, a new clock) starts afresh. ``describe`` puts what
the round trips told into words for the env's error messages.
"""

from __future__ import annotations

import collections
from typing import TYPE_CHECKING

from uniros_async.bus.messages import JointState

if TYPE_CHECKING:
    from uniros_async.bus.pubsub import Subscription

__all__ = ["SENT_RING", "TRANSIT_WINDOW_S", "StateTransit"]

TRANSIT_WINDOW_S = 60.0
"""How far back the quickest state and the round trips are looked at."""
SENT_RING = 256
"""How many of the env's newest command stamps an echo is matched against (25.6 s of commands at 10 Hz, 10 s at
25 Hz: longer than any round trip the env keeps stepping through)."""


class StateTransit:
    """The transit of the joint states of one subscription (see the module docstring).

    Feed it with ``sent`` for every command and ``observe`` for every new state (``follow`` does that for a
    subscription's states); ``transit_ns`` is a state's transit. Times are the env's ``time.monotonic_ns()``, stamps
    the arm's clock.

    Args:
        stall_s: no state for longer than this is a stall of the link (the env's robot timeout): a command sent
            before it ended is no round trip.
    """

    def __init__(self, stall_s: float = 0.5) -> None:
        self.stall_ns = round(stall_s * 1e9)
        self._floor: collections.deque[tuple[int, int]] = collections.deque()  # (arrival, D): D increasing
        self._trips: collections.deque[tuple[int, int, int]] = collections.deque()  # (arrival, offset, rtt): offset
        # decreasing, so the front is the largest offset of the window
        self._sent: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._echoed: int | None = None  # the command stamp of the last round trip taken
        self._unechoed_since: int | None = None  # with no round trip in the window: the first command sent since
        self._last_arrival: int | None = None
        self._stall_end = 0  # the arrival of the first state after the newest stall
        self._sub: Subscription[JointState] | None = None  # the subscription ``follow`` last saw
        self._seen = -1  # how many of its states were observed (its ``received``)
        self._domain_id = ""  # the domain id it was followed in
        self.echoes = False
        """Whether the arm echoes commands (a state with ``command_age_ns`` set was seen since ``clear``)."""
        self.round_trip_ns: int | None = None
        """The newest round trip measured (None: none since ``clear``)."""
        self.round_trips = 0
        """Round trips measured since ``clear``."""

    def clear(self) -> None:
        """Forget the states and round trips seen (a new connection to the arm: perhaps a new arm, a new clock).
        The send stamps are kept: they are the env's own."""
        self._floor.clear()
        self._trips.clear()
        self._echoed = self._unechoed_since = self._last_arrival = None
        self._stall_end = 0
        self.echoes = False
        self.round_trip_ns = None
        self.round_trips = 0

    def sent(self, stamp_ns: int) -> None:
        """The env sent a command stamped ``stamp_ns`` (its monotonic clock)."""
        sent = self._sent
        sent[stamp_ns] = None
        if len(sent) > SENT_RING:
            sent.popitem(last=False)
        if self._unechoed_since is None and not self._trips:
            self._unechoed_since = stamp_ns

    def observe(self, js: JointState, arrival_ns: int) -> None:
        """A new joint state ``js`` arrived at ``arrival_ns``: a sample for the quickest state, and a round trip when
        it is the first to echo one of our commands."""
        d = arrival_ns - js.header.stamp_ns
        if self._last_arrival is not None and arrival_ns - self._last_arrival > self.stall_ns:
            self._stall_end, self._unechoed_since = arrival_ns, None
        self._last_arrival = arrival_ns
        horizon = arrival_ns - round(TRANSIT_WINDOW_S * 1e9)
        floor = self._floor
        while floor and floor[-1][1] >= d:
            floor.pop()
        floor.append((arrival_ns, d))
        while len(floor) > 1 and floor[0][0] < horizon:
            floor.popleft()
        trips = self._trips
        while trips and trips[0][0] < horizon:  # all may go: then the states' age waits for a new echo
            trips.popleft()
        age = js.command_age_ns
        if age is None:
            return
        self.echoes = True
        echoed = js.command_stamp_ns
        # the fields come from the arm: checked, not trusted; only an echo of one of our own commands, the first
        if type(echoed) is not int or type(age) is not int or age < 0 or echoed == self._echoed:
            return
        if echoed < self._stall_end or echoed not in self._sent:  # sent before a stall ended: it waited through it
            return
        rtt = arrival_ns - echoed - age
        if rtt < 0:  # the age overstates the arm's wait: its clock is not a monotonic clock of real time
            return
        self._echoed = echoed
        self._unechoed_since = None
        self.round_trip_ns = rtt
        self.round_trips += 1
        offset = d - rtt // 2
        while trips and trips[-1][1] <= offset:
            trips.pop()
        trips.append((arrival_ns, offset, rtt))

    def follow(self, sub: Subscription[JointState], domain_id: str = "") -> None:
        """Observe the newest state of ``sub`` if it is new (each state once, at its arrival ``sub.latest_recv_ns``).
        A subscription other than the one followed before (the arm's domain joined again: perhaps a new arm, a new
        clock) is started afresh: ``clear`` first. So is the same subscription in a domain whose id changed (its
        node rejoined a restarted registry, where the arm may be a new process with another clock); the state it
        holds then, perhaps the old arm's, is not observed."""
        if self._sub is not sub:
            self._sub, self._seen, self._domain_id = sub, -1, domain_id
            self.clear()
        elif domain_id != self._domain_id:
            self._seen, self._domain_id = sub.received, domain_id
            self.clear()
        js = sub.latest()
        if js is not None and sub.received != self._seen:
            self._seen = sub.received
            self.observe(js, sub.latest_recv_ns)

    def describe(self, now_ns: int) -> str:
        """What the echo of our commands told of the link's round trip at ``now_ns``, for an error's message: the
        newest round trip and the one counted, or how long our commands went unechoed ("" when nothing)."""
        used = self.offset_round_trip_ns
        if self.round_trip_ns is not None and used is not None:
            return (
                f"the round trip to the arm measured {self.round_trip_ns / 1e9:.2f} s by its echo of our commands"
                f" (half of {used / 1e9:.2f} s counted as a state's transit)"
            )
        unechoed = self.unechoed_ns(now_ns)
        if unechoed:
            return (
                f"the arm echoed none of our commands of the last {unechoed / 1e9:.2f} s: a round trip at least that"
                " long"
            )
        return ""

    @property
    def awaiting_round_trip(self) -> bool:
        """The arm echoes, but the window holds no round trip of ours: a fixed delay on the link is not seen yet."""
        return self.echoes and not self._trips

    @property
    def offset_round_trip_ns(self) -> int | None:
        """The round trip whose offset is used (the window's most favourable to the states), or None."""
        return self._trips[0][2] if self._trips else None

    def unechoed_ns(self, now_ns: int) -> int:
        """How long the env has been commanding an echoing arm with no round trip in the window (0: not so)."""
        since = self._unechoed_since
        if since is None or not self.echoes or self._trips:
            return 0
        return max(0, now_ns - since)

    def transit_ns(self, js: JointState, arrival_ns: int) -> int:
        """How long state ``js``, arrived at ``arrival_ns``, spent on its way (at least 0; 0 before any state was
        observed)."""
        if not self._floor:
            return 0
        offset = self._floor[0][1]
        if self._trips:
            offset = min(offset, self._trips[0][1])
        transit = arrival_ns - js.header.stamp_ns - offset
        # no round trip yet, commands unechoed since then: a round trip longer than that, half of it this state's
        return max(0, transit, self.unechoed_ns(arrival_ns) // 2)
