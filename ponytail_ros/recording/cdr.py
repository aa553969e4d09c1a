"""Canonical CDR bytes from rclpy: alignment padding zeroed, trailing slack cut.

``rclpy.serialization.serialize_message`` (rmw_fastrtps, Fast CDR) has two quirks:

* alignment gaps are skipped without being written, so they hold whatever the heap held: two
  serialisations of equal messages can differ in those bytes (and leak a little process memory
  into a file);
* the returned length is the RMW's *estimate* of the serialised size, not the size written: for
  some types (``rcl_interfaces/msg/ParameterEvent``, whose values hold empty sequences) the data
  ends with several bytes of slack, and readers that check the length (``rosbags``: "CDR
  message size mismatch") reject it.

:func:`zero_padding` walks the data with the message type's layout (field order, sizes, string
lengths and sequence counts read from the data itself), zeroes every alignment gap and cuts the
data after its last field, padded with zeros to a multiple of 4 bytes as on the wire: equal
messages give equal bytes that every CDR reader accepts.

Layout: plain CDR (XCDR1) as ROS 2 uses it -- a 4-byte encapsulation header, then the fields in
order, each primitive aligned to its size (relative to the end of the header), strings and
sequences as a ``uint32`` length (strings counting their terminating NUL) followed by the
elements. Types this module does not know (wide strings) leave the data untouched, as does data
that does not match the type (a count or length running past the end).
"""
from __future__ import annotations

import importlib
import struct
from functools import cache

__all__ = ['zero_padding', 'serialize_canonical']

_HEADER = 4
_SIZES = {
    'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1,
    'int16': 2, 'uint16': 2, 'int32': 4, 'uint32': 4, 'float': 4,
    'int64': 8, 'uint64': 8, 'double': 8,
}
_U32 = struct.Struct('<I')
_ZEROS = tuple(bytes(n) for n in range(8))


class _Unsupported(Exception):
    pass


# A type compiles to a flat tuple of operations (nested structs inlined):
#   ('h', size, count): ``count`` primitives of one ``size``, contiguous once the first is
#                       aligned (runs of same-size primitives are merged into one);
#   ('s',):             a string;
#   ('q', elem):        a sequence; ``elem`` an ('h', ...) operation or a tuple of operations;
#   ('a', n, ops):      a fixed array of a type that is not a plain primitive run.


@cache
def _ops_of_class(cls) -> tuple:
    ops: list[tuple] = []
    for t in cls.SLOT_TYPES:
        ops.extend(_ops_of_type(t))
    return _merge(ops)


def _ops_of_type(t) -> tuple:
    kind = type(t).__name__
    if kind == 'BasicType':
        if t.typename not in _SIZES:
            raise _Unsupported(t.typename)
        return (('h', _SIZES[t.typename], 1),)
    if kind in ('UnboundedString', 'BoundedString'):
        return (('s',),)
    if kind in ('UnboundedSequence', 'BoundedSequence'):
        elem = _ops_of_type(t.value_type)
        return (('q', elem[0] if len(elem) == 1 and elem[0][0] == 'h' else elem),)
    if kind == 'Array':
        elem = _ops_of_type(t.value_type)
        if len(elem) == 1 and elem[0][0] == 'h':
            return (('h', elem[0][1], elem[0][2] * t.size),)
        return (('a', t.size, elem),)
    if kind == 'NamespacedType':
        module = importlib.import_module('.'.join(t.namespaces))
        return _ops_of_class(getattr(module, t.name))
    raise _Unsupported(kind)


def _merge(ops) -> tuple:
    out: list[tuple] = []
    for op in ops:
        if op[0] == 'h' and out and out[-1][0] == 'h' and out[-1][1] == op[1]:
            out[-1] = ('h', op[1], out[-1][2] + op[2])
        else:
            out.append(op)
    return tuple(out)


def _walk(ops: tuple, data: bytearray, off: int) -> int:
    """Zero the gaps of one value laid out as ``ops``, starting at ``off`` (relative to the
    CDR origin); return the offset after it. (Hot: alignment inlined; sizes are powers of 2;
    running past the end is checked once by the caller.)"""
    for op in ops:
        kind = op[0]
        if kind == 'h':
            size = op[1]
            aligned = (off + size - 1) & -size
            if aligned != off:
                data[_HEADER + off:_HEADER + aligned] = _ZEROS[aligned - off]
            off = aligned + size * op[2]
        elif kind == 's' or kind == 'q':
            aligned = (off + 3) & -4
            if aligned != off:
                data[_HEADER + off:_HEADER + aligned] = _ZEROS[aligned - off]
            n = _U32.unpack_from(data, _HEADER + aligned)[0]
            off = aligned + 4
            if kind == 's':
                off += n
                continue
            elem = op[1]
            if elem[0] == 'h':
                if n:
                    size = elem[1]
                    aligned = (off + size - 1) & -size
                    if aligned != off:
                        data[_HEADER + off:_HEADER + aligned] = _ZEROS[aligned - off]
                    off = aligned + n * size * elem[2]
            else:
                for _ in range(n):
                    off = _walk(elem, data, off)
        else:
            for _ in range(op[1]):
                off = _walk(op[2], data, off)
    return off


def zero_padding(data: bytes, msg_class) -> bytes:
    """``data`` (CDR of a ``msg_class`` message) with every alignment gap zeroed and cut after
    its last field (+ zeros to a multiple of 4 bytes); unchanged if the type is not supported
    or the data does not match it."""
    try:
        ops = _ops_of_class(msg_class)
        out = bytearray(data)
        end = _HEADER + _walk(ops, out, 0)
    except (_Unsupported, struct.error, ImportError, AttributeError):
        return data
    if end > len(data) or len(out) != len(data):
        return data  # counts or lengths that do not fit: not data of this type
    # The RMW reports its size estimate as the length: bytes past the last field are slack.
    padded = end + (-(end - _HEADER)) % 4
    del out[end:]
    return bytes(out) + bytes(padded - end)


def serialize_canonical(msg) -> bytes:
    """``serialize_message(msg)`` made canonical (:func:`zero_padding`)."""
    from rclpy.serialization import serialize_message
    return zero_padding(serialize_message(msg), type(msg))

