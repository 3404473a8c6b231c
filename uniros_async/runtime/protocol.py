"""The wire protocol between the supervisor and its workers: requests, replies and the step's own frames.

One frame per message, both directions: msgpack of plain data in which every numpy array travels as an ExtType
(code 42: dtype, shape, raw bytes) and numpy scalars as Python numbers (float32 and the like with their dtype),
converted by msgpack's own ``default`` /
``ext_hook`` hooks, so the C packer walks the message and Python sees only the arrays (a step reply costs less CPU
each way than a recursive walk in Python; ``to_wire``/``from_wire`` remain, for plain-data users). Anything else
msgpack cannot take travels as its ``repr`` (infos may hold odd objects). A request is
``{"op": ..., ...}``; a reply is ``{"ok": True, "result": ...}`` or ``{"ok": False, "error": "Type: message",
"traceback": "..."}``. A step, the hot path, has frames of its own (``pack_step_request``, ``pack_step_reply``;
first byte ``STEP_TAG``, which msgpack never uses): a fixed header (autoreset mode and reference time; reward and
flags), the action or observation as dtype/shape/bytes, the info in msgpack, so neither side builds or walks a
message map per step; ``unpack`` turns them into the same dicts. Spaces cross as plain data
(``space_to_plain``), never pickled.
"""

from __future__ import annotations

import struct
import traceback
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.bus.codec import array_bytes, array_from_bytes, array_head, encode_plain, pack_value, unpack_value
from uniros_async.errors import CodecError, ConfigError

__all__ = [
    "AUTORESET_MODES",
    "STEP_TAG",
    "PackedRequest",
    "array_head",
    "conform",
    "error_reply",
    "from_wire",
    "pack",
    "pack_step_reply",
    "pack_step_request",
    "reply_value",
    "result_value",
    "space_from_plain",
    "space_to_plain",
    "to_wire",
    "unpack",
    "unpack_step_reply_into",
]

AUTORESET_MODES = (None, "next_step", "same_step")


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


def pack(message: dict[str, Any] | PackedRequest) -> bytes:
    """One frame for ``message``.

    Raises:
        CodecError: ``message`` holds something that cannot be packed even as its repr.
    """
    if type(message) is PackedRequest:
        return message.frame
    try:
        return pack_value(message)
    except CodecError:
        # e.g. a dict key msgpack refuses: the slow, forgiving path, marked for unpack
        return encode_plain({"__to_wire__": to_wire(message)})


def unpack(frame: bytes | memoryview) -> dict[str, Any]:
    """The message in ``frame``.

    Raises:
        CodecError: the frame is not msgpack, or not a map (or a step frame that is malformed).
    """
    if frame and frame[0] == STEP_TAG:
        return _unpack_step(frame)
    msg = unpack_value(frame, "worker frame")
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
_MSGPACK, _ARRAY = 0, 1  # how the action (request) or observation (reply) travels: msgpack, or as ``codec.array_bytes``
_TERMINATED, _TRUNCATED = 1, 2
_EMPTY_MAP = 0x80  # msgpack's fixmap of no entries
_EMPTY_MAP_BYTES = bytes((_EMPTY_MAP,))
_FIXINTS = tuple(bytes((i,)) for i in range(128))
_MODE_INDEX = {mode: i for i, mode in enumerate(AUTORESET_MODES)}


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
    """(encoding, bytes) of an action or observation: an array of numbers as it is (``codec.array_bytes``: no msgpack
    ExtType and no hook on either side), anything else in msgpack."""
    kind = type(value)
    if kind is int and 0 <= value < 128:  # msgpack's positive fixint: the int's own byte (a Discrete action)
        return _MSGPACK, _FIXINTS[value]
    if kind is np.ndarray and not value.dtype.hasobject:
        return _ARRAY, array_bytes(value)
    return _MSGPACK, pack_value(value)


def pack_step_request(action: Any, autoreset: str | None, t: int | None) -> PackedRequest:
    """The frame of ``{"op": "step", "action": action, "autoreset": autoreset, "t": t}`` (no ``t`` when None) in the
    step's own format: a fixed header, then the action, so neither side builds or walks a map. ``unpack`` turns it
    back into that dict.

    Raises:
        ValueError: ``autoreset`` is not one of ``AUTORESET_MODES``.
    """
    try:
        mode = _MODE_INDEX[autoreset]
    except (KeyError, TypeError):
        raise ValueError(f"autoreset must be one of {AUTORESET_MODES}, got {autoreset!r}") from None
    enc, body = _part(action)
    return PackedRequest(_STEP_REQ.pack(STEP_TAG, _STEP_REQUEST, mode, enc, -1 if t is None else t) + body)


def pack_step_reply(result: list[Any]) -> bytes:
    """The reply frame of a step's ``[obs, reward, terminated, truncated, info]``: the reward and flags in a fixed
    header, the observation, then the info in msgpack. ``unpack`` turns it back into ``{"ok": True, "result":
    result}``."""
    obs, reward, terminated, truncated, info = result
    flags = (_TERMINATED if terminated else 0) | (_TRUNCATED if truncated else 0)
    try:
        enc, obs_part = _part(obs)
        info_part = pack_value(info) if info or type(info) is not dict else _EMPTY_MAP_BYTES
    except CodecError:  # something msgpack refuses: the general, forgiving path
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
    n = len(frame)
    if n < size:
        return None
    tag, kind, flags, enc, obs_len, reward = _STEP_REP.unpack_from(frame)
    if tag != STEP_TAG or kind != _STEP_REPLY or enc != _ARRAY:
        return None
    data = size + len(head)
    end = size + obs_len
    if end > n or end - data != len(out) or frame[size:data] != head:
        return None
    out[:] = frame[data:end]
    # an empty info is msgpack's empty map, one byte: the common case of a plain gymnasium env, read without msgpack
    info = {} if end == n - 1 and frame[end] == _EMPTY_MAP else _reply_info(frame, end)
    return reward, bool(flags & _TERMINATED), bool(flags & _TRUNCATED), info


def _reply_info(frame: bytes | memoryview, start: int) -> dict[str, Any]:
    """A step reply's info, the msgpack map from ``start`` to the frame's end.

    Raises:
        CodecError: not msgpack, or not a map.
    """
    info = unpack_value(frame[start:])
    if type(info) is not dict:
        raise CodecError(f"malformed step frame: a reply's info must be a map, got {type(info).__name__}")
    return info


def _unpart(enc: int, frame: bytes | memoryview, start: int, stop: int) -> Any:
    if enc == _MSGPACK:
        if stop - start == 1 and frame[start] < 0x80:  # msgpack's positive fixint (a Discrete action): its byte
            return frame[start]
        return unpack_value(frame[start:stop])
    if enc != _ARRAY:
        raise CodecError(f"malformed step frame: encoding {enc}; expected {_MSGPACK} (msgpack) or {_ARRAY} (array)")
    if stop > len(frame):
        raise CodecError(f"malformed step frame: {len(frame)} bytes, its array ends at {stop}")
    return array_from_bytes(frame, start, stop, "step frame")


def space_to_plain(space: gym.Space[Any]) -> dict[str, Any]:
    """A space as plain data (no pickles cross the wire): every space gymnasium's vector envs batch (Box of any
    shape and dtype, Discrete, MultiDiscrete, MultiBinary, Text, and Dict, Tuple, Sequence, OneOf and Graph nested
    in any way).

    A subclass of one of them (one that samples differently, say) travels as that space.

    Raises:
        ConfigError: another kind of space (a custom Space subclass), naming it.
    """
    spaces = gym.spaces
    known: tuple[type, ...] = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary, spaces.Text)
    known += (spaces.Dict, spaces.Tuple, spaces.Sequence, spaces.OneOf, spaces.Graph)
    t: type = next((c for c in type(space).__mro__ if c in known), type(space))
    if t is spaces.Box:
        b: Any = space
        return {"type": "Box", "low": b.low, "high": b.high, "dtype": np.dtype(b.dtype).str}
    if t is spaces.Discrete:
        d: Any = space
        return {"type": "Discrete", "n": int(d.n), "start": int(d.start), "dtype": np.dtype(d.dtype).str}
    if t is spaces.MultiDiscrete:
        m: Any = space
        return {"type": "MultiDiscrete", "nvec": m.nvec, "start": m.start, "dtype": np.dtype(m.dtype).str}
    if t is spaces.MultiBinary:
        mb: Any = space
        return {"type": "MultiBinary", "n": np.asarray(mb.n).tolist()}
    if t is spaces.Text:
        tx: Any = space
        charset = "".join(sorted(tx.character_set))
        return {"type": "Text", "max_length": tx.max_length, "min_length": tx.min_length, "charset": charset}
    if t is spaces.Dict:
        dd: Any = space
        return {"type": "Dict", "spaces": {k: space_to_plain(s) for k, s in dd.spaces.items()}}
    if t is spaces.Tuple:
        tt: Any = space
        return {"type": "Tuple", "spaces": [space_to_plain(s) for s in tt.spaces]}
    if t is spaces.Sequence:
        sq: Any = space
        return {"type": "Sequence", "space": space_to_plain(sq.feature_space), "stack": bool(sq.stack)}
    if t is spaces.OneOf:
        oo: Any = space
        return {"type": "OneOf", "spaces": [space_to_plain(s) for s in oo.spaces]}
    if t is spaces.Graph:
        g: Any = space
        edge = None if g.edge_space is None else space_to_plain(g.edge_space)
        return {"type": "Graph", "node_space": space_to_plain(g.node_space), "edge_space": edge}
    raise ConfigError(
        f"cannot send the space {space!r} between processes: expected Box, Discrete, MultiDiscrete, MultiBinary, "
        f"Text, Dict, Tuple, Sequence, OneOf or Graph (or a subclass of one), got {t.__name__}"
    )


def space_from_plain(plain: dict[str, Any]) -> gym.Space[Any]:
    """Inverse of ``space_to_plain``.

    Raises:
        ConfigError: an unknown space type.
    """
    kind = plain["type"]
    spaces = gym.spaces
    if kind == "Box":
        return spaces.Box(plain["low"], plain["high"], dtype=np.dtype(plain["dtype"]))
    if kind == "Discrete":
        return spaces.Discrete(plain["n"], start=plain["start"], dtype=np.dtype(plain.get("dtype", "<i8")))
    if kind == "MultiDiscrete":
        return spaces.MultiDiscrete(plain["nvec"], dtype=np.dtype(plain["dtype"]), start=plain["start"])
    if kind == "MultiBinary":
        return spaces.MultiBinary(plain["n"])
    if kind == "Text":
        return spaces.Text(plain["max_length"], min_length=plain["min_length"], charset=plain["charset"])
    if kind == "Dict":
        return spaces.Dict({k: space_from_plain(s) for k, s in plain["spaces"].items()})
    if kind == "Tuple":
        return spaces.Tuple([space_from_plain(s) for s in plain["spaces"]])
    if kind == "Sequence":
        return spaces.Sequence(space_from_plain(plain["space"]), stack=plain["stack"])
    if kind == "OneOf":
        return spaces.OneOf([space_from_plain(s) for s in plain["spaces"]])
    if kind == "Graph":
        edge = plain["edge_space"]
        return spaces.Graph(space_from_plain(plain["node_space"]), None if edge is None else space_from_plain(edge))
    raise ConfigError(f"unknown space type {kind!r}")


def conform(space: gym.Space[Any], value: Any) -> Any:
    """``value`` of ``space`` as it was before it crossed the wire: msgpack has no tuples (a Tuple's or a
    Sequence's element arrives as a list; a Graph's as a list of three). A Discrete's numpy scalar arrives as an
    int and stays one (as many envs return it).

    A value that does not fit ``space`` is returned as it is, as far as it does not (the env's own checks judge it).
    """
    t = type(space)
    spaces = gym.spaces
    if t is spaces.Box or t is spaces.MultiDiscrete or t is spaces.MultiBinary:
        return value if type(value) is np.ndarray else np.asarray(value, dtype=space.dtype)
    if t is spaces.Dict and type(value) is dict:
        sub: Any = space
        return {k: conform(sub.spaces[k], v) if k in sub.spaces else v for k, v in value.items()}
    if t is spaces.Tuple and isinstance(value, list | tuple):
        tt: Any = space
        return tuple(conform(s, v) for s, v in zip(tt.spaces, value, strict=False))
    if t is spaces.Sequence and isinstance(value, list | tuple):
        sq: Any = space
        if sq.stack:
            return value
        return tuple(conform(sq.feature_space, v) for v in value)
    if t is spaces.Graph and isinstance(value, list | tuple) and len(value) == 3:
        g: Any = space
        nodes, edges, links = value
        edges = None if edges is None or g.edge_space is None else np.asarray(edges, dtype=g.edge_space.dtype)
        links = None if links is None else np.asarray(links)
        return spaces.GraphInstance(np.asarray(nodes, dtype=g.node_space.dtype), edges, links)
    if t is spaces.OneOf and isinstance(value, list | tuple) and len(value) == 2:
        oo: Any = space
        return (np.int64(value[0]), conform(oo.spaces[int(value[0])], value[1]))
    return value


def reply_value(value: Any) -> Any:
    """A ``call``/``get`` result as it crosses the wire: a space as its plain form (``space_to_plain``), anything
    else as it is (``pack`` sends what msgpack cannot take as its repr). ``result_value`` undoes it."""
    if isinstance(value, gym.Space):
        try:
            return {_SPACE_KEY: space_to_plain(value)}
        except ConfigError:
            return repr(value)
    return value


def result_value(value: Any) -> Any:
    """Inverse of ``reply_value``."""
    if type(value) is dict and len(value) == 1 and _SPACE_KEY in value:
        return space_from_plain(value[_SPACE_KEY])
    return value


_SPACE_KEY = "__uniros_space__"


def error_reply(exc: BaseException, what: str) -> dict[str, Any]:
    """The reply that reports ``exc`` (raised while doing ``what``) with its traceback; the supervisor raises it as
    WorkerError."""
    return {
        "ok": False,
        "error": f"{what}: {type(exc).__name__}: {exc}",
        "type": type(exc).__name__,
        "traceback": "".join(traceback.format_exception(exc)),
    }
