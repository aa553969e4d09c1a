"""``ponytail_replay repair IN.mcap OUT.mcap``: rewrite a cut-short or damaged recording as a
complete, indexed MCAP file (like ``mcap recover``).

A recording whose writer was killed (SIGKILL, a crash, power loss) has no summary, no index and
no footer: stream readers (ours, Foxglove) read it, indexed readers (``rosbags``: "File end magic
is invalid"; mcap's ``SeekingReader``) refuse it. The repair reads every intact record
(``mcap_scan.McapScan`` with ``skip_damaged``: chunk CRCs checked, a damaged chunk skipped, a
broken record skipped up to the next intact chunk) and writes them, in their file order, into a
new file in rosbag2's layout (profile and library of the input's header, uncompressed chunks,
chunk/message/metadata indexes, statistics, summary offsets, data-section CRC):

* every schema, channel (with its metadata), message (log time, publish time, sequence),
  metadata record and attachment that could be read is kept, byte for byte;
* the ``rosbag2`` metadata record (``serialized_metadata``) is written once more at the end
  with the true counts, start time, duration and topics, as rosbag2's writer does on close, so
  ``ros2 bag info`` shows what the file holds.

Nothing is guessed: what was cut off or damaged is reported (:class:`RepairResult`), not
invented.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from .mcap_scan import McapScan, Problem, ScanError

__all__ = ['repair', 'RepairError', 'RepairResult']

_ROSBAG2 = 'rosbag2'
_MAX_TIME_NS = 2**63 - 1


class RepairError(Exception):
    """The input cannot be repaired or the output cannot be written; one line naming the file."""


@dataclass
class RepairResult:
    """What a repair kept and what it could not."""

    output: Path
    messages: int = 0
    topics: int = 0
    metadata: int = 0
    attachments: int = 0
    truncation: Problem | None = None
    damage: list[Problem] = field(default_factory=list)
    input_size: int = 0
    #: The input was already complete and undamaged (the output is a re-indexed copy).
    was_complete: bool = False

    def summary(self, input_path) -> str:
        kept = (f'{self.messages} messages on {self.topics} topics, {self.metadata} metadata '
                f'records' + (f', {self.attachments} attachments' if self.attachments else ''))
        if self.was_complete:
            state = 'it was complete and undamaged'
        else:
            lost = []
            if self.truncation is not None:
                lost.append(f'the input is {self.truncation.describe(self.input_size)} '
                            f'(the bytes from there on hold no complete record)')
            lost += [f'skipped: {p.describe(self.input_size)}' for p in self.damage]
            state = '; '.join(lost)
        return f'{input_path} -> {self.output}: kept {kept}; {state}'


def repair(input_path: str | os.PathLike, output_path: str | os.PathLike, *,
           overwrite: bool = False) -> RepairResult:
    """Rewrite ``input_path`` as a complete, indexed MCAP file ``output_path``.

    Raises:
        RepairError: the input is missing or not MCAP, holds no recoverable message, the output
            is the input, exists (and not ``overwrite``) or cannot be written.
    """
    src, dst = Path(input_path), Path(output_path)
    if src.is_dir():
        files = sorted(p.name for p in src.glob('*.mcap'))
        raise RepairError(f'{src} is a folder: repair works on one MCAP file; give the file to '
                          f'repair ({", ".join(files) or "it holds no .mcap file"}), then put '
                          f'the repaired file in its place')
    if not src.is_file():
        raise RepairError(f'{src}: no such file')
    if dst.exists() and dst.resolve() == src.resolve():
        raise RepairError(f'{dst}: the output would overwrite the input')
    scan = McapScan(src)
    with src.open('rb') as f:
        if f.read(8) != b'\x89MCAP0\r\n':
            raise RepairError(f'{src} is not an MCAP file (no leading magic)')
    try:
        stream = dst.open('wb' if overwrite else 'xb')
    except FileExistsError:
        raise RepairError(f'{dst} already exists (use --overwrite to replace it)') from None
    except OSError as exc:
        raise RepairError(f'cannot create {dst}: {exc.strerror or exc}') from None
    result = RepairResult(output=dst, input_size=scan.size)
    try:
        with stream:
            _copy(scan, stream, result)
    except (OSError, ScanError) as exc:
        dst.unlink(missing_ok=True)
        raise RepairError(f'repairing {src} into {dst} failed: {exc}') from None
    result.truncation, result.damage = scan.truncation, list(scan.damage)
    result.was_complete = scan.truncation is None and not scan.damage and scan.footer_seen
    if result.messages == 0 and not result.was_complete:
        dst.unlink(missing_ok=True)
        problems = ([scan.truncation] if scan.truncation else []) + list(scan.damage)
        raise RepairError(f'{src}: no message could be recovered ('
                          + '; '.join(p.describe(scan.size) for p in problems) + ')')
    return result


def _copy(scan: McapScan, stream, result: RepairResult) -> None:
    """Every intact record of the data section of ``scan`` into a new MCAP file on
    ``stream`` (its summary and index written anew), counted into ``result``."""
    copier = _Copier(stream, result)
    in_summary = False
    # Read to the end even past the data section: the scan checks the summary and footer too.
    for _, record in scan.records(skip_damaged=True):
        if isinstance(record, Header):
            copier.start(record.profile, record.library)
            continue
        copier.start()
        if type(record).__name__ == 'DataEnd':
            in_summary = True   # summary records repeat the data section's: not copied twice
        if not in_summary:
            copier.copy(record)
    copier.finish()


class _Copier:
    """The records of a data section copied one by one; schemas and channels re-numbered by
    the writer, a channel whose schema was lost dropped with its messages, and the counts and
    times of what was kept (the rosbag2 metadata is rewritten from them)."""

    def __init__(self, stream, result: RepairResult):
        self.writer = Writer(stream, compression=CompressionType.NONE, enable_data_crcs=True)
        self.result = result
        self.started = False
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.counts: dict[int, int] = {}
        self.first, self.last = _MAX_TIME_NS, 0
        self.rosbag2: dict[str, str] | None = None

    def start(self, profile: str = '', library: str = '') -> None:
        if not self.started:
            self.writer.start(profile=profile, library=library or 'ponytail_replay repair')
            self.started = True

    def copy(self, record) -> None:
        if isinstance(record, Schema):
            self._schema(record)
        elif isinstance(record, Channel):
            self._channel(record)
        elif isinstance(record, Message):
            self._message(record)
        elif isinstance(record, Metadata):
            if record.name == _ROSBAG2:
                self.rosbag2 = dict(record.metadata)
            self.writer.add_metadata(record.name, dict(record.metadata))
            self.result.metadata += 1
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name,
                                       record.media_type, record.data)
            self.result.attachments += 1

    def _schema(self, record: Schema) -> None:
        if record.id not in self.schema_ids:
            self.schema_ids[record.id] = self.writer.register_schema(
                record.name, record.encoding, record.data)
            self.schemas[record.id] = record

    def _channel(self, record: Channel) -> None:
        if record.id in self.channel_ids:
            return
        if record.schema_id and record.schema_id not in self.schema_ids:
            return  # its schema was in a damaged part: its messages cannot be read
        self.channel_ids[record.id] = self.writer.register_channel(
            record.topic, record.message_encoding,
            self.schema_ids.get(record.schema_id, 0), dict(record.metadata))
        self.channels[record.id] = record
        self.counts[record.id] = 0

    def _message(self, record: Message) -> None:
        new = self.channel_ids.get(record.channel_id)
        if new is None:
            return
        self.writer.add_message(new, record.log_time, record.data, record.publish_time,
                                record.sequence)
        self.counts[record.channel_id] += 1
        self.first = min(self.first, record.log_time)
        self.last = max(self.last, record.log_time)

    def finish(self) -> None:
        self.start()
        result = self.result
        result.messages = sum(self.counts.values())
        result.topics = len(self.channels)
        if self.rosbag2 is not None:
            self.writer.add_metadata(_ROSBAG2, _final_rosbag2(
                self.rosbag2, self.channels, self.schemas, self.counts, self.first, self.last,
                result.output.name))
            result.metadata += 1
        self.writer.finish()


def _final_rosbag2(record: dict[str, str], channels, schemas, counts, first: int, last: int,
                   file_name: str) -> dict[str, str]:
    """The input's last ``rosbag2`` record with the counts and times of what was kept."""
    from .bag.metadata import _dump_yaml
    try:
        bag = yaml.safe_load(record.get('serialized_metadata', '')) or {}
    except yaml.YAMLError:
        bag = {}
    if not isinstance(bag, dict):
        bag = {}
    total = sum(counts.values())
    start, duration = (first, last - first) if total else (_MAX_TIME_NS, 0)
    topics = []
    for cid, channel in channels.items():
        try:
            qos = yaml.safe_load(channel.metadata.get('offered_qos_profiles', '')) or []
        except yaml.YAMLError:
            qos = []
        schema = schemas.get(channel.schema_id)
        topics.append({'topic_metadata': {
            'name': channel.topic, 'type': schema.name if schema else '',
            'serialization_format': channel.message_encoding, 'offered_qos_profiles': qos,
            'type_description_hash': channel.metadata.get('topic_type_hash', '')},
            'message_count': counts[cid]})
    bag.setdefault('version', 9)
    bag.setdefault('storage_identifier', 'mcap')
    bag['duration'] = {'nanoseconds': duration}
    bag['starting_time'] = {'nanoseconds_since_epoch': start}
    bag['message_count'] = total
    bag['topics_with_message_count'] = topics
    bag['relative_file_paths'] = [file_name]
    bag['files'] = [{'path': file_name, 'starting_time': {'nanoseconds_since_epoch': start},
                     'duration': {'nanoseconds': duration}, 'message_count': total}]
    out = dict(record)
    out['serialized_metadata'] = _dump_yaml(bag)
    return out
