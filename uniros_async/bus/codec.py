"""The one module that knows msgpack: messages <-> frames.

A frame is::

    u32 body_len (little endian) | body (msgpack) | zero padding to 8 bytes | array blobs, each 8-aligned

``body`` is ``[type_name, [field values in declaration order], [[dtype, shape, offset], ...]]``. An array field
is an ExtType(1) whose data is the index into that table; the blob bytes travel beside the msgpack body, so a
900 KiB image costs no msgpack copy and the receiver views it in place (``np.frombuffer`` on the frame).
``encode`` returns the frame as a list of buffers (header bytes, then each array's own memory, no join), which
transports send back to back. ``decode`` checks the type name, field count, dtypes and ndims, and raises
CodecError naming the field; a frame that lacks trailing fields with a default (from a publisher older than a field
added to its message) decodes with those defaults.

Two more encodings live here, so that this stays the only module that imports msgpack:

- plain data (``encode_plain`` / ``decode_plain``): the registry's and handshakes' control traffic;
- values with arrays (``pack_value`` / ``unpack_value``): the worker protocol's messages (runtime/protocol.py), in
  which every numpy array travels as an ExtType (code 42: ``array_bytes``, dtype, shape and raw bytes), numpy
  float64, int64 and bool scalars as Python numbers and other numpy scalars as an ExtType (code 43: their dtype
  kept), converted by msgpack's own ``default`` / ``ext_hook`` hooks, so the C packer walks
  the value and Python sees only the arrays. ``array_bytes`` / ``array_from_bytes`` are also the step frames' own
  array format, outside msgpack.
"""

from __future__ import annotations

import math
import re
import struct
import threading
from collections.abc import Callable, Sequence
from typing import Any

import msgpack
import numpy as np

from uniros_async.bus.messages import FieldSpec, message_type
from uniros_async.errors import CodecError

__all__ = [
    "array_bytes",
    "array_from_bytes",
    "array_head",
    "decode",
    "decode_plain",
    "encode",
    "encode_plain",
    "frame_type_name",
    "pack_value",
    "unpack_value",
]

_ARRAY_EXT = 1
_U32 = struct.Struct("<I")
_PAD = bytes(8)
_EXT_CACHE = [msgpack.ExtType(_ARRAY_EXT, _U32.pack(i)) for i in range(64)]


def _ext(i: int) -> msgpack.ExtType:
    return _EXT_CACHE[i] if i < len(_EXT_CACHE) else msgpack.ExtType(_ARRAY_EXT, _U32.pack(i))


def _fields_to_list(msg: Any, arrays: list[np.ndarray]) -> list[Any]:
    out: list[Any] = []
    for spec in msg.__uniros_schema__:
        value = getattr(msg, spec.name)
        if value is None:
            out.append(None)
        elif spec.kind == "array":
            arrays.append(value)
            out.append(_ext(len(arrays) - 1))
        elif spec.kind == "message":
            out.append(_fields_to_list(value, arrays))
        else:
            out.append(value)
    return out


def encode(msg: Any, blob_offset: int = 0) -> list[bytes | memoryview]:
    """Encode a message into frame parts (send them back to back as one frame).

    The arrays' own memory is referenced, not copied: do not mutate them until the frame was sent.
    ``blob_offset``: the arrays' offsets in the table start there (a loaned frame whose array was written in place
    further into the frame, bus/_loan.py).

    Raises:
        CodecError: ``msg`` is not a registered message, or a field is not msgpack-able (named).
    """
    try:
        schema = msg.__uniros_schema__
    except AttributeError:
        raise CodecError(f"expected a @message instance, got {type(msg).__name__}") from None
    del schema
    arrays: list[np.ndarray] = []
    values = _fields_to_list(msg, arrays)
    table: list[list[Any]] = []
    blobs: list[bytes | memoryview] = []
    offset = blob_offset
    for a in arrays:
        if not a.flags.c_contiguous:
            a = np.ascontiguousarray(a)
        table.append([a.dtype.str, list(a.shape), offset])
        n = a.nbytes
        blobs.append(a.data.cast("B") if n else b"")
        pad = -n % 8
        if pad:
            blobs.append(_PAD[:pad])
        offset += n + pad
    try:
        body = msgpack.packb([type(msg).__name__, values, table], use_bin_type=True)
    except (TypeError, ValueError) as exc:
        raise CodecError(f"{type(msg).__name__}: a field is not msgpack-able: {exc}") from exc
    head_len = 4 + len(body)
    head = _U32.pack(len(body)) + body + _PAD[: -head_len % 8]
    if not blobs:
        return [head]
    return [head, *blobs]


def _ext_hook(code: int, data: bytes) -> Any:
    if code == _ARRAY_EXT:
        if len(data) != _U32.size:
            raise CodecError(f"array reference of {len(data)} bytes, expected {_U32.size}")
        return _ArrayRef(_U32.unpack(data)[0])
    raise CodecError(f"unknown msgpack extension type {code}")


class _ArrayRef:
    __slots__ = ("index",)

    def __init__(self, index: int) -> None:
        self.index = index


def frame_type_name(frame: bytes | memoryview) -> str:
    """The message type name of a frame, without decoding the rest (for introspection and filtering)."""
    view = memoryview(frame)
    body_len, head_len = _check_head(view)
    try:
        unp = msgpack.Unpacker(raw=False, ext_hook=_ext_hook)
        unp.feed(view[4 : 4 + body_len])
        unp.read_array_header()
        name = unp.unpack()
    except (ValueError, msgpack.UnpackException) as exc:
        raise CodecError(f"malformed frame body: {exc}") from exc
    if not isinstance(name, str):
        raise CodecError(f"malformed frame: type name is {type(name).__name__}, expected str")
    return name


def _check_head(view: memoryview) -> tuple[int, int]:
    if view.nbytes < 4:
        raise CodecError(f"frame of {view.nbytes} bytes is shorter than its 4-byte header")
    (body_len,) = _U32.unpack_from(view, 0)
    head_len = 4 + body_len
    head_len += -head_len % 8
    if 4 + body_len > view.nbytes:
        raise CodecError(f"frame announces a {body_len}-byte body but holds only {view.nbytes - 4} bytes")
    return body_len, head_len


def decode(frame: bytes | memoryview, expected: type | None = None) -> Any:
    """Decode a frame; array fields are read-only views into ``frame`` when it is read-only (no copy).

    Args:
        frame: the whole frame.
        expected: if given, the frame must hold this message type.

    Raises:
        CodecError: malformed frame, unknown type, a type other than ``expected``, or a field of the wrong
            kind, dtype, ndim or shape (the message names the field).
    """
    view = memoryview(frame)
    if view.format != "B" or view.ndim != 1:
        view = view.cast("B")
    body_len, head_len = _check_head(view)
    try:
        body = msgpack.unpackb(view[4 : 4 + body_len], raw=False, ext_hook=_ext_hook, strict_map_key=False)
        name, values, table = body
    except CodecError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise CodecError(f"malformed frame body: {exc}") from exc
    cls = message_type(name) if isinstance(name, str) else None
    if cls is None:
        raise CodecError(f"malformed frame: type name is {type(name).__name__}, expected str")
    if expected is not None and cls is not expected:
        raise CodecError(f"expected {expected.__name__}, got {name}")
    blob = view[head_len:]
    return _build(cls, values, table, blob)


def _array(spec: FieldSpec, cls: type, ref: _ArrayRef, table: list[Any], blob: memoryview) -> np.ndarray:
    try:
        dtype_str, shape, offset = table[ref.index]
        if type(dtype_str) is not str or type(offset) is not int:
            raise TypeError(f"expected [dtype str, shape, offset int], got {table[ref.index]!r:.80}")
        dtype = np.dtype(dtype_str)
        count = 1
        for s in shape:
            if type(s) is not int or s < 0:
                raise ValueError(f"shape {shape!r:.80} must hold integers >= 0")
            count *= s
    except (IndexError, TypeError, ValueError, SyntaxError) as exc:  # numpy parses some dtype strings with ast
        raise CodecError(f"{cls.__name__}.{spec.name}: malformed array table entry: {exc}") from exc
    if dtype != spec.dtype:
        raise CodecError(f"{cls.__name__}.{spec.name}: expected dtype {spec.dtype}, got {dtype}")
    if len(shape) != spec.ndim:
        raise CodecError(f"{cls.__name__}.{spec.name}: expected ndim {spec.ndim}, got shape {tuple(shape)}")
    nbytes = count * dtype.itemsize
    if offset < 0 or offset + nbytes > blob.nbytes:
        raise CodecError(f"{cls.__name__}.{spec.name}: array of {nbytes} bytes at offset {offset} overruns the frame")
    a = np.frombuffer(blob, dtype=dtype, count=count, offset=offset)
    return a if len(shape) == 1 else a.reshape(shape)


def _build(cls: type, values: Any, table: list[Any], blob: memoryview) -> Any:
    schema: Sequence[FieldSpec] = cls.__uniros_schema__  # type: ignore[attr-defined]
    if type(values) is not list or len(values) != len(schema):
        required: int = cls.__uniros_required__  # type: ignore[attr-defined]
        if type(values) is not list or not required <= len(values) < len(schema):
            n = len(values) if isinstance(values, list) else type(values).__name__
            expected = len(schema) if required == len(schema) else f"{required} to {len(schema)}"
            raise CodecError(f"{cls.__name__}: expected {expected} fields, got {n}")
        schema = schema[: len(values)]  # an older publisher's frame: the fields it lacks take their defaults
    kwargs: dict[str, Any] = {}
    for spec, value in zip(schema, values, strict=True):
        kind = spec.kind
        if value is None:
            kwargs[spec.name] = None
        elif kind == "array":
            if type(value) is not _ArrayRef:
                raise CodecError(f"{cls.__name__}.{spec.name}: expected an array, got {type(value).__name__}")
            kwargs[spec.name] = _array(spec, cls, value, table, blob)
        elif kind == "message":
            kwargs[spec.name] = _build(spec.message_cls, value, table, blob)  # type: ignore[arg-type]
        elif type(value) is _ArrayRef:
            raise CodecError(f"{cls.__name__}.{spec.name}: unexpected array")
        else:
            kwargs[spec.name] = value
    try:
        return cls(**kwargs)
    except CodecError:
        raise
    except (TypeError, ValueError) as exc:
        raise CodecError(f"{cls.__name__}: {exc}") from exc


def encode_plain(value: Any, default: Callable[[Any], Any] | None = None) -> bytes:
    """msgpack for control traffic (registry, handshakes): plain data only.

    Args:
        value: the data.
        default: called with what msgpack cannot pack itself, returns what to pack instead (or raises TypeError).

    Raises:
        CodecError: ``value`` holds something that is not plain data (and ``default`` did not turn it into some).
    """
    try:
        return msgpack.packb(value, use_bin_type=True, default=default)  # type: ignore[no-any-return]
    except (TypeError, ValueError, OverflowError) as exc:
        raise CodecError(f"value is not msgpack-able: {exc}") from exc


def decode_plain(frame: bytes | memoryview) -> Any:
    """Inverse of encode_plain; malformed input raises CodecError."""
    try:
        return msgpack.unpackb(frame, raw=False, strict_map_key=False)
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise CodecError(f"malformed control frame: {exc}") from exc


# ---------------------------------------------------------------- values with arrays (runtime/protocol.py)

_ND_EXT = 42
_SCALAR_EXT = 43  # a numpy scalar of a type Python's numbers do not keep (float32, int8, ...): dtype kept
_PLAIN_SCALARS = (np.float64, np.int64, np.bool_)
"""Numpy scalars that travel as Python numbers: a vector env's info batches them into arrays of the same dtype."""
_SHAPE = struct.Struct("<q")
_DTYPE_STR = re.compile(r"[<>|=][a-zA-Z][0-9]{0,6}(\[[0-9]{0,6}[a-zA-Z]{1,2}\])?")
"""The dtype strings ``array_bytes`` writes (``dtype.str``: byte order, kind, item size, a datetime unit): anything
else is refused before numpy parses it (numpy evaluates some dtype strings as Python literals, with warnings and
SyntaxError)."""


_PACKED_HEADS: dict[tuple[np.dtype[Any], tuple[int, ...]], bytes] = {}
"""Array headers by (dtype, shape), the packing side of ``_HEADS``: the same few every step (keyed by the dtype
itself: ``dtype.str`` builds a new string every call, which costs more than the lookup)."""


def _default(value: Any) -> Any:
    """msgpack's hook for what it cannot pack itself: arrays as ExtType, numpy float64, int64 and bool scalars as
    Python ones, other numpy scalars as ExtType (their dtype kept)."""
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            return value.tolist()
        return msgpack.ExtType(_ND_EXT, array_bytes(value))
    if isinstance(value, np.generic):
        if type(value) in _PLAIN_SCALARS or value.dtype.hasobject:
            return value.item()
        return msgpack.ExtType(_SCALAR_EXT, array_bytes(np.asarray(value)))
    if isinstance(value, tuple | list):  # subclasses msgpack refuses (named tuples are packed as lists)
        return list(value)
    return repr(value)


def array_bytes(value: np.ndarray) -> bytes:
    """An array on the wire: a header (dtype string, ndim, shape; cached by dtype and shape) and the data in C
    order, whatever the strides. The payload of the array ExtType, and a step frame's array as it is."""
    head = _PACKED_HEADS.get((value.dtype, value.shape))
    if head is None:
        head = array_head(value.dtype, value.shape)
    return head + value.tobytes()


def array_head(dtype: np.dtype[Any], shape: tuple[int, ...]) -> bytes:
    """The header ``array_bytes`` writes before the data of an array of ``dtype`` and ``shape``."""
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


def array_from_bytes(
    buf: bytes | memoryview, start: int = 0, stop: int | None = None, what: str = "array"
) -> np.ndarray:
    """The array ``array_bytes`` wrote in ``buf[start:stop]``, as a writable copy.

    Raises:
        CodecError: not such an array (the data does not match its header, a bad dtype, too short), named ``what``.
    """
    try:
        return _array_from_bytes(buf, start, len(buf) if stop is None else stop)
    except (ValueError, TypeError, IndexError, struct.error, SyntaxError) as exc:
        raise CodecError(f"malformed {what}: {exc}") from exc


def _array_from_bytes(buf: bytes | memoryview, start: int, stop: int) -> np.ndarray:
    n = buf[start]
    ndim = buf[start + 1 + n]
    data_start = start + 2 + n + 8 * ndim
    head = bytes(buf[start:data_start])
    parsed = _HEADS.get(head)
    if parsed is None:
        dtype_str = head[1 : 1 + n].decode("ascii")
        if not _DTYPE_STR.fullmatch(dtype_str):
            raise ValueError(f"dtype {dtype_str!r:.40} is not a dtype string such as '<f4'")
        dtype = np.dtype(dtype_str)
        if dtype.hasobject:
            raise ValueError(f"dtype {dtype_str!r}: object arrays do not travel")
        if start + len(head) != data_start:
            raise ValueError(f"its header of {ndim} dimensions ends at byte {data_start}, past the frame's end")
        shape = tuple(_SHAPE.unpack_from(head, 2 + n + 8 * i)[0] for i in range(ndim))
        if any(d < 0 for d in shape):
            raise ValueError(f"shape {shape} has a negative dimension")
        parsed = (dtype, shape, math.prod(shape))
        if len(_HEADS) < 256:
            _HEADS[head] = parsed
    dtype, shape, count = parsed
    if stop - data_start != count * dtype.itemsize:
        raise ValueError(f"an array of {dtype} {shape} needs {count * dtype.itemsize} bytes, got {stop - data_start}")
    return np.frombuffer(buf, dtype=dtype, count=count, offset=data_start).reshape(shape).copy()


def _value_ext_hook(code: int, data: bytes) -> Any:
    if code == _ND_EXT:
        return array_from_bytes(data)
    if code == _SCALAR_EXT:
        return array_from_bytes(data)[()]
    return msgpack.ExtType(code, data)


def _str_list_keys(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    return {str(tuple(k)) if isinstance(k, list) else k: v for k, v in pairs}


_local = threading.local()


def pack_value(value: Any) -> bytes:
    """``msgpack.packb(value, default=_default, use_bin_type=True)`` with a Packer kept per thread: ``packb`` builds
    a new Packer every call, which costs a quarter of packing a step reply (a Packer is not thread-safe: the
    ``default`` hook lets other threads run in the middle of a pack, hence one per thread). A pack that raises
    leaves the Packer reset.

    Raises:
        CodecError: ``value`` holds something msgpack refuses even through the hook (a dict key of an odd type, an
            int beyond 64 bits).
    """
    packer = getattr(_local, "packer", None)
    if packer is None:
        packer = _local.packer = msgpack.Packer(default=_default, use_bin_type=True)
    try:
        return packer.pack(value)  # type: ignore[no-any-return]
    except (TypeError, ValueError, OverflowError) as exc:
        raise CodecError(f"value is not msgpack-able: {exc}") from exc


def unpack_value(data: bytes | memoryview, what: str = "step frame") -> Any:
    """The value ``pack_value`` packed, its arrays writable copies; map keys that came as lists (tuple keys) as their
    str, as runtime/protocol.py's ``to_wire`` does.

    Raises:
        CodecError: ``data`` is not msgpack (named ``what``).
    """
    try:
        try:
            return msgpack.unpackb(data, raw=False, strict_map_key=False, ext_hook=_value_ext_hook)
        except TypeError:  # a map key that came as a list (a tuple key)
            return msgpack.unpackb(
                data, raw=False, strict_map_key=False, ext_hook=_value_ext_hook, object_pairs_hook=_str_list_keys
            )
    except CodecError:
        raise
    except (ValueError, TypeError, IndexError, msgpack.UnpackException) as exc:
        raise CodecError(f"malformed {what}: {exc}") from exc
