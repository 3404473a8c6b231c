"""``make_vec``: a gymnasium VectorEnv over worker processes, and ``.as_sb3()``: an SB3 VecEnv over the same workers
(runtime/sb3.py).

Its specs are env ids, ``(env id, kwargs)`` pairs or env factories, as gymnasium's AsyncVectorEnv and SB3's
SubprocVecEnv take them (runtime/specs.py). Each env runs in a worker process: one process per env, or, where
accelerated envs outnumber the cores, one process per core hosting several (``envs_per_worker="auto"``, the
default; a real-time env always has a process of its own).

Heterogeneous envs (an rx200 and a ned2, sim and emulated real) are padded to the largest observation and action
size, as the paper's multi-task experiment does: each worker wraps its env in ``envs.wrappers.PadSpaces`` (zeros
appended to observations, extra action entries ignored) and every info says which env it came from
(``info["env_id"]``) and how much was padded (``info["padding"]``). The vector observation space is the union of
the padded bounds; the action space is their intersection, so any action in it is valid for every sub-env.

Steps go to every worker before any reply is awaited (``step_async`` sends, ``step_wait`` collects: plain
methods, not coroutines). Autoreset follows gymnasium's ``AutoresetMode.NEXT_STEP`` (as AsyncVectorEnv): the step
after a sub-env's episode ended resets it, ignores its action and returns the reset observation with reward 0.
The SB3 VecEnv resets in the same step instead, as SB3 expects, with ``info["terminal_observation"]`` and
``info["TimeLimit.truncated"]``. ``step_wait(timeout)`` that runs out raises StepTimeoutError naming the first worker
still owing its reply; the step stays pending and the next ``step_wait`` collects it.
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

from uniros_async.errors import ConfigError, InvalidActionsError, StepTimeoutError, WorkerError
from uniros_async.runtime.protocol import (
    PackedRequest,
    array_head,
    conform,
    pack_step_request,
    result_value,
    space_from_plain,
    unpack,
    unpack_step_reply_into,
)
from uniros_async.runtime.ray_placement import apply_backend
from uniros_async.runtime.spaces import merge_spaces, vector_box
from uniros_async.runtime.specs import AUTO, EnvSpec, factory_of, normalize_specs
from uniros_async.runtime.supervisor import Supervisor

__all__ = ["UnirosVectorEnv", "make_vec"]

logger = logging.getLogger(__name__)


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
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ) -> None:
        self._sup = supervisor
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self._autoreset = _AUTORESET_WIRE[self.autoreset_mode]
        self.restart_on_failure = restart_on_failure  # (sets the supervisor's fail_fast: see the property)
        self.restarts = [0] * len(supervisor.workers)
        self._start_timeout_s = start_timeout_s
        self._pad_msg: dict[str, Any] | None = None
        self._closed_vec = False
        self._pending: Any = None  # the Supervisor._Pending of step_async
        self._last_obs: Any = None  # the last vector observation returned (reset with a reset_mask keeps its rows)
        workers = supervisor.workers
        self.num_envs = len(workers)
        self.env_ids = [w.spec.env_id for w in workers]
        self.pids = supervisor.pids()
        names = [f"{i}:{e}" for i, e in enumerate(self.env_ids)]
        obs_spaces = [space_from_plain(w.info["observation_space"]) for w in workers]
        act_spaces = [space_from_plain(w.info["action_space"]) for w in workers]
        same = all(o == obs_spaces[0] for o in obs_spaces) and all(a == act_spaces[0] for a in act_spaces)
        if pad and not same:  # identical spaces are never padded
            self._pad(names, obs_spaces, act_spaces)
            obs_spaces = [space_from_plain(w.info["observation_space"]) for w in workers]
            act_spaces = [space_from_plain(w.info["action_space"]) for w in workers]
        self.single_observation_space = merge_spaces(obs_spaces, names, union=True, what="observation")
        self.single_action_space = merge_spaces(act_spaces, names, union=False, what="action")
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
        # a value of another space than a Box crosses the wire without its tuples and numpy scalars (protocol.conform)
        self._conform_obs = not isinstance(obs_space, gym.spaces.Box)
        # a Dict of Boxes (a goal env's observation) is batched key by key into arrays made here: what gymnasium's
        # concatenate returns, at a fraction of its cost (its create_empty_array and per-key walk run every step)
        self._dict_form: tuple[tuple[str, tuple[int, ...], np.dtype[Any]], ...] | None = None
        if isinstance(obs_space, gym.spaces.Dict) and all(
            isinstance(sub, gym.spaces.Box) for sub in obs_space.spaces.values()
        ):
            self._dict_form = tuple(
                (key, sub.shape or (), np.dtype(sub.dtype)) for key, sub in obs_space.spaces.items()
            )
        first = workers[0].info
        self.metadata = {**first.get("metadata", {}), "autoreset_mode": self.autoreset_mode}
        self.render_mode = first.get("render_mode")
        self.spec = None
        self.closed = False

    @property
    def restart_on_failure(self) -> bool:
        """Whether a worker that dies is restarted (``make_vec``). Without it a step raises a Ray-placed worker's
        hang-up at once, not after the other workers' replies (``Supervisor.fail_fast``)."""
        return not self._sup.fail_fast

    @restart_on_failure.setter
    def restart_on_failure(self, value: bool) -> None:
        self._sup.fail_fast = not value

    def _pad(self, names: list[str], obs_spaces: list[gym.Space[Any]], act_spaces: list[gym.Space[Any]]) -> None:
        """Have every worker pad its env to the largest observation and action sizes (``PadSpaces``).

        Raises:
            ConfigError: the spaces differ and cannot be padded (not 1-D Boxes), naming the envs and their spaces.
        """
        obs_boxes = [vector_box(s) for s in obs_spaces]
        act_boxes = [vector_box(s) for s in act_spaces]
        bad = [i for i, (o, a) in enumerate(zip(obs_boxes, act_boxes, strict=True)) if o is None or a is None]
        if bad:
            listing = "; ".join(
                f"{names[i]}: observation {obs_spaces[i]}, action {act_spaces[i]}" for i in range(len(names))
            )
            raise ConfigError(
                f"the envs' spaces differ and cannot be padded ({listing}); padding needs 1-D Box observations (or a "
                f"Dict with a 1-D 'observation') and 1-D Box actions, which {[names[i] for i in bad]} do not have"
            )
        obs_size = max(b.shape[0] for b in obs_boxes if b is not None)
        act_size = max(b.shape[0] for b in act_boxes if b is not None)
        msg = {"op": "pad", "obs_size": obs_size, "action_size": act_size}
        self._pad_msg = msg
        sup = self._sup
        infos = sup.call(sup.request_all([msg] * self.num_envs))
        for w, info in zip(sup.workers, infos, strict=True):
            w.info = {**w.info, **info}

    # ---- gymnasium VectorEnv API

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-env; an int seed gives sub-env i the seed ``seed + i``. With ``options["reset_mask"]`` (a
        bool array, one per sub-env; gymnasium's DISABLED autoreset mode) only those sub-envs reset, and the others
        keep their last observation.

        Raises:
            WorkerError: a worker failed (index and traceback attached).
            ValueError, TypeError: a malformed ``reset_mask`` (as gymnasium's vector envs say it).
        """
        self._check_open()
        self._drop_pending()
        seeds = self._seeds(seed)
        mask = None
        if options is not None and "reset_mask" in options:
            options = dict(options)
            mask = _check_reset_mask(options.pop("reset_mask"), self.num_envs)
            if mask.all() or self._last_obs is None:  # every row is reset: an ordinary reset
                mask = None
        msgs: list[Any] = [{"op": "reset", "seed": s, "options": options} for s in seeds]
        if mask is not None:
            msgs = [m if keep else None for m, keep in zip(msgs, mask, strict=True)]
        replies = self._sup.call(self._sup.request_all(msgs))
        if mask is None:
            obs = self._stack_obs([r[0] for r in replies])
            infos = self._infos([r[1] for r in replies])
        else:
            rows = list(iterate(self.observation_space, self._last_obs))
            for i, r in enumerate(replies):
                if r is not None:
                    rows[i] = r[0]
            obs = self._stack_obs(rows)
            infos = {}
            for i, r in enumerate(replies):
                if r is not None:
                    infos = self._add_info(infos, r[1], i)
        self._last_obs = obs
        return obs, infos

    def step_async(self, actions: Any) -> None:
        """Send one action to every worker and return at once."""
        self._check_open()
        if self._pending is not None:
            raise gym.error.AlreadyPendingCallError("step_async was called twice without step_wait", "step")
        msgs = self._step_messages(actions, self._autoreset)
        self._pending = self._sup.submit_steps(msgs)

    def step_wait(self, timeout: float | None = None) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Collect the replies of ``step_async``, waiting at most ``timeout`` seconds (None: the call timeout).

        Raises:
            StepTimeoutError: not every reply came within ``timeout`` (the first worker still owing one named; the
                step stays pending: the next ``step_wait`` collects it), or a worker did not answer within the call
                timeout (that worker is broken).
            WorkerError: a worker raised or died (its index named).
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
        msgs = self._step_messages(actions, self._autoreset)
        sup = self._sup
        sent = sup.send_steps_now(msgs)
        returns = _Returns(self)  # made while the workers step
        return returns.finish(self._collect(sup.receive_steps_now(msgs, sent, returns.decode)))

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name`` of every sub-env (or read attribute ``name``), looked up through its wrappers as
        gymnasium's vector envs do; arguments and results are plain data, spaces and arrays (anything else comes
        back as its repr)."""
        self._check_open()
        msg = {"op": "call", "name": name, "args": list(args), "kwargs": kwargs}
        return tuple(result_value(r) for r in self._sup.call(self._sup.request_all([msg] * self.num_envs)))

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every sub-env: ``call(name)``, as gymnasium's vector envs have it (a method is
        called)."""
        return self.call(name)

    def set_attr(self, name: str, values: list[Any] | tuple[Any, ...] | Any) -> None:
        """Set attribute ``name`` of every sub-env: ``values[i]`` for sub-env i when a list or tuple, else the one
        value for all.

        Raises:
            ValueError: a list or tuple whose length is not the number of envs.
        """
        self._check_open()
        if not isinstance(values, list | tuple):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(
                "Values must be a list or tuple with length equal to the number of environments. "
                f"Got `{len(values)}` values for {self.num_envs} environments."
            )
        msgs = [{"op": "set", "name": name, "value": v} for v in values]
        self._sup.call(self._sup.request_all(msgs))

    def render(self) -> tuple[Any, ...] | None:
        """Every sub-env's ``render()`` (with ``render_mode="rgb_array"``: one frame each)."""
        self._check_open()
        return tuple(self._sup.call(self._sup.request_all([{"op": "render"}] * self.num_envs)))

    @property
    def np_random_seed(self) -> tuple[int, ...]:  # type: ignore[override]
        """Every sub-env's ``np_random_seed`` (as gymnasium's vector envs read it)."""
        return self.get_attr("np_random_seed")

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
        from uniros_async.runtime.sb3 import UnirosSB3VecEnv

        return UnirosSB3VecEnv(self)

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

    def _step_messages(self, actions: Any, autoreset: str | None) -> list[PackedRequest]:
        """One packed step request per worker (``pack_step_request``: no message map to build or walk)."""
        space = self.single_action_space
        form = self._action_form
        if form[0] is not space:  # worked out once per action space: a step then costs no isinstance or shape tuple
            form = self._action_form = _action_form(space, self.num_envs)
        _, kind, shape, dtype = form
        if kind == "box":  # each sub-env's row as given (its dtype too), as gymnasium's vector envs pass it
            per_env: Any = np.asarray(actions)
            if per_env.shape != shape and not (per_env.ndim and len(per_env) == shape[0] == per_env.size):
                _bad_actions(shape, per_env.shape)  # (n,) for n sub-envs of one entry each: their entries as given
        elif kind == "discrete":  # one array conversion, not gymnasium's iterate over the batch space
            batch = np.asarray(actions, dtype)
            if batch.shape != shape:
                _bad_actions(shape, batch.shape)
            per_env = batch.tolist()
        elif type(actions) is list and len(actions) == self.num_envs and kind == "composite":
            per_env = actions  # one action per sub-env, as SB3 passes them (a batch of a Dict or Tuple is no list)
        else:
            per_env = list(iterate(self.action_space, actions))
        # one reference time for the whole step, for the members on this machine (CLOCK_MONOTONIC is machine-wide):
        # a wall-clock env that must pick a new deadline decides it from this instant, so every member picks the
        # same one (RobotEnv._step_deadline); a remote worker's clock is another machine's
        t = time.monotonic_ns()
        workers = self._sup.workers
        if len(per_env) != len(workers):
            raise InvalidActionsError(f"expected one action per env ({len(workers)}), got {len(per_env)}")
        return [
            pack_step_request(a, autoreset, t if w.remote is None else None)
            for a, w in zip(per_env, workers)  # noqa: B905  (lengths checked above: no strict check per step)
        ]

    def _wait(self, timeout: float | None) -> list[Any]:
        fut = self._pending
        if fut is None:
            raise gym.error.NoAsyncCallError("Calling `step_wait` without any prior call to `step_async`.", "step")
        wait_s = self._sup.call_timeout_s + 5.0 if timeout is None else timeout
        try:
            result = fut.result(wait_s)
        except concurrent.futures.TimeoutError:
            raise StepTimeoutError(
                self._sup.first_owing(),
                f"no reply to 'step' within {wait_s} s (step_wait's timeout; the step stays pending, and the next "
                "step_wait collects it)",
            ) from None
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
                for j, returns in self._restart(i, r).items():
                    result[j] = returns
        return result

    def _restart(self, index: int, error: WorkerError) -> dict[int, list[Any]]:
        """Replace a dead worker and the other envs of its process, reset their envs; their episodes end as
        truncated. The returns of each, by index."""
        logger.warning("restarting worker %d after: %s", index, error)
        self._sup.restart(index, self._start_timeout_s)
        out: dict[int, list[Any]] = {}
        for j in self._sup.workers[index].group:
            w = self._sup.workers[j]
            if self._pad_msg is not None:
                self._sup.call(w.request(self._pad_msg, self._sup.call_timeout_s))
            obs, info = self._sup.call(w.request({"op": "reset"}, self._sup.call_timeout_s))
            self.restarts[j] += 1
            self.pids[j] = w.process.pid
            why = str(error) if j == index else f"its worker process, shared with env {index}, was restarted: {error}"
            out[j] = [obs, 0.0, False, True, {**info, "worker_restarted": True, "worker_error": why}]
        return out

    def _drop_pending(self) -> None:
        fut, self._pending = self._pending, None
        if fut is not None:
            try:
                fut.result(self._sup.call_timeout_s + 5.0)
            except (WorkerError, concurrent.futures.TimeoutError, concurrent.futures.CancelledError):
                pass

    def _stack_obs(self, obs: list[Any]) -> Any:
        space = self.single_observation_space
        form = self._dict_form
        if form is not None:
            out_dict = {}
            for key, shape, dtype in form:
                batch = np.empty((len(obs), *shape), dtype)
                for i, o in enumerate(obs):
                    batch[i] = o[key]
                out_dict[key] = batch
            return out_dict
        if self._conform_obs:
            obs = [conform(space, o) for o in obs]
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


def _bad_actions(expected: tuple[int, ...], got: tuple[int, ...]) -> None:
    """Raise what a vector step with actions of shape ``got`` raises: TypeError for a scalar (no action per sub-env
    at all), else InvalidActionsError."""
    if got == ():
        raise TypeError(f"actions must have shape {expected}, one per sub-env, got a scalar")
    raise InvalidActionsError(f"actions must have shape {expected}, got {got}")


def _check_reset_mask(mask: Any, n: int) -> np.ndarray:
    """``options["reset_mask"]`` checked as gymnasium's vector envs check it (their messages).

    Raises:
        TypeError: not a bool array.
        ValueError: not of shape ``(n,)``, or no True in it.
    """
    if not isinstance(mask, np.ndarray):
        raise TypeError(f"`options['reset_mask': mask]` must be a numpy array, got {type(mask)}")
    if mask.shape != (n,):
        raise ValueError(f"`options['reset_mask']` must have shape `({n},)`, got {mask.shape}")
    if mask.dtype != np.bool_:
        raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got {mask.dtype}")
    if not np.any(mask):
        raise ValueError(
            f"`options['reset_mask']` must contain a boolean array with at least one True value, got reset_mask={mask}"
        )
    return mask


_AUTORESET_WIRE = {
    AutoresetMode.NEXT_STEP: "next_step",
    AutoresetMode.SAME_STEP: "same_step",
    AutoresetMode.DISABLED: None,
}
"""Each gymnasium autoreset mode as the step request names it (protocol.AUTORESET_MODES)."""


def _autoreset_mode(mode: AutoresetMode | str) -> AutoresetMode:
    """``mode`` as an AutoresetMode (its value, e.g. ``"SameStep"``, or its name, ``"same_step"``, accepted).

    Raises:
        ConfigError: anything else.
    """
    if isinstance(mode, AutoresetMode):
        return mode
    for m in AutoresetMode:
        if isinstance(mode, str) and mode in (m.value, m.name, m.name.lower()):
            return m
    raise ConfigError(f"autoreset_mode must be one of {[m.value for m in AutoresetMode]}, got {mode!r}")


def _action_form(space: gym.Space[Any], n: int) -> tuple[Any, ...]:
    """(space, kind, batch shape, dtype) of a vector env's actions: kind "box" (an array of ``n`` rows), "discrete"
    (``n`` ints), "composite" (a Dict or Tuple: a batch iterated as gymnasium does, or a list of one action per
    sub-env) or "other" (iterated as gymnasium does)."""
    if isinstance(space, gym.spaces.Box):
        return space, "box", (n, *space.shape), np.dtype(space.dtype)
    if isinstance(space, gym.spaces.Discrete):
        return space, "discrete", (n,), np.dtype(np.int64)
    if isinstance(space, gym.spaces.Dict | gym.spaces.Tuple):
        return space, "composite", None, None
    return space, "other", None, None


class _Returns:
    """One vector step's returns, filled reply by reply: made (its arrays allocated) while the workers step; a
    reply that ``decode`` takes while it is still in the transport's ring leaves its observation in its row of the
    vector observation at once (a Box observation space; ``protocol.unpack_step_reply_into``), the others (a Dict
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
            if not info:  # nothing to add (a plain gymnasium env's info, at every step)
                continue
            if venv._conform_obs and "final_obs" in info:
                info["final_obs"] = conform(venv.single_observation_space, info["final_obs"])
            infos = venv._add_info(infos, info, i)
        if obs is None:
            obs = venv._stack_obs(others)
        venv._last_obs = obs
        return obs, self.rewards, self.terminated, self.truncated, infos


def make_vec(
    specs: Sequence[EnvSpec] | EnvSpec,
    *,
    num_envs: int | None = None,
    pad: bool = True,
    restart_on_failure: bool = False,
    start_timeout_s: float = 60.0,
    call_timeout_s: float = 60.0,
    transport: str = "shm",
    autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    backend: str = "local",
    envs_per_worker: int | str = AUTO,
    rt_rank_base: int = 0,
    loop_phase_base: int | None = None,
    **common_kwargs: Any,
) -> UnirosVectorEnv:
    """A gymnasium VectorEnv over worker processes: one per env, or one per core where accelerated envs outnumber
    the cores (``envs_per_worker``).

    Args:
        specs: env ids, ``(env_id, kwargs)`` pairs or env factories, mixed as you like, e.g.
            ``["uniros/Rx200Reach-v0", ("uniros/Ned2Reach-v0", {"robot": "emulated-real"})]`` or, as gymnasium's
            AsyncVectorEnv and SB3's SubprocVecEnv take them, ``[lambda: gym.make("CartPole-v1")] * 4``. Any
            gymnasium id, and for an env of your own gymnasium's ``"module:Id"`` (the worker imports ``module``,
            which registers ``Id``). A factory (a callable without arguments that returns a gymnasium.Env) is
            cloudpickled into its worker and called there (runtime/specs.py). ``{"worker": "ray"}`` or
            ``{"worker": {"ray": {...}}}`` has Ray place that spec's worker on a node of its cluster (see
            ``backend``; its pid in ``pids`` is on that node); ``"worker": None`` keeps it here. One spec given
            alone (an id, a pair or a factory) is ``num_envs`` copies of it, as
            ``gymnasium.make_vec("CartPole-v1", num_envs=4)``.
        num_envs: how many copies of the one spec given alone (default 1); not with a list.
        pad: when the envs' spaces differ, pad observations and actions to the largest sizes (1-D Box spaces, or a
            Dict with a 1-D ``observation``); identical spaces are never padded. Without it the spaces must match.
        start_timeout_s: bound on starting all workers and building their envs.
        restart_on_failure: when a worker dies (or stops answering) during a step, start a new one, reset its env
            and report that sub-env's step as truncated with ``info["worker_restarted"]``; otherwise the step raises
            WorkerError. Exceptions raised by the env itself are always raised.
        call_timeout_s: bound on each reset/step of a worker.
        transport: how the agent side talks to the workers: ``"shm"`` (default) or ``"tcp"`` (loopback).
        autoreset_mode: gymnasium's ``AutoresetMode``: ``NEXT_STEP`` (the default, as AsyncVectorEnv: the step
            after an episode's end resets that sub-env and ignores its action), ``SAME_STEP`` (the step that ends
            an episode resets at once; ``info["final_obs"]`` and ``info["final_info"]`` hold the ended episode's
            last returns) or ``DISABLED`` (the caller resets, ``reset(options={"reset_mask": ...})``).
        backend: where the workers run: ``"local"`` (here, the default) or ``"ray"`` (each placed by Ray's scheduler
            on a node of the connected cluster, runtime/ray_backend.py; a spec's ``{"worker": {"ray": {"resources":
            {"rx200_arm": 1}}}}`` or ``node_id`` pins it, ``"worker": None`` keeps it here).
        envs_per_worker: how many envs one worker process hosts (consecutive specs with the same placement), each
            with its own connection, all stepped on the process's one event loop. ``"auto"`` (the default): one
            process per core where accelerated envs outnumber the cores (the envs of a process share its caches,
            where a core switching between processes pays more per step), one per env otherwise, and a real-time
            env (wall clock) always alone; decided before any env is built, from the specs' ``clock`` and their
            registrations (the rule: runtime/specs.py). A count >= 1 is taken as given; a real-time env in a shared
            process then fails to start with a WorkerError that says so. A process that dies takes its envs with
            it: the first is reported, or all are restarted together (each step truncated,
            ``info["worker_restarted"]``).
        rt_rank_base: the lowest real-time rank of these envs' loops (``Supervisor``): above another vector env's
            real-time envs on the same host (the evaluation envs beside the training envs), so they do not share
            its loops' priorities.
        loop_phase_base: the tick phase of the lowest-ranked of these envs' loops, in ``worker.LOOP_PHASE_STEP_NS``
            (None: ``rt_rank_base``, each loop's phase its rank): beside another vector env's real-time envs, a
            range of phases of their own (``alongside.phase_bases``).
        **common_kwargs: passed to every env given by id (a spec's own kwargs win), e.g. ``clock="sim"``; not
            with factories.

    Raises:
        ConfigError: a malformed spec (or ``num_envs`` with a list), a factory that cannot be pickled (or with
            ``backend="ray"``, or with ``common_kwargs``), an unknown id or a ``worker`` that is neither None nor a
            Ray placement (before any process starts), an unknown or invalid keyword argument (before any worker is
            given its env: the workers' interpreters, started meanwhile, are stopped), or spaces that cannot be padded
            or combined (naming the envs; the workers are closed).
        WorkerError: a worker failed to start or to build its env, or Ray could not place or start it (its index
            and traceback; the others are closed).
    """
    norm = normalize_specs(specs, common_kwargs, num_envs)
    if backend == "ray" and any(factory_of(kw) is not None for _, kw in norm):
        raise ConfigError(
            "backend='ray' places workers built from env ids (their nodes are sent plain data, not pickles); env "
            "factories are built by workers on this machine: give ids, or backend='local'"
        )
    norm = apply_backend(norm, backend)
    sup = Supervisor(
        norm,
        start_timeout_s=start_timeout_s,
        call_timeout_s=call_timeout_s,
        transport=transport,
        envs_per_worker=envs_per_worker,
        rt_rank_base=rt_rank_base,
        loop_phase_base=loop_phase_base,
    )
    try:
        return UnirosVectorEnv(
            sup,
            pad=pad,
            restart_on_failure=restart_on_failure,
            start_timeout_s=start_timeout_s,
            autoreset_mode=autoreset_mode,
        )
    except BaseException:
        sup.close()
        raise
