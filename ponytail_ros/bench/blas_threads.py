"""One BLAS thread for the benchmark: reproducible timings, no contention in the dense solve.

BLAS reads its thread count once, when NumPy is first imported; so this module sets the
variables and must be imported before NumPy is. ``cli`` imports it first; anything that imports
NumPy earlier (a test session) keeps its own setting, and ``PINNED`` says which happened. Only
unset variables are set: a caller's ``OPENBLAS_NUM_THREADS=4`` wins.
"""
import os
import sys

#: True when NumPy was not loaded yet, so the setting below takes effect in this process.
PINNED: bool = 'numpy' not in sys.modules

for _name in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_name, '1')
