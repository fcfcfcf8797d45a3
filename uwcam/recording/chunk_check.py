"""Reading a recording whose bytes may be damaged: every MCAP chunk's CRC is checked, a chunk that
fails is left out (never read as data), and what was left out is said.

A flipped bit in a compressed chunk changes the frames decompressed from it, silently: the MCAP
reader checks the CRC only when asked, and then stops at the first bad chunk. Here each chunk is
checked on its own (its CRC covers its uncompressed records), so the good chunks around a bad one
are still read. Which frames a bad chunk held is read from its message index, which lies outside
the chunk; a recording without an index (a repaired one) says only the chunk's time range.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.reader import SeekingReader, breakup_chunk
from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader
from mcap.data_stream import ReadDataStream

_CHUNK_ERRORS = (McapError, ValueError, EOFError, OSError, RuntimeError, KeyError, IndexError)
"""What a damaged chunk raises while read or decompressed: a CRC mismatch, a bad length, an
lz4/zstd error (RuntimeError or ValueError depending on the codec), a truncated record."""


@dataclass(frozen=True)
class CorruptChunk:
    """One chunk left out, where it lies, the log times (ns) it covered and why."""

    offset: int | None
    start_ns: int
    end_ns: int
    reason: str
    frames_ns: tuple[int, ...] | None = None
    """Log times of the ranged frames (``/uwcam/ranging`` messages) it held; None: unknown."""


def _chunk_ok(chunk: Chunk) -> str | None:
    """None if the chunk's records decompress and match its CRC, else why not."""
    try:
        for _ in breakup_chunk(chunk, validate_crc=True):
            pass
    except _CHUNK_ERRORS as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def _message_times(stream: IO[bytes], offset: int) -> tuple[int, ...]:
    stream.seek(offset)
    record = next(StreamReader(stream, skip_magic=True).records)
    return tuple(t for t, _ in record.records) if isinstance(record, MessageIndex) else ()


def find_corrupt_chunks(stream: IO[bytes], frame_topic: str) -> list[CorruptChunk]:
    """Every chunk of the recording that fails its CRC check or cannot be read."""
    reader = SeekingReader(stream)
    summary = reader.get_summary()
    bad: list[CorruptChunk] = []
    if summary is not None and summary.chunk_indexes:
        frame_channels = {cid for cid, ch in summary.channels.items() if ch.topic == frame_topic}
        for ci in summary.chunk_indexes:
            try:
                stream.seek(ci.chunk_start_offset + 1 + 8)
                reason = _chunk_ok(Chunk.read(ReadDataStream(stream)))
            except _CHUNK_ERRORS as exc:
                reason = f"{type(exc).__name__}: {exc}"
            if reason is not None:
                try:
                    frames = tuple(sorted(t for cid, off in ci.message_index_offsets.items() if cid in frame_channels
                                          for t in _message_times(stream, off)))
                except _CHUNK_ERRORS:
                    frames = None
                bad.append(CorruptChunk(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time, reason, frames))
        return bad
    stream.seek(0)
    try:
        for record in StreamReader(stream, skip_magic=False, emit_chunks=True).records:
            if isinstance(record, Chunk):
                reason = _chunk_ok(record)
                if reason is not None:
                    bad.append(CorruptChunk(None, record.message_start_time, record.message_end_time, reason))
    except _CHUNK_ERRORS as exc:  # the records themselves are damaged: nothing after this point is read
        bad.append(CorruptChunk(None, 0, 2**63 - 1, f"unreadable records ({type(exc).__name__}: {exc})"))
    return bad


class CheckedReader(SeekingReader):
    """A seeking MCAP reader that never reads a damaged chunk: the indexed chunks at
    ``skip_offsets`` (found by :func:`find_corrupt_chunks`) are left out of the index it reads
    by, and in a recording without an index (read from start to end, in file order) every chunk
    is checked as it comes and a failing one passed over."""

    def __init__(self, stream: IO[bytes], skip_offsets: tuple[int, ...] = (), **kwargs: Any) -> None:
        super().__init__(stream, **kwargs)
        summary = self.get_summary()
        self._linear = summary is None or not summary.chunk_indexes
        if not self._linear and skip_offsets:
            skip = set(skip_offsets)
            summary.chunk_indexes = [ci for ci in summary.chunk_indexes if ci.chunk_start_offset not in skip]

    def iter_messages(self, topics=None, start_time=None, end_time=None, log_time_order=True, reverse=False, *,
                      starting_at=None, starting_after=None, ending_at=None, ending_before=None):
        if not self._linear:
            yield from super().iter_messages(topics, start_time, end_time, log_time_order, reverse, starting_at=starting_at,
                                             starting_after=starting_after, ending_at=ending_at, ending_before=ending_before)
            return
        lo = starting_at if starting_at is not None else (starting_after + 1 if starting_after is not None else start_time)
        hi = ending_before if ending_before is not None else (ending_at + 1 if ending_at is not None else end_time)
        selected = (m for m in self._linear_messages(topics)
                    if (lo is None or m[2].log_time >= lo) and (hi is None or m[2].log_time < hi))
        if reverse:  # only a few messages of one topic are asked for this way (the ambient estimate)
            yield from sorted(selected, key=lambda m: m[2].log_time, reverse=True)
        else:
            yield from selected  # a recording is written in log time order

    def _linear_messages(self, topics) -> Iterator[tuple[Schema | None, Channel, Message]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        wanted = None if topics is None else set([topics] if isinstance(topics, str) else topics)
        self._stream.seek(0, io.SEEK_SET)

        def records():
            try:
                for record in StreamReader(self._stream, skip_magic=False, emit_chunks=True).records:
                    if isinstance(record, Chunk):
                        if _chunk_ok(record) is None:
                            yield from breakup_chunk(record, validate_crc=False)
                    else:
                        yield record
            except _CHUNK_ERRORS:
                return  # damaged records: find_corrupt_chunks has said so

        for record in records():
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if wanted is None or channel.topic in wanted:
                    yield schemas.get(channel.schema_id), channel, record
