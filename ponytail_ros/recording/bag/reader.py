"""``BagReader``: a bag as rosbag2 writes it -- a folder (``metadata.yaml``) of one or more
MCAP or sqlite3 files, or a single file (``layout.py``) -- read back in log-time order with
bounded memory or in file order.

Each MCAP file is read by ``McapFileReader``, which checks every record (``mcap_scan.py``):
damage is an error naming the byte, a cut-off file is read up to the cut and says so. Each
``.db3`` file is read by ``Db3FileReader`` (``rosbags``). Compression as rosbag2 writes it
(zstd: whole files, single messages, MCAP chunks) is undone on the way.
"""
from __future__ import annotations

import heapq
import itertools
import os
import struct
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from rclpy.serialization import deserialize_message

from ..mcap_scan import MAGIC as _MCAP_MAGIC, McapScan, ScanError, is_finished
from .errors import BagError
from .layout import BagLayout, resolve_bag, zstd_module
from .msgdefs import _message_class
from .wanted import wanted_topics

__all__ = ['BagReader', 'McapFileReader']

class McapFileReader:
    """Reads one MCAP file, checked record by record (``mcap_scan.McapScan``).

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
        decompress: applied to every message's data (rosbag2's per-message compression).
        label: the file's name in messages (default ``path``; a file decompressed whole into
            a temporary folder is named as the user knows it).

    Raises:
        BagError: the file does not exist, cannot be read, or is not MCAP.
    """

    def __init__(self, path: str | os.PathLike,
                 decompress: Callable[[bytes], bytes] | None = None,
                 label: str | os.PathLike | None = None):
        self.path = Path(path)
        self.label = Path(label) if label is not None else self.path
        self._decompress = decompress
        try:
            with self.path.open('rb') as file:
                magic = file.read(len(_MCAP_MAGIC))
            self._finished = is_finished(self.path)
        except OSError as exc:
            raise BagError(f'cannot read bag {self.label}: {exc.strerror or exc}') from None
        if magic != _MCAP_MAGIC:
            raise BagError(f'{self.label} is not an MCAP file')
        #: Where and why the file is cut short ("truncated at byte N of M: ..."), known after a
        #: full read (:meth:`metadata`, :meth:`messages`); None for a complete file.
        self.truncation: str | None = None
        #: Messages of the last :meth:`messages` call stored before one with a later log time.
        self.out_of_order = 0

    @property
    def finished(self) -> bool:
        """The file ends with the MCAP magic (its writer closed it)."""
        return self._finished

    def _damaged(self, exc: ScanError) -> BagError:
        if exc.problem.kind != 'damaged':
            return BagError(f'{self.label} is {exc}')
        return BagError(f'{self.label} is {exc}; replaying it would use or skip corrupt data. '
                        f'"ponytail_replay repair {self.label} FIXED.mcap" keeps every intact '
                        f'record')

    def _scan(self, expand_chunks: bool = True) -> Iterator[tuple[int, Any]]:
        """``(offset, record)`` in file order; damage raises, a cut sets :attr:`truncation`."""
        try:
            scan = McapScan(self.path)
            yield from scan.records(expand_chunks=expand_chunks)
        except ScanError as exc:
            raise self._damaged(exc) from None
        except OSError as exc:
            raise BagError(f'cannot read bag {self.label}: {exc.strerror or exc}') from None
        self.truncation = (scan.truncation.describe(scan.size)
                           if scan.truncation is not None else None)

    def _records(self, emit_chunks: bool = False) -> Iterator[Any]:
        for _, record in self._scan(expand_chunks=not emit_chunks):
            yield record

    def check(self) -> str | None:
        """Read every record (chunk CRCs included); the truncation text or None.

        Raises:
            BagError: the file is damaged.
        """
        for _ in self._scan():
            pass
        return self.truncation

    def topics(self) -> dict[str, str]:
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
        schemas: dict[int, str] = {}
        topics: dict[str, str] = {}
        for record in self._records():
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                topics[record.topic] = schemas.get(record.schema_id, '')
        return topics

    def messages(self, topics: None | str | Iterable[str] | Mapping[str, str | type]
                 = None, order: str = 'log_time', raw: bool = False
                 ) -> Iterator[tuple[str, str, Any, int]]:
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

        unpack = self._decompress

        def decode(data, name):
            if unpack is not None:
                data = unpack(data)
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

    def _message_records(self, wanted: set) -> Iterator[tuple[int, str, str, Message]]:
        """``(offset, topic, type, Message record)`` of the ``wanted`` topics in file order."""
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        for offset, record in self._scan():
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, schemas.get(record.schema_id, ''))
            elif isinstance(record, Message):
                if record.channel_id not in channels:
                    raise BagError(f'{self.label}: a message at byte {offset} is on channel '
                                   f'{record.channel_id}, which no channel record defines')
                name, type_name = channels[record.channel_id]
                if name in wanted:
                    yield offset, name, type_name, record

    def _wanted_topics(self, topics, raw: bool) -> tuple[set, dict[str, str]]:
        """The topics :meth:`messages` reads (checked against what was recorded), and the
        recorded topic -> type."""
        recorded = self.topics()
        return wanted_topics(self.label, recorded, topics, raw), recorded

    def _chunk_bounds(self) -> dict[int, float]:
        """Log-time order with bounded memory: chunk offset -> the earliest log time it or any
        later chunk may hold (each chunk's ``message_start_time``, suffix minimum), which says
        which buffered messages are due. A file already in order buffers at most one chunk."""
        try:
            units = McapScan(self.path).chunk_start_times()
        except OSError as exc:
            raise BagError(f'cannot read bag {self.label}: {exc.strerror or exc}') from None
        bound: dict[int, float] = {}
        low = float('inf')
        for offset, start in reversed(units):
            low = min(low, start)
            bound[offset] = low
        return bound

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records, name -> key/value dict (the last record of a name wins, as in
        rosbag2), e.g. ``rosbag2`` and :data:`PARAMETERS_METADATA`."""
        return {record.name: dict(record.metadata)
                for record in self._records(emit_chunks=True) if isinstance(record, Metadata)}


class BagReader:
    """A rosbag2 bag (folder, ``metadata.yaml``, or one ``.mcap`` / ``.db3`` file; see
    ``layout.py``), every file it lists read in order, each checked by its file reader.

    * Messages come in log-time order across all files (ties in file order), or in file order
      (``order='file'``: the files one after the other, each in the order it was written).
    * :attr:`notes`: what a user should be told about the input (one file of a split bag
      given alone, a folder without ``metadata.yaml``).
    * :attr:`truncation` after a full read: where the bag is cut short (a file without its
      footer), else None; :attr:`finished`: every file was closed by its writer.

    Raises:
        BagError: the path is not a bag (see ``layout.resolve_bag``), a file cannot be read,
            is not MCAP / sqlite3, or (reading) is damaged.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.layout: BagLayout = resolve_bag(self.path)
        self.notes = list(self.layout.notes)
        self._tmp: Any = None
        unpack = zstd_module().decompress if self.layout.compression_mode == 'message' else None
        cls: Any = McapFileReader
        if self.layout.storage == 'sqlite3':
            from .db3 import Db3FileReader
            cls = Db3FileReader
        self.files = [cls(disk, unpack, label)
                      for disk, label in self._storage_files()]
        self._topics: dict[str, str] | None = None
        self._file_topics: list = []

    def _storage_files(self):
        """``(file to read, its name in messages)`` in order: whole-file compressed files
        (``.zstd``) decompressed into a temporary folder first, as rosbags does."""
        files = self.layout.files
        if not any(f.suffix == '.zstd' for f in files):
            return [(f, f) for f in files]
        zstd = zstd_module()
        self._tmp = tempfile.TemporaryDirectory(prefix='ponytail_bag_')
        out = []
        for f in files:
            if f.suffix != '.zstd':
                out.append((f, f))
                continue
            disk = Path(self._tmp.name) / f.stem
            try:
                with f.open('rb') as src, zstd.open(src, 'rb') as unpacked, \
                        disk.open('wb') as dst:
                    while True:
                        block = unpacked.read(1 << 20)
                        if not block:
                            break
                        dst.write(block)
            except OSError as exc:
                raise BagError(f'cannot read bag {f}: {exc.strerror or exc}') from None
            except Exception as exc:  # noqa: BLE001 - zstd's errors: a damaged file
                raise BagError(f'{f} does not decompress (zstd: {exc}): the file is damaged '
                               f'or cut short') from None
            out.append((disk, f))
        return out

    @property
    def finished(self) -> bool:
        """Every file ends as its writer closed it (MCAP: the trailing magic)."""
        return all(f.finished for f in self.files)

    @property
    def truncation(self) -> str | None:
        """Where the bag is cut short ("truncated at byte N of M: ..."), known after a full read
        (:meth:`metadata`, :meth:`messages`); None for a complete bag."""
        cut = [(f, f.truncation) for f in self.files if f.truncation]
        if not cut:
            return None
        if len(self.files) == 1 and not self.layout.is_folder:
            return cut[0][1]
        return '; '.join(f'cut short in {f.label.name} ({text})' for f, text in cut)

    @property
    def out_of_order(self) -> int:
        """Messages of the last :meth:`messages` call stored before one with a later log
        time (within a file)."""
        return sum(f.out_of_order for f in self.files)

    def check(self) -> str | None:
        """Read every record of every file; the truncation text or None.

        Raises:
            BagError: a file is damaged.
        """
        for f in self.files:
            f.check()
        return self.truncation

    def topics(self) -> dict[str, str]:
        """Topic name -> message type ``pkg/msg/Type`` (over all files)."""
        if self._topics is None:
            self._file_topics = [f.topics() for f in self.files]
            merged: dict[str, str] = {}
            for f, topics in zip(self.files, self._file_topics, strict=True):
                for name, type_name in topics.items():
                    if merged.setdefault(name, type_name) != type_name:
                        raise BagError(f'{self.path}: topic {name} holds {merged[name]} in one '
                                       f'file and {type_name} in {f.label.name}')
            self._topics = merged
        return dict(self._topics)

    def messages(self, topics: None | str | Iterable[str] | Mapping[str, str | type]
                 = None, order: str = 'log_time', raw: bool = False
                 ) -> Iterator[tuple[str, str, Any, int]]:
        """Yield ``(topic, 'pkg/msg/Type', deserialised message, log_time_ns)``.

        Args:
            topics: all topics (None), a name, names, or a mapping name -> expected type
                (class or ``pkg/msg/Type``) to check what was recorded.
            order: ``'log_time'`` (default): by log time over all files, ties in file order,
                as rosbag2 plays a bag; messages stored out of that order are counted in
                :attr:`out_of_order`. ``'file'``: in the order they were written.
            raw: yield the CDR bytes instead of deserialised messages (no message class
                needed).

        With ``topics`` None, topics whose message type is not installed (``tf2_msgs`` with
        the PyPI wheels) are left out unless ``raw``.

        Raises:
            BagError: a requested topic is not in the bag, was recorded with another type, or
                its message type is not installed; a file is damaged.
        """
        if order not in ('log_time', 'file'):
            raise ValueError(f'order must be log_time or file, not {order!r}')
        recorded = self.topics()
        wanted = wanted_topics(self.path, recorded, topics, raw)
        if not raw:
            for name in wanted:
                _message_class(recorded[name])     # (not installed: said before any read)
        streams = []
        for f, in_file in zip(self.files, self._file_topics, strict=True):
            mine = {name: recorded[name] for name in sorted(wanted) if name in in_file}
            if mine:
                streams.append(f.messages(mine, order=order, raw=raw))
        if len(streams) == 1:
            yield from streams[0]
        elif order == 'file':
            yield from itertools.chain(*streams)
        else:
            yield from heapq.merge(*streams, key=lambda m: m[3])

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records, name -> key/value dict (the last record of a name wins, as in
        rosbag2), e.g. ``rosbag2`` and :data:`PARAMETERS_METADATA`. For a bag folder the
        ``rosbag2`` entry is its ``metadata.yaml`` (the whole bag's counts)."""
        out: dict[str, dict[str, str]] = {}
        for f in self.files:
            out.update(f.metadata())
        if self.layout.info is not None:
            import yaml
            out['rosbag2'] = {'serialized_metadata': yaml.safe_dump(
                {'rosbag2_bagfile_information': self.layout.info}, sort_keys=False)}
        return out

    def span_ns(self) -> tuple[int, int] | None:
        """(first, last) log time of a finished bag (its rosbag2 metadata or MCAP summary),
        else None."""
        if not self.finished:
            return None
        info = self.layout.info
        if info is not None:
            try:
                start = int(info['starting_time']['nanoseconds_since_epoch'])
                return start, start + int(info['duration']['nanoseconds'])
            except (KeyError, TypeError, ValueError):
                return None
        if self.layout.storage != 'mcap':
            return None
        from mcap.reader import make_reader
        try:
            with self.files[0].path.open('rb') as f:
                summary = make_reader(f).get_summary()
            stats = summary.statistics if summary is not None else None
            if stats is None:
                return None
            return stats.message_start_time, stats.message_end_time
        except Exception:  # noqa: BLE001 - only a progress bar needs it
            return None
