"""The contact stage's model and data: its tolerances, the constant tuples it reads, the row
tables' columns, and the workspace every stage writes into (numba, nopython, ``cache=True``).

Model (constant for a run, built by ``collision.Unilateral``): ``model`` (the chains' masses,
inertias, topology and limits, indices ``LENGTH`` …), ``det`` (the colliding segments and the
colliders' constants, ``D_*``; ``collision._Detector``), ``split`` (their split by chain,
``SP_*``: each chain is resolved on its own, ``chain_model``, ``chain_det``). The colliders'
pose at one instant is ``pose`` (``P_*``, ``broad_phase.collider_pose``).

Data (per call, kept across calls by the caller): the workspace (``workspace``,
``resolve_workspace``; indices ``WS_*`` and the names of its stacked arrays' rows), like
MuJoCo's ``mjData`` arena.

A row r (a contact normal or a limit) is one line of ``R`` ``(k, NCOL)`` (floats) and of
``I`` ``(k, 3)`` (integers), columns named below; its Jacobian acts on segment ``seg``
(linear ``lin``, angular ``ang``) and, for a limit, on the parent segment (``ang_par``;
``par = -1``: the anchor body, which never moves). ``depth`` (m or rad, > 0 violated),
``sep = J_r u`` (m/s or rad/s, < 0 closing), ``mu`` (Coulomb friction), ``arm`` (contact
point minus the segment's centre, m) and ``v_other`` (the collider material's velocity at the
point, m/s). All vectors are in the world frame, SI units.

Kernels marked ``_nrt=False`` (here and in the other contact modules) borrow every array they
touch (they allocate nothing and return no array; their callers own all of them): compiled
without numba's reference counting, they skip the atomic increment and decrement each array
bound, sliced or passed costs otherwise.

Compile time (a cold cache compiles the contact stage at a node's first start): a kernel only
other kernels call is compiled without the CPython and C wrappers (``no_cpython_wrapper``,
``no_cfunc_wrapper``: each as large as its arguments' unboxing); ``inline='always'`` is kept
for the workspace's view accessors and the small helpers of a hot loop, where a call costs
speed, and never for a large function called from several places (numba copies and types an
inlined callee again at each call site): ``contact_rows.build_rows_into`` is one call from
three places. Every integer argument is an int64 (a literal makes another specialisation).
"""
import numpy as np
from numba import njit

from .small_solves import dense_scratch

POSITION_ITERATIONS = 4      # passes of the position LCP per step, at most
POSITION_TOLERANCE = 1e-5    # m (contacts), rad (limits): stop once no violation exceeds this
POSITION_SKIN = 1e-3         # m: contacts this close (plus 4× the deepest violation) join the
                             # position LCP as inequalities (a correction must not push a
                             # neighbouring segment in)
ANGLE_SKIN = 1e-3            # rad: the same for limits
VELOCITY_SKIN = 1e-4         # m: a contact this close is touching for the velocity stage
SPECULATIVE_STEPS = 2.0      # a gap closing within this many steps joins the velocity stage
MAX_ROTATION = 0.25          # rad: largest rotation of one segment per position pass
MOBILITY = 1e-8              # a row the jointed chain moves less than this fraction of its
                             # free segment's mobility (a contact at the anchor) is left out
ROW_COLLIDERS = 8            # the row tables hold m × min(K, this) + 2 n_l rows (m colliding
                             # segments, K colliders, n_l limited joints); more are allocated


# Columns of a row.
LIN, ANG, APAR, ARM, VOTH, DEPTH, SEP, MU, NCOL = 0, 3, 6, 9, 12, 15, 16, 17, 18
SEG, PAR, CONTACT = 0, 1, 2

# The constant tuples (``collision.Unilateral.model_args``, ``_Detector.args``) and the pose.
(LENGTH, INV_MASS, INV_INERTIA, INV_I_MAX, IS_FIRST, HAS_CHILD, PARENT, CHAIN_OF, CHAIN_START,
 CHAIN_END, AXISYMMETRIC, LIMITED, SWING_LIMIT, TWIST_LIMIT) = range(14)
(D_SEG, D_RADIUS, D_LENGTH, D_INNER, D_FIRST_OF, D_FIRST_CHAIN, D_ROOT_FIXED, D_ROOTED_FIXED,
 D_SUM_RADIUS, D_CHAINS, D_CHAIN_REACH, D_MAX_HALF, D_N_SPHERE, D_N_ROUND, D_COL_RADIUS,
 D_FRICTION) = range(16)
P_A0, P_D2, P_NORMAL, P_ORIGIN, P_VELOCITY, P_OMEGA, P_SPEED = range(7)

# Status of ``resolve`` (``NO_ROOM``: of ``resolve_chains_into``, the row tables
# overflowed: its caller grows them and resolves that chain again).
OK, NOT_POSITIVE_DEFINITE, NO_ROOM = 0, 1, 2


# -- the workspace of one ``resolve`` call -------------------------------------------------------
# Every array the stages need, allocated once per call (~100 allocations a step otherwise), as
# few arrays as possible: each array in the tuple costs a reference-count increment and
# decrement wherever the tuple is bound, and the stages bind it several times a step. Sizes:
# n segments, m colliding segments, K colliders, n_l limited joints, k_max = m K + 2 n_l
# candidate rows, cap the row tables' rows (``ROW_COLLIDERS``). Indices into the tuple, and
# into the first axis of its stacked arrays:
(WS_VEC, WS_MAT, WS_TABLES, WS_IDS, WS_DET, WS_OWN, WS_Q, WS_AXIS, WS_LIM, WS_ROWVEC,
 WS_KEEP, WS_PAIRS, WS_SLOTS, WS_CHAIN_SLOT, WS_STATE, WS_BOX, WS_TOUCHED, WS_SOLVE,
 WS_ORDER, WS_SWEEP) = range(20)
# WS_VEC (7, n, 3): the half-vectors of the factorisation, four scratch vectors, then the
# step's velocities on entry (kept to resolve it again if the row tables overflow).
V_H, V_N0, V_N1, V_N2, V_N3, V_V0, V_W0 = range(7)
# WS_MAT (3, n, 3, 3): the factorisation (I⁻¹, pivots, Lo: ``contact_joints.joint_factors``).
M_INV_I, M_PIVOTS, M_LO = range(3)
# WS_TABLES (3, cap, NCOL) floats and WS_IDS (3, cap, 3) integers: the row tables.
T_ROWS, T_SEL, T_FRIC = range(3)
# WS_DET (3, m, K): detection (``detect``); WS_LIM (2, 2 n_l): the limits' gaps and rates.
DT_DEPTH, DT_S, DT_T = range(3)
L_GAP, L_SEP = range(2)
# WS_ROWVEC (4, k_max): per-row right-hand side, impulses, slip speeds, friction bounds.
R_B, R_LAM, R_SPEED, R_BOUND = range(4)
# WS_PAIRS (nd, K) and WS_SLOTS (3, nd) integers, WS_STATE (nd, K) bytes, WS_BOX (K, 7)
# floats and WS_ORDER (K,) integers: the per-pair broad phase (``near_pairs``: kept pairs,
# slots, pair states, the round colliders' boxes and their sweep order, ``sweep_order``).
S_COUNT, S_FIRST, S_END = range(3)
# WS_SWEEP (5,) floats: what ``broad_phase_setup`` found for this step's colliders (whether
# the sweep is on, its axis, the widest box along it, the largest bound, the fastest
# collider's surface speed), for every chain's ``near_pairs``.
SW_ON, SW_AXIS, SW_WIDEST, SW_BOUND, SW_FASTEST = range(5)
# WS_TOUCHED (2, C) integers: a mark per chain and the list of the chains with rows
# (``contact_joints.touched_joint_factors``).
# WS_SOLVE: ``solve_rows_into``'s scratch (``solve_scratch``), sized for the usual row groups.
# Indices into it:
SC_INT, SC_MOBILE, SC_RESP, SC_CDOT, SC_W, SC_LC, SC_DS = range(7)


# The workspace is sized for the largest chain (``resolve_workspace``) and a call resolves one
# chain: its per-segment arrays are taken at that chain's length (leading-axis views, the same
# C-contiguous types), so that no loop over an array's length reads another chain's leftovers.
@njit(cache=True, inline='always')
def zero_pair(a, b):
    """``a[:] = 0; b[:] = 0`` for two ``(n, 3)`` arrays, as plain loops (a slice assignment
    of a 2-D view costs more than its few stores, and these are zeroed at every step)."""
    for i in range(a.shape[0]):
        for k in range(3):
            a[i, k] = 0.0
            b[i, k] = 0.0


@njit(cache=True, inline='always')
def vec(ws, i, n):
    """The workspace's vector ``i`` (``V_*``), ``(n, 3)``."""
    return ws[WS_VEC][i][:n]


@njit(cache=True, inline='always')
def mat(ws, i, n):
    """The workspace's block array ``i`` (``M_*``), ``(n, 3, 3)``."""
    return ws[WS_MAT][i][:n]


@njit(cache=True, inline='always')
def joint_factor_views(ws, n):
    """The factorisation in the workspace (half-vectors, I⁻¹, pivots, Lo) of ``n`` segments."""
    return vec(ws, V_H, n), mat(ws, M_INV_I, n), mat(ws, M_PIVOTS, n), mat(ws, M_LO, n)
SOLVE_GROUP_ROWS = 32        # the workspace's solve scratch holds row groups up to this many
                             # rows (a larger group's scratch is allocated by its call)


@njit(cache=True)
def solve_scratch(k, kg, nc, n_chains):
    """Scratch of ``solve_rows_into`` for up to ``k`` rows, groups of up to ``kg`` rows and
    chains of up to ``nc`` segments (``n_chains`` chains): the row grouping's integers
    (``group_rows_into``), the rows' mobility mask, the responses ``(2, kg, nc, 3)``, the joint
    scratch ``(nc, 3)``, W ``(kg, kg)``, a group's λ ``(kg,)`` and the dense problems'
    scratch (``dense_scratch``)."""
    return (np.empty(4 * k + 1 + n_chains, dtype=np.int64), np.empty(k, dtype=np.bool_),
            np.empty((2, kg, nc, 3)), np.empty((nc, 3)), np.empty((kg, kg)), np.empty(kg),
            dense_scratch(kg))


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def workspace(n, m, K, nl, nd, n_chains, nc_max):
    """The workspace of ``resolve`` (indices ``WS_*`` and, within the stacked arrays, the
    names above): half-vectors and scratch vectors, the factorisation, the row tables (all
    rows, a selection, friction rows; ``grown`` gives larger ones when needed), detection
    tables ``(m, K)``, one ``(n, 4)``, the limits' axes ``(2 n_l, 3)``,
    gaps and rates, per-row vectors and a mask ``(k_max)``, the per-pair broad phase's
    tables (nd colliding chains of n_chains), the touched chains' marks and the row solve's
    scratch (chains of up to ``nc_max`` segments)."""
    k_max = m * K + 2 * nl
    # The row tables' capacity: a crowd's segments each near a few colliders of many (a
    # workspace this small is reused by malloc, not mapped and faulted in at every call).
    cap = m * min(K, ROW_COLLIDERS) + 2 * nl
    return (np.empty((7, n, 3)), np.empty((3, n, 3, 3)), np.empty((3, cap, NCOL)),
            np.empty((3, cap, 3), dtype=np.int64), np.empty((3, m, K)),
            np.empty((m, K), dtype=np.bool_), np.empty((n, 4)),
            np.empty((2 * nl, 3)), np.empty((2, 2 * nl)), np.empty((4, k_max)),
            np.empty(k_max, dtype=np.bool_), np.empty((nd, K), dtype=np.int64),
            np.empty((3, nd), dtype=np.int64), np.empty(n_chains, dtype=np.int64),
            np.empty((nd, K), dtype=np.uint8), np.empty((K, 7)),
            np.empty((2, n_chains), dtype=np.int64),
            solve_scratch(cap, min(cap, SOLVE_GROUP_ROWS), nc_max, n_chains),
            np.empty(K, dtype=np.int64), np.empty(5))


@njit(cache=True, _nrt=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def grown(ws):
    """``ws`` with row tables that hold every candidate row (``k_max``: each colliding segment
    in each collider, and each limit twice), for the rare call whose rows overflow the usual
    ones (a segment near more than ``ROW_COLLIDERS`` colliders)."""
    k_max = ws[WS_ROWVEC].shape[1]
    return (ws[WS_VEC], ws[WS_MAT], np.empty((3, k_max, NCOL)),
            np.empty((3, k_max, 3), dtype=np.int64), ws[WS_DET], ws[WS_OWN], ws[WS_Q],
            ws[WS_AXIS], ws[WS_LIM], ws[WS_ROWVEC], ws[WS_KEEP], ws[WS_PAIRS], ws[WS_SLOTS],
            ws[WS_CHAIN_SLOT], ws[WS_STATE], ws[WS_BOX], ws[WS_TOUCHED], ws[WS_SOLVE],
            ws[WS_ORDER], ws[WS_SWEEP])


@njit(cache=True)
def resolve_workspace(model, det, split, pose, has_colliders):
    """``workspace`` for resolving a model's chains one at a time (``resolve_chains_into``):
    sized for its largest chain (segments, colliding segments, limited joints), against all
    the colliders."""
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    lim, rows = split[SP_LIM_RANGE], split[SP_DET_RANGE]
    # (every size an int64 from the start: a literal 0 would be typed, and its callees
    # compiled, once more as a constant while numba unifies the loop)
    n = m = nl = np.int64(0)
    for c in range(chain_start.shape[0]):
        n = max(n, chain_end[c] - chain_start[c])
        m = max(m, rows[1, c] - rows[0, c])
        nl = max(nl, lim[1, c] - lim[0, c])
    K, nd, one = pose[P_A0].shape[0], np.int64(1), np.int64(1)
    if not has_colliders:
        m, K, nd = np.int64(0), np.int64(0), np.int64(0)
    return workspace(n, m, K, nl, nd, one, n)


# -- one chain at a time ----------------------------------------------------------------------
# Chains do not touch one another (colliders are kinematic bodies), so each chain's contacts
# and limits are resolved on their own: its own rows, skin, deepest violation, position passes,
# factorisation and projections, as if it were alone with all the colliders. A stage that
# pooled the chains (one skin, one deepest violation, passes and re-projection of all of
# them) made a character's motion depend on what the others touched.
# The split of the constant tuples (``collision.Unilateral.split_args``), what a chain's own
# tuples (``chain_model``, ``chain_det``) take besides views of the whole model's: parent
# indices in chain numbering (n), zeros (n), each chain's segment count (C), the limited
# joints in chain numbering (n_l, chain by chain) and each chain's range of them (2, C), each
# chain's range of the colliding segments (2, C), those in chain numbering (m) and their index
# among the chain's first segments (0 or -1, m), each chain's slot among the colliding chains
# and the index of its first segment among all first colliding segments (C, -1: none), and
# each chain's longest half colliding segment (C, m).
(SP_PARENT, SP_ZERO, SP_COUNT, SP_LIMITED, SP_LIM_RANGE, SP_DET_RANGE, SP_DET_SEG,
 SP_FIRST_OF, SP_SLOT, SP_FIRST, SP_MAX_HALF) = range(11)


@njit(cache=True, inline='always')
def chain_model(model, split, c):
    """The model tuple of chain ``c`` alone (views of ``model`` and ``split``)."""
    s, e = model[CHAIN_START][c], model[CHAIN_END][c]
    ls, le = split[SP_LIM_RANGE][0, c], split[SP_LIM_RANGE][1, c]
    zero = split[SP_ZERO]
    return (model[LENGTH][s:e], model[INV_MASS][s:e], model[INV_INERTIA][s:e],
            model[INV_I_MAX][s:e], model[IS_FIRST][s:e], model[HAS_CHILD][s:e],
            split[SP_PARENT][s:e], zero[s:e], zero[0:1], split[SP_COUNT][c:c + 1],
            model[AXISYMMETRIC], split[SP_LIMITED][ls:le], model[SWING_LIMIT][s:e],
            model[TWIST_LIMIT][s:e])


@njit(cache=True, inline='always')
def chain_det(det, split, c):
    """The detector tuple of chain ``c`` alone, with every collider (views)."""
    ms, me = split[SP_DET_RANGE][0, c], split[SP_DET_RANGE][1, c]
    slot, f = split[SP_SLOT][c], split[SP_FIRST][c]
    ns, nf = (1 if slot >= 0 else 0), (1 if f >= 0 else 0)
    slot, f = max(slot, 0), max(f, 0)
    zero = split[SP_ZERO]
    return (split[SP_DET_SEG][ms:me], det[D_RADIUS][ms:me], det[D_LENGTH][ms:me],
            det[D_INNER][ms:me], split[SP_FIRST_OF][ms:me], zero[0:nf],
            det[D_ROOT_FIXED][f:f + nf], det[D_ROOTED_FIXED][f:f + nf],
            det[D_SUM_RADIUS][ms:me], zero[0:ns], det[D_CHAIN_REACH][slot:slot + ns],
            split[SP_MAX_HALF][c], det[D_N_SPHERE], det[D_N_ROUND], det[D_COL_RADIUS],
            det[D_FRICTION])


@njit(cache=True, inline='always')
def chain_anchor(anchor, c):
    """Chain ``c``'s row of the anchors' ``(position, velocity, orientation, ω)`` (views)."""
    return (anchor[0][c:c + 1], anchor[1][c:c + 1], anchor[2][c:c + 1], anchor[3][c:c + 1])


@njit(cache=True)
def chain_args(model, det, split, c):
    """``(chain_model, chain_det)`` of chain ``c`` (for callers in Python)."""
    return chain_model(model, split, c), chain_det(det, split, c)


@njit(cache=True, inline='always')
def chain_is_free(split, has_colliders, c):
    """Whether chain ``c`` has nothing to resolve (no colliding segment, no limit)."""
    collides = has_colliders and split[SP_SLOT][c] >= 0
    return not collides and split[SP_LIM_RANGE][1, c] == split[SP_LIM_RANGE][0, c]


@njit(cache=True, inline='always')
def rows_of(ws, k):
    """The first ``k`` rows of the workspace's row table (``build_rows_into``): ``(R, I)``
    views."""
    return ws[WS_TABLES][T_ROWS][:max(k, 0)], ws[WS_IDS][T_ROWS][:max(k, 0)]
