"""The env worker process: one environment, served to the agent side over the project's own transports.

A worker is started by the supervisor (``multiprocessing.get_context("spawn")``, ``daemon=True``) with one frozen
``WorkerSpec``. It listens on ``shm://`` (a unique name), hands the listen URI to the supervisor through the
start-up pipe, accepts one connection, builds its env with ``gymnasium.make(env_id, **kwargs)`` and then answers
requests until told to close or until the supervisor goes away.

One event loop per worker (docs/architecture.md): a uniros env is made inside ``envs.runtime.deferred_start()`` and
started on the worker's own loop (``await env.astart()``), so its bus, servo sim and env loop run beside the
request handler, and a step is ``await env.astep(action)`` in the handler's own task: no loop thread, no hand-over
between threads, and the reply leaves as soon as the step's coroutine returns (before the rest of what the same
sim event woke runs). The wrappers gymnasium and ``make_vec`` put around it (OrderEnforcing, TimeLimit, PadSpaces)
are applied by ``astep_through`` / ``areset_through`` with the same semantics; an env with any other wrapper, or
one that is not a uniros BaseEnv, runs on a loop thread and is stepped through its synchronous API as before.

Wire format (both directions): one frame per message, msgpack of plain data in which every numpy array travels as
an ExtType (code 42: dtype, shape, raw bytes) and numpy scalars as Python numbers, converted by msgpack's own
``default`` / ``ext_hook`` hooks, so the C packer walks the message and Python sees only the arrays (a step
reply: ~10 us of CPU each way instead of ~13-33 us for a recursive walk in Python; ``to_wire``/``from_wire``
remain, for plain-data users). Anything else msgpack cannot take travels as its ``repr`` (infos may hold odd
objects). A request is ``{"op": ..., ...}``; a reply is ``{"ok": True, "result": ...}`` or ``{"ok": False,
"error": "Type: message", "traceback": "..."}``. A step, the hot path, has frames of its own (``pack_step_request``,
``pack_step_reply``; first byte ``STEP_TAG``, which msgpack never uses): a fixed header (autoreset mode and
reference time; reward and flags), the action or observation as dtype/shape/bytes, the info in msgpack, so
neither side builds or walks a message map per step; ``unpack`` turns them into the same dicts, and a worker
steps a synchronous env without a coroutine in between. An exception while serving a request is sent back (the
supervisor raises it as WorkerError) and the worker keeps serving; an exception while building the env is sent as
the reply to the first request, and the worker exits.

Lifetime: the worker ignores SIGINT (the agent's Ctrl-C is the supervisor's business), stops on SIGTERM
(the root task is cancelled, the env closed in ``finally``), and stops when the supervisor dies: the connection
breaks (EOF on the shm socket) and, as a backstop for a worker blocked in a long env call, a watchdog thread sees
the parent pid change, cancels the root task and, if that has not ended the process within ``exit_grace_s``,
calls ``os._exit``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import struct
import threading
import time
import traceback
from typing import Any

import gymnasium as gym
import msgpack
import numpy as np

from uniros_async._signals import cancel_on_signals
from uniros_async.bus.codec import decode_plain, encode_plain  # noqa: F401  (decode_plain: compatibility)
from uniros_async.errors import CodecError, ConfigError, TransportError

__all__ = [
    "WorkerSpec",
    "from_wire",
    "pack",
    "space_from_plain",
    "space_to_plain",
    "to_wire",
    "unpack",
    "worker_entry",
    "worker_main",
]

logger = logging.getLogger(__name__)

AUTORESET_MODES = (None, "next_step", "same_step")
LOOP_PHASE_STEP_NS = 1_000_000
"""A real-time env's loop ticks and step deadlines fall ``rt_rank`` times this much after the common grid
(``RobotEnv.loop_phase_ns``), so the members of a vector env tick and return one after the other, the
highest-ranked last. On one instant, four workers on 2 cores ran in priority order anyway, and the later ones
started whenever the others' variable work let them: the last reply, which the agent waits for, came 2.1 ms after
the deadline with an IQR of 0.43 ms. Staggered, each runs alone and the last reply comes from the worker with the
highest priority: IQR 0.1 ms (docs/perf/history.md). 1 ms is well above a worker's tick or return (0.2-0.4 ms when
its caches are cold); the first member's returns wait up to ``(n - 1)`` ms longer for the agent."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class WorkerSpec:
    """Everything a worker needs, fixed at start.

    Attributes:
        index: the sub-environment index (named in every WorkerError).
        env_id: a registered gymnasium id.
        kwargs: keyword arguments for ``gymnasium.make`` (plain, picklable data).
        parent_pid: the supervisor's pid; the worker exits when its parent changes.
        accept_timeout_s: how long the worker waits for the supervisor to connect.
        exit_grace_s: after the supervisor died, how long a clean shutdown may take before ``os._exit``.
        listen_uri: where the worker listens for the supervisor: ``shm://`` (a unique name; same machine) or
            ``tcp://127.0.0.1:0`` (a free port).
        auth_key: shared key the supervisor must prove (HMAC handshake) before the worker serves it; a worker
            started by a remote launcher listens on tcp with the launcher's key.
        rt_rank: for a real-time env, the rank of its SCHED_RR priority among the workers of its vector env
            (``priority.raise_loop_priority``; the supervisor gives the first worker the highest), and of its loop
            phase (``LOOP_PHASE_STEP_NS``).
    """

    index: int
    env_id: str
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    parent_pid: int = 0
    accept_timeout_s: float = 60.0
    exit_grace_s: float = 3.0
    listen_uri: str = "shm://"
    auth_key: bytes | None = None
    rt_rank: int = 0


# ---------------------------------------------------------------- wire format


def to_wire(value: Any) -> Any:
    """Plain data for msgpack: arrays as ``{"__nd__": [dtype, shape, bytes]}``, numpy scalars as Python ones,
    tuples as lists; anything else msgpack cannot take becomes its ``repr`` (infos may hold odd objects)."""
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        if a.dtype == object:
            return [to_wire(v) for v in a.tolist()]
        return {"__nd__": [a.dtype.str, list(a.shape), a.tobytes()]}
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str | bytes):
        return value
    if isinstance(value, dict):
        return {str(k): to_wire(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_wire(v) for v in value]
    return repr(value)


def from_wire(value: Any) -> Any:
    """Inverse of ``to_wire`` (arrays come back writable)."""
    if isinstance(value, dict):
        nd = value.get("__nd__")
        if nd is not None and len(value) == 1:
            dtype, shape, data = nd
            return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(shape).copy()
        return {k: from_wire(v) for k, v in value.items()}
    if isinstance(value, list):
        return [from_wire(v) for v in value]
    return value


_ND_EXT = 42
_SHAPE = struct.Struct("<q")


_PACKED_HEADS: dict[tuple[np.dtype[Any], tuple[int, ...]], bytes] = {}
"""Array headers by (dtype, shape), the packing side of ``_HEADS``: the same few every step (keyed by the dtype
itself: ``dtype.str`` builds a new string every call, which costs more than the lookup)."""


def _default(value: Any) -> Any:
    """msgpack's hook for what it cannot pack itself: arrays as ExtType, numpy scalars as Python ones."""
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            return value.tolist()
        return msgpack.ExtType(_ND_EXT, _array_part(value))
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple | list):  # subclasses msgpack refuses (named tuples are packed as lists)
        return list(value)
    return repr(value)


def _array_part(value: np.ndarray) -> bytes:
    """An array on the wire: a header (dtype string, ndim, shape; cached by dtype and shape) and the data in C
    order, whatever the strides. The payload of the array ExtType, and a step frame's array as it is."""
    head = _PACKED_HEADS.get((value.dtype, value.shape))
    if head is None:
        head = array_head(value.dtype, value.shape)
    return head + value.tobytes()


def array_head(dtype: np.dtype[Any], shape: tuple[int, ...]) -> bytes:
    """The header ``_array_part`` writes before the data of an array of ``dtype`` and ``shape``."""
    head = _PACKED_HEADS.get((dtype, shape))
    if head is None:
        d = dtype.str.encode()
        head = bytes((len(d),)) + d + bytes((len(shape),)) + b"".join(_SHAPE.pack(n) for n in shape)
        if len(_PACKED_HEADS) < 256:
            _PACKED_HEADS[(dtype, shape)] = head
    return head


_HEADS: dict[bytes, tuple[np.dtype[Any], tuple[int, ...], int]] = {}
"""Parsed array headers (dtype, shape, element count) by their bytes: a worker sees the same few every step, and
parsing one (a dtype from its string, a struct unpack per dimension) costs more than the array itself."""


def _array_from(buf: bytes | memoryview, start: int = 0, stop: int | None = None) -> np.ndarray:
    """The array ``_array_part`` wrote in ``buf[start:stop]``, as a writable copy.

    Raises:
        ValueError, TypeError, IndexError: not such an array (the data does not match its header, a bad dtype, too
            short); the callers turn these into CodecError.
    """
    stop = len(buf) if stop is None else stop
    n = buf[start]
    ndim = buf[start + 1 + n]
    data_start = start + 2 + n + 8 * ndim
    head = bytes(buf[start:data_start])
    parsed = _HEADS.get(head)
    if parsed is None:
        dtype = np.dtype(head[1 : 1 + n].decode())
        shape = tuple(_SHAPE.unpack_from(head, 2 + n + 8 * i)[0] for i in range(ndim))
        parsed = (dtype, shape, math.prod(shape))
        if len(_HEADS) < 256:
            _HEADS[head] = parsed
    dtype, shape, count = parsed
    if stop - data_start != count * dtype.itemsize:
        raise ValueError(f"an array of {dtype} {shape} needs {count * dtype.itemsize} bytes, got {stop - data_start}")
    return np.frombuffer(buf, dtype=dtype, count=count, offset=data_start).reshape(shape).copy()


def _ext_hook(code: int, data: bytes) -> Any:
    if code != _ND_EXT:
        return msgpack.ExtType(code, data)
    return _array_from(data)


def _str_list_keys(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    return {str(tuple(k)) if isinstance(k, list) else k: v for k, v in pairs}


_local = threading.local()


def _packb(value: Any) -> bytes:
    """``msgpack.packb(value, default=_default, use_bin_type=True)`` with a Packer kept per thread: ``packb`` builds
    a new Packer every call, which costs a quarter of packing a step reply (a Packer is not thread-safe: the
    ``default`` hook lets other threads run in the middle of a pack, hence one per thread). A pack that raises
    leaves the Packer reset."""
    packer = getattr(_local, "packer", None)
    if packer is None:
        packer = _local.packer = msgpack.Packer(default=_default, use_bin_type=True)
    return packer.pack(value)  # type: ignore[no-any-return]


def pack(message: dict[str, Any] | PackedRequest) -> bytes:
    """One frame for ``message``.

    Raises:
        CodecError: ``message`` holds something that cannot be packed even as its repr.
    """
    if type(message) is PackedRequest:
        return message.frame
    try:
        return _packb(message)
    except (TypeError, ValueError, OverflowError):
        # e.g. a dict key msgpack refuses: the slow, forgiving path, marked for unpack
        return encode_plain({"__to_wire__": to_wire(message)})


def unpack(frame: bytes | memoryview) -> dict[str, Any]:
    """The message in ``frame``.

    Raises:
        CodecError: the frame is not msgpack, or not a map (or a step frame that is malformed).
    """
    if frame and frame[0] == STEP_TAG:
        return _unpack_step(frame)
    msg = _unpackb(frame, "worker frame")
    if not isinstance(msg, dict):
        raise CodecError(f"expected a map, got {type(msg).__name__}")
    if "__to_wire__" in msg:
        msg = from_wire(msg["__to_wire__"])
        if not isinstance(msg, dict):
            raise CodecError(f"expected a map, got {type(msg).__name__}")
    return msg


# ------------------------------------------------------ the step's own frames

STEP_TAG = 0xC1
"""First byte of a step request or reply frame: a byte msgpack never uses, so no msgpack frame starts with it."""
_STEP_REQUEST, _STEP_REPLY = 1, 2
_STEP_REQ = struct.Struct("<BBBBq")  # tag, kind, autoreset mode (index in AUTORESET_MODES), body, reference time ns
_STEP_REP = struct.Struct("<BBBBId")  # tag, kind, flags, observation's encoding, observation's bytes, reward
_MSGPACK, _ARRAY = 0, 1  # how the action (request) or observation (reply) travels: msgpack, or as ``_array_part``
_TERMINATED, _TRUNCATED = 1, 2


class PackedRequest:
    """A step request already packed (``pack_step_request``): the supervisor sends ``frame`` as it is (``pack``
    returns it) and asks it only for its op, as of a message dict (``get("op")``)."""

    __slots__ = ("frame",)
    op = "step"

    def __init__(self, frame: bytes) -> None:
        self.frame = frame

    def get(self, key: str, default: Any = None) -> Any:
        return self.op if key == "op" else default


def _part(value: Any) -> tuple[int, bytes]:
    """(encoding, bytes) of an action or observation: an array of numbers as it is (``_array_part``: no msgpack
    ExtType and no hook on either side), anything else in msgpack."""
    if type(value) is np.ndarray and not value.dtype.hasobject:
        return _ARRAY, _array_part(value)
    return _MSGPACK, _packb(value)


def pack_step_request(action: Any, autoreset: str | None, t: int | None) -> PackedRequest:
    """The frame of ``{"op": "step", "action": action, "autoreset": autoreset, "t": t}`` (no ``t`` when None) in the
    step's own format: a fixed header, then the action, so neither side builds or walks a map. ``unpack`` turns it
    back into that dict.

    Raises:
        ValueError: ``autoreset`` is not one of ``AUTORESET_MODES``.
    """
    if autoreset not in AUTORESET_MODES:
        raise ValueError(f"autoreset must be one of {AUTORESET_MODES}, got {autoreset!r}")
    enc, body = _part(action)
    mode = AUTORESET_MODES.index(autoreset)
    return PackedRequest(_STEP_REQ.pack(STEP_TAG, _STEP_REQUEST, mode, enc, -1 if t is None else t) + body)


def pack_step_reply(result: list[Any]) -> bytes:
    """The reply frame of a step's ``[obs, reward, terminated, truncated, info]``: the reward and flags in a fixed
    header, the observation, then the info in msgpack. ``unpack`` turns it back into ``{"ok": True, "result":
    result}``."""
    obs, reward, terminated, truncated, info = result
    flags = (_TERMINATED if terminated else 0) | (_TRUNCATED if truncated else 0)
    try:
        enc, obs_part = _part(obs)
        info_part = _packb(info)
    except (TypeError, ValueError, OverflowError):  # something msgpack refuses: the general, forgiving path
        return pack({"ok": True, "result": result})
    return _STEP_REP.pack(STEP_TAG, _STEP_REPLY, flags, enc, len(obs_part), reward) + obs_part + info_part


def _unpack_step(frame: bytes | memoryview) -> dict[str, Any]:
    """The message in a frame that starts with STEP_TAG (see ``pack_step_request`` / ``pack_step_reply``)."""
    kind = frame[1] if len(frame) > 1 else None
    size = _STEP_REQ.size if kind == _STEP_REQUEST else _STEP_REP.size
    if len(frame) < size:
        raise CodecError(f"malformed step frame: {len(frame)} bytes, the header alone is {size}")
    if kind == _STEP_REQUEST:
        _, _, mode, enc, t = _STEP_REQ.unpack_from(frame)
        if mode >= len(AUTORESET_MODES):
            raise CodecError(f"malformed step frame: autoreset mode {mode}; expected 0-{len(AUTORESET_MODES) - 1}")
        msg = {"op": "step", "action": _unpart(enc, frame, size, len(frame)), "autoreset": AUTORESET_MODES[mode]}
        if t >= 0:
            msg["t"] = t
        return msg
    if kind == _STEP_REPLY:
        _, _, flags, enc, obs_len, reward = _STEP_REP.unpack_from(frame)
        obs = _unpart(enc, frame, size, size + obs_len)
        info = _reply_info(frame, size + obs_len)
        return {"ok": True, "result": [obs, reward, bool(flags & _TERMINATED), bool(flags & _TRUNCATED), info]}
    raise CodecError(f"malformed step frame: kind {kind}; expected {_STEP_REQUEST} (request) or {_STEP_REPLY} (reply)")


def unpack_step_reply_into(
    frame: bytes | memoryview, out: memoryview, head: bytes
) -> tuple[float, bool, bool, dict[str, Any]] | None:
    """A step reply's reward, terminated, truncated and info, with its observation's bytes copied straight into
    ``out`` (the bytes of a sub-env's row of the vector observation), when the observation is an array whose
    header is ``head`` (``array_head``) and whose data fills ``out``: one copy from the frame, no array of its own to
    make and stack. None when it is not such a reply (nothing is written then): ``unpack`` takes it.

    Raises:
        CodecError: the info is not a map, or not msgpack.
    """
    size = _STEP_REP.size
    if len(frame) < size or frame[0] != STEP_TAG or frame[1] != _STEP_REPLY:
        return None
    _, _, flags, enc, obs_len, reward = _STEP_REP.unpack_from(frame)
    data = size + len(head)
    end = size + obs_len
    if enc != _ARRAY or end > len(frame) or end - data != len(out) or frame[size:data] != head:
        return None
    out[:] = frame[data:end]
    return reward, bool(flags & _TERMINATED), bool(flags & _TRUNCATED), _reply_info(frame, end)


def _reply_info(frame: bytes | memoryview, start: int) -> dict[str, Any]:
    """A step reply's info, the msgpack map from ``start`` to the frame's end.

    Raises:
        CodecError: not msgpack, or not a map.
    """
    info = _unpackb(frame[start:])
    if type(info) is not dict:
        raise CodecError(f"malformed step frame: a reply's info must be a map, got {type(info).__name__}")
    return info


def _unpart(enc: int, frame: bytes | memoryview, start: int, stop: int) -> Any:
    if enc == _MSGPACK:
        return _unpackb(frame[start:stop])
    if enc != _ARRAY:
        raise CodecError(f"malformed step frame: encoding {enc}; expected {_MSGPACK} (msgpack) or {_ARRAY} (array)")
    if stop > len(frame):
        raise CodecError(f"malformed step frame: {len(frame)} bytes, its array ends at {stop}")
    try:
        return _array_from(frame, start, stop)
    except (ValueError, TypeError, IndexError) as exc:
        raise CodecError(f"malformed step frame: {exc}") from exc


def _unpackb(data: bytes | memoryview, what: str = "step frame") -> Any:
    """msgpack's unpackb with the worker protocol's hooks; map keys that came as lists (tuple keys) as their str,
    as ``to_wire`` does.

    Raises:
        CodecError: ``data`` is not msgpack (named ``what``).
    """
    try:
        try:
            return msgpack.unpackb(data, raw=False, strict_map_key=False, ext_hook=_ext_hook)
        except TypeError:  # a map key that came as a list (a tuple key)
            return msgpack.unpackb(
                data, raw=False, strict_map_key=False, ext_hook=_ext_hook, object_pairs_hook=_str_list_keys
            )
    except (ValueError, TypeError, IndexError, msgpack.UnpackException) as exc:
        raise CodecError(f"malformed {what}: {exc}") from exc


def space_to_plain(space: gym.Space[Any]) -> dict[str, Any]:
    """Box, Discrete and Dict spaces as plain data (no pickles cross the wire).

    Raises:
        ConfigError: another kind of space.
    """
    if isinstance(space, gym.spaces.Box):
        return {"type": "Box", "low": space.low, "high": space.high, "dtype": np.dtype(space.dtype).str}
    if isinstance(space, gym.spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, gym.spaces.Dict):
        return {"type": "Dict", "spaces": {k: space_to_plain(s) for k, s in space.spaces.items()}}
    raise ConfigError(f"expected a Box, Discrete or Dict space, got {space}")


def space_from_plain(plain: dict[str, Any]) -> gym.Space[Any]:
    """Inverse of ``space_to_plain``."""
    kind = plain["type"]
    if kind == "Box":
        return gym.spaces.Box(plain["low"], plain["high"], dtype=np.dtype(plain["dtype"]))
    if kind == "Discrete":
        return gym.spaces.Discrete(plain["n"], start=plain["start"])
    if kind == "Dict":
        return gym.spaces.Dict({k: space_from_plain(s) for k, s in plain["spaces"].items()})
    raise ConfigError(f"unknown space type {kind!r}")


# ---------------------------------------------------------------- the worker


def _real_time(kwargs: dict[str, Any]) -> bool:
    """Whether an env made with ``kwargs`` runs an env loop on the wall clock (the default)."""
    clock = kwargs.get("clock")
    if clock is None:
        clock = "sim" if kwargs.get("turn_based") else "wall"
    return clock == "wall"


def worker_entry(spec: WorkerSpec, conn: multiprocessing.connection.Connection) -> None:
    """Process target: run ``worker_main`` and exit."""
    # The agent's Ctrl-C reaches every process of the group; the supervisor decides how workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # multiprocessing forbids children of daemon processes; an env with robot="sim-process" or "emulated-real"
    # starts its own servo process (itself daemonic, and it exits with us). Clearing the flag in this process only
    # changes what this process believes about itself; the supervisor still treats us as daemonic.
    multiprocessing.current_process()._config["daemon"] = False  # type: ignore[attr-defined]
    if _real_time(spec.kwargs):  # its env loop must wake on time beside learners and other loops
        from uniros_async.priority import raise_loop_priority

        raise_loop_priority(spec.rt_rank)
    try:
        asyncio.run(worker_main(spec, conn))
    except (KeyboardInterrupt, asyncio.CancelledError):
        pass
    finally:
        conn.close()


def _start_watchdog(spec: WorkerSpec, loop: asyncio.AbstractEventLoop, task: asyncio.Task[Any]) -> None:
    parent = spec.parent_pid or os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.1)
        logger.warning("worker %d: supervisor %d is gone; stopping", spec.index, parent)
        try:
            loop.call_soon_threadsafe(task.cancel)
        except RuntimeError:  # the loop already closed: we are exiting anyway
            return
        time.sleep(spec.exit_grace_s)
        os._exit(1)

    threading.Thread(target=watch, name=f"uniros-worker-{spec.index}-watchdog", daemon=True).start()


# ---------------------------------------------------------------- async stepping through known wrappers


def _async_wrappers() -> tuple[type, ...]:
    from uniros_async.envs import wrappers as uw

    return (gym.wrappers.OrderEnforcing, gym.wrappers.TimeLimit, uw.TimeLimit, uw.PadSpaces)


def supports_async(env: gym.Env[Any, Any]) -> bool:
    """Whether ``env`` is an attached uniros BaseEnv under wrappers that ``astep_through`` knows (exact types)."""
    from uniros_async.envs.base import BaseEnv

    known = _async_wrappers()
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if type(e) not in known:
            return False
        e = e.env
    return isinstance(e, BaseEnv) and e.attached and type(e).step is BaseEnv.step and type(e).reset is BaseEnv.reset


async def astep_through(env: Any, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
    """``env.step(action)`` for a stack ``supports_async`` accepted, awaiting the base env's ``astep``."""
    from uniros_async.envs import wrappers as uw

    t = type(env)
    if t is uw.PadSpaces:
        a = np.asarray(action, dtype=np.float32)
        if a.shape != env.action_space.shape:
            raise gym.error.InvalidAction(f"action must have shape {env.action_space.shape}, got {a.shape}")
        obs, reward, terminated, truncated, info = await astep_through(env.env, a[: env._n_act])
        return env._pad(obs), reward, terminated, truncated, {**info, "padding": dict(env.padding)}
    if t is gym.wrappers.OrderEnforcing:
        if not env._has_reset:
            raise gym.error.ResetNeeded("Cannot call env.step() before calling env.reset()")
        return await astep_through(env.env, action)
    if t is gym.wrappers.TimeLimit or t is uw.TimeLimit:
        obs, reward, terminated, truncated, info = await astep_through(env.env, action)
        env._elapsed_steps += 1
        if env._elapsed_steps >= env._max_episode_steps:
            truncated = True
        if t is uw.TimeLimit and truncated and not terminated:
            info = {**info, "is_success": False}
        return obs, reward, terminated, truncated, info
    return await env.astep(action)  # type: ignore[no-any-return]


async def areset_through(env: Any, seed: int | None, options: dict[str, Any] | None) -> tuple[Any, dict[str, Any]]:
    """``env.reset(seed=seed, options=options)`` for a stack ``supports_async`` accepted."""
    from uniros_async.envs import wrappers as uw

    t = type(env)
    if t is uw.PadSpaces:
        obs, info = await areset_through(env.env, seed, options)
        return env._pad(obs), {**info, "padding": dict(env.padding)}
    if t is gym.wrappers.OrderEnforcing:
        env._has_reset = True
        return await areset_through(env.env, seed, options)
    if t is gym.wrappers.TimeLimit or t is uw.TimeLimit:
        env._elapsed_steps = 0
        return await areset_through(env.env, seed, options)
    return await env.areset(seed=seed, options=options)  # type: ignore[no-any-return]


async def worker_main(spec: WorkerSpec, conn: multiprocessing.connection.Connection) -> None:
    """Listen, hand the URI over ``conn``, accept the supervisor, build the env, serve until closed."""
    from uniros_async.transports.base import listen

    loop = asyncio.get_running_loop()
    task = cancel_on_signals(signal.SIGTERM)
    _start_watchdog(spec, loop, task)
    from uniros_async.transports.base import TransportOptions

    listener = await listen(spec.listen_uri, TransportOptions(auth_key=spec.auth_key))
    transport = None
    server = _Server(spec)
    try:
        conn.send(listener.uri)
        async with asyncio.timeout(spec.accept_timeout_s):
            transport = await listener.accept()
        await listener.aclose()
        await server.build()
        if hasattr(transport, "spin_ns"):  # shm and tcp
            # a real-time env loop shares this event loop now: its ticks matter more than the wake-up a poll
            # for the next request would save, and the poll would hold the loop (up to 50 us)
            transport.spin_ns = 0 if server.realtime else turn_spin_ns(transport)
        if hasattr(transport, "on_shared_core") and not server.realtime:
            transport.on_shared_core = _move_off_core
        await server.serve(transport)
    except TransportError:
        logger.info("worker %d: the supervisor went away", spec.index)
    finally:
        await server.aclose()
        if transport is not None:
            await transport.aclose()
        await listener.aclose()


TURN_SPIN_NS = 200_000
"""How long a worker without a real-time env loop polls for the next request before it sleeps: the agent's turn
between two steps (collect the returns, pick the next actions, pack them: ~60 us for one env here) is longer than
``ShmTransport.spin_ns``, so with the default every step would wake the worker from sleep (~40 us on an idle core).
The spin credit still stops the polling when requests come slower than this (a learner's update between steps).
Not for a tcp connection on loopback: see ``turn_spin_ns``."""


def turn_spin_ns(transport: Any) -> int:
    """How long this worker polls for its next request: ``TURN_SPIN_NS``, but a tcp connection on loopback keeps
    the transport's own ``spin_ns`` (50 us). A socket wakes its reader with a sync wake-up (the kernel is told that
    the waker is about to sleep), which places a woken worker on its agent's core, and tcp carries no hint of where
    the peer runs for a poll to see (shm's ``ShmTransport._peer_here``). There a 200 us poll held the agent off its
    own core for the whole window: two tcp vector envs stepped in turn took ~400 us a step, ~140 us with 50 us
    polls, while one env's steps cost the same with either (docs/perf/history.md). A worker on another host never
    shares its agent's core and keeps the longer poll."""
    if getattr(transport, "scheme", None) == "tcp":
        try:
            if ipaddress.ip_address(transport.sockname[0]).is_loopback:
                return int(transport.spin_ns)
        except (AssertionError, ValueError):  # closed (no socket), or not an IP address
            pass
    return TURN_SPIN_NS


def _move_off_core(cpu: int) -> None:
    """Move this worker off ``cpu``, its agent's core (``ShmTransport.on_shared_core``): the scheduler often wakes a
    worker on the core of the agent that woke it (in a VM, whose halted vCPU looks busy, nearly always), and the two
    then take turns on one core while the other idles. Pinned away for a moment, then allowed everywhere again: the
    worker stays on its new core until a later wake-up places it anew."""
    try:
        allowed = os.sched_getaffinity(0)
        others = allowed - {cpu}
        if others:
            os.sched_setaffinity(0, others)  # migrates at once
            os.sched_setaffinity(0, allowed)
    except OSError as exc:  # not permitted here: the turns on one core go on, correct if slower
        logger.debug("could not move off cpu %d: %s", cpu, exc)


class _Server:
    """The env and the request handlers of one worker."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self.env: gym.Env[Any, Any] | None = None
        self.build_error: dict[str, Any] | None = None
        self.needs_autoreset = False
        self.attached = False  # the env runs on this process's event loop and is stepped with astep_through
        self.realtime = False  # ... and its env loop follows the wall clock

    async def build(self) -> None:
        import uniros_async  # noqa: F401  (registers the uniros ids in this fresh interpreter)
        from uniros_async.envs.base import BaseEnv
        from uniros_async.envs.runtime import deferred_start

        try:
            with deferred_start():
                self.env = env = gym.make(self.spec.env_id, **self.spec.kwargs)
            base = env.unwrapped
            realtime = getattr(getattr(base, "config", None), "clock", "sim") != "sim"
            if realtime and hasattr(base, "loop_phase_ns"):
                base.loop_phase_ns = self.spec.rt_rank * LOOP_PHASE_STEP_NS  # before its loop starts
            if isinstance(base, BaseEnv) and base.attached:
                if supports_async(env):
                    await base.astart()
                    self.attached = True
                    self.realtime = realtime
                else:
                    base.start_thread()  # unknown wrappers: the synchronous API over a loop thread, as in-process
        except gym.error.UnregisteredEnv as exc:  # registered where the caller runs, as it was checked there
            where = (
                "this worker is a fresh interpreter, where only the uniros ids, gymnasium's own and the ids that "
                "modules imported at start-up register exist: register the env when a module is imported and name it "
                "'module:Id', or register it at the top level of the main script (not under "
                "if __name__ == '__main__')"
            )
            self.build_error = _error_reply(exc, f"could not make {self.spec.env_id} ({where})")
        except Exception as exc:  # noqa: BLE001 - sent back to the supervisor
            self.build_error = _error_reply(exc, f"could not make {self.spec.env_id}")

    async def serve(self, transport: Any) -> None:
        try_send = getattr(transport, "try_send", None)  # shm, tcp: a step's reply leaves without a coroutine
        while True:
            frame = await transport.receive()
            try:
                request = unpack(frame)
            except Exception as exc:  # noqa: BLE001
                await transport.send(pack(_error_reply(exc, "bad request")))
                continue
            op = request.get("op")
            if self.build_error is not None:
                await transport.send(pack(self.build_error))
                return
            try:
                if op == "step" and not self.attached:  # a synchronous env's step: no coroutine in the way
                    result = self._step_now(request["action"], request.get("autoreset"))
                else:
                    result = await self.handle(op, request)
            except Exception as exc:  # noqa: BLE001 - sent back; the env stays usable when it can
                reply = _error_reply(exc, f"{op} failed")
            else:
                if op == "step":
                    frame = pack_step_reply(result)
                    if try_send is None or not try_send(frame):
                        await transport.send(frame)
                    continue
                reply = {"ok": True, "result": result}
            await transport.send(pack(reply))
            if op == "close":
                return

    async def handle(self, op: Any, request: dict[str, Any]) -> Any:
        env = self.env
        assert env is not None
        if op == "step":
            ref = request.get("t")
            if ref is not None and self.attached:
                base: Any = env.unwrapped
                base.step_reference_ns = ref  # see RobotEnv._step_deadline
            return await self._step(request["action"], request.get("autoreset"))
        if op == "spaces":
            return self._spaces()
        if op == "pad":
            from uniros_async.envs.wrappers import PadSpaces

            self.env = PadSpaces(env, int(request["obs_size"]), int(request["action_size"]))
            return self._spaces()
        if op == "reset":
            self.needs_autoreset = False
            obs, info = await self._reset(request.get("seed"), request.get("options"))
            return [obs, self._info(info)]
        if op == "call":
            name = request["name"]
            if name.startswith("_"):
                raise AttributeError(f"refusing to call private attribute {name!r}")
            attr = getattr(env, name) if hasattr(env, name) else getattr(env.unwrapped, name)
            return attr(*request.get("args", []), **request.get("kwargs", {})) if callable(attr) else attr
        if op == "get":
            name = request["name"]
            return getattr(env, name) if hasattr(env, name) else getattr(env.unwrapped, name)
        if op == "set":
            setattr(env.unwrapped, request["name"], request["value"])
            return None
        if op == "close":
            await self.aclose()
            return None
        raise ValueError(f"unknown op {op!r}; expected spaces, pad, reset, step, call, get, set or close")

    def _spaces(self) -> dict[str, Any]:
        env = self.env
        assert env is not None
        return {
            "observation_space": space_to_plain(env.observation_space),
            "action_space": space_to_plain(env.action_space),
            "metadata": {k: v for k, v in env.metadata.items() if isinstance(v, int | float | str | list)},
            "max_episode_steps": env.spec.max_episode_steps if env.spec is not None else None,
            "pid": os.getpid(),
            "realtime": self.realtime,  # a real-time env loop shares this worker's event loop
        }

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        return {**info, "env_id": self.spec.env_id}

    async def _reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        env = self.env
        assert env is not None
        if self.attached:
            return await areset_through(env, seed, options)
        return env.reset(seed=seed, options=options)

    async def _step(self, action: Any, autoreset: str | None) -> list[Any]:
        env = self.env
        assert env is not None
        if not self.attached:
            return self._step_now(action, autoreset)
        if self._reset_instead(autoreset):
            obs, info = await self._reset()
            return [obs, 0.0, False, False, self._info(info)]
        result, reset = self._returns(*await astep_through(env, action), autoreset)
        if reset:
            result[0], _ = await self._reset()
        return result

    def _step_now(self, action: Any, autoreset: str | None) -> list[Any]:
        """``_step`` for an env stepped through its synchronous API (not attached), in the caller's frame."""
        env = self.env
        assert env is not None
        if self._reset_instead(autoreset):
            obs, info = env.reset()
            return [obs, 0.0, False, False, self._info(info)]
        result, reset = self._returns(*env.step(action), autoreset)
        if reset:
            result[0], _ = env.reset()
        return result

    def _reset_instead(self, autoreset: str | None) -> bool:
        """Whether this step resets instead (gymnasium's NEXT_STEP mode: the step after an episode's end resets and
        ignores the action).

        Raises:
            ValueError: an unknown autoreset mode.
        """
        if autoreset not in AUTORESET_MODES:
            raise ValueError(f"autoreset must be one of {AUTORESET_MODES}, got {autoreset!r}")
        if autoreset == "next_step" and self.needs_autoreset:
            self.needs_autoreset = False
            return True
        return False

    def _returns(
        self, obs: Any, reward: Any, terminated: Any, truncated: Any, info: dict[str, Any], autoreset: str | None
    ) -> tuple[list[Any], bool]:
        """A step's reply, and whether its observation must now be replaced by a reset's (SB3's SAME_STEP
        convention: the final observation goes in the info)."""
        done = bool(terminated or truncated)
        info = self._info(info)
        if autoreset == "next_step":
            self.needs_autoreset = done
        elif autoreset == "same_step" and done:
            return [obs, float(reward), bool(terminated), bool(truncated), {**info, "final_obs": obs}], True
        return [obs, float(reward), bool(terminated), bool(truncated), info], False

    async def aclose(self) -> None:
        env, self.env = self.env, None
        if env is None:
            return
        if self.attached:
            base: Any = env.unwrapped
            await base.aclose()  # the wrappers' close() only passes close on
        else:
            env.close()


def _error_reply(exc: BaseException, what: str) -> dict[str, Any]:
    return {
        "ok": False,
        "error": f"{what}: {type(exc).__name__}: {exc}",
        "type": type(exc).__name__,
        "traceback": "".join(traceback.format_exception(exc)),
    }
