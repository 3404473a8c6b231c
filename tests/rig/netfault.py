"""Faults on an arm's link, injected with the kernel's own tools, for the fault tests (tests/faults/).

``open_netns_pair()`` creates two network namespaces, ``arm`` and ``env``, joined by a veth pair with the addresses
``ARM_IP`` and ``ENV_IP`` (a /30 that exists only inside them: nothing is routed anywhere else), and removes both
namespaces (and so the link) when the block ends, also on failure. Processes run in them with ``ip netns exec``
(``NetnsPair.popen``). The faults, all on the arm's end of the link:

- ``partition()``: nftables drops every packet in and out;
- ``loss(pct)``: nftables drops ``pct`` % of the packets each way (``numgen random mod 100 < pct drop``);
- ``tcp_reset()``: nftables answers every tcp segment that arrives with a reset (``reject with tcp reset``);
- ``starve(rate)``: a ``tbf`` qdisc on both ends limits the link to ``rate`` (e.g. ``"8kbit"``);
- ``link_down()`` / ``link_up()``: the veth end goes down and up;
- ``drop_output()``: nftables drops every packet the arm's namespace sends, on every interface (loopback too: the
  arm's own node loses its registry when both are in one process);
- ``remove_address()`` / ``restore_address()``: the arm's address is deleted with ``ip addr del`` and added again;
- ``block_port(port)``: nftables drops every tcp segment to ``port`` in the arm's namespace (its registry's);
- ``clear()``: removes the nftables tables and the qdiscs, brings the link and the address back, and checks that
  nothing is left (``faults_left()``), raising when something is.

A frozen peer is ``os.kill(pid, SIGSTOP)`` / ``SIGCONT`` of the arm's process. This kernel has no ``netem``
(CONFIG_NET_SCH_NETEM is off), so delay and jitter come from the tests' own delaying relay
(``rig.delayrelay``): ``delay_through(port, mark)`` redirects every tcp connection across the link to it.

``python -m rig.netfault drive --robot tcp://HOST:PORT ...`` is the agent side: it makes a reach
env on that arm and steps it forever, resetting after every episode end and every RobotError, and prints each
event as a JSON line with its ``time.monotonic_ns()`` (one clock for every namespace of the machine): ``reset`` and
``step`` (with the age of the joint state they returned on, by its stamp and as the env estimates it, the link's
round trip the env measured, and at an episode's end why, from ``info``), ``robot_error`` (the message) and
``error`` (anything else: an uncaught exception, with its traceback).

``python -m rig.netfault commands --master URI --ros-host IP`` is a bare commander on a ROS 1 arm:
the ROS 1 bridge (``adapters.ros1_bridge``) and, on its bus, a publisher of ``JointCommand`` at the hardware rate
that never stops (no env and its own staleness check in front of the bridge). Command ``seq`` moves the waist to
``command_position(seq)``, so whoever receives the driver's messages can tell which command each was; it prints
``sent`` (``seq``) for every command and the bridge's counters (``stats``) every second.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = [
    "ARM_IP",
    "ENV_IP",
    "WAIST_STEP_RAD",
    "EventPeer",
    "NetnsPair",
    "command_position",
    "fault_figures",
    "netfault_missing",
    "open_netns_pair",
]

ARM_IP = "10.200.0.1"
ENV_IP = "10.200.0.2"
PREFIX_LEN = 30
TABLE = "uniros_fault"
DELAY_TABLE = "uniros_delay"
_counter = itertools.count()


def _run(*cmd: str, check: bool = True, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    # spawning ip/nft/tc can take seconds on a loaded 2-core host
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=30, input=stdin)
    if check and out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}): {out.stderr.strip()}")
    return out


def netfault_missing() -> str | None:
    """Why the fault tests cannot run here (not root, ``ip``, ``nft`` or ``tc`` missing, namespaces refused), or
    None when they can."""
    if os.geteuid() != 0:
        return "fault injection needs root (network namespaces, nftables)"
    for tool, pkg in (("ip", "iproute2"), ("tc", "iproute2"), ("nft", "nftables")):
        if shutil.which(tool) is None:
            return f"fault injection needs `{tool}`: apt-get install -y {pkg}"
    name = f"uniros-probe-{os.getpid()}"
    probe = _run("ip", "netns", "add", name, check=False)
    if probe.returncode != 0:
        return f"cannot create a network namespace: {probe.stderr.strip()}"
    _run("ip", "netns", "del", name, check=False)
    return None


@dataclass
class NetnsPair:
    """Two namespaces joined by a veth pair (see the module docstring); from ``open_netns_pair``."""

    arm_ns: str
    env_ns: str
    arm_dev: str
    env_dev: str
    arm_ip: str = ARM_IP
    env_ip: str = ENV_IP

    @property
    def ends(self) -> tuple[tuple[str, str], tuple[str, str]]:
        """(namespace, device) of the link's two ends: the arm's, then the env's."""
        return ((self.arm_ns, self.arm_dev), (self.env_ns, self.env_dev))

    def popen(self, side: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[str]:
        """Start ``argv`` in the ``arm`` or ``env`` namespace (text mode, stdout piped unless told otherwise)."""
        ns = self.arm_ns if side == "arm" else self.env_ns
        kwargs.setdefault("stdout", subprocess.PIPE)
        kwargs.setdefault("text", True)
        return subprocess.Popen(["ip", "netns", "exec", ns, *argv], **kwargs)

    def _nft(self, rule_in: str, rule_out: str | None) -> None:
        self.clear_nft()
        script = [f"table inet {TABLE} {{", "  chain input {", "    type filter hook input priority 0; policy accept;"]
        script += [f"    {rule_in}", "  }"]
        if rule_out:
            script += ["  chain output {", "    type filter hook output priority 0; policy accept;", f"    {rule_out}"]
            script += ["  }"]
        script += ["}", ""]
        _run("ip", "netns", "exec", self.arm_ns, "nft", "-f", "-", stdin="\n".join(script))

    def partition(self) -> None:
        """Drop every packet into and out of the arm's namespace."""
        self._nft(f'iifname "{self.arm_dev}" drop', f'oifname "{self.arm_dev}" drop')

    def loss(self, pct: int) -> None:
        """Drop ``pct`` % of the packets each way, at random."""
        if not 0 < pct < 100:
            raise ValueError(f"loss: expected a percentage in 1..99, got {pct}")
        self._nft(
            f'iifname "{self.arm_dev}" numgen random mod 100 < {pct} drop',
            f'oifname "{self.arm_dev}" numgen random mod 100 < {pct} drop',
        )

    def tcp_reset(self) -> None:
        """Answer every tcp segment that reaches the arm with a reset (connections break, new ones are refused)."""
        self._nft(f'iifname "{self.arm_dev}" meta l4proto tcp reject with tcp reset', None)

    def starve(self, rate: str = "8kbit") -> None:
        """Limit the link to ``rate`` each way (a ``tbf`` qdisc on both ends; excess waits up to 200 ms, then is
        dropped)."""
        for ns, dev in self.ends:
            _run("ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "tbf", "rate", rate,
                 "burst", "1600", "latency", "200ms")  # fmt: skip

    def drop_output(self) -> None:
        """Drop every packet the arm's namespace sends, on every interface, loopback included."""
        self._nft("counter", "drop")  # the input chain only counts (the rig always writes one)

    def block_port(self, port: int) -> None:
        """Drop every tcp segment to ``port`` in the arm's namespace, from the link and from loopback."""
        self._nft(f"tcp dport {port} drop", None)

    def remove_address(self) -> None:
        _run("ip", "-n", self.arm_ns, "addr", "del", f"{self.arm_ip}/{PREFIX_LEN}", "dev", self.arm_dev)

    def restore_address(self) -> None:
        """Add the arm's address back (nothing when it is there)."""
        shown = _run("ip", "-n", self.arm_ns, "-o", "addr", "show", "dev", self.arm_dev).stdout
        if f" {self.arm_ip}/" not in shown:
            _run("ip", "-n", self.arm_ns, "addr", "add", f"{self.arm_ip}/{PREFIX_LEN}", "dev", self.arm_dev)

    def link_down(self) -> None:
        _run("ip", "-n", self.arm_ns, "link", "set", self.arm_dev, "down")

    def link_up(self) -> None:
        _run("ip", "-n", self.arm_ns, "link", "set", self.arm_dev, "up")

    def delay_through(self, relay_port: int, mark: int) -> None:
        """Redirect every tcp connection across the link, whichever side opens it, to the delaying relay listening
        on ``relay_port`` in the arm's namespace (``rig.delayrelay``; this kernel has no netem), which connects
        on to each connection's original destination with ``SO_MARK`` ``mark``, left alone here. Only
        connections opened after this are redirected (nftables' nat acts on a connection's first packet)."""
        script = [
            f"table ip {DELAY_TABLE} {{",
            "  chain prerouting {",
            "    type nat hook prerouting priority dstnat; policy accept;",
            f'    iifname "{self.arm_dev}" meta l4proto tcp redirect to :{relay_port}',
            "  }",
            "  chain output {",
            "    type nat hook output priority -100; policy accept;",
            f'    oifname "{self.arm_dev}" meta mark != {mark} meta l4proto tcp redirect to :{relay_port}',
            "  }",
            "}",
            "",
        ]
        _run("ip", "netns", "exec", self.arm_ns, "nft", "-f", "-", stdin="\n".join(script))

    def clear_nft(self) -> None:
        _run("ip", "netns", "exec", self.arm_ns, "nft", "delete", "table", "inet", TABLE, check=False)
        _run("ip", "netns", "exec", self.arm_ns, "nft", "delete", "table", "ip", DELAY_TABLE, check=False)

    def faults_left(self) -> list[str]:
        """What of the faults is in effect: our nftables tables, a qdisc of ours on either end, the arm's end down,
        the arm's address missing. Empty when the link is clean."""
        left: list[str] = []
        tables = _run("ip", "netns", "exec", self.arm_ns, "nft", "list", "tables").stdout.split()
        left += [f"nftables table {t}" for t in (TABLE, DELAY_TABLE) if t in tables]
        for _ns, dev, shown in self._our_qdiscs():
            left.append(f"{dev}: {shown}")
        link = _run("ip", "-n", self.arm_ns, "-o", "link", "show", "dev", self.arm_dev).stdout
        flags = link.split("<", 1)[1].split(">", 1)[0].split(",") if "<" in link else []
        if "UP" not in flags:
            left.append(f"{self.arm_dev} is down: {link.strip()}")
        addrs = _run("ip", "-n", self.arm_ns, "-o", "addr", "show", "dev", self.arm_dev).stdout
        if f" {self.arm_ip}/" not in addrs:
            left.append(f"{self.arm_dev} has no address {self.arm_ip}")
        return left

    def clear(self) -> None:
        """Remove every fault: the nftables tables, the qdiscs, a link left down, an address removed. Every step
        runs even when one fails, twice if something is still left.

        Raises:
            RuntimeError: something is still in effect afterwards (what, and why each step failed).
        """
        problems: list[str] = []
        for _attempt in range(2):
            problems.clear()
            for step in (self.clear_nft, self._clear_qdiscs, self.link_up, self.restore_address):
                try:
                    step()
                except (RuntimeError, subprocess.TimeoutExpired) as exc:
                    problems.append(f"{step.__name__}: {exc}")
            left = self.faults_left()
            if not left:
                return
        raise RuntimeError(f"{self.arm_ns}: still in effect after clear(): {left}; {problems}")

    def _our_qdiscs(self) -> list[tuple[str, str, str]]:
        """(namespace, device, ``tc qdisc show`` of it) for each end that carries a qdisc of ours (``starve``'s
        ``tbf``)."""
        ours = []
        for ns, dev in self.ends:
            shown = _run("ip", "netns", "exec", ns, "tc", "qdisc", "show", "dev", dev).stdout
            if " tbf " in shown:
                ours.append((ns, dev, shown.strip()))
        return ours

    def _clear_qdiscs(self) -> None:
        for ns, dev, _shown in self._our_qdiscs():
            _run("ip", "netns", "exec", ns, "tc", "qdisc", "del", "dev", dev, "root")


@contextlib.contextmanager
def open_netns_pair() -> Iterator[NetnsPair]:
    """Two fresh namespaces joined by a veth pair, both removed when the block ends (see the module docstring).

    Raises:
        RuntimeError: an ``ip`` command failed (its message is included); whatever was created is removed.
    """
    n = next(_counter)
    tag = f"{os.getpid()}-{n}"
    pair = NetnsPair(
        arm_ns=f"uniros-arm-{tag}",
        env_ns=f"uniros-env-{tag}",
        arm_dev=f"ua{os.getpid() % 100000}{n}",  # interface names are at most 15 characters
        env_dev=f"ue{os.getpid() % 100000}{n}",
    )
    try:
        _run("ip", "netns", "add", pair.arm_ns)
        _run("ip", "netns", "add", pair.env_ns)
        _run("ip", "link", "add", pair.arm_dev, "netns", pair.arm_ns, "type", "veth",
             "peer", "name", pair.env_dev, "netns", pair.env_ns)  # fmt: skip
        for ns, dev, ip in ((pair.arm_ns, pair.arm_dev, pair.arm_ip), (pair.env_ns, pair.env_dev, pair.env_ip)):
            _run("ip", "-n", ns, "addr", "add", f"{ip}/{PREFIX_LEN}", "dev", dev)
            _run("ip", "-n", ns, "link", "set", dev, "up")
            _run("ip", "-n", ns, "link", "set", "lo", "up")
        yield pair
    finally:
        # deleting a namespace deletes the veth end in it, and with it the other end
        for ns in (pair.arm_ns, pair.env_ns):
            _run("ip", "netns", "del", ns, check=False)


# ================================================================================================ event lines


@dataclass
class EventPeer:
    """A process that prints JSON event lines (``{"ev": ..., "t_ns": ...}``) on stdout, read by a thread."""

    proc: subprocess.Popen[str]
    events: list[dict[str, Any]] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)
    reader: threading.Thread | None = None

    def start_reader(self) -> None:
        def read() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                self.lines.append(line)
                if line.startswith("{"):
                    with contextlib.suppress(ValueError):
                        self.events.append(json.loads(line))

        self.reader = threading.Thread(target=read, daemon=True)
        self.reader.start()

    def after(self, t_ns: int, ev: str) -> list[dict[str, Any]]:
        """Events of kind ``ev`` at or after ``t_ns``."""
        return [e for e in list(self.events) if e["ev"] == ev and e["t_ns"] >= t_ns]

    def wait_for(
        self,
        t_ns: int,
        ev: str,
        timeout_s: float,
        what: str,
        where: Callable[[dict[str, Any]], bool] | None = None,
    ) -> dict[str, Any]:
        """The first ``ev`` event at or after ``t_ns`` (for which ``where`` is true, when given), waiting up to
        ``timeout_s``.

        Raises:
            AssertionError: none came, or the process ended (its last lines are in the message).
        """
        deadline = time.monotonic() + timeout_s
        while True:
            found = [e for e in self.after(t_ns, ev) if where is None or where(e)]
            if found:
                return found[0]
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = "".join(self.lines[-20:])
                raise AssertionError(f"no {ev!r} event ({what}) within {timeout_s} s; output:\n{tail}")
            time.sleep(0.02)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        """Resume it if frozen, send ``sig``, kill after 10 s; reap it and close its pipes."""
        proc = self.proc
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)  # a frozen process cannot handle the signal
            proc.send_signal(sig)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        if self.reader is not None:
            self.reader.join(5)
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                with contextlib.suppress(BrokenPipeError):  # what was written and not read: the process is gone
                    pipe.close()


def fault_figures(
    name: str,
    arm: EventPeer,
    agent: EventPeer,
    *,
    t_fault: int,
    t_clear: int,
    recovered_ns: int,
    robot_timeout_s: float,
) -> dict[str, Any]:
    """One fault's figures from the arm's and the agent's event lines (times in s from the fault or its clearing):

    ``hold_after_fault_s`` (the arm's first watchdog hold after the fault), ``hold_after_last_command_s`` (that hold
    after the last command the arm applied before it), ``hold_ticks_after_last_command`` (the same in the arm's own
    ticks, one hardware period of sim time each, whatever the host's scheduling), ``notice_after_fault_s`` (the
    agent's first RobotError), ``agent_saw`` (its message), ``agent_loop_late_s`` (how late the agent's env loop ran
    before it: the host's scheduling), ``robot_errors``, ``recovery_after_clear_s`` (the agent's first step after
    the fault was cleared), ``stale_commands_applied`` (commands applied older than ``robot_timeout_s``, over the
    whole run), ``stale_commands_dropped`` (since the fault), ``max_age_applied_s``, ``max_state_stamp_age_at_step_s``
    (the oldest joint state, by its stamp, that a step returned on since the fault) and ``uncaught_exceptions``.
    """
    s = 1e-9
    cmds = [e for e in list(arm.events) if e["ev"] == "cmd"]
    errors = [e for e in agent.after(t_fault, "robot_error") if e["t_ns"] <= t_clear]
    holds = arm.after(t_fault, "hold")
    hold = holds[0] if holds else None
    before_hold = [e for e in cmds if e["applied"] and hold is not None and e["t_ns"] < hold["t_ns"]]
    since_fault = [e for e in cmds if e["t_ns"] >= t_fault]
    return {
        "fault": name,
        "hold_after_fault_s": round((hold["t_ns"] - t_fault) * s, 3) if hold else None,
        "hold_after_last_command_s": (
            round((hold["t_ns"] - before_hold[-1]["t_ns"]) * s, 3) if hold and before_hold else None
        ),
        "hold_ticks_after_last_command": (
            hold["tick"] - before_hold[-1]["tick"] if hold and before_hold and "tick" in hold else None
        ),
        "notice_after_fault_s": round((errors[0]["t_ns"] - t_fault) * s, 3) if errors else None,
        "agent_saw": errors[0]["msg"] if errors else "no error",
        "agent_loop_late_s": errors[0].get("loop_late_s") if errors else None,
        "robot_errors": len(errors),
        "recovery_after_clear_s": round((recovered_ns - t_clear) * s, 3),
        "stale_commands_applied": sum(1 for e in cmds if e["applied"] and e["age_ns"] > robot_timeout_s / s),
        "stale_commands_dropped": sum(1 for e in since_fault if not e["applied"]),
        "max_age_applied_s": round(max((e["age_ns"] for e in since_fault if e["applied"]), default=0) * s, 3),
        "max_state_stamp_age_at_step_s": round(
            max((e.get("state_stamp_age_s", -1.0) for e in agent.after(t_fault, "step")), default=-1.0), 3
        ),
        "uncaught_exceptions": len([e for e in agent.events if e["ev"] == "error"]),
    }


# ================================================================================================ the agent side


def _emit(event: str, **fields: Any) -> None:
    sys.stdout.write(json.dumps({"ev": event, "t_ns": time.monotonic_ns(), **fields}) + "\n")
    sys.stdout.flush()


_END_KEYS = ("is_success", "unsafe_reason", "not_executable", "action_projected", "TimeLimit.truncated")
"""What a step event carries of ``info`` when the episode ended: why it ended."""


def _plain(value: Any) -> Any:
    """``value`` as JSON can write it (numpy scalars as Python's, anything else unknown as text)."""
    value = value.item() if hasattr(value, "item") else value
    return value if isinstance(value, bool | int | float | str) or value is None else str(value)


def _state_fields(u: Any) -> dict[str, Any]:
    """The newest joint state's age by its stamp (meaningful when the arm shares this machine's monotonic clock) and
    as the env estimates it, and the link's round trip the env measured (the newest, and the one its clock offset
    comes from; None: none). Read on the env's own loop, whose bookkeeping reading the age updates."""

    async def read() -> dict[str, Any]:
        js = u._js.latest()
        rtt, used = u._transit.round_trip_ns, u._transit.offset_round_trip_ns
        return {
            "state_stamp_age_s": (time.monotonic_ns() - js.header.stamp_ns) / 1e9 if js is not None else -1.0,
            "state_age_s": u._state_age_s(),
            "round_trip_s": None if rtt is None else rtt / 1e9,
            "offset_round_trip_s": None if used is None else used / 1e9,
        }

    try:
        return dict(u._call(read(), 5.0))
    except Exception as exc:  # noqa: BLE001 - the env's world is gone: said here, raised by the next step or reset
        return {"state_fields_error": f"{type(exc).__name__}: {exc}"}


def _loop_late_s(u: Any, window_s: float) -> float:
    """How late the env loop's ticks ran over the last ``window_s`` plus two periods (the largest gap between ticks,
    or since the last one, beyond one hardware period): the host's scheduling, which a notice's time includes."""
    period_ns = round(1e9 / float(u.robot_spec.hardware_rate_hz))
    now = time.monotonic_ns()
    since = now - round(window_s * 1e9) - 2 * period_ns
    ticks: list[int] = [int(t) for t in list(u.timing.tick_ns) if t >= since] + [now]
    gaps = [b - a for a, b in zip(ticks, ticks[1:], strict=False)]
    return round(max(max(gaps, default=0) - period_ns, 0) / 1e9, 3)


def drive(
    robot: str,
    *,
    env_id: str,
    robot_timeout_s: float,
    action_cycle_s: float,
    reset_timeout_s: float,
    ros_host: str | None = None,
) -> None:
    """Step a reach env on ``robot`` until SIGTERM, printing every event (see the module docstring)."""
    import gymnasium as gym
    import numpy as np

    import uniros_async  # noqa: F401  (registers the ids)
    from uniros_async.errors import RobotError

    stop = False

    def on_term(signum: int, frame: Any) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_term)
    # ROS 1 cannot authenticate peers: a bridge beyond loopback must be allowed explicitly (here: inside the test's
    # own namespaces, which nothing else reaches)
    extra: dict[str, Any] = {"ros1": {"ros_host": ros_host, "insecure": True}} if ros_host else {}
    from uniros_async.priority import raise_loop_priority, thread_ids

    before = thread_ids()
    env = gym.make(
        env_id,
        robot=robot,
        robot_timeout_s=robot_timeout_s,
        action_cycle_s=action_cycle_s,
        reset_timeout_s=reset_timeout_s,
        **extra,
    )
    u: Any = env.unwrapped
    # the env loop runs in this process, as in a worker, which takes the real-time class once its env is built:
    # for this thread (it steps) and the threads the build started (the env's loop thread among them)
    raise_loop_priority()
    for tid in thread_ids() - before:
        raise_loop_priority(thread_id=tid)
    action = np.zeros(env.action_space.shape or (), np.float32)
    _emit("ready")
    need_reset = True
    try:
        while not stop:
            try:
                if need_reset:
                    env.reset()
                    need_reset = False
                    _emit("reset", **_state_fields(u))
                    continue
                _, _, terminated, truncated, info = env.step(action)
                age = u.timing.observation_age_ns[-1] if u.timing.observation_age_ns else -1
                why = {k: _plain(info[k]) for k in _END_KEYS if k in info} if terminated or truncated else {}
                _emit(
                    "step",
                    obs_age_ns=age,
                    **_state_fields(u),
                    terminated=bool(terminated),
                    truncated=bool(truncated),
                    info=why,
                )
                need_reset = terminated or truncated
            except RobotError as exc:
                _emit("robot_error", msg=str(exc), loop_late_s=_loop_late_s(u, robot_timeout_s), **_state_fields(u))
                need_reset = True
            except Exception as exc:  # noqa: BLE001 - counted as uncaught by the tests, never hidden
                _emit("error", kind=type(exc).__name__, msg=str(exc), tb=traceback.format_exc())
                need_reset = True
                time.sleep(0.1)
    finally:
        env.close()
        _emit("closed")


WAIST_STEP_RAD = 0.001
"""``command_position(seq)`` moves the waist by this per ``seq``, modulo 1000 (at most 1 rad from home)."""


def command_position(seq: int, n_joints: int) -> list[float]:
    """The arm position that command ``seq`` asks for (``commands``): the waist at ``(seq % 1000) * WAIST_STEP_RAD``,
    the other joints at 0; ``round(position[0] / WAIST_STEP_RAD)`` gives ``seq % 1000`` back."""
    return [(seq % 1000) * WAIST_STEP_RAD] + [0.0] * (n_joints - 1)


def commands(robot: str, *, master_uri: str, ros_host: str, max_command_age_s: float | None) -> None:
    """Run the ROS 1 bridge and command it at the hardware rate until SIGTERM (see the module docstring)."""
    import asyncio

    import numpy as np

    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge
    from uniros_async.bus import open_domain, open_node
    from uniros_async.bus.messages import Header, JointCommand
    from uniros_async.bus.qos import latest
    from uniros_async.robots import get_robot_spec

    spec = get_robot_spec(robot)
    config = Ros1BridgeConfig(
        robot=robot, master_uri=master_uri, ros_host=ros_host, insecure=True, max_command_age_s=max_command_age_s
    )

    async def run() -> None:
        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
        async with (
            open_domain("memory://") as domain,
            open_ros1_bridge(config, domain=domain) as bridge,
            open_node("commander", domain=domain, namespace=f"/{spec.name}") as node,
        ):
            pub = await node.create_publisher(JointCommand, "command", qos=latest())
            _emit("ready")
            period_ns = round(1e9 / spec.hardware_rate_hz)
            next_ns = time.monotonic_ns()
            seq = 0
            while not stop.is_set():
                seq += 1
                q = command_position(seq, len(spec.arm_joint_names))
                _emit("sent", seq=seq)
                pub.publish(JointCommand(header=Header(stamp_ns=time.monotonic_ns(), seq=seq), position=np.asarray(q)))
                if seq % round(spec.hardware_rate_hz) == 0:
                    _emit("stats", **asdict(bridge.stats))
                next_ns += period_ns
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), max(next_ns - time.monotonic_ns(), 0) / 1e9)
            _emit("stats", **asdict(bridge.stats))

    asyncio.run(run())


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rig.netfault drive ...``."""
    parser = argparse.ArgumentParser(prog="python -m rig.netfault")
    sub = parser.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("drive", help="step a reach env on an arm, printing events as JSON lines")
    d.add_argument("--robot", required=True, help="tcp://HOST:PORT or ros1://HOST:PORT")
    d.add_argument("--env-id", default="uniros/Rx200Reach-v0")
    d.add_argument("--robot-timeout", type=float, default=0.5)
    d.add_argument("--action-cycle", type=float, default=0.2)
    d.add_argument("--reset-timeout", type=float, default=10.0)
    d.add_argument("--ros-host", default=None, help="with ros1://: the address ROS peers reach the bridge at")
    c = sub.add_parser("commands", help="the ROS 1 bridge, commanded at the hardware rate; prints sent commands")
    c.add_argument("--robot", default="rx200")
    c.add_argument("--master", required=True, help="the ROS master, http://HOST:PORT/")
    c.add_argument("--ros-host", required=True, help="the address ROS peers reach the bridge at")
    c.add_argument("--max-command-age", type=float, default=0.5, help="the bridge's max_command_age_s; 0: unguarded")
    args = parser.parse_args(argv)
    if args.cmd == "commands":
        commands(
            args.robot, master_uri=args.master, ros_host=args.ros_host, max_command_age_s=args.max_command_age or None
        )
        return 0
    drive(
        args.robot,
        env_id=args.env_id,
        robot_timeout_s=args.robot_timeout,
        action_cycle_s=args.action_cycle,
        reset_timeout_s=args.reset_timeout,
        ros_host=args.ros_host,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
