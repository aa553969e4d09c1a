"""``BagReader``: an MCAP bag read back, checked record by record (``mcap_scan.py``), in
log-time order with bounded memory or in file order.
"""
from __future__ import annotations

import heapq
import os
import struct
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Mapping, Optional, Tuple, Union

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from rclpy.serialization import deserialize_message

from ..mcap_scan import MAGIC as _MCAP_MAGIC
from ..mcap_scan import McapScan, ScanError, is_finished
from .errors import BagError
from .msgdefs import _message_class, _type_string

__all__ = ['BagReader']

class BagReader:
    """Reads an MCAP bag, checked record by record (``mcap_scan.McapScan``).

    * A file cut short by a killed writer (no summary or footer) is read up to the cut; after a
      full read, :attr:`truncation` says where and why (None for a complete file).
    * A damaged file (changed bytes: a chunk CRC or data-section CRC mismatch, a record that
      does not fit its length, an unknown opcode, a length past the end of a finished file)
      raises :class:`BagError` naming the file, the byte offset and the problem, with the
      repair command; no record of a damaged chunk is ever returned.
    * Messages come in log-time order (ties in file order), as the ``mcap`` and ``rosbags``
      readers and ``ros2 bag play`` give them, or in file order (``order='file'``).

    Args:
        path: the ``.mcap`` file.

    Raises:
        BagError: the file does not exist, cannot be read, or is not MCAP.
    """

    def __init__(self, path: Union[str, os.PathLike]):
        self.path = Path(path)
        try:
            with self.path.open('rb') as file:
                magic = file.read(len(_MCAP_MAGIC))
            self._finished = is_finished(self.path)
        except OSError as exc:
            raise BagError(f'cannot read bag {self.path}: {exc.strerror or exc}') from None
        if magic != _MCAP_MAGIC:
            raise BagError(f'{self.path} is not an MCAP file')
        #: Where and why the file is cut short ("truncated at byte N of M: ..."), known after a
        #: full read (:meth:`metadata`, :meth:`messages`); None for a complete file.
        self.truncation: Optional[str] = None
        #: Messages of the last :meth:`messages` call stored before one with a later log time.
        self.out_of_order = 0

    @property
    def finished(self) -> bool:
        """The file ends with the MCAP magic (its writer closed it)."""
        return self._finished

    def _damaged(self, exc: ScanError) -> BagError:
        if exc.problem.kind != 'damaged':
            return BagError(f'{self.path} is {exc}')
        return BagError(f'{self.path} is {exc}; replaying it would use or skip corrupt data. '
                        f'"ponytail_replay repair {self.path} FIXED.mcap" keeps every intact '
                        f'record')

    def _scan(self, expand_chunks: bool = True) -> Iterator[Tuple[int, Any]]:
        """``(offset, record)`` in file order; damage raises, a cut sets :attr:`truncation`."""
        try:
            scan = McapScan(self.path)
            yield from scan.records(expand_chunks=expand_chunks)
        except ScanError as exc:
            raise self._damaged(exc) from None
        except OSError as exc:
            raise BagError(f'cannot read bag {self.path}: {exc.strerror or exc}') from None
        self.truncation = (scan.truncation.describe(scan.size)
                           if scan.truncation is not None else None)

    def _records(self, emit_chunks: bool = False) -> Iterator[Any]:
        for _, record in self._scan(expand_chunks=not emit_chunks):
            yield record

    def check(self) -> Optional[str]:
        """Read every record (chunk CRCs included); the truncation text or None.

        Raises:
            BagError: the file is damaged.
        """
        for _ in self._scan():
            pass
        return self.truncation

    def topics(self) -> Dict[str, str]:
        """Topic name -> message type ``pkg/msg/Type``."""
        if self._finished:
            try:
                with self.path.open('rb') as file:
                    summary = SeekingReader(file).get_summary()
            except (McapError, struct.error, ValueError, UnicodeDecodeError):
                summary = None  # unreadable summary: scan the data section like a cut file
            if summary is not None:
                return {channel.topic: summary.schemas[channel.schema_id].name
                        for channel in summary.channels.values()
                        if channel.schema_id in summary.schemas}
        schemas: Dict[int, str] = {}
        topics: Dict[str, str] = {}
        for record in self._records():
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                topics[record.topic] = schemas.get(record.schema_id, '')
        return topics

    def messages(self, topics: Union[None, str, Iterable[str], Mapping[str, Union[str, type]]]
                 = None, order: str = 'log_time', raw: bool = False
                 ) -> Iterator[Tuple[str, str, Any, int]]:
        """Yield ``(topic, 'pkg/msg/Type', deserialised message, log_time_ns)``.

        Args:
            topics: all topics (None), a name, names, or a mapping name -> expected type
                (class or ``pkg/msg/Type``) to check what was recorded.
            order: ``'log_time'`` (default): by log time, ties in file order, as rosbag2 plays
                a bag; messages stored out of that order are counted in :attr:`out_of_order`.
                ``'file'``: in the order they were written.
            raw: yield the CDR bytes instead of deserialised messages (no message class
                needed).

        With ``topics`` None, topics whose message type is not installed (``tf2_msgs`` with
        the PyPI wheels) are left out unless ``raw``.

        Raises:
            BagError: a requested topic is not in the bag, was recorded with another type, or
                its message type is not installed; the file is damaged.
        """
        if order not in ('log_time', 'file'):
            raise ValueError(f'order must be log_time or file, not {order!r}')
        wanted, recorded = self._wanted_topics(topics, raw)
        classes = {} if raw else {name: _message_class(recorded[name]) for name in wanted}

        def decode(data, name):
            return bytes(data) if raw else deserialize_message(data, classes[name])

        bound = self._chunk_bounds() if order == 'log_time' else {}
        pending: list = []
        sequence = 0
        newest = -1
        self.out_of_order = 0

        def due(limit):
            while pending and pending[0][0] <= limit:
                log_time, _, name, type_name, data = heapq.heappop(pending)
                yield name, type_name, decode(data, name), log_time

        for offset, name, type_name, record in self._message_records(wanted):
            if record.log_time < newest:
                self.out_of_order += 1
            newest = max(newest, record.log_time)
            if order == 'file':
                yield name, type_name, decode(record.data, name), record.log_time
                continue
            yield from due(bound.get(offset, -1))
            heapq.heappush(pending, (record.log_time, sequence, name, type_name, record.data))
            sequence += 1
        yield from due(float('inf'))

    def _message_records(self, wanted: set) -> Iterator[Tuple[int, str, str, Message]]:
        """``(offset, topic, type, Message record)`` of the ``wanted`` topics in file order."""
        schemas: Dict[int, str] = {}
        channels: Dict[int, Tuple[str, str]] = {}
        for offset, record in self._scan():
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, schemas.get(record.schema_id, ''))
            elif isinstance(record, Message):
                if record.channel_id not in channels:
                    raise BagError(f'{self.path}: a message at byte {offset} is on channel '
                                   f'{record.channel_id}, which no channel record defines')
                name, type_name = channels[record.channel_id]
                if name in wanted:
                    yield offset, name, type_name, record

    def _wanted_topics(self, topics, raw: bool) -> Tuple[set, Dict[str, str]]:
        """The topics :meth:`messages` reads (checked against what was recorded), and the
        recorded topic -> type."""
        recorded = self.topics()
        if topics is None:
            wanted = set(recorded)
            if not raw:
                for name in list(wanted):
                    try:
                        _message_class(recorded[name])
                    except BagError:
                        wanted.discard(name)
            return wanted, recorded
        expected = (dict(topics) if isinstance(topics, Mapping)
                    else dict.fromkeys([topics] if isinstance(topics, str) else topics))
        missing = sorted(set(expected) - set(recorded))
        if missing:
            raise BagError(f'{self.path} has no topic {", ".join(missing)} '
                           f'(recorded: {", ".join(sorted(recorded)) or "none"})')
        for name, msg_type in expected.items():
            if msg_type is not None and _type_string(msg_type) != recorded[name]:
                raise BagError(f'{self.path}: topic {name} holds {recorded[name]}, '
                               f'not {_type_string(msg_type)}')
        return set(expected), recorded

    def _chunk_bounds(self) -> Dict[int, float]:
        """Log-time order with bounded memory: chunk offset -> the earliest log time it or any
        later chunk may hold (each chunk's ``message_start_time``, suffix minimum), which says
        which buffered messages are due. A file already in order buffers at most one chunk."""
        try:
            units = McapScan(self.path).chunk_start_times()
        except OSError as exc:
            raise BagError(f'cannot read bag {self.path}: {exc.strerror or exc}') from None
        bound: Dict[int, float] = {}
        low = float('inf')
        for offset, start in reversed(units):
            low = min(low, start)
            bound[offset] = low
        return bound

    def metadata(self) -> Dict[str, Dict[str, str]]:
        """Metadata records, name -> key/value dict (the last record of a name wins, as in
        rosbag2), e.g. ``rosbag2`` and :data:`PARAMETERS_METADATA`."""
        return {record.name: dict(record.metadata)
                for record in self._records(emit_chunks=True) if isinstance(record, Metadata)}
