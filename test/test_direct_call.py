"""``DirectCall``: a compiled kernel called without numba's per-call dispatch gives what the
dispatcher gives, and the simulator's step goes through it."""
import numba
import numpy as np

from ponytail_ros.core.direct_call import DirectCall

from helpers import chain_sim, reference_ponytail


@numba.njit(cache=False)
def _weighted(a, b, k):
    out = 0.0
    for i in range(a.shape[0]):
        out += k * a[i] * b[i]
    return out


def test_a_direct_call_gives_what_the_dispatcher_gives():
    a, b = np.arange(5.0), np.linspace(1.0, 2.0, 5)
    call = DirectCall(_weighted)
    assert call(a, b, 3) == _weighted(a, b, 3)
    assert call._call is not _weighted                    # the compiled version, directly
    assert call(b, a, 2) == _weighted(b, a, 2)            # (new values, same types)


def test_the_simulator_steps_through_a_direct_call_to_the_same_bits():
    """Two simulators of one scene, one stepped through the direct call and one through the
    dispatcher, end in the same bits."""
    from ponytail_ros.core import SwayYawMotion
    motion = SwayYawMotion()
    a, b = (chain_sim(reference_ponytail(n=6), motion, 'rk4', 1e-3) for _ in range(2))
    for k in range(1, 30):
        a.advance_to(k / 120, motion)
    kernel_b = b._kernel(b._step_model())
    kernel_b._call = kernel_b.kernel                      # (numba's dispatch at every call)
    for k in range(1, 30):
        b.advance_to(k / 120, motion)
    assert a._kernel(a._step_model())._call is not kernel_b.kernel
    for name in ('x', 'q', 'v', 'w'):
        assert np.array_equal(getattr(a.state, name), getattr(b.state, name))
