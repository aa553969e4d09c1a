"""Which topics a ``messages`` call reads: the request checked against what was recorded."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .errors import BagError
from .msgdefs import _message_class, _type_string

__all__ = ['wanted_topics']


def wanted_topics(label, recorded: dict[str, str], topics, raw: bool) -> set[str]:
    """The topic names to read.

    Args:
        label: the bag, in messages.
        recorded: topic -> ``pkg/msg/Type`` of the bag.
        topics: all topics (None: those whose message type is installed, or all if ``raw``),
            a name, names, or a mapping name -> expected type (class or ``pkg/msg/Type``).

    Raises:
        BagError: a requested topic is not in the bag or was recorded with another type.
    """
    if topics is None:
        wanted = set(recorded)
        if not raw:
            for name in list(wanted):
                try:
                    _message_class(recorded[name])
                except BagError:
                    wanted.discard(name)
        return wanted
    expected: dict[str, Any] = (
        dict(topics) if isinstance(topics, Mapping)
        else dict.fromkeys([topics] if isinstance(topics, str) else topics))
    missing = sorted(set(expected) - set(recorded))
    if missing:
        raise BagError(f'{label} has no topic {", ".join(missing)} '
                       f'(recorded: {", ".join(sorted(recorded)) or "none"})')
    for name, msg_type in expected.items():
        if msg_type is not None and _type_string(msg_type) != recorded[name]:
            raise BagError(f'{label}: topic {name} holds {recorded[name]}, '
                           f'not {_type_string(msg_type)}')
    return set(expected)
