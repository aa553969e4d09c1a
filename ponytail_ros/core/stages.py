"""The named stages of a compiled step and the cycle counter that times them.

Like Box2D v3's ``b2Profile``: a step's ``profile`` array (int64) holds the CPU cycles spent
in each of ``PROFILE_STAGES``, then in the whole call, then in each of ``CONTACT_STAGES``;
``Simulator.last_report`` (``StepReport``) reads them by these names.
"""
import platform

import numba as nb
from llvmlite import ir
from numba.core import cgutils
from numba.core.extending import intrinsic

__all__ = ['PROFILE_STAGES', 'CONTACT_STAGES', 'PROFILE_SIZE', 'PROFILE_ROWS',
           'PROFILE_POSITIONS', 'PROFILE_VELOCITIES', 'HAS_CYCLE_COUNTER', 'cycles']

#: The stages ``step_unilateral.advance_unilateral`` times (its ``profile`` array: CPU cycles
#: spent in each, then in the whole call), like Box2D's ``b2Profile``: the chains' own steps
#: (forces, joint solves, integration, projection) and the contact and limit stage
#: (``resolve``).
PROFILE_STAGES = ('integrate', 'contacts')
#: The parts of ``contacts`` that ``contact_stage`` times, after the whole call's cycles in
#: the same array (``PROFILE_SIZE`` entries in all): the rows (broad phase, detection, the
#: contact and limit rows, at the step's end and again after a position pass), the positions
#: (the position passes, the limits' projection and, after a move, the chain refactorised and
#: its velocities projected onto the joints) and the velocities (the inelastic impulses and
#: friction, the chain factorised first if nothing moved). What ``contacts`` holds beyond
#: their sum: the colliders posed at the step's end, the step's positions kept, and the call
#: into each chain's stages with its views of the model.
CONTACT_STAGES = ('rows', 'positions', 'velocities')
PROFILE_SIZE = len(PROFILE_STAGES) + 1 + len(CONTACT_STAGES)
PROFILE_ROWS, PROFILE_POSITIONS, PROFILE_VELOCITIES = range(len(PROFILE_STAGES) + 1,
                                                            PROFILE_SIZE)
#: Whether ``cycles`` reads a counter here (x86-64's time-stamp counter); elsewhere it is 0
#: and the profile stays empty. (A counter that user code may read exists on other CPUs, e.g.
#: AArch64's CNTVCT_EL0, but not through one LLVM intrinsic: ``readcyclecounter`` there is the
#: privileged PMU counter.)
HAS_CYCLE_COUNTER = platform.machine().lower() in ('x86_64', 'amd64')


@intrinsic
def cycles(typingctx):
    """The CPU's time-stamp counter (``rdtsc``), or 0 where ``HAS_CYCLE_COUNTER`` is False:
    ~20 ns to read, ordered with nothing (enough for stages of microseconds and more)."""
    def codegen(context, builder, signature, args):
        if not HAS_CYCLE_COUNTER:
            return ir.Constant(ir.IntType(64), 0)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(64), []),
                                            'llvm.readcyclecounter')
        return builder.call(fn, [])
    return nb.types.int64(), codegen
