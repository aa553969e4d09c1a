"""Where a bag's messages are: a path as a user gives it resolved to the storage files rosbag2
wrote, in order, with their storage and compression.

Accepted (what ``ros2 bag record`` and the ``rosbags`` writer produce):

* a bag folder (``metadata.yaml`` + the files it lists in ``relative_file_paths``, e.g.
  ``my_bag_0.mcap``, ``my_bag_1.mcap`` after a split), or its ``metadata.yaml``;
* storage ``mcap`` or ``sqlite3`` (``.db3``);
* compression (``compression_mode``/``compression_format``) ``file`` (each file zstd-compressed
  whole, ``my_bag_0.mcap.zstd``) or ``message`` (each message's data); zstd chunk compression
  inside an MCAP file (``storage`` compression) is the MCAP reader's business;
* a folder without ``metadata.yaml`` whose storage files are all ``<folder>_<N>.<ext>`` (a
  recorder killed before it wrote its metadata): read in the order of ``N``, with a note;
* a single ``.mcap`` or ``.db3`` file. If it is one of several files of a bag folder, a note
  says so (the rest of the run is in the other files).

Anything else is a :class:`BagError` naming the path and what is wrong. Does not read messages.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .errors import BagError

__all__ = ['BagLayout', 'resolve_bag', 'bags_in', 'STORAGE_SUFFIXES', 'zstd_module']

#: storage identifier -> file suffix
STORAGE_SUFFIXES = {'mcap': '.mcap', 'sqlite3': '.db3'}
_SUFFIX_STORAGE = {v: k for k, v in STORAGE_SUFFIXES.items()}
_METADATA = 'metadata.yaml'


@dataclass
class BagLayout:
    """A bag's storage files (in order) and how they are stored.

    Attributes:
        path: what was given (folder, ``metadata.yaml`` or file).
        name: the bag's name (the folder's, else the file's stem).
        files: the storage files as on disk (maybe zstd-compressed whole), in order.
        storage: ``'mcap'`` or ``'sqlite3'``.
        compression_mode: ``''``, ``'file'`` or ``'message'``.
        info: the ``rosbag2_bagfile_information`` of ``metadata.yaml`` (None without one).
        notes: things worth saying about the input (a split bag given by one file, ...).
    """

    path: Path
    name: str
    files: list[Path]
    storage: str
    compression_mode: str = ''
    info: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def is_folder(self) -> bool:
        return self.path.is_dir() or self.path.name == _METADATA


def zstd_module():
    """The zstd module rosbags uses (``compression.zstd`` on Python 3.14+, else
    ``backports.zstd``); BagError if neither is installed."""
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        try:
            from backports import zstd
        except ImportError:
            raise BagError('reading zstd-compressed bags needs backports.zstd, which comes with '
                           'rosbags (pip install rosbags)') from None
    return zstd


def _read_metadata(folder: Path) -> dict[str, Any]:
    meta = folder / _METADATA
    try:
        tree = yaml.safe_load(meta.read_text())
    except OSError as exc:
        raise BagError(f'cannot read {meta}: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise BagError(f'{meta} is not valid YAML: {exc}') from None
    info = tree.get('rosbag2_bagfile_information') if isinstance(tree, dict) else None
    if not isinstance(info, dict):
        raise BagError(f'{meta} has no rosbag2_bagfile_information: not a rosbag2 bag\'s '
                       f'metadata')
    return info


def _from_metadata(folder: Path, given: Path) -> BagLayout:
    info = _read_metadata(folder)
    meta = folder / _METADATA
    storage = info.get('storage_identifier', '')
    if storage not in STORAGE_SUFFIXES:
        raise BagError(f'{meta}: storage_identifier {storage!r} is not supported (mcap or '
                       f'sqlite3)')
    mode = str(info.get('compression_mode') or '').lower()
    mode = '' if mode == 'none' else mode
    fmt = str(info.get('compression_format') or '').lower()
    if mode not in ('', 'file', 'message'):
        raise BagError(f'{meta}: compression_mode {mode!r} is not supported (file or message)')
    if mode and fmt != 'zstd':
        raise BagError(f'{meta}: compression_format {fmt!r} is not supported (zstd)')
    names = info.get('relative_file_paths') or []
    if not names:
        raise BagError(f'{meta} lists no files (relative_file_paths is empty)')
    # rosbag2 writes names relative to the folder (older versions: with the folder in front)
    files = [folder / Path(str(n)).name for n in names]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise BagError(f'{folder}: {len(missing)} of the {len(files)} files its metadata.yaml '
                       f'lists are missing: {", ".join(missing)}')
    return BagLayout(path=given, name=folder.name, files=files, storage=storage,
                     compression_mode=mode, info=info)


def _storage_of(path: Path) -> str | None:
    """The storage of a file by its suffix (``.zstd`` whole-file compression looked through)."""
    suffix = Path(path.stem).suffix if path.suffix == '.zstd' else path.suffix
    return _SUFFIX_STORAGE.get(suffix)


def _storage_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and _storage_of(p))


def _unindexed_split(folder: Path) -> list[Path] | None:
    """``<folder>_<N>.<ext>`` files of one storage: a bag without its metadata, in N order."""
    files = _storage_files(folder)
    pattern = re.compile(re.escape(folder.name) + r'_(\d+)$')
    numbered = []
    for f in files:
        stem = Path(f.stem).stem if f.suffix == '.zstd' else f.stem
        match = pattern.match(stem)
        if match is None:
            return None
        numbered.append((int(match.group(1)), f))
    if not numbered or len({_storage_of(f) for _, f in numbered}) != 1:
        return None
    return [f for _, f in sorted(numbered)]


def bags_in(folder: str | os.PathLike) -> list[Path]:
    """The bags a folder holds when it is not one bag itself: its sub-folders with a
    ``metadata.yaml`` and its storage files (``.mcap``, ``.db3``), sorted by name."""
    folder = Path(folder)
    out = []
    for p in sorted(folder.iterdir()):
        if p.is_dir() and (p / _METADATA).is_file():
            out.append(p)
        elif p.is_file() and _storage_of(p):
            out.append(p)
    return out


def is_one_bag(path: str | os.PathLike) -> bool:
    """A file, a ``metadata.yaml``, a bag folder, or a folder of one bag's unindexed files."""
    path = Path(path)
    if not path.is_dir():
        return True
    return (path / _METADATA).is_file() or _unindexed_split(path) is not None


def resolve_bag(path: str | os.PathLike) -> BagLayout:
    """The bag at ``path`` (folder, its ``metadata.yaml``, or a storage file).

    Raises:
        BagError: nothing there, not a bag, a listed file missing, an unsupported storage or
            compression; a folder of several bags (give them one by one, or to
            ``ponytail_replay -o DIR``).
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f'cannot read bag {path}: No such file or directory')
    if path.is_dir():
        if (path / _METADATA).is_file():
            return _from_metadata(path, path)
        split = _unindexed_split(path)
        if split is not None:
            storage = _storage_of(split[0]) or 'mcap'
            layout = BagLayout(path=path, name=path.name, files=split, storage=storage,
                               compression_mode='file' if split[0].suffix == '.zstd' else '')
            layout.notes.append(
                f'{path} has no metadata.yaml (was its recorder killed?): reading its '
                f'{len(split)} file(s) {", ".join(f.name for f in split)} in that order '
                f'("ros2 bag reindex {path}" writes the metadata)')
            return layout
        bags = bags_in(path)
        if bags:
            raise BagError(f'{path} is not one bag (no metadata.yaml) but a folder of '
                           f'{len(bags)}: {", ".join(b.name for b in bags[:5])}'
                           f'{" ..." if len(bags) > 5 else ""}; replay them all with '
                           f'"ponytail_replay {path} -o OUT_DIR"')
        raise BagError(f'{path} is not a rosbag2 bag: no metadata.yaml and no .mcap or .db3 '
                       f'file in it')
    if path.name == _METADATA:
        return _from_metadata(path.parent, path)
    # (an MCAP file by another name is still read; the MCAP reader checks its magic)
    storage = _storage_of(path) or 'mcap'
    layout = BagLayout(path=path, name=path.stem, files=[path], storage=storage,
                       compression_mode='file' if path.suffix == '.zstd' else '')
    _note_part_of_split(layout)
    return layout


def _note_part_of_split(layout: BagLayout) -> None:
    """A file given alone that is one of several of its folder's bag: say where the rest is."""
    folder = layout.path.parent
    if not (folder / _METADATA).is_file():
        return
    try:
        info = _read_metadata(folder)
    except BagError:
        return
    names = [Path(str(n)).name for n in info.get('relative_file_paths') or []]
    if layout.path.name not in names:
        return
    if str(info.get('compression_mode') or '').lower() == 'message':
        layout.compression_mode = 'message'
    if len(names) > 1:
        i = names.index(layout.path.name)
        layout.notes.append(
            f'{layout.path} is file {i + 1} of the {len(names)} files of bag {folder} (see its '
            f'metadata.yaml): only this part of the recording is read; give the folder '
            f'{folder} to read the whole bag')
