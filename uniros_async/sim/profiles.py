"""Servo target profiles of ``ServoSim``: each produces the servo targets of the arm joints for the next n physics
substeps; ``None`` means "constant", which lets a period run as one mj_step(nstep=n) call. ``ServoSim`` picks one
per command (its module docstring says which, per ``RobotSpec.servo_profile`` and controller mode)."""

from __future__ import annotations

from typing import cast

import numpy as np

__all__ = ["AccelLimited", "Brake", "Constant", "Integrate", "Profile", "TimeSegment", "VelocityLimited"]


class Profile:
    pos: np.ndarray  # the target at the end of the last substep produced
    vel: np.ndarray

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        raise NotImplementedError


class Constant(Profile):
    def __init__(self, pos: np.ndarray) -> None:
        self.pos = pos.copy()
        self.vel = np.zeros_like(pos)

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        return None


class TimeSegment(Profile):
    """Synchronised trapezoid from p0 to goal in total_s with accel_s of acceleration (Dynamixel time-based)."""

    def __init__(self, p0: np.ndarray, goal: np.ndarray, total_s: float, accel_s: float) -> None:
        self.p0, self.goal = p0.copy(), goal.copy()
        self.total_s, self.accel_s = total_s, accel_s
        self.peak = (goal - p0) / (total_s - accel_s)  # cruise velocity
        self.t = 0.0
        self.pos, self.vel = p0.copy(), np.zeros_like(p0)
        self.done = False

    def _at(self, t: np.ndarray) -> np.ndarray:
        T, Ta, v = self.total_s, self.accel_s, self.peak
        t = np.clip(t, 0.0, T)[:, None]
        if Ta > 0.0:
            acc = 0.5 * v / Ta * t**2
            cruise = v * (Ta / 2.0) + v * (t - Ta)
            dec = (self.goal - self.p0) - 0.5 * v / Ta * (T - t) ** 2
            s = np.where(t < Ta, acc, np.where(t <= T - Ta, cruise, dec))
        else:
            s = v * t
        return cast(np.ndarray, self.p0 + s)

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        if self.done:
            return None
        times = self.t + dt * np.arange(1, n + 1)
        out = self._at(times)
        prev = self.pos
        self.t = float(times[-1])
        self.pos = out[-1].copy()
        self.vel = (out[-1] - (out[-2] if n > 1 else prev)) / dt
        if self.t >= self.total_s:
            self.pos, self.vel, self.done = self.goal.copy(), np.zeros_like(self.goal), True
        return out


class VelocityLimited(Profile):
    """The target steps toward the goal at most at vmax per joint (no acceleration limit)."""

    def __init__(self, p0: np.ndarray, goal: np.ndarray, vmax: np.ndarray) -> None:
        self.p0, self.goal, self.vmax = p0.copy(), goal.copy(), vmax
        self.t = 0.0
        self.pos, self.vel = p0.copy(), np.zeros_like(p0)
        self.done = bool(np.array_equal(p0, goal))

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        if self.done:
            return None
        times = (self.t + dt * np.arange(1, n + 1))[:, None]
        reach = self.vmax * times
        out: np.ndarray = self.p0 + np.clip(self.goal - self.p0, -reach, reach)
        prev = self.pos
        self.t = float(times[-1, 0])
        self.pos = out[-1].copy()
        self.vel = (out[-1] - (out[-2] if n > 1 else prev)) / dt
        if np.array_equal(self.pos, self.goal):
            self.vel, self.done = np.zeros_like(self.goal), True
        return out


class AccelLimited(Profile):
    """Online trapezoid: follow the goal within vmax and amax, starting from the current target velocity."""

    def __init__(self, p: np.ndarray, v: np.ndarray, goal: np.ndarray, vmax: np.ndarray, amax: np.ndarray) -> None:
        self.pos, self.vel, self.goal, self.vmax, self.amax = p.copy(), v.copy(), goal.copy(), vmax, amax
        self.done = False

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        if self.done:
            return None
        out = np.empty((n, self.pos.size))
        p, v, goal, vmax, amax = self.pos, self.vel, self.goal, self.vmax, self.amax
        for i in range(n):
            e = goal - p
            v_des = np.sign(e) * np.minimum(vmax, np.sqrt(2.0 * amax * np.abs(e)))
            v = v + np.clip(v_des - v, -amax * dt, amax * dt)
            p_new = p + v * dt
            arrived = (goal - p_new) * e <= 0.0  # reached or crossed the goal during this substep
            if arrived.any():
                p_new = np.where(arrived, goal, p_new)
                v = np.where(arrived, 0.0, v)
            p = p_new
            out[i] = p
        self.pos, self.vel = p, v
        if np.array_equal(p, goal) and not v.any():
            self.done = True
        return out


class Integrate(Profile):
    """Velocity mode: the target moves at the commanded velocity, clipped to the joint limits."""

    def __init__(self, p0: np.ndarray, v: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
        self.p0, self.v, self.lower, self.upper = p0.copy(), v.copy(), lower, upper
        self.t = 0.0
        self.pos, self.vel = p0.copy(), v.copy()

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        times = (self.t + dt * np.arange(1, n + 1))[:, None]
        out: np.ndarray = np.clip(self.p0 + self.v * times, self.lower, self.upper)
        self.t = float(times[-1, 0])
        self.pos = out[-1].copy()
        self.vel = np.where((self.pos <= self.lower) | (self.pos >= self.upper), 0.0, self.v)
        return out


class Brake(Profile):
    """Stop: decelerate the target from its current velocity at ``decel`` and keep it where it stops."""

    def __init__(self, p0: np.ndarray, v0: np.ndarray, decel: float, lower: np.ndarray, upper: np.ndarray) -> None:
        self.p0, self.v0, self.decel, self.lower, self.upper = p0.copy(), v0.copy(), decel, lower, upper
        self.t_stop = np.abs(v0) / decel
        self.t = 0.0
        self.pos, self.vel = p0.copy(), v0.copy()
        self.done = not v0.any()

    def advance(self, n: int, dt: float) -> np.ndarray | None:
        if self.done:
            return None
        times = (self.t + dt * np.arange(1, n + 1))[:, None]
        t = np.minimum(times, self.t_stop)
        out: np.ndarray = np.clip(
            self.p0 + self.v0 * t - 0.5 * np.sign(self.v0) * self.decel * t**2, self.lower, self.upper
        )
        self.t = float(times[-1, 0])
        self.pos = out[-1].copy()
        self.vel = np.where(self.t < self.t_stop, self.v0 - np.sign(self.v0) * self.decel * self.t, 0.0)
        if self.t >= float(self.t_stop.max()):
            self.vel, self.done = np.zeros_like(self.v0), True
        return out
