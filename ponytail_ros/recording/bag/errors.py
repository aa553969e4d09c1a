"""The error of every bag operation."""
from __future__ import annotations

__all__ = ['BagError']


class BagError(Exception):
    """A bag cannot be created, written or read; the message names the file and the reason."""
