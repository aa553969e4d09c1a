"""Message definitions and type hashes from the installed interface packages: the ``ros2msg``
schema text rosbag2 writes (a type's ``.msg`` followed by its nested types), the ``RIHS01``
type hash, and the Python message class of a ``pkg/msg/Type`` name. Never from copies in this
code.
"""
from __future__ import annotations

import importlib
import json
import os
import re
import sys
from functools import cache
from pathlib import Path

from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

try:
    from rosidl_runtime_py.utilities import get_message as _get_message
except ImportError:  # not shipped as a PyPI wheel; _message_class imports the module itself
    _get_message = None

from .errors import BagError

__all__ = ['message_definition', 'message_definition_of_text', 'type_hash']

# Field types and .msg parsing exactly as rosbag2_cpp's local_message_definition_source.cpp.
_PRIMITIVE_TYPES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string'})
_MSG_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_ROS_NAME = '[a-zA-Z][a-zA-Z0-9_]*'
_TYPE_NAME = re.compile(rf'({_ROS_NAME})/(?:({_ROS_NAME})/)?({_ROS_NAME})')
_DELIMITER = '=' * 80 + '\n'


def _split_type(type_name: str) -> tuple[str, str, str]:
    """``'pkg/msg/Type'`` or ``'pkg/Type'`` -> ``('pkg', 'msg', 'Type')``."""
    match = _TYPE_NAME.fullmatch(type_name)
    if match is None:
        raise BagError(f'invalid message type name {type_name!r} (expected pkg/msg/Type)')
    package, namespace, name = match.groups()
    return package, namespace or 'msg', name


def _type_string(msg_type: str | type) -> str:
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


@cache
def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type, byte for byte as rosbag2 writes it.

    The type's own ``.msg`` text, then for each dependency not written yet (sorted names, depth
    first): a newline, 80 ``=``, ``MSG: <name as referenced>`` and that type's text.
    """
    return message_definition_of_text(type_name, None)


def message_definition_of_text(type_name: str, text: str | None) -> str:
    """:func:`message_definition` of a type whose own ``.msg`` text is ``text`` (for a type
    whose package is not installed, e.g. ``tf2_msgs``), its dependencies read from the
    installed packages; ``text`` None: read it too."""
    seen = set()

    def full_text(name: str, own: str | None = None) -> str:
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


@cache
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
