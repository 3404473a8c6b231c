"""BagReader: the messages of an MCAP bag as our message types, and what a bag holds.

The reader walks the file record by record (the ``mcap`` library parses each record; the walk is ours, so that it
knows every record's offset). A chunk is decompressed and its CRC checked before any of its messages is given out,
so a torn or corrupt chunk gives none: the messages before it are read, then a BagDamagedError names the byte offset
of the damaged record. That is what a recording killed mid-write or stopped by a full disk leaves: a file without
its summary whose last chunk is torn. ``messages(strict=False)`` stops there quietly and sets ``damage``.

ROS 2 channels (CDR) come back as our standard types (``schemas.py``); a channel of a ROS 2 type we have no type
for, or of another encoding, is listed by ``info`` and skipped by ``messages`` unless ``raw=True``.
"""

from __future__ import annotations

import dataclasses
import io
import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from uniros_async.bag import schemas
from uniros_async.bag.errors import BagDamagedError, BagError
from uniros_async.bag.step import EpisodeStep  # registered by its import: episode bags read in any process
from uniros_async.errors import CodecError

__all__ = ["BagInfo", "BagMessage", "BagReader", "EpisodeStep", "TopicInfo"]

MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")


@dataclasses.dataclass(frozen=True, slots=True)
class BagMessage:
    """One message of a bag: its topic, log time (the recorder's clock, ns), publish time (the message's stamp
    where it has one, else the log time) and the message (our type; with ``raw=True`` the bytes)."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    message: Any
    type_name: str


@dataclasses.dataclass(slots=True)
class TopicInfo:
    """A topic of a bag: our type name, the MCAP schema and message encoding, and how many messages."""

    topic: str
    type_name: str
    schema_name: str
    message_encoding: str
    count: int = 0


@dataclasses.dataclass(slots=True)
class BagInfo:
    """What ``uniros bag info`` prints: the topics, the time span, the chunks and their compression, the size,
    and where the file is damaged (None: it is whole, footer and all)."""

    path: str
    size_bytes: int
    topics: dict[str, TopicInfo]
    start_ns: int | None
    end_ns: int | None
    chunks: int
    compression: set[str]
    metadata: dict[str, dict[str, str]]
    complete: bool
    damage: str | None

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    @property
    def duration_s(self) -> float:
        return 0.0 if self.start_ns is None or self.end_ns is None else (self.end_ns - self.start_ns) / 1e9

    def format(self) -> str:
        """The info as lines for a person."""
        lines = [
            f"path:        {self.path}",
            f"size:        {self.size_bytes / 1e6:.3f} MB",
            f"messages:    {self.message_count}",
            f"duration:    {self.duration_s:.3f} s",
            f"start/end:   {self.start_ns} / {self.end_ns} ns",
            f"chunks:      {self.chunks} ({', '.join(sorted(self.compression)) or 'none'})",
            f"complete:    {'yes' if self.complete else 'no (no summary: read to its end)'}",
        ]
        if self.damage:
            lines.append(f"damaged:     {self.damage}")
        lines.append("topics:")
        width = max((len(t) for t in self.topics), default=0)
        for t in sorted(self.topics.values(), key=lambda t: t.topic):
            lines.append(
                f"  {t.topic:<{width}}  {t.count:>8} msgs  {t.type_name} ({t.schema_name}, {t.message_encoding})"
            )
        return "\n".join(lines)


@dataclasses.dataclass(slots=True)
class _Channel:
    topic: str
    type_name: str
    schema: schemas.Schema | None


class BagReader:
    """Reads the MCAP bag at ``path`` (see the module docstring).

    Raises:
        BagError: no such file, or not an MCAP file (names the path).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
        except OSError as exc:
            raise BagError(f"cannot open bag {self.path}: {exc.strerror or exc}") from exc
        if head != MAGIC:
            raise BagError(f"{self.path} is not an MCAP file (its first bytes are {head!r}, expected {MAGIC!r})")
        self.damage: BagDamagedError | None = None

    def __iter__(self) -> Iterator[BagMessage]:
        return self.messages()

    def messages(
        self, topics: Iterable[str] | None = None, *, strict: bool = True, raw: bool = False
    ) -> Iterator[BagMessage]:
        """The bag's messages in file order (the order they were written), of ``topics`` (None: all).

        Args:
            topics: only these topics.
            strict: True raises BagDamagedError at a torn or corrupt record; False stops there and sets
                ``self.damage``.
            raw: give each message's bytes as written (CDR or msgpack) instead of decoding them.

        Raises:
            BagDamagedError: damage at an offset (everything before it was given).
            BagError: a message that does not decode as its channel's type (names the topic and offset).
        """
        wanted = None if topics is None else set(topics)
        for item in self._walk(strict=strict):
            offset, ch, rec = item
            if wanted is not None and ch.topic not in wanted:
                continue
            if raw:
                msg: Any = bytes(rec.data)
            else:
                if ch.schema is None:
                    continue
                try:
                    msg = schemas.decode(rec.data, ch.schema)
                except CodecError as exc:
                    raise BagError(f"{self.path}: message of {ch.topic} at byte {offset}: {exc}") from exc
            yield BagMessage(ch.topic, rec.log_time, rec.publish_time, msg, ch.type_name)

    def info(self) -> BagInfo:
        """What the bag holds: from its summary when it is complete (nothing decompressed), else by reading it to
        its end; a damaged bag's info covers what reads, and says where the damage is."""
        from mcap.records import Chunk, Metadata

        summarised = self._summary_info()
        if summarised is not None:
            return summarised

        topics: dict[str, TopicInfo] = {}
        start = end = None
        chunks = 0
        compression: set[str] = set()
        metadata: dict[str, dict[str, str]] = {}
        complete = False
        self.damage = None
        for offset, ch, rec in self._walk(strict=False, chunks_too=True):
            del offset
            if isinstance(rec, Chunk):
                chunks += 1
                compression.add(rec.compression or "none")
                continue
            if isinstance(rec, Metadata):
                metadata[rec.name] = dict(rec.metadata)
                continue
            if rec is None:
                complete = True
                continue
            t = topics.get(ch.topic)
            if t is None:
                t = topics[ch.topic] = TopicInfo(
                    ch.topic,
                    ch.type_name or "?",
                    ch.schema.name if ch.schema else "?",
                    ch.schema.message_encoding if ch.schema else "?",
                )
            t.count += 1
            start = rec.log_time if start is None else min(start, rec.log_time)
            end = rec.log_time if end is None else max(end, rec.log_time)
        return BagInfo(
            str(self.path),
            self.path.stat().st_size,
            topics,
            start,
            end,
            chunks,
            compression,
            metadata,
            complete,
            str(self.damage) if self.damage else None,
        )

    def _summary_info(self) -> BagInfo | None:
        """The info from a complete bag's summary (statistics, channels, chunk indexes), or None: no summary."""
        from mcap.reader import make_reader

        try:
            with open(self.path, "rb") as f:
                reader = make_reader(f)
                summary = reader.get_summary()
                if summary is None or summary.statistics is None:
                    return None
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception:  # no footer, a torn summary, ...: the walk reads what there is and names the damage
            return None
        stats = summary.statistics
        topics: dict[str, TopicInfo] = {}
        for cid, c in summary.channels.items():
            ch = _channel(c, summary.schemas.get(c.schema_id))
            t = topics.setdefault(
                ch.topic,
                TopicInfo(
                    ch.topic,
                    ch.type_name or "?",
                    ch.schema.name if ch.schema else "?",
                    ch.schema.message_encoding if ch.schema else "?",
                ),
            )
            t.count += stats.channel_message_counts.get(cid, 0)
        self.damage = None
        n = stats.message_count
        return BagInfo(
            str(self.path),
            self.path.stat().st_size,
            topics,
            stats.message_start_time if n else None,
            stats.message_end_time if n else None,
            stats.chunk_count,
            {i.compression or "none" for i in summary.chunk_indexes},
            metadata,
            True,
            None,
        )

    # ---- the walk

    def _damaged(self, offset: int, what: str) -> BagDamagedError:
        return BagDamagedError(
            f"{self.path} is damaged at byte {offset}: {what}; everything before that byte was read",
            path=str(self.path),
            offset=offset,
        )

    def _walk(self, *, strict: bool, chunks_too: bool = False) -> Iterator[tuple[int, Any, Any]]:
        """Yields (offset, channel, Message record) for each message; with ``chunks_too`` also (offset, None,
        Chunk | Metadata) and, at a clean end, (offset, None, None)."""
        from mcap.data_stream import ReadDataStream
        from mcap.opcode import Opcode
        from mcap.records import Channel, Chunk, Message, Metadata, Schema

        schemas_by_id: dict[int, Any] = {}
        channels: dict[int, _Channel] = {}

        def on_record(opcode: int, body: bytes) -> Any:
            stream = ReadDataStream(io.BytesIO(body))
            if opcode == Opcode.SCHEMA:
                s = Schema.read(stream)
                schemas_by_id[s.id] = s
            elif opcode == Opcode.CHANNEL:
                c = Channel.read(stream)
                if c.id not in channels:
                    channels[c.id] = _channel(c, schemas_by_id.get(c.schema_id))
            elif opcode == Opcode.MESSAGE:
                return Message.read(stream, len(body))
            elif opcode == Opcode.METADATA:
                return Metadata.read(stream)
            return None

        try:
            f = open(self.path, "rb")  # noqa: SIM115 (closed in finally; a generator holds it)
        except OSError as exc:
            raise BagError(f"cannot open bag {self.path}: {exc.strerror or exc}") from exc
        try:
            f.seek(len(MAGIC))
            offset = len(MAGIC)
            while True:
                head = f.read(_HEAD.size)
                if not head:
                    err = self._damaged(offset, "the file ends without a footer (a recording that did not finish)")
                    break
                if len(head) < _HEAD.size:
                    err = self._damaged(offset, f"a record header is cut short ({len(head)} of {_HEAD.size} bytes)")
                    break
                opcode, length = _HEAD.unpack(head)
                if length > 1 << 34:
                    err = self._damaged(offset, f"record length {length} is not plausible (opcode {opcode:#x})")
                    break
                body = f.read(length)
                if len(body) < length:
                    err = self._damaged(offset, f"a record of {length} bytes is cut short at {len(body)}")
                    break
                try:
                    if opcode == Opcode.CHUNK:
                        chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
                        inner = _unchunk(chunk)
                        if chunks_too:
                            yield offset, None, chunk
                        for sub_op, sub_body in inner:
                            rec = on_record(sub_op, sub_body)
                            if isinstance(rec, Message) and rec.channel_id in channels:
                                yield offset, channels[rec.channel_id], rec
                    elif opcode == Opcode.FOOTER:
                        if chunks_too:
                            yield offset, None, None
                        return
                    elif opcode == Opcode.DATA_END:
                        pass
                    else:
                        rec = on_record(opcode, body)
                        if isinstance(rec, Message) and rec.channel_id in channels:
                            yield offset, channels[rec.channel_id], rec
                        elif isinstance(rec, Metadata) and chunks_too:
                            yield offset, None, rec
                except _ChunkError as exc:
                    err = self._damaged(offset, str(exc))
                    break
                except (struct.error, UnicodeDecodeError, ValueError, KeyError, IndexError) as exc:
                    err = self._damaged(offset, f"record {opcode:#x} of {length} bytes does not parse ({exc})")
                    break
                offset += _HEAD.size + length
        finally:
            f.close()
        self.damage = err
        if strict:
            raise err


def _channel(c: Any, s: Any) -> _Channel:
    """Our view of an MCAP channel ``c`` of schema ``s`` (None: unknown): its type, and its schema if we read it."""
    type_name = c.metadata.get("uniros_type", "")
    schema = None
    if s is not None:
        schema = schemas.Schema(s.name, s.encoding, bytes(s.data), c.message_encoding)
        if not type_name and s.name in schemas.ROS2_TYPES.values():
            type_name = next(k for k, v in schemas.ROS2_TYPES.items() if v == s.name)
        elif not type_name and s.name.startswith(schemas.OWN_PACKAGE):
            type_name = s.name.removeprefix(schemas.OWN_PACKAGE)
    if schema is not None and not _readable(schema):
        schema = None
    return _Channel(c.topic, type_name, schema)


def _readable(schema: schemas.Schema) -> bool:
    return schema.message_encoding == "cdr" and (
        schema.name in schemas.ROS2_TYPES.values() or schema.name.startswith(schemas.OWN_PACKAGE)
    )


class _ChunkError(Exception):
    pass


def _unchunk(chunk: Any) -> list[tuple[int, bytes]]:
    """A chunk's records as (opcode, body), after decompressing it and checking its CRC."""
    try:
        if chunk.compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
        elif chunk.compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(chunk.data)
        elif chunk.compression == "":
            data = bytes(chunk.data)
        else:
            raise _ChunkError(f"chunk compression {chunk.compression!r} is not zstd, lz4 or none")
    except _ChunkError:
        raise
    except Exception as exc:  # zstandard.ZstdError, RuntimeError of lz4
        raise _ChunkError(f"a {chunk.compression} chunk does not decompress ({exc})") from exc
    if len(data) != chunk.uncompressed_size:
        raise _ChunkError(f"a chunk holds {len(data)} bytes, its header says {chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise _ChunkError("a chunk's CRC does not match its content")
    out = []
    pos = 0
    while pos < len(data):
        if pos + _HEAD.size > len(data):
            raise _ChunkError("a chunk ends inside a record header")
        opcode, length = _HEAD.unpack_from(data, pos)
        pos += _HEAD.size
        if pos + length > len(data):
            raise _ChunkError("a chunk's record runs past the chunk's end")
        out.append((opcode, data[pos : pos + length]))
        pos += length
    return out
