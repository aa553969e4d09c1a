"""Calling a compiled kernel without numba's per-call type dispatch.

numba's dispatcher types every argument of every call to pick the compiled version; for a
``StepModel`` (a named tuple of 27 fields) and an ``AnchorTable`` that costs more than the
compiled steps of a short chain's tick. ``DirectCall(kernel)`` picks the version once, at its
first call, for the types of that call's arguments, and afterwards calls it directly.

The caller guarantees that later calls pass arguments of the same types (the same model
object, C-contiguous float64 arrays of the same dimensions, ints and floats): a version
compiled for other types would read the arrays wrongly. The simulator keeps one per
``StepModel`` (``Simulator._kernel``), whose arrays it builds itself.
"""
from numba import typeof
from numba.core.typing.typeof import Purpose

__all__ = ['DirectCall']


class DirectCall:
    """``kernel(*args)``, the compiled version found at the first call (see the module
    docstring); through the dispatcher when numba has no such version to give."""

    def __init__(self, kernel):
        self.kernel = kernel
        self._call = None

    def __call__(self, *args):
        if self._call is not None:
            return self._call(*args)
        result = self.kernel(*args)
        found = self.kernel.overloads.get(tuple(typeof(a, Purpose.argument) for a in args))
        self._call = self.kernel if found is None else found.entry_point
        return result
