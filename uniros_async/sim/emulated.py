"""The emulated real arm: the servo sim with perturbed dynamics, sensor noise and a network in between.

An emulated real robot stands in for the physical arm in tests and sim-to-real
experiments: the same ServoSim, run as a separate service behind tcp, whose dynamics differ from the nominal
model the policy trained on, whose sensors are noisy, and whose messages arrive late, jittered, or not at all.

Everything is drawn from one seed (``EmulationConfig.seed``), so an emulated arm is reproducible. The bounds:

=============================  ==========================================  =====================================
what                           how                                         default bound
=============================  ==========================================  =====================================
link masses (and inertias)     every body x U(1 - m, 1 + m); inertia       m = ``mass_scale`` = 0.10 (+/-10 %)
                               scales with the mass (same gyration radius)
joint damping                  every dof x U(1 - d, 1 + d)                 d = ``damping_scale`` = 0.30
joint friction (frictionloss)  every dof x U(1 - f, 1 + f)                 f = ``friction_scale`` = 0.30
servo gains                    each arm actuator's kp x U(1 - k, 1 + k);   k = ``kp_scale`` = 0.15 (+/-15 %)
                               kv x sqrt(same factor) (damping ratio kept)
position noise                 + N(0, sigma) on every published position   sigma = 0.002 rad (or m)
velocity noise                 + N(0, sigma) on every published velocity   sigma = 0.01 rad/s
joint_states and commands      delay = max(0, base + jitter draw), FIFO    base 5 ms, jitter N(0, 2 ms), loss 0
                               (a late message never overtakes an earlier
                               one, as on TCP); dropped with p = ``loss``
=============================  ==========================================  =====================================

Each scale must lie in [0, 0.9] and each probability in [0, 1). The delay queues are driven by the domain's
clock, so with a SimClock the delays are sim time (the discrete-event driver steps to each delivery).
"""

from __future__ import annotations

import asyncio
import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import mujoco
import numpy as np

from uniros_async.bus.messages import Header, JointState
from uniros_async.clock import Clock
from uniros_async.errors import ConfigError

__all__ = ["DelayLine", "EmulationConfig", "LatencyModel", "add_sensor_noise", "perturb_model"]

T = TypeVar("T")

DISTRIBUTIONS = ("normal", "uniform", "exponential", "constant")


@dataclass(frozen=True, kw_only=True)
class LatencyModel:
    """One direction of the emulated network.

    Attributes:
        base_s: the fixed part of the delay.
        jitter_s: scale of the random part: the standard deviation (normal), the half width (uniform), or the
            mean (exponential); ignored for constant.
        distribution: ``"normal"``, ``"uniform"``, ``"exponential"`` or ``"constant"``.
        loss: probability that a message is dropped.
    """

    base_s: float = 0.005
    jitter_s: float = 0.002
    distribution: str = "normal"
    loss: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.base_s) and self.base_s >= 0.0):
            raise ConfigError(f"LatencyModel.base_s: expected a finite value >= 0, got {self.base_s}")
        if not (math.isfinite(self.jitter_s) and self.jitter_s >= 0.0):
            raise ConfigError(f"LatencyModel.jitter_s: expected a finite value >= 0, got {self.jitter_s}")
        if self.distribution not in DISTRIBUTIONS:
            raise ConfigError(f"LatencyModel.distribution: expected one of {DISTRIBUTIONS}, got {self.distribution!r}")
        if not 0.0 <= self.loss < 1.0:
            raise ConfigError(f"LatencyModel.loss: expected a probability in [0, 1), got {self.loss}")

    @property
    def is_zero(self) -> bool:
        """No delay and no loss: messages can pass straight through."""
        return self.base_s == 0.0 and (self.jitter_s == 0.0 or self.distribution == "constant") and self.loss == 0.0

    def draw_s(self, rng: np.random.Generator) -> float:
        """One delay in seconds (>= 0)."""
        if self.distribution == "normal":
            extra = rng.normal(0.0, self.jitter_s) if self.jitter_s > 0 else 0.0
        elif self.distribution == "uniform":
            extra = rng.uniform(-self.jitter_s, self.jitter_s)
        elif self.distribution == "exponential":
            extra = rng.exponential(self.jitter_s) if self.jitter_s > 0 else 0.0
        else:
            extra = 0.0
        return max(0.0, self.base_s + float(extra))


@dataclass(frozen=True, kw_only=True)
class EmulationConfig:
    """How an emulated real arm differs from the nominal sim (bounds in the module docstring).

    Attributes:
        seed: seeds every draw (model perturbation, noise, delays).
        mass_scale: relative half range of the link mass factors.
        damping_scale: relative half range of the joint damping factors.
        friction_scale: relative half range of the joint friction (frictionloss) factors.
        kp_scale: relative half range of the servo kp factors.
        position_noise_std: Gaussian noise on published positions (rad or m).
        velocity_noise_std: Gaussian noise on published velocities (rad/s or m/s).
        state_latency: the network between the arm and its joint_states subscribers.
        command_latency: the network between a commander and the arm.
        state_repeat: probability that a tick sends the previous joint state again (new stamp, old values) in
            place of the new one, as a driver does when a read fails.
    """

    seed: int = 0
    mass_scale: float = 0.10
    damping_scale: float = 0.30
    friction_scale: float = 0.30
    kp_scale: float = 0.15
    position_noise_std: float = 0.002
    velocity_noise_std: float = 0.01
    state_latency: LatencyModel = field(default_factory=LatencyModel)
    command_latency: LatencyModel = field(default_factory=LatencyModel)
    state_repeat: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.state_repeat < 1.0:
            raise ConfigError(
                f"EmulationConfig.state_repeat: expected a probability in [0, 1), got {self.state_repeat}"
            )
        for name in ("mass_scale", "damping_scale", "friction_scale", "kp_scale"):
            v = getattr(self, name)
            if not 0.0 <= v <= 0.9:
                raise ConfigError(f"EmulationConfig.{name}: expected a relative range in [0, 0.9], got {v}")
        for name in ("position_noise_std", "velocity_noise_std"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"EmulationConfig.{name}: expected a finite value >= 0, got {v}")

    @classmethod
    def nominal(cls, seed: int = 0) -> EmulationConfig:
        """No perturbation, no noise, no delay (for tests of the machinery)."""
        zero = LatencyModel(base_s=0.0, jitter_s=0.0, distribution="constant")
        return cls(
            seed=seed,
            mass_scale=0.0,
            damping_scale=0.0,
            friction_scale=0.0,
            kp_scale=0.0,
            position_noise_std=0.0,
            velocity_noise_std=0.0,
            state_latency=zero,
            command_latency=zero,
        )


def perturb_model(
    model: mujoco.MjModel, config: EmulationConfig, rng: np.random.Generator, *, actuator_ids: Any = None
) -> dict[str, np.ndarray]:
    """Scale masses, damping, friction and servo gains of ``model`` in place.

    Args:
        model: the loaded model (modified in place).
        config: the bounds.
        rng: the random source (``np.random.default_rng(config.seed)``).
        actuator_ids: the position actuators whose kp is perturbed; default: all.

    Returns:
        The factors drawn, by name (``mass``, ``damping``, ``friction``, ``kp``), for logs and tests.
    """

    def factors(n: int, half: float) -> np.ndarray:
        return rng.uniform(1.0 - half, 1.0 + half, size=n) if half > 0 else np.ones(n)

    out: dict[str, np.ndarray] = {}
    mass = factors(model.nbody, config.mass_scale)
    mass[0] = 1.0  # the world body
    model.body_mass[:] *= mass
    model.body_inertia[:] *= mass[:, None]
    out["mass"] = mass
    out["damping"] = factors(model.nv, config.damping_scale)
    model.dof_damping[:] *= out["damping"]
    out["friction"] = factors(model.nv, config.friction_scale)
    model.dof_frictionloss[:] *= out["friction"]
    ids = np.arange(model.nu) if actuator_ids is None else np.asarray(actuator_ids)
    kp = factors(len(ids), config.kp_scale)
    for i, f in zip(ids, kp, strict=True):
        # position actuator: force = kp * ctrl - kp * q - kv * qdot  (gainprm[0] = kp, biasprm = [0, -kp, -kv])
        model.actuator_gainprm[i, 0] *= f
        model.actuator_biasprm[i, 1] *= f
        model.actuator_biasprm[i, 2] *= math.sqrt(f)
    out["kp"] = kp
    # keep the model's derived constants (e.g. actuator_acc0 and dampratio conversions) consistent
    mujoco.mj_setConst(model, mujoco.MjData(model))
    return out


def add_sensor_noise(state: JointState, config: EmulationConfig, rng: np.random.Generator) -> JointState:
    """A copy of ``state`` with Gaussian noise on positions and velocities (efforts untouched)."""
    n = len(state.name)
    pos, vel = state.position, state.velocity
    if config.position_noise_std > 0:
        pos = pos + rng.normal(0.0, config.position_noise_std, size=n)
    if config.velocity_noise_std > 0:
        vel = vel + rng.normal(0.0, config.velocity_noise_std, size=n)
    h = state.header
    return JointState(
        header=Header(stamp_ns=h.stamp_ns, seq=h.seq, frame_id=h.frame_id),
        name=state.name,
        position=pos,
        velocity=vel,
        effort=state.effort,
        command_stamp_ns=state.command_stamp_ns,
        command_age_ns=state.command_age_ns,
    )


class DelayLine(Generic[T]):
    """A FIFO that releases each item after a drawn delay of ``clock`` time, or drops it.

    ``push`` never waits; ``run(deliver)`` (a task) calls ``deliver(item)`` at each item's due time. An item is
    never delivered before one pushed earlier (TCP-like ordering), so a short delay drawn after a long one waits.
    """

    def __init__(self, latency: LatencyModel, rng: np.random.Generator, clock: Clock) -> None:
        self.latency = latency
        self.rng = rng
        self.clock = clock
        self._queue: collections.deque[tuple[int, T]] = collections.deque()
        self._wake = asyncio.Event()
        self._last_due_ns = 0
        self.pushed = 0
        self.lost = 0
        self.delivered = 0

    def push(self, item: T) -> bool:
        """Queue ``item``; returns False if the emulated network lost it."""
        self.pushed += 1
        lat = self.latency
        if lat.loss > 0.0 and self.rng.random() < lat.loss:
            self.lost += 1
            return False
        due = self.clock.now_ns() + round(lat.draw_s(self.rng) * 1e9)
        due = max(due, self._last_due_ns)
        self._last_due_ns = due
        self._queue.append((due, item))
        self._wake.set()
        return True

    def clear(self) -> None:
        """Drop everything in flight."""
        self._queue.clear()

    def __len__(self) -> int:
        return len(self._queue)

    async def run(self, deliver: Callable[[T], Any]) -> None:
        """Deliver items at their due times until cancelled (items in flight are then dropped)."""
        clock, queue = self.clock, self._queue
        while True:
            while not queue:
                self._wake.clear()
                await self._wake.wait()
            due, _ = queue[0]
            await clock.sleep_until(due)
            if queue and queue[0][0] <= clock.now_ns():
                _, item = queue.popleft()
                self.delivered += 1
                deliver(item)
