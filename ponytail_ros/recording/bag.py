"""MCAP bags laid out the way rosbag2's MCAP storage plugin writes them.

A file written by :class:`BagWriter` opens in ``ros2 bag info`` / ``ros2 bag play``, Foxglove and
the ``rosbags`` library like one recorded by ``ros2 bag record -s mcap``:

* header profile ``ros2``;
* one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``, whose data is the
  type's ``.msg`` text followed by every nested non-primitive type (a line of 80 ``=``,
  ``MSG: pkg/Type``, its text), depth first, each dependency once, dependencies of one message in
  sorted order -- what rosbag2_cpp's ``LocalMessageDefinitionSource::get_full_text`` produces;
* one channel per topic, message encoding ``cdr``, with the channel metadata
  ``offered_qos_profiles`` (the YAML rosbag2 writes, metadata version 9 policy names) and
  ``topic_type_hash`` (``RIHS01_...``);
* messages serialised with ``rclpy.serialization`` (padding zeroed, see ``cdr``); ``log_time`` and
  ``publish_time`` in ns;
* a ``rosbag2`` metadata record (``serialized_metadata``: the YAML bag metadata, version 9, plus
  ``ROS_DISTRO``) written when the file is opened and again, with the final counts, when it is
  closed -- as rosbag2's ``SequentialWriter`` does with ``update_metadata`` on open and close;
* uncompressed chunks, like rosbag2's default storage options.

The ``.msg`` texts and type hashes are read from the installed interface packages
(``share/<pkg>/msg/<Type>.msg`` and ``.json``), never from copies in this code.

Time: every time in this module is an integer number of nanoseconds (``*_ns``), on whatever
clock the caller uses for log time (normally the simulation clock).

Durability: file I/O happens on a background thread. The current chunk is pushed to the
operating system when it reaches ``chunk_size`` bytes, when its messages span
``chunk_duration_ns`` of log time, and when no message has arrived for ``chunk_duration_ns`` of
wall time. If the process is killed (SIGKILL, a crash), every chunk pushed before that survives
and :class:`BagReader` reads it back; what is lost is the chunk being built -- messages within
``chunk_duration_ns`` of log time (default 0.5 s) of the end -- plus any messages still queued
for the writer thread (normally none: the thread keeps up unless the disk stalls). Data is not
``fsync``-ed, so this bound covers the death of the process, not of the machine. Such a file has
no summary or index: ``ponytail_replay repair`` rewrites it as a complete, indexed file that
indexed readers (``rosbags``, mcap's ``SeekingReader``) open too.

Reading (:class:`BagReader`) checks every record (``mcap_scan.py``): a damaged file (chunk or
data-section CRC mismatch, a record that does not fit its length) is an error naming the byte,
never a shorter file; a cut-short one is read up to the cut and says where it is cut.

Signals: :meth:`BagWriter.close` is idempotent and safe to call from a signal handler, a
``finally`` block or ``atexit`` (every writer registers it with ``atexit``, so a normal
interpreter exit finalises the file). SIGTERM's default action kills the process without running
``atexit``; call :meth:`BagWriter.close_on_signals` to finalise on SIGINT/SIGTERM.

This module imports rclpy; nothing in ``ponytail_ros.core`` may import it.
"""
from __future__ import annotations

import atexit
import heapq
import importlib
import json
import operator
import os
import queue
import re
import signal
import struct
import sys
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Mapping, Optional, Tuple, Union

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from mcap import __version__ as _MCAP_VERSION
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer
from rclpy.qos import (
    QoSDurabilityPolicy, QoSHistoryPolicy, QoSLivelinessPolicy, QoSProfile, QoSReliabilityPolicy,
)
from rclpy.serialization import deserialize_message

from ponytail_ros.recording.cdr import serialize_canonical
from ponytail_ros.recording.mcap_scan import MAGIC as _MCAP_MAGIC
from ponytail_ros.recording.mcap_scan import McapScan, ScanError, is_finished

try:
    from rosidl_runtime_py.utilities import get_message as _get_message
except ImportError:  # not shipped as a PyPI wheel; _message_class imports the module itself
    _get_message = None

__all__ = ['BagError', 'BagWriter', 'BagReader', 'PARAMETERS_METADATA']

#: Metadata record name for the parameters in effect during a recording (str -> str).
PARAMETERS_METADATA = 'ponytail_ros/parameters'

_PROFILE = 'ros2'
_LIBRARY = f'ponytail_ros.recording.bag (mcap-python {_MCAP_VERSION})'
_ROSBAG2_RECORD = 'rosbag2'
_ROSBAG2_METADATA_VERSION = 9
# The PyPI wheels this package targets are Kilted builds and do not set ROS_DISTRO.
_DEFAULT_ROS_DISTRO = 'kilted'
_MAX_TIME_NS = 2**63 - 1  # rosbag2's "no message yet" starting time (nanoseconds::max())
# opcode 1 + record length 8 + channel id 2 + sequence 4 + log time 8 + publish time 8 bytes
_MESSAGE_RECORD_OVERHEAD = 31

# Field types and .msg parsing exactly as rosbag2_cpp's local_message_definition_source.cpp.
_PRIMITIVE_TYPES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string'})
_MSG_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_ROS_NAME = '[a-zA-Z][a-zA-Z0-9_]*'
_TYPE_NAME = re.compile(rf'({_ROS_NAME})/(?:({_ROS_NAME})/)?({_ROS_NAME})')
_DELIMITER = '=' * 80 + '\n'


class BagError(Exception):
    """A bag cannot be created, written or read; the message names the file and the reason."""


# --------------------------------------------------------------------------------------------
# Interface definitions from the installed packages


def _split_type(type_name: str) -> Tuple[str, str, str]:
    """``'pkg/msg/Type'`` or ``'pkg/Type'`` -> ``('pkg', 'msg', 'Type')``."""
    match = _TYPE_NAME.fullmatch(type_name)
    if match is None:
        raise BagError(f'invalid message type name {type_name!r} (expected pkg/msg/Type)')
    package, namespace, name = match.groups()
    return package, namespace or 'msg', name


def _type_string(msg_type: Union[str, type]) -> str:
    """Full type name ``pkg/msg/Type`` of a message class or type string."""
    if isinstance(msg_type, str):
        return '/'.join(_split_type(msg_type))
    # Generated classes live in modules named pkg.msg._type.
    package, namespace = msg_type.__module__.split('.')[:2]
    return f'{package}/{namespace}/{msg_type.__name__}'


def _message_class(type_name: str) -> type:
    """The installed Python class of ``pkg/msg/Type``."""
    package, namespace, name = _split_type(type_name)
    try:
        if _get_message is not None:
            return _get_message(f'{package}/{namespace}/{name}')
        return getattr(importlib.import_module(f'{package}.{namespace}'), name)
    except (ImportError, AttributeError, ValueError) as exc:
        raise BagError(f'message type {type_name} is not installed ({exc})') from None


def _share_dir(package: str) -> Path:
    """The ``share/<package>`` directory of an installed ROS package.

    A sourced workspace (AMENT_PREFIX_PATH set) is asked through the ament index. The PyPI
    wheels set no AMENT_PREFIX_PATH but install their share directories under the environment
    prefix, so ``sys.prefix/share`` is searched next.
    """
    searched = []
    if os.environ.get('AMENT_PREFIX_PATH'):
        try:
            return Path(get_package_share_directory(package))
        except PackageNotFoundError:
            searched.append('the ament index (AMENT_PREFIX_PATH)')
    candidate = Path(sys.prefix) / 'share' / package
    if candidate.is_dir():
        return candidate
    searched.append(str(candidate))
    raise BagError(
        f'ROS package {package!r} is not installed: searched {" and ".join(searched)}')


def _interface_file(type_name: str, suffix: str) -> Path:
    package, namespace, name = _split_type(type_name)
    return _share_dir(package) / namespace / f'{name}{suffix}'


def _msg_dependencies(text: str, package: str) -> set:
    """Non-primitive field types of a .msg text, qualified with ``package`` when bare."""
    dependencies = set()
    for match in _MSG_FIELD_TYPE.finditer(text):
        field_type = match.group(1)
        if field_type in _PRIMITIVE_TYPES:
            continue
        dependencies.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return dependencies


@lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type, byte for byte as rosbag2 writes it.

    The type's own ``.msg`` text, then for each dependency not written yet (sorted names, depth
    first): a newline, 80 ``=``, ``MSG: <name as referenced>`` and that type's text.
    """
    return message_definition_of_text(type_name, None)


def message_definition_of_text(type_name: str, text: Optional[str]) -> str:
    """:func:`message_definition` of a type whose own ``.msg`` text is ``text`` (for a type
    whose package is not installed, e.g. ``tf2_msgs``), its dependencies read from the
    installed packages; ``text`` None: read it too."""
    seen = set()

    def full_text(name: str, own: Optional[str] = None) -> str:
        if own is not None:
            text = own
        else:
            path = _interface_file(name, '.msg')
            try:
                text = path.read_bytes().decode('utf-8')
            except OSError as exc:
                raise BagError(f'no .msg definition for {name}: {path}: {exc.strerror}') from None
        result = text
        for dependency in sorted(_msg_dependencies(text, _split_type(name)[0])):
            if dependency not in seen:
                seen.add(dependency)
                result += f'\n{_DELIMITER}MSG: {dependency}\n' + full_text(dependency)
        return result

    return full_text(type_name, text)


@lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The ``RIHS01_<sha256>`` type description hash rosidl generated for a type.

    Read from the ``share/<pkg>/msg/<Type>.json`` type description installed since Iron
    (the Python message classes do not expose it). Empty, as rosbag2 records it, when the
    installation has no such file.
    """
    path = _interface_file(type_name, '.json')
    try:
        description = json.loads(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        return ''
    for entry in description.get('type_hashes', ()):
        if entry.get('type_name') == type_name:
            return entry['hash_string']
    return ''


# --------------------------------------------------------------------------------------------
# YAML in rosbag2's layout


class _YamlCppDumper(yaml.SafeDumper):
    """PyYAML emitting the block style of yaml-cpp, which rosbag2 uses.

    Sequences indented under their key, ``~`` for null, ``""`` for the empty string. Key order
    is the insertion order of the dicts, which follows rosbag2's encoders.
    """

    def increase_indent(self, flow=False, indentless=False):
        return super().increase_indent(flow, False)


_YamlCppDumper.add_representer(
    type(None), lambda dumper, _: dumper.represent_scalar('tag:yaml.org,2002:null', '~'))
_YamlCppDumper.add_representer(
    str, lambda dumper, value: dumper.represent_scalar(
        'tag:yaml.org,2002:str', value, style='"' if value == '' else None))


def _dump_yaml(data: Any) -> str:
    # yaml-cpp's Dump has no trailing newline; width=inf keeps long strings on one line.
    return yaml.dump(data, Dumper=_YamlCppDumper, sort_keys=False, default_flow_style=False,
                     width=float('inf')).rstrip('\n')


def _rmw_time(duration) -> dict:
    """An rclpy Duration as rmw_time_t ``{sec, nsec}`` (infinite -> 9223372036 s 854775807 ns)."""
    return {'sec': duration.nanoseconds // 10**9, 'nsec': duration.nanoseconds % 10**9}


def _qos_dict(qos: QoSProfile) -> dict:
    """One QoS profile as rosbag2 (metadata version 9) encodes it: policy names, rmw times."""
    return {
        'history': QoSHistoryPolicy(qos.history).short_key,
        'depth': qos.depth,
        'reliability': QoSReliabilityPolicy(qos.reliability).short_key,
        'durability': QoSDurabilityPolicy(qos.durability).short_key,
        'deadline': _rmw_time(qos.deadline),
        'lifespan': _rmw_time(qos.lifespan),
        'liveliness': QoSLivelinessPolicy(qos.liveliness).short_key,
        'liveliness_lease_duration': _rmw_time(qos.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': qos.avoid_ros_namespace_conventions,
    }


# --------------------------------------------------------------------------------------------
# Writer


@dataclass
class _Topic:
    """Everything recorded about a topic; built on the caller thread by add_topic."""

    name: str
    type_name: str
    msg_class: type
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

    Raises:
        BagError: the file exists (and ``overwrite`` is false), its folder is missing, it is
            not writable, or the first bytes cannot be written.
    """

    def __init__(self, path: Union[str, os.PathLike], *, overwrite: bool = False,
                 chunk_size: int = 64 * 1024, chunk_duration_ns: int = 500_000_000):
        if chunk_size <= 0 or chunk_duration_ns <= 0:
            raise BagError('chunk_size and chunk_duration_ns must be positive')
        self.path = Path(path)
        self._chunk_size = chunk_size
        self._chunk_duration_ns = chunk_duration_ns
        self._ros_distro = os.environ.get('ROS_DISTRO') or _DEFAULT_ROS_DISTRO
        self._topics: Dict[str, _Topic] = {}
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: Optional[BagError] = None
        self._closed = False
        # Writer-thread state: message statistics and the chunk being built.
        self._schema_ids: Dict[str, int] = {}
        self._first_log_time_ns = _MAX_TIME_NS
        self._last_log_time_ns = 0
        self._message_count = 0
        self._chunk_start_ns: Optional[int] = None
        self._chunk_bytes = 0

        self._stream = self._open(self.path, overwrite)
        # Chunks are cut by _flush_chunk (size or log-time span, then flushed to the OS), so
        # mcap's own size trigger is disabled. No compression, as rosbag2's default.
        self._mcap = Writer(self._stream, chunk_size=2**62, compression=CompressionType.NONE)
        try:
            self._mcap.start(profile=_PROFILE, library=_LIBRARY)
            self._mcap.add_metadata(_ROSBAG2_RECORD, self._rosbag2_metadata())
            self._stream.flush()
        except OSError as exc:
            _close_quietly(self._stream)
            raise BagError(f'cannot write bag {self.path}: {_reason(exc)}') from None
        self._thread = threading.Thread(target=self._run, name=f'BagWriter {self.path.name}',
                                        daemon=True)
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
    def error(self) -> Optional[BagError]:
        """The I/O error that stopped recording, or None while all is well."""
        return self._error

    def add_topic(self, name: str, msg_type: Union[str, type],
                  qos: Union[QoSProfile, int] = 10, *, definition: Optional[str] = None,
                  type_hash_: Optional[str] = None) -> None:
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
        self._queue.put(('topic', topic))

    def write(self, topic: str, msg: Any, log_time_ns: int,
              publish_time_ns: Optional[int] = None) -> None:
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
                         publish_time_ns: Optional[int] = None) -> None:
        """Queue an already CDR-serialised message; arguments as :meth:`write`."""
        if topic not in self._topics:
            raise BagError(f'topic {topic!r} was not added to bag {self.path}')
        log_time_ns = operator.index(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else operator.index(
            publish_time_ns)
        if log_time_ns < 0 or publish_time_ns < 0:
            raise BagError(f'negative time for a message on {topic!r}')
        if self._closed:
            raise BagError(f'bag {self.path} is closed')
        if self._error is None:  # after an I/O error messages are dropped, not queued
            self._queue.put(('message', topic, bytes(data), log_time_ns, publish_time_ns))

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
        self._queue.put(('metadata', name, dict(data)))

    def close(self) -> None:
        """Write out everything queued, the final metadata and the summary; close the file.

        Idempotent, and safe from a signal handler or ``atexit``: it only enqueues and joins
        the writer thread. Every call returns only once the file is finalised, so a signal
        handler that interrupts a ``close`` in progress still waits for it. Does not raise on
        I/O errors; check :attr:`error`.
        """
        if not self._closed:
            self._closed = True
            self._queue.put(_CLOSE)
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

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        self.close()
        if exc_type is None and self._error is not None:
            raise self._error

    # -- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        idle_timeout_s = self._chunk_duration_ns / 1e9
        while True:
            try:
                item = self._queue.get(timeout=idle_timeout_s)
            except queue.Empty:
                item = ('idle',)
            if item is _CLOSE:
                self._finish()
                return
            if self._error is not None:
                continue  # recording stopped; drain the queue until close
            try:
                self._handle(item)
            # Any failure (ENOSPC, EIO, ...) stops recording; it must never reach the caller.
            except Exception as exc:  # noqa: BLE001
                self._error = BagError(
                    f'writing bag {self.path} failed: {_reason(exc)}; recording stopped')

    def _handle(self, item: tuple) -> None:
        kind = item[0]
        if kind == 'message':
            _, name, data, log_time_ns, publish_time_ns = item
            topic = self._topics[name]
            topic.message_count += 1
            # rosbag2 records the publisher's sequence number; ours counts per topic from 1.
            self._mcap.add_message(topic.channel_id, log_time_ns, data, publish_time_ns,
                                   sequence=topic.message_count)
            self._message_count += 1
            self._first_log_time_ns = min(self._first_log_time_ns, log_time_ns)
            self._last_log_time_ns = max(self._last_log_time_ns, log_time_ns)
            if self._chunk_start_ns is None:
                self._chunk_start_ns = log_time_ns
            self._chunk_bytes += len(data) + _MESSAGE_RECORD_OVERHEAD
            if (self._chunk_bytes >= self._chunk_size
                    or log_time_ns - self._chunk_start_ns >= self._chunk_duration_ns):
                self._flush_chunk()
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

    def _rosbag2_metadata(self) -> Dict[str, str]:
        """The ``rosbag2`` record: rosbag2_storage's YAML encoding of BagMetadata (version 9)."""
        if self._message_count:
            starting_time = self._first_log_time_ns
            duration = self._last_log_time_ns - self._first_log_time_ns
        else:
            starting_time, duration = _MAX_TIME_NS, 0
        file_name = self.path.name
        metadata = {
            'version': _ROSBAG2_METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': starting_time},
            'message_count': self._message_count,
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
                       'message_count': self._message_count}],
            'custom_data': None,
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


# --------------------------------------------------------------------------------------------
# Reader


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
