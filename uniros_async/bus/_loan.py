"""Loaned messages: a message whose array the producer writes once, in place, where the transport sends it from.

``Publisher.loan(shape, dtype)`` (bus/pubsub.py) hands out a ``Loan``: its ``array`` is written by the producer (a
renderer, a capture), then the producer sets ``message`` to a message whose one array field is that very array.
When the block ends the message is published:

- to one remote subscriber over ``shm`` (and none in this process), the array is the frame's own place in that
  subscriber's ring (``ShmTransport.loan``): the frame is never copied on the publishing side, and the subscriber
  reads it in place (``zero_copy`` subscriptions: a read-only view, valid during the callback);
- otherwise the array is a buffer of the publisher's own and the message is published as ``publish`` does
  (in-process subscribers get the object; each remote subscriber's transport sends it with one copy).

A loaned frame is an ordinary codec frame (bus/codec.py): ``HEAD_BYTES`` are reserved for its head (the u32 length,
the msgpack body and its padding), then the array starts at byte ``HEAD_BYTES`` of the frame. The head is encoded
when the block ends, its array table offset pointing past the bytes the head leaves unused, so any subscriber
decodes it as it decodes every other frame.
"""

from __future__ import annotations

from typing import Any, Generic, TypeVar

import numpy as np

from uniros_async.bus import codec
from uniros_async.errors import CodecError

__all__ = ["HEAD_BYTES", "Loan", "check_message", "encode_head"]

M = TypeVar("M")

HEAD_BYTES = 1024
"""The room a loaned frame keeps for its head before the array (a multiple of 8)."""

_MIN_OFFSET = 256
"""The array's table offset is kept at 256 or more, so msgpack spells it in three bytes whatever it is, and the
head's length does not depend on it."""


class Loan(Generic[M]):
    """One loaned message being written: fill ``array``, then set ``message`` (its array field is ``array``).

    ``in_place``: True when ``array`` is the frame's place in a shared-memory ring (no copy after the producer's).
    Neither ``array`` nor views of it may be used after the ``async with`` block.
    """

    def __init__(self, array: np.ndarray, *, in_place: bool) -> None:
        self.array = array
        self.in_place = in_place
        self.message: M | None = None


def _arrays(msg: Any) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for spec in msg.__uniros_schema__:
        value = getattr(msg, spec.name)
        if value is None:
            continue
        if spec.kind == "array":
            out.append(value)
        elif spec.kind == "message":
            out.extend(_arrays(value))
    return out


def check_message(topic: str, msg_type: type, loan: Loan[Any]) -> Any:
    """The loan's message, checked: a ``msg_type`` whose only array is the loaned ``array``.

    Raises:
        CodecError: no message was set, it is another type, or its arrays are not exactly the loaned one (named).
    """
    msg = loan.message
    if msg is None:
        raise CodecError(f"{topic}: the loan's message was not set; set loan.message before the block ends")
    if type(msg) is not msg_type:
        raise CodecError(f"{topic}: expected {msg_type.__name__}, got {type(msg).__name__}")
    arrays = _arrays(msg)
    a = loan.array
    if len(arrays) != 1 or arrays[0].nbytes != a.nbytes or not np.shares_memory(arrays[0], a):
        raise CodecError(
            f"{topic}: a loaned {msg_type.__name__} must hold exactly one array, the loan's own "
            f"({a.shape} {a.dtype}); got {len(arrays)} array(s)"
        )
    if arrays[0].ctypes.data != a.ctypes.data or not arrays[0].flags.c_contiguous:
        raise CodecError(f"{topic}: the message's array must be the whole loaned array, not a slice or a view of it")
    return msg


def encode_head(msg: Any) -> bytes:
    """The head of ``msg``'s loaned frame, whose array starts at byte ``HEAD_BYTES``.

    Raises:
        CodecError: the head needs more than ``HEAD_BYTES - 256`` bytes (its fields other than the array are too
            long: a shorter ``frame_id`` or encoding).
    """
    head = codec.encode(msg, blob_offset=_MIN_OFFSET)[0]
    n = len(head)
    if n > HEAD_BYTES - _MIN_OFFSET:
        raise CodecError(
            f"{type(msg).__name__}: the fields beside the array take {n} bytes; a loaned frame has room for "
            f"{HEAD_BYTES - _MIN_OFFSET}"
        )
    head = codec.encode(msg, blob_offset=HEAD_BYTES - n)[0]
    if len(head) != n:  # pragma: no cover - msgpack spells every offset in 256..65535 in three bytes
        raise CodecError(f"{type(msg).__name__}: the loaned frame's head changed length")
    return bytes(head)
