"""NumPy references of the compiled code, for the tests only (never imported by the package).

Each is a second, independent implementation of equations the product runs compiled, written
for clarity with NumPy and SciPy's LAPACK, so that a test can hold the compiled result to it:

- ``forces`` (applied forces), ``solver`` (``Dynamics``: the joint forces by A f_c = b, banded
  or dense, and the implicit joint damping), ``integrators`` (RK4, symplectic Euler, RATTLE)
  and ``stabilization`` (the joints closed after a step): together the reference of the free
  step (``step``, ``lanes``), run by ``step.ReferenceStep`` as the simulator runs the
  compiled one;
- beside this package, ``_oracle_collision`` and ``_oracle_limits``: the reference of the
  contact and limit stage (they close the joints with ``stabilization``).

``test_oracle_step`` checks every integrator and every force term of the compiled step
against this reference over one second of simulated time.
"""
