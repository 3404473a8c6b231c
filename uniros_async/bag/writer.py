"""BagWriter: messages into an MCAP file from a thread of its own, with bounded memory and counted drops.

``put`` never waits and never does I/O: it appends the message to a queue bounded in messages and in bytes (a
full queue drops the new message and counts it, per topic), and the writer thread encodes (CDR or msgpack,
``schemas.py``), compresses (zstd or lz4 chunks, by the ``mcap`` library) and writes. The thread closes the chunk
in progress and flushes the file at least every ``flush_interval_s``, so a process killed mid-recording leaves a
file whose complete chunks all read (``BagReader`` stops at the torn one and names its offset). A write that fails
(a full disk: ENOSPC) stops the recording: ``put`` refuses from then on, ``error`` holds the cause, ``close``
raises a BagError naming the file and the offset, and what was written before stays readable.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import io
import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from uniros_async.bag import schemas
from uniros_async.bag.errors import BagError
from uniros_async.errors import CodecError, ConfigError

__all__ = ["BagWriter", "WriterStats"]

logger = logging.getLogger(__name__)

COMPRESSIONS = ("zstd", "lz4", "none")


@dataclasses.dataclass(slots=True)
class WriterStats:
    """What a BagWriter did: messages written and dropped per topic, bytes in the file, CPU seconds of its thread."""

    written: dict[str, int] = dataclasses.field(default_factory=dict)
    dropped: dict[str, int] = dataclasses.field(default_factory=dict)
    file_bytes: int = 0
    thread_cpu_s: float = 0.0

    @property
    def total_written(self) -> int:
        return sum(self.written.values())

    @property
    def total_dropped(self) -> int:
        return sum(self.dropped.values())


def _size(msg: Any) -> int:
    n = 256
    for spec in getattr(msg, "__uniros_arrays__", ()):
        a = getattr(msg, spec.name)
        if a is not None:
            n += a.nbytes
    return n


class BagWriter:
    """Writes messages to the MCAP file ``path`` from a thread of its own (see the module docstring).

    Args:
        path: the file to create (its directory must exist).
        compression: "zstd" (default), "lz4" or "none", per chunk.
        chunk_bytes: a chunk is closed once it holds this many uncompressed bytes.
        flush_interval_s: and at least this often, and the file flushed: what a crash can lose.
        max_queue: messages waiting at most; a message past that is dropped and counted.
        max_queue_bytes: and their arrays' bytes at most.
        ros2: write the standard types as ROS 2 CDR (default); False writes every type as our own.
        metadata: MCAP metadata records to write first, name -> {key: value}.
        nice: the writer thread lowers its own scheduling priority by this much (Linux nice, per thread), so that
            on a busy machine compressing and writing yield the CPU to loops and publishers; its queue then fills
            and drops, counted, instead.

    Raises:
        ConfigError: a bad setting. BagError: the file cannot be created.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        compression: str = "zstd",
        chunk_bytes: int = 4 << 20,
        flush_interval_s: float = 1.0,
        max_queue: int = 10_000,
        max_queue_bytes: int = 256 << 20,
        ros2: bool = True,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        nice: int = 10,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        if compression not in COMPRESSIONS:
            raise ConfigError(f"bag compression: expected one of {COMPRESSIONS}, got {compression!r}")
        if chunk_bytes < 1024 or flush_interval_s <= 0 or max_queue < 1 or max_queue_bytes < 1:
            raise ConfigError(
                "bag writer: expected chunk_bytes >= 1024, flush_interval_s > 0, max_queue >= 1, max_queue_bytes"
                f" >= 1; got {chunk_bytes}, {flush_interval_s}, {max_queue}, {max_queue_bytes}"
            )
        self.path = Path(path)
        self.ros2 = ros2
        self.stats = WriterStats()
        self.error: BaseException | None = None
        self._flush_interval_s = flush_interval_s
        self._nice = nice
        self._max_queue = max_queue
        self._max_queue_bytes = max_queue_bytes
        self._queue: collections.deque[tuple[str, Any, int, int, int]] = collections.deque()
        self._queued_bytes = 0
        self._cond = threading.Condition()
        self._closing = False
        self._channels: dict[tuple[str, str], int] = {}
        self._schema_ids: dict[str, int] = {}
        try:
            self._file: io.BufferedWriter = open(self.path, "wb")  # noqa: SIM115 (closed by the thread)
        except OSError as exc:
            raise BagError(f"cannot create bag {self.path}: {exc.strerror or exc}") from exc
        kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._mcap = Writer(self._file, chunk_size=chunk_bytes, compression=kind)
        try:
            self._mcap.start(profile="ros2" if ros2 else "", library="uniros_async")
            for name, data in (metadata or {}).items():
                self._mcap.add_metadata(name, {str(k): str(v) for k, v in data.items()})
            self._file.flush()
        except OSError as exc:
            self._file.close()
            raise BagError(f"cannot write bag {self.path}: {exc.strerror or exc}") from exc
        self._thread = threading.Thread(target=self._run, name=f"bag writer {self.path.name}", daemon=True)
        self._thread.start()

    # ---- the producers' side: never waits, never does I/O

    def put(self, topic: str, msg: Any, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        """Queue ``msg`` of ``topic`` for writing; False when it was dropped (queue full, or the writer stopped).

        Do not mutate ``msg``'s arrays afterwards (bus messages are never mutated).

        Raises:
            ConfigError: a negative time (MCAP's times are unsigned ns).
        """
        if log_time_ns < 0 or (publish_time_ns is not None and publish_time_ns < 0):
            raise ConfigError(f"{topic}: bag times are ns >= 0, got log {log_time_ns} and publish {publish_time_ns}")
        size = _size(msg)
        with self._cond:
            if (
                self.error is not None
                or self._closing
                or len(self._queue) >= self._max_queue
                or (self._queued_bytes + size > self._max_queue_bytes and self._queue)
            ):
                self.stats.dropped[topic] = self.stats.dropped.get(topic, 0) + 1
                return False
            self._queue.append(
                (topic, msg, log_time_ns, log_time_ns if publish_time_ns is None else publish_time_ns, size)
            )
            self._queued_bytes += size
            if len(self._queue) == 1:
                self._cond.notify()
        return True

    @property
    def queued(self) -> int:
        """Messages waiting for the writer thread."""
        return len(self._queue)

    def close(self) -> WriterStats:
        """Write what is queued, the summary and the footer, and close the file; idempotent.

        Raises:
            BagError: the recording stopped on a failed write (the file reads up to there); names the cause.
        """
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()
        if self.error is not None:
            raise BagError(
                f"recording to {self.path} stopped at byte {self.stats.file_bytes}: {self.error}; the file reads up "
                "to its last complete chunk"
            ) from self.error
        return self.stats

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- the writer thread

    def _channel(self, topic: str, type_name: str) -> int:
        key = (topic, type_name)
        cid = self._channels.get(key)
        if cid is None:
            schema = schemas.schema_for(type_name, standard=self.ros2)
            sid = self._schema_ids.get(schema.name)
            if sid is None:
                sid = self._schema_ids[schema.name] = self._mcap.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            cid = self._channels[key] = self._mcap.register_channel(
                topic, schema.message_encoding, sid, {"uniros_type": type_name}
            )
        return cid

    def _run(self) -> None:
        if self._nice > 0:
            with contextlib.suppress(OSError, AttributeError):  # best effort: not on every OS
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self._nice)
        t0 = time.thread_time()
        last_flush = time.monotonic()
        try:
            while True:
                with self._cond:
                    while not self._queue and not self._closing:
                        left = self._flush_interval_s - (time.monotonic() - last_flush)
                        if left <= 0:
                            break
                        self._cond.wait(left)
                    batch = list(self._queue)
                    self._queue.clear()
                    self._queued_bytes = 0
                    closing = self._closing
                for topic, msg, log_ns, pub_ns, _ in batch:
                    self._write(topic, msg, log_ns, pub_ns)
                if closing:
                    self._mcap.finish()  # type: ignore[no-untyped-call]
                    break
                if time.monotonic() - last_flush >= self._flush_interval_s:
                    self._mcap.flush()  # type: ignore[no-untyped-call]
                    last_flush = time.monotonic()
                self.stats.file_bytes = self._file.tell()
        except Exception as exc:  # OSError (a full disk), or a record mcap refuses: the recording stops, named
            with self._cond:
                self.error = exc
                for topic, *_ in self._queue:
                    self.stats.dropped[topic] = self.stats.dropped.get(topic, 0) + 1
                self._queue.clear()
            logger.error("recording to %s stopped: %s", self.path, exc)
        finally:
            with contextlib.suppress(OSError, ValueError):
                self.stats.file_bytes = self._file.tell()
            with contextlib.suppress(OSError):
                self._file.close()
            self.stats.thread_cpu_s = time.thread_time() - t0

    def _write(self, topic: str, msg: Any, log_ns: int, pub_ns: int) -> None:
        type_name = type(msg).__name__
        try:
            cid = self._channel(topic, type_name)
            data = schemas.encode(msg, schemas.schema_for(type_name, standard=self.ros2))
        except CodecError as exc:
            self.stats.dropped[topic] = self.stats.dropped.get(topic, 0) + 1
            logger.warning("bag %s: %s not written: %s", self.path.name, topic, exc)
            return
        self._mcap.add_message(cid, log_time=log_ns, data=data, publish_time=pub_ns)
        self.stats.written[topic] = self.stats.written.get(topic, 0) + 1
