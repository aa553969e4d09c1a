"""Every record of an MCAP file, read with its byte offset and checked.

mcap's ``StreamReader`` stops quietly when a read comes up short and checks no CRC unless asked,
so a file damaged in the middle reads as a shorter file. :class:`McapScan` frames each record
itself (opcode, length, content) and tells three cases apart:

* **truncated**: the file ends inside a record, or after a complete record but before the
  footer -- what a killed writer leaves. Everything before the cut is good. Recorded in
  :attr:`McapScan.truncation`; the caller decides how loudly to say it.
* **damaged**: an unknown opcode, a record whose fields do not fit its length, a chunk whose
  CRC (``uncompressed_crc``) does not match its records, a data-section CRC (``DataEnd``)
  mismatch, a length running past the end of a file that has its footer, or a missing trailing
  magic. Strict reading (the default) raises :class:`ScanError`; ``skip_damaged`` records the
  problem in :attr:`McapScan.damage`, skips the damaged record (or, if its framing is broken,
  searches forward for the next intact chunk) and goes on: the repair path.

Records inside chunks are yielded after the chunk's own CRC check, never before, so no byte of
a damaged chunk reaches a caller.

Every offset in this module is in bytes from the start of the file.
"""
from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError, UnsupportedCompressionError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

__all__ = ['MAGIC', 'McapScan', 'Problem', 'ScanError', 'is_finished']

MAGIC = b'\x89MCAP0\r\n'
_FRAME = struct.Struct('<BQ')  # opcode, content length
_READERS: dict[int, Callable[[ReadDataStream], McapRecord]] = {
    Opcode.ATTACHMENT: Attachment.read, Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
    Opcode.CHANNEL: Channel.read, Opcode.CHUNK: Chunk.read, Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.DATA_END: DataEnd.read, Opcode.FOOTER: Footer.read, Opcode.HEADER: Header.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read, Opcode.METADATA: Metadata.read,
    Opcode.METADATA_INDEX: MetadataIndex.read, Opcode.SCHEMA: Schema.read,
    Opcode.STATISTICS: Statistics.read, Opcode.SUMMARY_OFFSET: SummaryOffset.read,
}
_IN_CHUNK = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)
# How far past a record with broken framing the repair path looks for the next intact chunk.
_RESYNC_WINDOW = 256 * 1024 * 1024


@dataclass(frozen=True)
class Problem:
    """What is wrong at ``offset`` (bytes): ``kind`` ``'truncated'``, ``'damaged'`` or
    ``'unreadable'`` (intact, but needs a decompressor that is not installed)."""

    kind: str
    offset: int
    text: str

    def describe(self, size: int) -> str:
        return f'{self.kind} at byte {self.offset} of {size}: {self.text}'


class ScanError(Exception):
    """The file is damaged (strict reading); ``problem`` says where and how."""

    def __init__(self, problem: Problem, size: int):
        super().__init__(problem.describe(size))
        self.problem = problem


def is_finished(path: str | os.PathLike) -> bool:
    """Whether the file ends with the MCAP magic (a writer that finished it)."""
    with open(path, 'rb') as f:
        size = f.seek(0, os.SEEK_END)
        if size < 2 * len(MAGIC):
            return False
        f.seek(-len(MAGIC), os.SEEK_END)
        return f.read() == MAGIC


_MESSAGE_FIELDS = struct.Struct('<HIQQ')   # channel id, sequence, log time, publish time
_INDEX_FIELDS = struct.Struct('<HI')        # channel id, bytes of the entries


def _parse(opcode: int, content: bytes) -> McapRecord:
    """One record from exactly its content bytes; raises on fields that do not fit."""
    # The two frequent records read with struct (what mcap's readers give for them; anything
    # that does not fit them goes the slow way, for its error).
    if opcode == Opcode.MESSAGE and len(content) >= 22:
        channel_id, sequence, log_time, publish_time = _MESSAGE_FIELDS.unpack_from(content)
        return Message(channel_id=channel_id, log_time=log_time, data=content[22:],
                       publish_time=publish_time, sequence=sequence)
    if opcode == Opcode.MESSAGE_INDEX and len(content) >= 6:
        channel_id, size = _INDEX_FIELDS.unpack_from(content)
        if size % 16 == 0 and 6 + size <= len(content):
            flat = struct.unpack_from(f'<{size // 8}Q', content, 6)
            return MessageIndex(channel_id, list(zip(flat[::2], flat[1::2], strict=True)))
    stream = ReadDataStream(BytesIO(content))
    if opcode == Opcode.MESSAGE:
        if len(content) < 22:
            raise ValueError(f'{len(content)} bytes, a message needs at least 22')
        return Message.read(stream, len(content))
    record = _READERS[opcode](stream)
    if opcode == Opcode.CHUNK and stream.count != len(content):
        raise ValueError(f'its data ends {len(content) - stream.count} bytes before the record')
    return record


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower().replace('_', ' ')
    except ValueError:
        return f'opcode {opcode:#04x}'


#: ``McapScan._next_record``: nothing more can be read.
_STOP = object()


@dataclass
class _Walk:
    """Where a walk through the records is: the next offset, the running CRC of the bytes
    read (the data section's, while ``in_data``) and its value at the ``DataEnd`` record."""

    offset: int
    crc: int
    in_data: bool = True
    data_crc: int = 0


class McapScan:
    """Reads an MCAP file record by record (see the module docstring).

    Attributes:
        path, size: the file and its size in bytes.
        finished: the file ends with the trailing magic.
        truncation: the :class:`Problem` where the file is cut short, or None.
        damage: problems skipped with ``skip_damaged`` (empty in strict reading).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.finished = is_finished(self.path)
        self.truncation: Problem | None = None
        self.damage: list[Problem] = []
        self.footer_seen = False

    # -- problems ----------------------------------------------------------------------------
    def _damaged(self, offset: int, text: str, skip: bool) -> None:
        problem = Problem('damaged', offset, text)
        if not skip:
            raise ScanError(problem, self.size)
        self.damage.append(problem)

    def _cut(self, offset: int, text: str, skip: bool) -> None:
        """The data stops at ``offset``: truncated, unless the file has its footer (then
        something in the middle is wrong)."""
        if self.finished:
            self._damaged(offset, text, skip)
        else:
            self.truncation = Problem('truncated', offset, text)

    # -- reading -----------------------------------------------------------------------------
    def records(self, *, expand_chunks: bool = True, skip_damaged: bool = False
                ) -> Iterator[tuple[int, McapRecord]]:
        """``(offset, record)`` for every record in file order; records inside a chunk come
        after its CRC check, with the chunk's offset (``expand_chunks``), else the chunk itself.
        The trailing magic is checked after the footer.

        Raises:
            ScanError: damage, in strict reading.
            OSError: the file cannot be read.
        """
        self.truncation = None
        self.damage = []
        self.footer_seen = False
        with self.path.open('rb') as f:
            if f.read(len(MAGIC)) != MAGIC:
                self._damaged(0, 'not an MCAP file (no leading magic)', False)
            walk = _Walk(offset=len(MAGIC), crc=zlib.crc32(MAGIC))
            while True:
                item = self._next_record(f, walk, skip_damaged)
                if item is _STOP:
                    return
                if item is None:
                    continue
                here, record = item
                self._check_data_end(here, record, walk, skip_damaged)
                if isinstance(record, Chunk) and expand_chunks:
                    for inner in self._chunk_records(here, record, skip_damaged) or ():
                        yield here, inner
                    continue
                yield here, record
                if isinstance(record, Footer):
                    self.footer_seen = True
                    if f.read(len(MAGIC)) != MAGIC:
                        self._damaged(walk.offset, 'no trailing magic after the footer',
                                      skip_damaged)
                    return

    def _next_record(self, f, walk: _Walk, skip: bool):
        """The next record at ``walk.offset`` as ``(offset, record)``; None when there was
        none to give there (damage skipped, a user opcode); ``_STOP`` at the end of what can
        be read (a cut, or damage that cannot be skipped past)."""
        offset = walk.offset
        frame = f.read(_FRAME.size)
        if not frame:
            self._cut(offset, 'the file ends before its footer (summary and index '
                              'missing: was its writer killed?)', skip)
            return _STOP
        if len(frame) < _FRAME.size:
            self._cut(offset, f'the last record is cut short ({len(frame)} bytes of '
                              f'its 9-byte header)', skip)
            return _STOP
        opcode, length = _FRAME.unpack(frame)
        known = opcode in _READERS or opcode == Opcode.MESSAGE
        if not known and (0x01 <= opcode <= 0x7F or opcode == 0):
            # 0x01-0x7F are reserved for the spec (0x10-0x7F unused so far); an unknown
            # opcode there, or 0, is not a record.
            return self._resync(f, walk, f'{_opcode_name(opcode)} is not a record type', skip)
        remaining = self.size - offset - _FRAME.size
        if length > remaining:
            text = (f'{_opcode_name(opcode)} record claims {length} bytes but only '
                    f'{remaining} follow')
            if self.finished:
                return self._resync(f, walk, text, skip)
            self.truncation = Problem('truncated', offset, text + ' (the file is cut short)')
            return _STOP
        content = f.read(length)
        if opcode == Opcode.DATA_END and walk.in_data:
            walk.data_crc = walk.crc
        walk.crc = zlib.crc32(content, zlib.crc32(frame, walk.crc))
        walk.offset = offset + _FRAME.size + length
        if not known:
            return None  # a user opcode (0x80-0xFF): skipped
        try:
            return offset, _parse(opcode, content)
        except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
            self._damaged(offset, f'malformed {_opcode_name(opcode)} record '
                                  f'({exc or type(exc).__name__})', skip)
            return None

    def _resync(self, f, walk: _Walk, text: str, skip: bool):
        """Damage at ``walk.offset``: on at the next record found (None), or ``_STOP``; the
        data-section CRC cannot be checked any more either way."""
        resync = self._damaged_frame(f, walk.offset, text, skip)
        if resync is None:
            return _STOP
        walk.offset = resync
        walk.in_data = False
        return None

    def _check_data_end(self, offset: int, record: McapRecord, walk: _Walk,
                        skip: bool) -> None:
        """At the data section's end: its CRC (when it was read through) against the stored."""
        if not isinstance(record, DataEnd):
            return
        if walk.in_data and record.data_section_crc and record.data_section_crc != walk.data_crc:
            self._damaged(offset, f'the data section CRC does not match (stored '
                                  f'{record.data_section_crc:#010x}, computed '
                                  f'{walk.data_crc:#010x}): bytes were changed', skip)
        walk.in_data = False

    def _chunk_records(self, offset: int, chunk: Chunk, skip: bool
                       ) -> list[McapRecord] | None:
        """The records of a chunk, checked; None (damage recorded) if it is damaged."""
        data = self._chunk_data(offset, chunk, skip)
        if data is None:
            return None
        out = []
        pos = 0
        while pos < len(data):
            if len(data) - pos < _FRAME.size:
                self._damaged(offset, f'chunk ends inside a record header (at {pos} of '
                                      f'{len(data)} bytes)', skip)
                return None
            opcode, length = _FRAME.unpack_from(data, pos)
            start = pos + _FRAME.size
            if length > len(data) - start:
                self._damaged(offset, f'a {_opcode_name(opcode)} record in the chunk claims '
                                      f'{length} bytes, only {len(data) - start} follow', skip)
                return None
            pos = start + length
            if opcode not in _IN_CHUNK:
                continue  # unknown in-chunk record types are skipped (the spec's rule)
            try:
                out.append(_parse(opcode, data[start:pos]))
            except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
                self._damaged(offset, f'malformed {_opcode_name(opcode)} record in the chunk '
                                      f'({exc or type(exc).__name__})', skip)
                return None
        return out

    def _chunk_data(self, offset: int, chunk: Chunk, skip: bool) -> bytes | None:
        """A chunk's records as bytes, decompressed and checked (size, CRC); None (damage
        recorded) if damaged. A compression mcap cannot read is an error, not damage."""
        try:
            if chunk.compression == '':
                data = chunk.data
            else:
                from mcap.stream_reader import get_chunk_data_stream
                stream, n = get_chunk_data_stream(chunk)
                data = stream.read(n)
        except UnsupportedCompressionError:
            package = {'zstd': 'zstandard', 'lz4': 'lz4'}.get(chunk.compression)
            raise ScanError(Problem(
                'unreadable', offset, f'its chunks are compressed with {chunk.compression!r}'
                + (f', which needs the Python package {package} (pip install {package})'
                   if package else ', which mcap does not support')), self.size) from None
        except Exception as exc:  # noqa: BLE001 - any other decompression failure is damage
            self._damaged(offset, f'chunk does not decompress ({chunk.compression}: {exc})',
                          skip)
            return None
        if len(data) != chunk.uncompressed_size:
            self._damaged(offset, f'chunk holds {len(data)} bytes, its header says '
                                  f'{chunk.uncompressed_size}', skip)
            return None
        if chunk.uncompressed_crc:
            actual = zlib.crc32(data)
            if actual != chunk.uncompressed_crc:
                self._damaged(offset, f'chunk CRC mismatch (stored {chunk.uncompressed_crc:#010x}'
                                      f', computed {actual:#010x}): its bytes were changed',
                              skip)
                return None
        return data

    def _damaged_frame(self, f, offset: int, text: str, skip: bool) -> int | None:
        """A record whose framing cannot be trusted: raise (strict) or find the next intact
        chunk after ``offset`` (its offset, the file positioned there) or None (give up)."""
        self._damaged(offset, text, skip)
        position = offset + 1
        end = min(self.size, offset + _RESYNC_WINDOW)
        while position < end:
            f.seek(position)
            window = f.read(min(1 << 20, end - position))
            if not window:
                break
            i = window.find(bytes([Opcode.CHUNK]))
            while i >= 0:
                candidate = position + i
                if self._is_chunk_at(f, candidate):
                    self.damage[-1] = Problem(
                        'damaged', offset, f'{text}; skipped {candidate - offset} bytes to the '
                                           f'next intact chunk at byte {candidate}')
                    f.seek(candidate)
                    return candidate
                i = window.find(bytes([Opcode.CHUNK]), i + 1)
            position += len(window)
        return None

    def _is_chunk_at(self, f, candidate: int) -> bool:
        f.seek(candidate)
        frame = f.read(_FRAME.size)
        if len(frame) < _FRAME.size:
            return False
        opcode, length = _FRAME.unpack(frame)
        if opcode != Opcode.CHUNK or length > self.size - candidate - _FRAME.size or length < 40:
            return False
        try:
            chunk = _parse(opcode, f.read(length))
        except (McapError, struct.error, UnicodeDecodeError, ValueError):
            return False
        if not isinstance(chunk, Chunk) or chunk.uncompressed_crc == 0:
            return False  # no way to tell a real chunk from chance bytes
        probe = McapScan.__new__(McapScan)
        probe.size, probe.damage = self.size, []
        return probe._chunk_records(candidate, chunk, True) is not None and not probe.damage

    def chunk_start_times(self) -> list[tuple[int, int]]:
        """``(offset, log time)`` for each unit of messages in file order (a chunk, or a
        message outside chunks): the earliest log time it claims (``message_start_time``; 0
        for a chunk without messages): a quick walk that reads only record headers. Stops
        quietly where :meth:`records` would report a problem.
        """
        out: list[tuple[int, int]] = []
        with self.path.open('rb') as f:
            offset = len(MAGIC)
            f.seek(offset)
            while True:
                frame = f.read(_FRAME.size)
                if len(frame) < _FRAME.size:
                    return out
                opcode, length = _FRAME.unpack(frame)
                if length > self.size - offset - _FRAME.size:
                    return out
                if opcode == Opcode.CHUNK:
                    head = f.read(min(length, 16))
                    if len(head) < 16:
                        return out
                    out.append((offset, struct.unpack_from('<Q', head)[0]))
                elif opcode == Opcode.MESSAGE:
                    head = f.read(min(length, 14))
                    if len(head) < 14:
                        return out
                    out.append((offset, struct.unpack_from('<Q', head, 6)[0]))
                elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                    return out
                offset += _FRAME.size + length
                f.seek(offset)
