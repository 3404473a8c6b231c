"""``make_vec``: a gymnasium VectorEnv over one worker process per env, and ``.as_sb3()``: an SB3 VecEnv over the
same workers.

Heterogeneous envs (an rx200 and a ned2, sim and emulated real) are padded to the largest observation and action
size, as the paper's multi-task experiment does: each worker wraps its env in ``envs.wrappers.PadSpaces`` (zeros
appended to observations, extra action entries ignored) and every info says which env it came from
(``info["env_id"]``) and how much was padded (``info["padding"]``). The vector observation space is the union of
the padded bounds; the action space is their intersection, so any action in it is valid for every sub-env.

Steps go to every worker before any reply is awaited (``step_async`` sends, ``step_wait`` collects: plain
methods, not coroutines). Autoreset follows gymnasium's ``AutoresetMode.NEXT_STEP`` (as AsyncVectorEnv): the step
after a sub-env's episode ended resets it, ignores its action and returns the reset observation with reward 0.
The SB3 VecEnv resets in the same step instead, as SB3 expects, with ``info["terminal_observation"]`` and
``info["TimeLimit.truncated"]``.
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime.supervisor import Supervisor
from uniros_async.runtime.worker import (
    PackedRequest,
    array_head,
    pack_step_request,
    space_from_plain,
    unpack,
    unpack_step_reply_into,
)

__all__ = ["UnirosVectorEnv", "make_vec"]

logger = logging.getLogger(__name__)

EnvSpec = str | tuple[str, dict[str, Any]]


def _normalize_specs(specs: Sequence[EnvSpec]) -> list[tuple[str, dict[str, Any]]]:
    out: list[tuple[str, dict[str, Any]]] = []
    for i, s in enumerate(specs):
        if isinstance(s, str):
            out.append((s, {}))
        elif isinstance(s, tuple | list) and len(s) == 2 and isinstance(s[0], str) and isinstance(s[1], dict):
            out.append((s[0], dict(s[1])))
        else:
            raise ConfigError(f"spec {i}: expected an env id or an (env id, kwargs) pair, got {s!r:.80}")
    return out


def _vector_box(space: gym.Space[Any]) -> gym.spaces.Box | None:
    """The 1-D Box that padding applies to (the ``observation`` key of a goal env), or None."""
    if isinstance(space, gym.spaces.Dict):
        space = space.spaces.get("observation")  # type: ignore[assignment]
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
        return space
    return None


def _listing(names: list[str], spaces: list[gym.Space[Any]]) -> str:
    return "; ".join(f"{n}: {s}" for n, s in zip(names, spaces, strict=True))


def _merge(spaces: list[gym.Space[Any]], names: list[str], *, union: bool, what: str) -> gym.Space[Any]:
    """One space covering ``spaces`` (bounds: union or intersection); ConfigError naming the envs if they differ."""
    first = spaces[0]
    if isinstance(first, gym.spaces.Dict):
        if not all(isinstance(s, gym.spaces.Dict) and s.spaces.keys() == first.spaces.keys() for s in spaces):
            raise ConfigError(f"{what} spaces differ in kind or keys: {_listing(names, spaces)}")
        return gym.spaces.Dict(
            {k: _merge([s[k] for s in spaces], names, union=union, what=f"{what}[{k!r}]") for k in first.spaces}  # type: ignore[index]
        )
    if isinstance(first, gym.spaces.Box):
        boxes = [
            s for s in spaces if isinstance(s, gym.spaces.Box) and (s.shape, s.dtype) == (first.shape, first.dtype)
        ]
        if len(boxes) != len(spaces):
            raise ConfigError(f"{what} spaces cannot be combined: {_listing(names, spaces)}")
        lows = np.stack([b.low for b in boxes])
        highs = np.stack([b.high for b in boxes])
        low, high = (lows.min(0), highs.max(0)) if union else (lows.max(0), highs.min(0))
        if np.any(low > high):
            raise ConfigError(f"{what} spaces have no common range: " + ", ".join(names))
        return gym.spaces.Box(low, high, dtype=first.dtype)
    if not all(s == first for s in spaces):
        raise ConfigError(f"{what} spaces differ: {_listing(names, spaces)}")
    return first


class UnirosVectorEnv(VectorEnv[Any, Any, Any]):
    """A gymnasium VectorEnv over worker processes (see the module docstring and ``make_vec``)."""

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        supervisor: Supervisor,
        *,
        pad: bool = True,
        restart_on_failure: bool = False,
        start_timeout_s: float = 60.0,
    ) -> None:
        self._sup = supervisor
        self.restart_on_failure = restart_on_failure
        self.restarts = [0] * len(supervisor.workers)
        self._start_timeout_s = start_timeout_s
        self._pad_msg: dict[str, Any] | None = None
        self._closed_vec = False
        self._pending: Any = None  # the Supervisor._Pending of step_async
        workers = supervisor.workers
        self.num_envs = len(workers)
        self.env_ids = [w.spec.env_id for w in workers]
        self.pids = supervisor.pids()
        names = [f"{i}:{e}" for i, e in enumerate(self.env_ids)]
        if pad:
            obs_boxes = [_vector_box(space_from_plain(w.info["observation_space"])) for w in workers]
            act_boxes = [_vector_box(space_from_plain(w.info["action_space"])) for w in workers]
            bad = [n for n, o, a in zip(names, obs_boxes, act_boxes, strict=True) if o is None or a is None]
            if bad:
                raise ConfigError(
                    f"cannot pad envs {bad}: padding needs 1-D Box observations (or a Dict with a 1-D "
                    "'observation') and 1-D Box actions"
                )
            obs_size = max(b.shape[0] for b in obs_boxes if b is not None)
            act_size = max(b.shape[0] for b in act_boxes if b is not None)
            msg = {"op": "pad", "obs_size": obs_size, "action_size": act_size}
            self._pad_msg = msg
            infos = supervisor.call(supervisor.request_all([msg] * self.num_envs))
            for w, info in zip(workers, infos, strict=True):
                w.info = {**w.info, **info}
        obs_spaces = [space_from_plain(w.info["observation_space"]) for w in workers]
        act_spaces = [space_from_plain(w.info["action_space"]) for w in workers]
        self.single_observation_space = _merge(obs_spaces, names, union=True, what="observation")
        self.single_action_space = _merge(act_spaces, names, union=False, what="action")
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        obs_space = self.single_observation_space
        # a Box observation goes from each reply straight into its row of the vector observation (_Returns)
        self._obs_head: bytes | None = None
        self._obs_batch: tuple[tuple[int, ...], np.dtype[Any]] | None = None  # its shape and dtype
        if isinstance(obs_space, gym.spaces.Box):
            self._obs_head = array_head(obs_space.dtype, obs_space.shape)
            self._obs_batch = ((self.num_envs, *obs_space.shape), np.dtype(obs_space.dtype))
        self._action_form: tuple[Any, ...] = (None,)  # _action_form of single_action_space, made at the first step
        self.metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}
        self.render_mode = None
        self.spec = None
        self.closed = False

    # ---- gymnasium VectorEnv API

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-env; an int seed gives sub-env i the seed ``seed + i``.

        Raises:
            WorkerError: a worker failed (index and traceback attached).
        """
        self._check_open()
        self._drop_pending()
        seeds = self._seeds(seed)
        replies = self._sup.call(self._sup.request_all([{"op": "reset", "seed": s, "options": options} for s in seeds]))
        return self._stack_obs([r[0] for r in replies]), self._infos([r[1] for r in replies])

    def step_async(self, actions: Any) -> None:
        """Send one action to every worker and return at once."""
        self._check_open()
        if self._pending is not None:
            raise gym.error.AlreadyPendingCallError("step_async was called twice without step_wait", "step")
        msgs = self._step_messages(actions, "next_step")
        self._pending = self._sup.submit_steps(msgs)

    def step_wait(self, timeout: float | None = None) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Collect the replies of ``step_async``.

        Raises:
            WorkerError: a worker raised, died or did not answer within the call timeout (its index named).
        """
        return _Returns(self).finish(self._wait(timeout))

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """``step_async`` then ``step_wait``, in one run of the supervisor's loop.

        Raises:
            WorkerError: as ``step_wait``.
        """
        if self._closed_vec:
            self._check_open()
        if self._pending is not None:
            raise gym.error.AlreadyPendingCallError("step was called while a step_async is pending", "step")
        msgs = self._step_messages(actions, "next_step")
        sup = self._sup
        sent = sup.send_steps_now(msgs)
        returns = _Returns(self)  # made while the workers step
        return returns.finish(self._collect(sup.receive_steps_now(msgs, sent, returns.decode)))

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name`` (or read attribute ``name``) of every sub-env; plain data in and out."""
        self._check_open()
        msg = {"op": "call", "name": name, "args": list(args), "kwargs": kwargs}
        return tuple(self._sup.call(self._sup.request_all([msg] * self.num_envs)))

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every sub-env (plain data)."""
        self._check_open()
        return tuple(self._sup.call(self._sup.request_all([{"op": "get", "name": name}] * self.num_envs)))

    def close(self, **kwargs: Any) -> None:
        """Stop every worker; idempotent and bounded in time."""
        if self._closed_vec:
            return
        self._closed_vec = True
        self.closed = True
        self._drop_pending()
        self._sup.close()

    def as_sb3(self) -> Any:
        """An SB3 ``VecEnv`` over the same workers (same-step autoreset, as SB3 expects)."""
        return _sb3_class()(self)

    # ---- helpers (also used by the SB3 adapter)

    def _check_open(self) -> None:
        if self._closed_vec:
            raise gym.error.ClosedEnvironmentError("the vector env is closed; make a new one")

    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, int | np.integer):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ConfigError(f"expected {self.num_envs} seeds, got {len(seeds)}")
        return seeds

    def _step_messages(self, actions: Any, autoreset: str) -> list[PackedRequest]:
        """One packed step request per worker (``pack_step_request``: no message map to build or walk)."""
        space = self.single_action_space
        form = self._action_form
        if form[0] is not space:  # worked out once per action space: a step then costs no isinstance or shape tuple
            form = self._action_form = _action_form(space, self.num_envs)
        _, kind, shape, dtype = form
        if kind == "box":
            per_env: Any = np.asarray(actions, dtype)
            if per_env.shape != shape:
                raise gym.error.InvalidAction(f"actions must have shape {shape}, got {per_env.shape}")
        elif kind == "discrete":  # gymnasium's iterate over the batch space costs ~7 us here
            batch = np.asarray(actions, dtype)
            if batch.shape != shape:
                raise gym.error.InvalidAction(f"actions must have shape {shape}, got {batch.shape}")
            per_env = batch.tolist()
        else:
            per_env = list(iterate(self.action_space, actions))
        # one reference time for the whole step, for the members on this machine (CLOCK_MONOTONIC is machine-wide):
        # a wall-clock env that must pick a new deadline decides it from this instant, so every member picks the
        # same one (RobotEnv._step_deadline); a remote worker's clock is another machine's
        t = time.monotonic_ns()
        workers = self._sup.workers
        if len(per_env) != len(workers):
            raise gym.error.InvalidAction(f"expected one action per env ({len(workers)}), got {len(per_env)}")
        return [
            pack_step_request(a, autoreset, t if w.remote is None else None)
            for a, w in zip(per_env, workers)  # noqa: B905  (lengths checked: the strict check costs ~0.5 us here)
        ]

    def _wait(self, timeout: float | None) -> list[Any]:
        fut = self._pending
        if fut is None:
            raise gym.error.NoAsyncCallError("step_wait called without step_async", "step")
        try:
            result = fut.result(self._sup.call_timeout_s + 5.0 if timeout is None else timeout)
        except concurrent.futures.TimeoutError:
            raise gym.error.AlreadyPendingCallError(f"the step did not finish within {timeout} s", "step") from None
        finally:
            if fut.done():
                self._pending = None
        return self._collect(result)

    def _collect(self, result: list[Any]) -> list[Any]:
        """Replies in index order; a broken worker is restarted (``restart_on_failure``) or its error raised."""
        for i, r in enumerate(result):
            if isinstance(r, WorkerError):
                if not self.restart_on_failure or self._sup.workers[i].broken is None:
                    raise r
                result[i] = self._restart(i, r)
        return result

    def _restart(self, index: int, error: WorkerError) -> list[Any]:
        """Replace a dead worker, reset its env; its episode ends as truncated."""
        logger.warning("restarting worker %d after: %s", index, error)
        w = self._sup.restart(index, self._start_timeout_s)
        if self._pad_msg is not None:
            self._sup.call(w.request(self._pad_msg, self._sup.call_timeout_s))
        obs, info = self._sup.call(w.request({"op": "reset"}, self._sup.call_timeout_s))
        self.restarts[index] += 1
        self.pids[index] = w.process.pid
        info = {**info, "worker_restarted": True, "worker_error": str(error)}
        return [obs, 0.0, False, True, info]

    def _drop_pending(self) -> None:
        fut, self._pending = self._pending, None
        if fut is not None:
            try:
                fut.result(self._sup.call_timeout_s + 5.0)
            except (WorkerError, concurrent.futures.TimeoutError, concurrent.futures.CancelledError):
                pass

    def _stack_obs(self, obs: list[Any]) -> Any:
        space = self.single_observation_space
        if isinstance(space, gym.spaces.Box):  # gymnasium's concatenate does this, after an allocation of its own
            return np.array(obs, dtype=space.dtype)  # as np.stack, a quarter of its cost
        out: Any = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, obs, out)

    def _infos(self, infos: list[dict[str, Any]]) -> dict[str, Any]:
        vector_infos: dict[str, Any] = {}
        for i, info in enumerate(infos):
            vector_infos = self._add_info(vector_infos, info, i)
        return vector_infos

    def _add_info(self, vector_infos: dict[str, Any], env_info: dict[str, Any], env_num: int) -> dict[str, Any]:
        """gymnasium's ``VectorEnv._add_info``, the same result (tested against it), without the arrays it allocates
        and drops for keys it already has, and with ``np.empty`` for object arrays (None-filled, as ``np.full`` with
        None, at a third of its cost): it ran every step, for every key of every sub-env's info."""
        n = self.num_envs
        for key, value in env_info.items():
            if key == "final_obs":
                array = vector_infos.get(key)
                if array is None:
                    array = np.empty(n, object)
                array[env_num] = value
            elif isinstance(value, dict):
                array = self._add_info(vector_infos.get(key, {}), value, env_num)
            else:
                array = vector_infos.get(key)
                if array is None:
                    kind = type(value)
                    if kind is int or kind is float or kind is bool or issubclass(kind, np.number):
                        array = np.zeros(n, kind)
                    elif isinstance(value, np.ndarray):
                        array = np.zeros((n, *value.shape), value.dtype)
                    else:
                        array = np.empty(n, object)
                array[env_num] = value
            mask_key = f"_{key}"
            mask = vector_infos.get(mask_key)
            if mask is None:
                mask = np.zeros(n, _BOOL)
            mask[env_num] = True
            vector_infos[key] = array
            vector_infos[mask_key] = mask
        return vector_infos

    def __repr__(self) -> str:
        return f"UnirosVectorEnv({self.env_ids})"


_FLOAT64, _BOOL = np.dtype(np.float64), np.dtype(np.bool_)


def _action_form(space: gym.Space[Any], n: int) -> tuple[Any, ...]:
    """(space, kind, batch shape, dtype) of a vector env's actions: kind "box" (an array of ``n`` rows), "discrete"
    (``n`` ints) or "other" (iterated as gymnasium does)."""
    if isinstance(space, gym.spaces.Box):
        return space, "box", (n, *space.shape), np.dtype(space.dtype)
    if isinstance(space, gym.spaces.Discrete):
        return space, "discrete", (n,), np.dtype(np.int64)
    return space, "other", None, None


class _Returns:
    """One vector step's returns, filled reply by reply: made (its arrays allocated) while the workers step; a
    reply that ``decode`` takes while it is still in the transport's ring leaves its observation in its row of the
    vector observation at once (a Box observation space; ``worker.unpack_step_reply_into``), the others (a Dict
    observation, a reply taken by the event loop, a restarted worker's) go through ``finish`` as results."""

    __slots__ = ("venv", "obs", "raw", "row_bytes", "rewards", "terminated", "truncated")

    def __init__(self, venv: UnirosVectorEnv) -> None:
        n = venv.num_envs
        self.venv = venv
        self.rewards = np.empty(n, _FLOAT64)  # dtypes given by position: by keyword, numpy takes twice as long
        self.terminated = np.empty(n, _BOOL)
        self.truncated = np.empty(n, _BOOL)
        batch = venv._obs_batch
        if batch is None:
            self.obs: np.ndarray | None = None
            self.raw: memoryview | None = None  # the bytes of ``obs``, row after row
            self.row_bytes = 0
        else:
            self.obs = obs = np.empty(*batch)
            self.raw = obs.data.cast("B")
            self.row_bytes = obs.nbytes // n

    def decode(self, i: int, frame: memoryview) -> Any:
        """Sub-env ``i``'s step reply: its info (a dict) when the rest went straight into place, else its result
        (``[obs, reward, terminated, truncated, info]``, a list) for ``finish``."""
        raw = self.raw
        if raw is not None:  # (a Box observation: the venv has its header)
            k = self.row_bytes
            got = unpack_step_reply_into(frame, raw[i * k : i * k + k], self.venv._obs_head)  # type: ignore[arg-type]
            if got is not None:
                self.rewards[i], self.terminated[i], self.truncated[i], info = got
                return info
        return unpack(frame)["result"]

    def finish(self, results: list[Any]) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """The vector returns, from ``results`` (what ``decode`` returned, or the results of the usual path)."""
        venv = self.venv
        obs = self.obs
        others: list[Any] = []
        infos: dict[str, Any] = {}
        for i, r in enumerate(results):
            if type(r) is dict:  # decoded in place; only its info is left
                info = r
            else:
                o, self.rewards[i], self.terminated[i], self.truncated[i], info = r
                if obs is not None:
                    obs[i] = o
                else:
                    others.append(o)
            infos = venv._add_info(infos, info, i)
        if obs is None:
            obs = venv._stack_obs(others)
        return obs, self.rewards, self.terminated, self.truncated, infos


_SB3_CLASS: list[type] = []


def _sb3_class() -> type:
    """The SB3 adapter class, defined on first use (SB3 imports torch, which a plain gymnasium user need not pay)."""
    if _SB3_CLASS:
        return _SB3_CLASS[0]
    from stable_baselines3.common.vec_env.base_vec_env import VecEnv as SB3VecEnv

    class UnirosSB3VecEnv(SB3VecEnv):
        """An SB3 VecEnv over the workers of a UnirosVectorEnv (same-step autoreset; SB3's info conventions)."""

        def __init__(self, venv: UnirosVectorEnv) -> None:
            self.venv = venv
            super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

        def reset(self) -> Any:
            seeds = list(self._seeds)
            options = self._options[0] if self._options and self._options[0] else None
            v = self.venv
            v._check_open()
            v._drop_pending()
            msgs = [{"op": "reset", "seed": s, "options": options} for s in seeds]
            replies = v._sup.call(v._sup.request_all(msgs))
            self.reset_infos = [r[1] for r in replies]
            self._reset_seeds()
            self._reset_options()
            return v._stack_obs([r[0] for r in replies])

        def step_async(self, actions: np.ndarray) -> None:
            v = self.venv
            v._check_open()
            if v._pending is not None:
                raise gym.error.AlreadyPendingCallError("step_async was called twice without step_wait", "step")
            msgs = v._step_messages(actions, "same_step")
            v._pending = v._sup.submit_steps(msgs)

        def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict[str, Any]]]:
            replies = self.venv._wait(None)
            infos: list[dict[str, Any]] = []
            dones = np.zeros(self.num_envs, dtype=np.bool_)
            for i, (_, _, terminated, truncated, info) in enumerate(replies):
                dones[i] = terminated or truncated
                if "final_obs" in info:
                    info["terminal_observation"] = info.pop("final_obs")
                    info["TimeLimit.truncated"] = bool(truncated and not terminated)
                elif dones[i]:  # a restarted worker: its final observation died with it
                    info["terminal_observation"] = replies[i][0]
                    info["TimeLimit.truncated"] = True
                infos.append(info)
            obs = self.venv._stack_obs([r[0] for r in replies])
            rewards = np.array([r[1] for r in replies], dtype=np.float32)
            return obs, rewards, dones, infos

        def close(self) -> None:
            self.venv.close()

        def _targets(self, indices: Any) -> list[int]:
            if indices is None:
                return list(range(self.num_envs))
            if isinstance(indices, int | np.integer):
                return [int(indices)]
            return [int(i) for i in indices]

        def _each(self, msg: dict[str, Any], indices: Any) -> list[Any]:
            v = self.venv
            targets = set(self._targets(indices))
            msgs = [msg if i in targets else None for i in range(self.num_envs)]
            try:
                out = v._sup.call(v._sup.request_all(msgs))
            except WorkerError as exc:
                if "AttributeError" in str(exc):
                    raise AttributeError(str(exc)) from exc
                raise
            return [out[i] for i in sorted(targets)]

        def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
            return self._each({"op": "get", "name": attr_name}, indices)

        def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
            self._each({"op": "set", "name": attr_name, "value": value}, indices)

        def env_method(
            self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
        ) -> list[Any]:
            msg = {"op": "call", "name": method_name, "args": list(method_args), "kwargs": method_kwargs}
            return self._each(msg, indices)

        def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
            # wrappers live in the workers; only the padding wrapper is ever added there, never SB3's
            return [False for _ in self._targets(indices)]

    _SB3_CLASS.append(UnirosSB3VecEnv)
    return UnirosSB3VecEnv


def make_vec(
    specs: Sequence[EnvSpec],
    *,
    pad: bool = True,
    restart_on_failure: bool = False,
    start_timeout_s: float = 60.0,
    call_timeout_s: float = 60.0,
    transport: str = "shm",
    **common_kwargs: Any,
) -> UnirosVectorEnv:
    """A gymnasium VectorEnv over one worker process per spec.

    Args:
        specs: env ids or ``(env_id, kwargs)`` pairs, e.g. ``["uniros/Rx200Reach-v0", ("uniros/Ned2Reach-v0",
            {"robot": "emulated-real"})]``; any gymnasium id, and for an env of your own gymnasium's
            ``"module:Id"`` (the worker imports ``module``, which registers ``Id``). ``{"worker":
            "tcp://HOST:PORT"}`` (or a ``RemoteWorker``) runs that spec's worker on a launcher on another host
            (``uniros worker serve``, runtime/remote.py; its pid in ``pids`` is on that host); ``"worker": None``
            keeps it here.
        pad: pad observations and actions to the largest sizes (required when the envs differ); without it the
            spaces must match.
        start_timeout_s: bound on starting all workers and building their envs.
        restart_on_failure: when a worker dies (or stops answering) during a step, start a new one, reset its env
            and report that sub-env's step as truncated with ``info["worker_restarted"]``; otherwise the step raises
            WorkerError. Exceptions raised by the env itself are always raised.
        call_timeout_s: bound on each reset/step of a worker.
        transport: how the agent side talks to the workers: ``"shm"`` (default) or ``"tcp"`` (loopback).
        **common_kwargs: passed to every env (a spec's own kwargs win), e.g. ``clock="sim"``.

    Raises:
        ConfigError: a malformed spec, an unknown id or keyword argument (before any process starts; for a remote
            spec, by its launcher), or spaces that cannot be padded or combined (naming the envs; the workers are
            closed).
        WorkerError: a worker failed to start or to build its env, or its launcher is unreachable or refused it
            (its index and traceback; the others are closed).
    """
    norm = [(env_id, {**common_kwargs, **kw}) for env_id, kw in _normalize_specs(specs)]
    sup = Supervisor(norm, start_timeout_s=start_timeout_s, call_timeout_s=call_timeout_s, transport=transport)
    try:
        return UnirosVectorEnv(sup, pad=pad, restart_on_failure=restart_on_failure, start_timeout_s=start_timeout_s)
    except BaseException:
        sup.close()
        raise
