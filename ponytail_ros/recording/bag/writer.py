"""``BagWriter``: an MCAP bag in rosbag2's layout, written on a background thread (the caller
never waits on the disk). See the package docstring for the layout and the durability.
"""
from __future__ import annotations

import atexit
import operator
import os
import queue
import signal
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap import __version__ as _MCAP_VERSION
from rclpy.qos import QoSProfile

from ..cdr import serialize_canonical
from .errors import BagError
from .mcap_out import McapOut
from .metadata import (
    _DEFAULT_ROS_DISTRO,
    _MAX_TIME_NS,
    _ROSBAG2_METADATA_VERSION,
    _ROSBAG2_RECORD,
    _dump_yaml,
    _qos_dict,
)
from .msgdefs import _message_class, _type_string, message_definition, type_hash

__all__ = ['BagWriter']

_PROFILE = 'ros2'
_LIBRARY = f'ponytail_ros.recording.bag (mcap-python {_MCAP_VERSION})'
# opcode 1 + record length 8 + channel id 2 + sequence 4 + log time 8 + publish time 8 bytes
_MESSAGE_RECORD_OVERHEAD = 31


@dataclass
class _Topic:
    """Everything recorded about a topic; built on the caller thread by add_topic."""

    name: str
    type_name: str
    msg_class: type | None      # None: a type not installed (written serialised only)
    definition: str
    qos: dict
    type_hash: str
    # Written by the writer thread only.
    channel_id: int = 0
    message_count: int = 0


_CLOSE = object()  # queue sentinel: finalise the file and end the thread


class BagWriter:
    """Records ROS messages into one MCAP file in rosbag2's layout, off the caller's thread.

    ``write`` serialises on the caller thread and only enqueues; a background thread does all
    file I/O, so a simulation tick never waits on the disk. See the module docstring for the
    durability bound (what a SIGKILL loses) and signal handling.

    Use as a context manager or call :meth:`close`. I/O errors after opening (disk full, ...)
    never raise into ``write``: the writer thread records the first one in :attr:`error`,
    stops writing and drops later messages; leaving the ``with`` block raises it.

    Args:
        path: the ``.mcap`` file to create.
        overwrite: replace an existing file; otherwise an existing file is an error.
        chunk_size: bytes of message data after which a chunk is written out.
        chunk_duration_ns: log time (ns) a chunk may span before it is written out; also the
            wall time without messages after which a partial chunk is written out.
        background: write on a background thread (the default: a live node's tick never
            waits on the disk). False: write in the caller's thread, for an offline run that
            waits on nothing: it saves the thread hand-offs (~10 % of a replay's CPU).

    Raises:
        BagError: the file exists (and ``overwrite`` is false), its folder is missing, it is
            not writable, or the first bytes cannot be written.
    """

    def __init__(self, path: str | os.PathLike, *, overwrite: bool = False,
                 chunk_size: int = 64 * 1024, chunk_duration_ns: int = 500_000_000,
                 background: bool = True):
        if chunk_size <= 0 or chunk_duration_ns <= 0:
            raise BagError('chunk_size and chunk_duration_ns must be positive')
        self.path = Path(path)
        self._chunk_size = chunk_size
        self._chunk_duration_ns = chunk_duration_ns
        self._ros_distro = os.environ.get('ROS_DISTRO') or _DEFAULT_ROS_DISTRO
        self._topics: dict[str, _Topic] = {}
        #: rosbag2's ``custom_data`` (str -> str) of the final metadata record (e.g. that the
        #: run is partial); set it before :meth:`close`.
        self.custom_data: dict[str, str] = {}
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BagError | None = None
        self._closed = False
        # Writer-thread state: the chunk being built (the message statistics: McapOut's).
        self._schema_ids: dict[str, int] = {}
        self._chunk_start_ns: int | None = None
        self._chunk_bytes = 0

        self._stream = self._open(self.path, overwrite)
        # Chunks are cut by _flush_chunk (size or log-time span, then flushed to the OS). No
        # compression, as rosbag2's default. The bytes are mcap's Writer's (mcap_out.py).
        self._mcap = McapOut(self._stream)
        try:
            self._mcap.start(profile=_PROFILE, library=_LIBRARY)
            self._mcap.add_metadata(_ROSBAG2_RECORD, self._rosbag2_metadata())
            self._stream.flush()
        except OSError as exc:
            _close_quietly(self._stream)
            raise BagError(f'cannot write bag {self.path}: {_reason(exc)}') from None
        self._thread: threading.Thread | None = None
        self._finished = False
        if background:
            self._thread = threading.Thread(target=self._run,
                                            name=f'BagWriter {self.path.name}', daemon=True)
            self._thread.start()
        atexit.register(self.close)

    @staticmethod
    def _open(path: Path, overwrite: bool):
        try:
            return path.open('wb' if overwrite else 'xb')
        except FileExistsError:
            reason = 'file already exists (pass overwrite=True to replace it)'
        except FileNotFoundError:
            reason = f'folder {path.parent} does not exist'
        except PermissionError:
            reason = 'permission denied'
        except OSError as exc:
            reason = exc.strerror or str(exc)
        raise BagError(f'cannot create bag {path}: {reason}')

    @property
    def error(self) -> BagError | None:
        """The I/O error that stopped recording, or None while all is well."""
        return self._error

    def add_topic(self, name: str, msg_type: str | type,
                  qos: QoSProfile | int = 10, *, definition: str | None = None,
                  type_hash_: str | None = None) -> None:
        """Declare a topic before writing to it.

        Args:
            name: topic name, e.g. ``'/ponytail/markers'``.
            msg_type: message class or type string ``'pkg/msg/Type'``.
            qos: the publisher's QoS profile, or a history depth for rclpy's default
                (keep last, reliable, volatile); recorded as ``offered_qos_profiles`` so that
                ``ros2 bag play`` republishes with it.

            definition, type_hash_: the ``ros2msg`` schema text and ``RIHS01`` hash of a type
                whose Python package is not installed (``tf2_msgs``); its messages are then
                written with :meth:`write_serialized` only.

        Raises:
            BagError: the topic exists, the writer is closed, or the type's definition is not
                installed.
        """
        if self._closed:
            raise BagError(f'bag {self.path} is closed')
        if name in self._topics:
            raise BagError(f'topic {name!r} already added to bag {self.path}')
        type_name = _type_string(msg_type)
        profile = qos if isinstance(qos, QoSProfile) else QoSProfile(depth=qos)
        if definition is not None:
            topic = _Topic(name=name, type_name=type_name, msg_class=None, definition=definition,
                           qos=_qos_dict(profile), type_hash=type_hash_ or '')
        else:
            topic = _Topic(name=name, type_name=type_name,
                           msg_class=_message_class(type_name),
                           definition=message_definition(type_name), qos=_qos_dict(profile),
                           type_hash=type_hash(type_name))
        self._topics[name] = topic
        self._submit(('topic', topic))

    def write(self, topic: str, msg: Any, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Serialise ``msg`` and queue it for writing; never waits on the disk.

        Args:
            topic: a topic declared with :meth:`add_topic`.
            msg: a message of that topic's type.
            log_time_ns: recording time, ns (rosbag2's receive time; simulation clock).
            publish_time_ns: publication time, ns; defaults to ``log_time_ns``.

        Raises:
            BagError: unknown topic, wrong message type, or the writer is closed.
        """
        entry = self._topics.get(topic)
        if entry is None:
            raise BagError(f'topic {topic!r} was not added to bag {self.path}')
        if type(msg) is not entry.msg_class:
            raise BagError(f'topic {topic!r} records {entry.type_name}, '
                           f'got {type(msg).__module__}.{type(msg).__name__}')
        # Canonical CDR: rclpy leaves padding uninitialised and may append slack bytes that
        # rosbags rejects (recording/cdr.py).
        self.write_serialized(topic, serialize_canonical(msg), log_time_ns, publish_time_ns)

    def write_serialized(self, topic: str, data: bytes, log_time_ns: int,
                         publish_time_ns: int | None = None) -> None:
        """Queue an already CDR-serialised message; arguments as :meth:`write`."""
        entry = self._topics.get(topic)
        if entry is None:
            raise BagError(f'topic {topic!r} was not added to bag {self.path}')
        log_time_ns = operator.index(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else operator.index(
            publish_time_ns)
        if log_time_ns < 0 or publish_time_ns < 0:
            raise BagError(f'negative time for a message on {topic!r}')
        if self._closed:
            raise BagError(f'bag {self.path} is closed')
        if self._error is None:  # after an I/O error messages are dropped, not queued
            if self._thread is None:
                # (no thread: written now, as _process would, without the hand-offs)
                try:
                    self._message(entry, bytes(data), log_time_ns, publish_time_ns)
                except Exception as exc:  # noqa: BLE001 - as in _process
                    self._failed_io(exc)
            else:
                self._queue.put(('message', entry, bytes(data), log_time_ns, publish_time_ns))

    def write_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Store a metadata record (e.g. :data:`PARAMETERS_METADATA`); all keys and values str.

        Raises:
            BagError: reserved name ``rosbag2``, non-string entries, or the writer is closed.
        """
        if name == _ROSBAG2_RECORD:
            raise BagError('metadata name "rosbag2" is reserved for the bag metadata')
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise BagError(f'metadata {name!r} must map str to str')
        if self._closed:
            raise BagError(f'bag {self.path} is closed')
        self._submit(('metadata', name, dict(data)))

    def close(self) -> None:
        """Write out everything queued, the final metadata and the summary; close the file.

        Idempotent, and safe from a signal handler or ``atexit``: it only enqueues and joins
        the writer thread. Every call returns only once the file is finalised, so a signal
        handler that interrupts a ``close`` in progress still waits for it. Does not raise on
        I/O errors; check :attr:`error`.
        """
        if not self._closed:
            self._closed = True
            self._submit(_CLOSE)
        if self._thread is not None:
            self._thread.join()
        atexit.unregister(self.close)

    def close_on_signals(self, signals: Iterable[int] = (signal.SIGINT, signal.SIGTERM)) -> None:
        """Finalise the bag when one of ``signals`` arrives, then act as before.

        The handler closes the writer and then calls the handler that was installed before
        (SIGINT: KeyboardInterrupt); for a default action (SIGTERM: terminate) it restores the
        default and re-sends the signal, so the exit status still says "killed by SIGTERM".
        Must be called from the main thread. SIGKILL cannot be caught; see the module docstring
        for what it loses.
        """
        for signum in signals:
            previous = signal.getsignal(signum)

            def handler(received, frame, previous=previous):
                self.close()
                if callable(previous):
                    previous(received, frame)
                elif previous == signal.SIG_DFL:
                    signal.signal(received, signal.SIG_DFL)
                    os.kill(os.getpid(), received)

            signal.signal(signum, handler)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        self.close()
        if exc_type is None and self._error is not None:
            raise self._error

    # -- writer thread ----------------------------------------------------------------------

    def _submit(self, item) -> None:
        """To the writer thread's queue, or (no thread) written now."""
        if self._thread is not None:
            self._queue.put(item)
        else:
            self._process(item)

    def _run(self) -> None:
        idle_timeout_s = self._chunk_duration_ns / 1e9
        while True:
            try:
                item = self._queue.get(timeout=idle_timeout_s)
            except queue.Empty:
                item = ('idle',)
            self._process(item)
            if item is _CLOSE:
                return

    def _process(self, item) -> None:
        if item is _CLOSE:
            if not self._finished:
                self._finished = True
                self._finish()
            return
        if self._error is not None:
            return  # recording stopped; drain the queue until close
        try:
            self._handle(item)
        # Any failure (ENOSPC, EIO, ...) stops recording; it must never reach the caller.
        except Exception as exc:  # noqa: BLE001
            self._failed_io(exc)

    def _failed_io(self, exc: Exception) -> None:
        self._error = BagError(
            f'writing bag {self.path} failed: {_reason(exc)}; recording stopped')

    def _message(self, topic: _Topic, data: bytes, log_time_ns: int,
                 publish_time_ns: int) -> None:
        """One message into the chunk (the writer thread's, or the caller's without one)."""
        topic.message_count += 1
        # rosbag2 records the publisher's sequence number; ours counts per topic from 1.
        self._mcap.add_message(topic.channel_id, log_time_ns, data, publish_time_ns,
                               topic.message_count)
        if self._chunk_start_ns is None:
            self._chunk_start_ns = log_time_ns
        self._chunk_bytes += len(data) + _MESSAGE_RECORD_OVERHEAD
        if (self._chunk_bytes >= self._chunk_size
                or log_time_ns - self._chunk_start_ns >= self._chunk_duration_ns):
            self._flush_chunk()

    def _handle(self, item: tuple) -> None:
        kind = item[0]
        if kind == 'message':
            self._message(*item[1:])
        elif kind == 'idle':
            if self._chunk_start_ns is not None:
                self._flush_chunk()
        elif kind == 'topic':
            topic = item[1]
            schema_id = self._schema_ids.get(topic.type_name)
            if schema_id is None:
                schema_id = self._mcap.register_schema(
                    name=topic.type_name, encoding='ros2msg',
                    data=topic.definition.encode('utf-8'))
                self._schema_ids[topic.type_name] = schema_id
            topic.channel_id = self._mcap.register_channel(
                topic=topic.name, message_encoding='cdr', schema_id=schema_id,
                metadata={'offered_qos_profiles': _dump_yaml([topic.qos]),
                          'topic_type_hash': topic.type_hash})
        elif kind == 'metadata':
            self._mcap.add_metadata(item[1], item[2])
            self._stream.flush()

    def _flush_chunk(self) -> None:
        """Write the current chunk and its index and hand them to the OS."""
        self._mcap.flush()
        self._chunk_start_ns = None
        self._chunk_bytes = 0

    def _finish(self) -> None:
        try:
            if self._error is None:
                self._mcap.add_metadata(_ROSBAG2_RECORD, self._rosbag2_metadata())
                self._mcap.finish()
            self._stream.close()
        except Exception as exc:  # noqa: BLE001 - as in _run
            if self._error is None:
                self._error = BagError(f'finalising bag {self.path} failed: {_reason(exc)}')
            _close_quietly(self._stream)

    def _rosbag2_metadata(self) -> dict[str, str]:
        """The ``rosbag2`` record: rosbag2_storage's YAML encoding of BagMetadata (version 9)."""
        message_count, first_ns, last_ns = self._mcap.stats()
        if message_count:
            starting_time = first_ns
            duration = last_ns - first_ns
        else:
            starting_time, duration = _MAX_TIME_NS, 0
        file_name = self.path.name
        metadata = {
            'version': _ROSBAG2_METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': starting_time},
            'message_count': message_count,
            'topics_with_message_count': [
                {'topic_metadata': {'name': topic.name,
                                    'type': topic.type_name,
                                    'serialization_format': 'cdr',
                                    'offered_qos_profiles': [topic.qos],
                                    'type_description_hash': topic.type_hash},
                 'message_count': topic.message_count}
                # list(): one atomic copy, as add_topic may run on the caller thread meanwhile
                for topic in list(self._topics.values()) if topic.channel_id],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [file_name],
            'files': [{'path': file_name,
                       'starting_time': {'nanoseconds_since_epoch': starting_time},
                       'duration': {'nanoseconds': duration},
                       'message_count': message_count}],
            'custom_data': dict(self.custom_data) or None,
            'ros_distro': self._ros_distro,
        }
        # Current rosbag2 keeps the distro in serialized_metadata only; earlier releases wrote
        # this ROS_DISTRO key, which rosbag2's reader still honours, so both are written.
        return {'serialized_metadata': _dump_yaml(metadata), 'ROS_DISTRO': self._ros_distro}


def _reason(exc: Exception) -> str:
    """'No space left on device' for an OSError, the repr of anything else."""
    return exc.strerror if isinstance(exc, OSError) and exc.strerror else repr(exc)


def _close_quietly(stream) -> None:
    """Close a file whose writing already failed; its final flush may fail the same way."""
    try:
        stream.close()
    except OSError:
        pass  # the failure is reported by the caller; the descriptor is released regardless
