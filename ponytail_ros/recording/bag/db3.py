"""``Db3FileReader``: one rosbag2 sqlite3 storage file (``.db3``), read with ``rosbags``
(its ``Sqlite3Reader``), with the interface of ``McapFileReader``.

SQLite keeps its own integrity (a damaged file is an error from SQLite, said with the file's
name); there is no file order distinct from log-time order (rosbag2 reads a ``.db3`` by
timestamp), so ``order='file'`` gives log-time order too.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message

from .errors import BagError
from .msgdefs import _message_class
from .wanted import wanted_topics

__all__ = ['Db3FileReader']


class Db3FileReader:
    """Reads one ``.db3`` file (see the module docstring).

    Raises:
        BagError: the file cannot be opened as a rosbag2 sqlite3 file (named, with SQLite's
            or rosbags' reason).
    """

    #: A .db3 is complete or SQLite says otherwise.
    finished = True
    truncation: str | None = None

    def __init__(self, path: str | os.PathLike,
                 decompress: Callable[[bytes], bytes] | None = None,
                 label: str | os.PathLike | None = None):
        self.path = Path(path)
        self.label = Path(label) if label is not None else self.path
        self._decompress = decompress
        self.out_of_order = 0
        with self._open() as reader:
            self._topics = {c.topic: c.msgtype for c in reader.connections}

    @contextmanager
    def _open(self) -> Iterator[Any]:
        try:
            from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader
        except ImportError:
            raise BagError(f'{self.label}: reading sqlite3 (.db3) bags needs rosbags (pip '
                           f'install rosbags; ROS: python3-rosbags)') from None
        reader = Sqlite3Reader(self.path)
        try:
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags' ReaderError, SQLite's (apsw) errors
            raise BagError(f'cannot read bag {self.label}: {exc}') from None
        try:
            yield reader
        finally:
            reader.close()

    def check(self) -> str | None:
        return None

    def topics(self) -> dict[str, str]:
        return dict(self._topics)

    def metadata(self) -> dict[str, dict[str, str]]:
        return {}

    def messages(self, topics=None, order: str = 'log_time', raw: bool = False
                 ) -> Iterator[tuple[str, str, Any, int]]:
        """As ``McapFileReader.messages``: ``(topic, type, message or CDR bytes, log_time_ns)``
        in log-time order."""
        if order not in ('log_time', 'file'):
            raise ValueError(f'order must be log_time or file, not {order!r}')
        wanted = wanted_topics(self.label, self._topics, topics, raw)
        classes = {} if raw else {n: _message_class(self._topics[n]) for n in wanted}
        unpack = self._decompress
        with self._open() as reader:
            connections = [c for c in reader.connections if c.topic in wanted]
            if not connections:
                return
            try:
                for conn, log_ns, data in reader.messages(connections):
                    if unpack is not None:
                        data = unpack(data)
                    yield (conn.topic, conn.msgtype,
                           bytes(data) if raw else deserialize_message(data, classes[conn.topic]),
                           log_ns)
            except BagError:
                raise
            except Exception as exc:  # noqa: BLE001 - SQLite's errors mid-read
                raise BagError(f'cannot read bag {self.label}: {exc}') from None
