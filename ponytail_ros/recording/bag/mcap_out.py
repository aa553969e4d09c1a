"""``McapOut``: the MCAP file ``BagWriter`` writes, its per-message path cheap.

The bytes are exactly those of ``mcap.writer.Writer(stream, chunk_size=2**62,
compression=CompressionType.NONE)`` with its other options at their defaults (every index,
schemas and channels repeated in the summary, statistics, summary offsets, CRCs of the chunks
and the summary, no data-section CRC) for the same calls -- a test checks it byte for byte. The
chunks are cut by the caller (:meth:`flush`), never by size here.

Why not ``mcap``'s writer: a message there is a ``Message`` dataclass, statistics and chunk
bookkeeping through several calls and a ``BytesIO`` record builder with a seek back per
record: several times the Python per message, and a replay writes 4-5 messages per tick. Here
a message is one ``struct.pack`` of its 31-byte record head appended to the chunk, and its
index entry. The rare records (header, schemas, channels, metadata, the summary) are written by
``mcap``'s own record classes.
"""
from __future__ import annotations

import struct
import zlib
from typing import IO

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC

__all__ = ['McapOut']

# opcode, record length, channel id, sequence, log time, publish time (then the data)
_MESSAGE_HEAD = struct.Struct('<BQHIQQ')
_MESSAGE_FIXED = _MESSAGE_HEAD.size - 9          # the record's fields before the data
# opcode, record length, start, end, uncompressed size, CRC, compression '' (length 0), size
_CHUNK_HEAD = struct.Struct('<BQQQQIIQ')
# opcode, record length, channel id, bytes of the (time, offset) entries
_INDEX_HEAD = struct.Struct('<BQHI')


class McapOut:
    """An MCAP file written to ``stream`` (positioned at 0), chunked by :meth:`flush`."""

    def __init__(self, stream: IO[bytes]):
        self._stream = stream
        self._offset = 0                  # bytes written to the stream
        self._records = RecordBuilder()   # rare records, written out by _flush_records
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indices: list[ChunkIndex] = []
        self._metadata_indices: list[MetadataIndex] = []
        self._metadata_count = 0
        self._chunk_count = 0
        self._message_count = 0
        self._message_start = 0
        self._message_end = 0
        #: channel id -> messages (in the order of their first message, as mcap counts them)
        self._channel_counts: dict[int, int] = {}
        # The chunk being built: its records, their message index entries per channel (first
        # message order), its messages and log-time span.
        self._chunk = bytearray()
        self._chunk_index: dict[int, list[int]] = {}
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0

    # -- the data section ------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._offset += len(data)

    def _flush_records(self) -> None:
        self._write(self._records.end())

    def start(self, profile: str, library: str) -> None:
        self._write(MCAP0_MAGIC)
        Header(profile, library).write(self._records)
        self._flush_records()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._flush_records()
        offset = self._offset
        self._metadata_count += 1
        Metadata(name=name, metadata=data).write(self._records)
        self._metadata_indices.append(MetadataIndex(offset=offset, length=self._records.count,
                                                    name=name))
        self._flush_records()

    def _in_chunk(self, record) -> None:
        builder = RecordBuilder()
        record.write(builder)
        self._chunk += builder.end()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        schema = Schema(id=schema_id, data=data, encoding=encoding, name=name)
        self._schemas[schema_id] = schema
        self._in_chunk(schema)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str]) -> int:
        channel_id = len(self._channels) + 1
        channel = Channel(id=channel_id, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=metadata)
        self._channels[channel_id] = channel
        self._in_chunk(channel)
        return channel_id

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int) -> None:
        """One message into the chunk (times in ns, as ``mcap``'s ``Writer.add_message``). The
        file's statistics take in the chunk's when it is written out (:meth:`stats`)."""
        chunk = self._chunk
        if self._chunk_messages:
            if log_time < self._chunk_start:
                self._chunk_start = log_time
            elif log_time > self._chunk_end:
                self._chunk_end = log_time
        else:
            self._chunk_start = log_time
            if log_time > self._chunk_end:
                self._chunk_end = log_time
        self._chunk_messages += 1
        entries = self._chunk_index.get(channel_id)
        if entries is None:
            entries = self._chunk_index[channel_id] = []
        entries += (log_time, len(chunk))
        chunk += _MESSAGE_HEAD.pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id,
                                    sequence, log_time, publish_time)
        chunk += data

    def stats(self):
        """``(messages, first log time, last log time)`` so far (the chunk being built
        included); the times are 0 without messages."""
        count, start, end = self._message_count, self._message_start, self._message_end
        if self._chunk_messages:
            start = self._chunk_start if not count else min(start, self._chunk_start)
            end = max(end, self._chunk_end)
            count += self._chunk_messages
        return count, start, end

    def _merge_chunk_stats(self) -> None:
        """The chunk's messages into the file's statistics (mcap counts the channels in the
        order of their first message: chunk after chunk, in each in that order)."""
        self._message_count, self._message_start, self._message_end = self.stats()
        counts = self._channel_counts
        for channel_id, entries in self._chunk_index.items():
            counts[channel_id] = counts.get(channel_id, 0) + len(entries) // 2

    def _finalize_chunk(self) -> None:
        if not self._chunk_messages:
            return
        self._merge_chunk_stats()
        self._chunk_count += 1
        data = bytes(self._chunk)
        self._flush_records()
        chunk_start_offset = self._offset
        head = _CHUNK_HEAD.pack(Opcode.CHUNK, _CHUNK_HEAD.size - 9 + len(data),
                                self._chunk_start, self._chunk_end, len(data),
                                zlib.crc32(data), 0, len(data))
        self._write(head)
        self._write(data)
        message_index_start = self._offset
        offsets: dict[int, int] = {}
        parts = []
        at = 0
        for channel_id, entries in self._chunk_index.items():
            offsets[channel_id] = message_index_start + at
            body = struct.pack(f'<{len(entries)}Q', *entries)
            part = _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + len(body), channel_id,
                                    len(body)) + body
            parts.append(part)
            at += len(part)
        self._write(b''.join(parts))
        self._chunk_indices.append(ChunkIndex(
            message_start_time=self._chunk_start, message_end_time=self._chunk_end,
            chunk_start_offset=chunk_start_offset, chunk_length=len(head) + len(data),
            message_index_offsets=offsets, message_index_length=at, compression='',
            compressed_size=len(data), uncompressed_size=len(data)))
        self._chunk = bytearray()
        self._chunk_index = {}
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0

    def flush(self) -> None:
        """The chunk in progress (if it has messages) written out; the stream flushed."""
        self._finalize_chunk()
        self._flush_records()
        self._stream.flush()

    # -- the summary -----------------------------------------------------------------------
    def finish(self) -> None:
        """The last chunk, the data end, the summary, the footer and the closing magic (the
        stream is not closed)."""
        self._finalize_chunk()
        DataEnd(0).write(self._records)
        self._flush_records()
        summary_start = self._offset
        summary = RecordBuilder()
        offsets = []

        def group(opcode, records):
            start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=summary.count - start))
        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [Statistics(
            attachment_count=0, channel_count=len(self._channels),
            channel_message_counts=self._channel_counts, chunk_count=self._chunk_count,
            message_count=self._message_count, message_end_time=self._message_end,
            message_start_time=self._message_start, metadata_count=self._metadata_count,
            schema_count=len(self._schemas))])
        group(Opcode.CHUNK_INDEX, self._chunk_indices)
        group(Opcode.ATTACHMENT_INDEX, [])
        group(Opcode.METADATA_INDEX, self._metadata_indices)
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        crc = zlib.crc32(data)
        crc = zlib.crc32(struct.pack('<BQQQ', Opcode.FOOTER, 8 + 8 + 4,
                                     0 if not data else summary_start, summary_offset_start),
                         crc)
        self._write(data)
        Footer(summary_start=0 if not data else summary_start,
               summary_offset_start=summary_offset_start, summary_crc=crc).write(self._records)
        self._flush_records()
        self._write(MCAP0_MAGIC)
