"""Compiled head kinematics (numba, nopython, no fastmath): the pose fit and the anchor track.

Two per-tick computations of the head side, written per sample and per chain so that a tick
costs microseconds instead of hundreds of NumPy calls:

* ``loess_fit``: ``HeadEstimator``'s local weighted least-squares polynomial fit of the pose
  samples around one instant (the equations and the bandwidth rule are in
  ``head_estimation``'s docstrings), solved as NumPy's ``lstsq`` does (an SVD solve:
  ``svd_lstsq``); ``states_fit`` fits several bodies' histories in one call, their fit
  times included (``fit_time``: ``t - delay``, warped past the newest sample);
* ``track_table``: ``AnchorTrack``'s quintic Hermite of each attachment point between two
  frames, the slerped anchor-body orientation and the interpolated angular velocity, at all the
  stage times of a call (the compiled step's anchor table);
* ``point_kinematics``: the motion of points fixed in kinematic bodies (Eq. 1–3 of ``head``);
  ``frame_ends`` evaluates it at both ends of a frame in one call (the track's two ends);
  ``frame_tables`` does a tick's whole head side in one call: the ends of the anchors' and
  the colliders' bodies' tracks and both tables at the stage times of the call's steps;
  ``sinusoid_table`` evaluates a motion of sinusoids in closed form (``head.SinusoidMotion``)
  and its points at the stage times of a call's steps, in one call.
* ``add_samples``: ``HeadEstimator.add`` of one pose of each of many bodies at one stamp (a
  crowd's poses, one message for all its frames), its checks and arithmetic; and
  ``longest_median_interval``, the input period of a crowd (``median_interval`` of each).

Units and frames: s, m, rad; world frame; quaternions scalar-last ``(x, y, z, w)`` body to
world (as ``rotations``).
"""
import math

import numpy as np
from numba import njit

from .vec import add, cross, dot, qconj, qfrom_rotvec, qmul, qnormalize, qrotate, qto_rotvec, scale

__all__ = ['loess_fit', 'states_fit', 'fits_at', 'fit_time', 'svd_lstsq', 'track_table',
           'point_kinematics', 'frame_ends', 'frame_tables', 'sinusoid_table', 'median_interval',
           'add_samples', 'longest_median_interval', 'FIT_SIZE', 'ACCEPTED', 'SINUSOID_COLUMNS']

#: The columns of ``sinusoid_table``'s coefficients, per body: p0, A, A ω, -A ω², ω, φ
#: (3 each, per axis), then Y, Y ω_y, -Y ω_y², ω_y, φ_y.
SINUSOID_COLUMNS = 23
#: Length of ``loess_fit``'s output: p (3), q (4), ṗ (3), ω (3), p̈ (3), α (3).
FIT_SIZE = 19
EPS = np.finfo(np.float64).eps
#: Sweeps of ``svd_lstsq``'s Jacobi rotations, at most (it converges quadratically: a fit's
#: few columns are orthogonal to working precision after a handful).
JACOBI_SWEEPS = 30


@njit(cache=True)
def _left_jacobian_rates(phi, phid, phidd):
    """World angular velocity and acceleration of ``q(t) = exp(φ(t)) ⊗ q_ref``.

    ``ω = J_l(φ) φ̇`` and ``α = J_l(φ) φ̈ + J̇_l φ̇``, with the left Jacobian of SO(3)
    ``J_l = I + a [φ]× + b [φ]×²``, ``a = (1 - cos θ)/θ²``, ``b = (θ - sin θ)/θ³``, ``θ = |φ|``;
    applied to ``φ̇`` its time derivative is (``[φ̇]× φ̇ = 0`` drops one term)

        J̇_l φ̇ = (a'/θ)(φ·φ̇) φ×φ̇ + (b'/θ)(φ·φ̇) φ×(φ×φ̇) + b φ̇×(φ×φ̇).

    Exact for any ``θ`` (Taylor series below θ = 0.1 avoid the cancellations).
    """
    th2 = dot(phi, phi)
    th = math.sqrt(th2)
    if th < 0.1:
        a = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
        b = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0
        da = -1.0 / 12.0 + th2 / 180.0 - th2 * th2 / 6720.0
        db = -1.0 / 60.0 + th2 / 1260.0 - th2 * th2 / 60480.0
    else:
        s, c = math.sin(th), math.cos(th)
        a = (1.0 - c) / th2
        b = (th - s) / (th2 * th)
        da = (th * s - 2.0 * (1.0 - c)) / (th2 * th2)
        db = ((1.0 - c) / (th2 * th) - 3.0 * (th - s) / (th2 * th2)) / th
    pxd = cross(phi, phid)
    ppxd = cross(phi, pxd)
    omega = add(add(phid, scale(a, pxd)), scale(b, ppxd))
    pxdd = cross(phi, phidd)
    alpha = add(add(phidd, scale(a, pxdd)), scale(b, cross(phi, pxdd)))
    pd = dot(phi, phid)
    alpha = add(alpha, add(add(scale(da * pd, pxd), scale(db * pd, ppxd)),
                           scale(b, cross(phid, pxd))))
    return omega, alpha


@njit(cache=True)
def svd_lstsq(A, B, rcond, X):
    """The minimum-norm least-squares solution ``X`` ``(p, m)`` of ``A X ≈ B`` (``A``
    ``(k, p)``, ``k ≥ p``; ``A`` is overwritten), singular values below ``rcond`` times the
    largest taken as zero: what LAPACK's ``gelsd`` (``np.linalg.lstsq``) returns, equal to
    rounding.

    One-sided Jacobi (Hestenes): plane rotations of column pairs, accumulated in ``W``,
    until every pair of columns of ``A W = U Σ`` is orthogonal to working precision; then
    ``X = W Σ⁺ Uᵀ B``. For the fit's few columns (a weighted Vandermonde matrix, ``p ≤ 10``)
    this is a few hundred flops per sweep and a handful of sweeps, without LAPACK's workspace
    query, allocations and copies into Fortran order, which cost more than the solve itself
    at this size. Jacobi's singular values are accurate to the columns' own rounding.
    """
    k, p = A.shape
    m = B.shape[1]
    W = np.zeros((p, p))
    for i in range(p):
        W[i, i] = 1.0
    for _ in range(JACOBI_SWEEPS):
        rotated = False
        for i in range(p - 1):
            for j in range(i + 1, p):
                alpha = 0.0
                beta = 0.0
                gamma = 0.0
                for r in range(k):
                    alpha += A[r, i] * A[r, i]
                    beta += A[r, j] * A[r, j]
                    gamma += A[r, i] * A[r, j]
                if gamma == 0.0 or abs(gamma) <= EPS * math.sqrt(alpha * beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for r in range(k):
                    ai, aj = A[r, i], A[r, j]
                    A[r, i] = c * ai - s * aj
                    A[r, j] = s * ai + c * aj
                for r in range(p):
                    wi, wj = W[r, i], W[r, j]
                    W[r, i] = c * wi - s * wj
                    W[r, j] = s * wi + c * wj
        if not rotated:
            break
    sigma = np.empty(p)
    s_max = 0.0
    for i in range(p):
        s2 = 0.0
        for r in range(k):
            s2 += A[r, i] * A[r, i]
        sigma[i] = math.sqrt(s2)
        s_max = max(s_max, sigma[i])
    for i in range(p):
        for a in range(m):
            X[i, a] = 0.0
    for i in range(p):
        if sigma[i] <= rcond * s_max or sigma[i] == 0.0:
            continue
        for a in range(m):
            # (u_i · b_a) / σ_i with u_i = A[:, i] / σ_i
            d = 0.0
            for r in range(k):
                d += A[r, i] * B[r, a]
            d /= sigma[i] * sigma[i]
            for row in range(p):
                X[row, a] += W[row, i] * d


@njit(cache=True)
def bandwidth(ts, n, te, window, min_samples):
    """``loess_fit``'s bandwidth ``H`` and the samples it weighs: ``(H, lo, hi, nearest)``,
    samples ``lo:hi`` those with ``|t_i - te| < H``, ``nearest`` the first sample nearest
    ``te``. ``ts[:n]`` must increase (as ``HeadEstimator`` stores them; ``ValueError``
    otherwise).

    ``H`` is ``window`` widened to the ``(min_samples + 1)``-th nearest sample, past any sample
    tied with the ``min_samples``-th (a tick on a sample of a regular stream would otherwise
    drop both); with ``n ≤ min_samples`` it is 1.1 times the farthest sample's distance.
    Increasing stamps make ``|t_i - te|`` fall to its least at ``nearest`` and then rise, so
    the distances in increasing order come from a merge outward from ``nearest`` (a few steps
    instead of sorting the whole history), and the weighed samples are one run of indices.
    """
    for i in range(1, n):
        if not ts[i] > ts[i - 1]:
            raise ValueError('loess_fit: the sample times must increase')
    # nearest: the first stamp at or after te, or the one before it if that is as near.
    a, b = 0, n
    while a < b:
        mid = (a + b) // 2
        if ts[mid] < te:
            a = mid + 1
        else:
            b = mid
    if a == n:
        nearest = n - 1
    elif a == 0:
        nearest = 0
    else:
        nearest = a - 1 if abs(ts[a - 1] - te) <= abs(ts[a] - te) else a
    m = min(min_samples, n)
    H = 1.1 * max(abs(ts[0] - te), abs(ts[n - 1] - te))
    if n > m:
        left, right = nearest - 1, nearest + 1
        d = abs(ts[nearest] - te)
        kth = d if m >= 1 else np.inf      # (no nearest count: the farthest bounds H)
        for taken in range(2, n + 1):
            dl = abs(ts[left] - te) if left >= 0 else np.inf
            dr = abs(ts[right] - te) if right < n else np.inf
            if dl <= dr:
                d = dl
                left -= 1
            else:
                d = dr
                right += 1
            if taken <= m:
                kth = d                     # the m-th nearest distance
            elif d > kth:
                H = d                       # the first farther than it
                break
        H = max(window, H)
    H = max(H, 1e-9)
    lo = nearest
    while lo > 0 and abs(ts[lo - 1] - te) < H:
        lo -= 1
    hi = nearest + 1
    while hi < n and abs(ts[hi] - te) < H:
        hi += 1
    return H, lo, hi, nearest


@njit(cache=True)
def loess_fit(ts, ps, qs, n, te, window, degree, min_samples, rate, rate_d, out):
    """The body's state at ``te`` from the first ``n`` samples (``ts`` s, ``ps`` m, ``qs``
    unit quaternions, sign-continuous), into ``out`` ``(FIT_SIZE,)``.

    Tricube-weighted degree-``degree`` fit in ``τ = (t - te)/H`` of the positions and of the
    rotation vectors ``φ_i = log(q_i ⊗ q_ref⁻¹)`` (``q_ref`` the sample nearest ``te``);
    ``H`` is ``window`` widened to the ``(min_samples + 1)``-th nearest sample (past any
    sample tied with the ``min_samples``-th, so that at least ``min_samples`` weigh:
    ``bandwidth``). ``rate`` and ``rate_d`` are the time warp's ``dt_warped/dt`` and its
    derivative (1, 0 unless the stream is stale and braking), applied by the chain rule.
    ``n ≥ 2``, ``ts[:n]`` increasing.
    """
    H, lo, hi, nearest = bandwidth(ts, n, te, window, min_samples)
    k = hi - lo
    deg = min(degree, k - 1)
    npar = deg + 1
    q_ref = qconj((qs[nearest, 0], qs[nearest, 1], qs[nearest, 2], qs[nearest, 3]))
    mean = np.zeros(3)
    for i in range(lo, hi):
        for a in range(3):
            mean[a] += ps[i, a]
    for a in range(3):
        mean[a] /= k
    V = np.empty((k, npar))
    Y = np.empty((k, 6))
    for r in range(k):
        i = lo + r
        tau = (ts[i] - te) / H
        u = abs(ts[i] - te) / H
        wt = math.sqrt((1.0 - u * u * u) ** 3)
        x = wt
        for c in range(npar):
            V[r, c] = x
            x *= tau
        phi = qto_rotvec(qmul((qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3]), q_ref))
        for a in range(3):
            Y[r, a] = (ps[i, a] - mean[a]) * wt
            Y[r, 3 + a] = phi[a] * wt
    # An SVD solve with NumPy's default cutoff: a sample at the bandwidth's edge enters with a
    # weight ~1e-22, and truncating that singular value keeps the fit the lower-degree one of
    # the others (a QR solve would fit the tenth coefficient to it).
    c = np.empty((npar, 6))
    svd_lstsq(V, Y, EPS * max(k, npar), c)
    val = np.zeros(6)
    vel = np.zeros(6)
    acc = np.zeros(6)
    for a in range(6):
        val[a] = c[0, a]
        if deg >= 1:
            vel[a] = c[1, a] / H
        if deg >= 2:
            acc[a] = 2.0 * c[2, a] / (H * H)
        acc[a] = acc[a] * (rate * rate) + vel[a] * rate_d
        vel[a] = vel[a] * rate
    phi = (val[3], val[4], val[5])
    omega, alpha = _left_jacobian_rates(phi, (vel[3], vel[4], vel[5]), (acc[3], acc[4], acc[5]))
    q = qnormalize(qmul(qfrom_rotvec(phi), qconj(q_ref)))
    for a in range(3):
        out[a] = val[a] + mean[a]
        out[7 + a] = vel[a]
        out[10 + a] = omega[a]
        out[13 + a] = acc[a]
        out[16 + a] = alpha[a]
    for a in range(4):
        out[3 + a] = q[a]


@njit(cache=True)
def _brake_warp(x):
    """Time warp of the braking phase, ``x`` clipped to [0, 1]: ``g(0)=0, g'(0)=1, g''(0)=0``,
    ``g'(1)=g''(1)=0``, ``g(1)=1/2``. Returns ``(g, g', g'')``."""
    x = min(max(x, 0.0), 1.0)
    x2 = x * x
    return x - x2 * x + 0.5 * x2 * x2, 1.0 - 3.0 * x2 + 2.0 * x2 * x, -6.0 * x + 6.0 * x2


@njit(cache=True)
def _return_warp(y):
    """The return to the newest sample, ``y`` clipped to [0, 1]: ``f = 1 - S(y)`` with ``S``
    the quintic smoothstep (``f(0) = 1``, ``f(1) = 0``, ``f'`` and ``f''`` zero at both
    ends). Returns ``(f, f', f'')``."""
    y = min(max(y, 0.0), 1.0)
    u = 1.0 - y
    return (1.0 - y * y * y * (10.0 - 15.0 * y + 6.0 * y * y), -30.0 * y * y * u * u,
            -60.0 * y * u * (1.0 - 2.0 * y))


@njit(cache=True)
def fit_time(ts, n, t, delay, max_extrapolation, max_gap):
    """``HeadEstimator.fit_time``: ``(te, rate, rate_d)`` of the fit of the first ``n`` ≥ 2
    stamps ``ts`` asked at ``t`` (s): ``t - delay`` within the history; past the newest stamp
    warped (full-speed extrapolation for half of ``max_extrapolation``, then a C² brake; from
    ``max_gap`` after it, a gap, a C² return over ``max_extrapolation`` to the newest stamp,
    held there: the last pose the stream gave, not the braked extrapolation); before the
    oldest, the oldest held (rate 0: the body at rest there, as a head held across a gap
    before its stream resumed)."""
    te = t - delay
    if te < ts[0]:
        return ts[0], 0.0, 0.0
    t_last = ts[n - 1]
    rate, rate_d = 1.0, 0.0
    s = te - t_last
    if s > 0.0:
        half = 0.5 * max_extrapolation
        gap = max(max_gap, max_extrapolation)
        if s > gap:
            if max_extrapolation > 0.0:
                f, fd, fdd = _return_warp((s - gap) / max_extrapolation)
                held = 1.5 * half               # (where the brake stops: half + half g(1))
                s, rate = held * f, held * fd / max_extrapolation
                rate_d = held * fdd / (max_extrapolation * max_extrapolation)
            else:
                s, rate = 0.0, 0.0
        elif s > half:
            if half > 0.0:
                g, gd, gdd = _brake_warp((s - half) / half)
                s, rate, rate_d = half + half * g, gd, gdd / half
            else:
                s, rate = 0.0, 0.0
        te = t_last + s
    return max(te, ts[0]), rate, rate_d


@njit(cache=True)
def states_fit(ts, ps, qs, ns, t, delays, max_extrapolations, max_gap, window, degree,
               min_samples, out):
    """Every body's ``HeadEstimator.state_at(t)`` numbers into the rows of ``out`` ``(K,
    FIT_SIZE)`` (zeros on entry): ``K`` bodies' histories in the rows of ``ts`` ``(K, M)``,
    ``ps`` ``(K, M, 3)``, ``qs`` ``(K, M, 4)`` (the first ``ns[k]`` samples), each body's fit time
    from its ``delays[k]`` and ``max_extrapolations[k]`` (``fit_time``); a body with one
    sample: that pose at rest, with none: the origin, unrotated."""
    for k in range(ns.shape[0]):
        n = ns[k]
        if n >= 2:
            te, rate, rate_d = fit_time(ts[k], n, t, delays[k], max_extrapolations[k], max_gap)
            loess_fit(ts[k], ps[k], qs[k], n, te, window, degree, min_samples, rate, rate_d,
                      out[k])
        else:
            out[k, 6] = 1.0
            if n == 1:
                for a in range(3):
                    out[k, a] = ps[k, 0, a]
                for a in range(4):
                    out[k, 3 + a] = qs[k, 0, a]


@njit(cache=True)
def fits_at(ts, ps, qs, n, times, delay, max_extrapolation, max_gap, window, degree,
            min_samples, out):
    """One body's ``HeadEstimator.state_at`` numbers at every time of ``times`` ``(T,)`` into
    the rows of ``out`` ``(T, FIT_SIZE)``: for each, its fit time (``fit_time``) and the fit
    (``loess_fit``) of the first ``n`` ≥ 2 samples, as one call each would give them."""
    for r in range(times.shape[0]):
        te, rate, rate_d = fit_time(ts, n, times[r], delay, max_extrapolation, max_gap)
        loess_fit(ts, ps, qs, n, te, window, degree, min_samples, rate, rate_d, out[r])


#: ``add_samples``' outcome of an accepted sample; a rejected one's is its reason's index in
#: ``head_estimation.REJECT_REASONS`` (these constants).
ACCEPTED, NONFINITE, ZERO_QUATERNION, NON_UNIT_QUATERNION, STAMP_BACKWARDS, STAMP_REPEATED = (
    -1, 1, 2, 3, 4, 5)


@njit(cache=True)
def add_samples(ts, ps, qs, ns, t, poses, restart, min_interval, max_gap, quat_tolerance,
                outcome):
    """``HeadEstimator.add`` of one pose per body at one stamp ``t`` (s), all ``K`` bodies in
    one call (a crowd's ``frames_topic`` message): ``poses`` ``(K, 7)`` rows (x, y, z, qx, qy,
    qz, qw), body ``k``'s history the first ``ns[k]`` rows of ``ts[k]``, ``ps[k]``, ``qs[k]``
    (updated in place, ``ns`` too). The same checks and arithmetic as ``HeadEstimator.check``
    then ``add_checked`` (pose finite, ``|q|`` not below 1e-9 and within ``quat_tolerance`` of
    1, then renormalised; a finite stamp; a stamp more than ``min_interval`` after the newest,
    the quaternion flipped to its hemisphere; more than ``max_gap`` after it: a new history;
    a full history drops its oldest sample). ``restart[k]``: a stamp before the newest starts
    a new history instead of being rejected (the stream restarted). ``outcome[k]``:
    ``ACCEPTED``, ``-2`` accepted as a restart, or the reason code."""
    m = ts.shape[1]
    for k in range(ns.shape[0]):
        px, py, pz = poses[k, 0], poses[k, 1], poses[k, 2]
        qx, qy, qz, qw = poses[k, 3], poses[k, 4], poses[k, 5], poses[k, 6]
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz) and np.isfinite(qx)
                and np.isfinite(qy) and np.isfinite(qz) and np.isfinite(qw)):
            outcome[k] = NONFINITE
            continue
        norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if norm < 1e-9:
            outcome[k] = ZERO_QUATERNION
            continue
        if abs(norm - 1.0) > quat_tolerance:
            outcome[k] = NON_UNIT_QUATERNION
            continue
        if not np.isfinite(t):
            outcome[k] = NONFINITE
            continue
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        n = ns[k]
        outcome[k] = ACCEPTED
        if n and restart[k] and t < ts[k, n - 1]:
            n = 0
            outcome[k] = -2
        if n:
            dt = t - ts[k, n - 1]
            if abs(dt) <= min_interval:
                outcome[k] = STAMP_REPEATED
                continue
            if dt < 0.0:
                outcome[k] = STAMP_BACKWARDS
                continue
            if (qx * qs[k, n - 1, 0] + qy * qs[k, n - 1, 1] + qz * qs[k, n - 1, 2]
                    + qw * qs[k, n - 1, 3]) < 0.0:
                qx, qy, qz, qw = -qx, -qy, -qz, -qw
            if dt > max_gap:
                n = 0
        if n == m:
            for j in range(m - 1):
                ts[k, j] = ts[k, j + 1]
                for a in range(3):
                    ps[k, j, a] = ps[k, j + 1, a]
                for a in range(4):
                    qs[k, j, a] = qs[k, j + 1, a]
            n -= 1
        ts[k, n] = t
        ps[k, n, 0], ps[k, n, 1], ps[k, n, 2] = px, py, pz
        qs[k, n, 0], qs[k, n, 1], qs[k, n, 2], qs[k, n, 3] = qx, qy, qz, qw
        ns[k] = n + 1


@njit(cache=True)
def longest_median_interval(ts, ns, rows):
    """The largest ``median_interval`` of the bodies ``rows`` with two stamps or more (s),
    -1.0 if none has."""
    longest = -1.0
    for k in rows:
        if ns[k] >= 2:
            longest = max(longest, median_interval(ts[k], ns[k]))
    return longest


@njit(cache=True)
def median_interval(ts, n):
    """Median of the ``n - 1`` intervals between the first ``n`` stamps ``ts`` (s), ``n ≥ 2``
    (as ``np.median(np.diff(ts[:n]))``)."""
    return np.median(ts[1:n] - ts[:n - 1])


# Spherical linear interpolation of unit quaternions (``rotations.quat_slerp``) in two parts:
# the arc, which does not depend on the fraction (a track computes it once per pair of ends:
# its log map is half of a slerp's transcendental functions), and the rotation at a fraction.
@njit(cache=True, inline='always')
def _slerp_arc(q0, q1):
    """The slerp's rotation vector from ``q0`` to ``q1`` (the nearer of ``±q1``)."""
    if dot((q0[0], q0[1], q0[2]), (q1[0], q1[1], q1[2])) + q0[3] * q1[3] < 0.0:
        q1 = (-q1[0], -q1[1], -q1[2], -q1[3])
    return qto_rotvec(qmul(q1, qconj(q0)))


@njit(cache=True, inline='always')
def _slerp_at(q0, phi, s):
    """The slerp from ``q0`` at fraction ``s`` of its arc ``phi`` (``_slerp_arc``)."""
    return qmul(qfrom_rotvec(scale(s, phi)), q0)


@njit(cache=True)
def track_table(times, t0, h, end_p, end_v, end_a, q_ends, w_ends,
                position, velocity, acceleration, orientation, angular_velocity):
    """``AnchorTrack`` at every time of ``times`` ``(S,)``, into the ``(S, C, 3|4)`` outputs.

    ``end_p/v/a`` ``(2, C, 3)``: the attachment points' kinematics at both frames, ``t0`` and
    ``t0 + h``: inside, the quintic Hermite through both ends' p, ṗ, p̈ (its monomial
    coefficients in ``s = (t - t0)/h``), outside the 2nd-order Taylor
    expansion from the nearer end; ``q_ends`` ``(2, C, 4)`` and ``w_ends`` ``(2, C, 3)``: the
    anchor bodies' orientation (slerped) and angular velocity (linear) at both frames, held
    outside.
    """
    C = end_p.shape[1]
    coef = np.empty((6, C, 3))
    # Each anchor's slerp arc, once for all rows.
    arc = np.empty((C, 3))
    for c in range(C):
        phi = _slerp_arc((q_ends[0, c, 0], q_ends[0, c, 1], q_ends[0, c, 2], q_ends[0, c, 3]),
                         (q_ends[1, c, 0], q_ends[1, c, 1], q_ends[1, c, 2], q_ends[1, c, 3]))
        for a in range(3):
            arc[c, a] = phi[a]
    for c in range(C):
        for a in range(3):
            p0, p1 = end_p[0, c, a], end_p[1, c, a]
            hv0, hv1 = h * end_v[0, c, a], h * end_v[1, c, a]
            ha0, ha1 = h * h * end_a[0, c, a], h * h * end_a[1, c, a]
            dp = p1 - p0
            coef[0, c, a] = p0
            coef[1, c, a] = hv0
            coef[2, c, a] = 0.5 * ha0
            coef[3, c, a] = 10.0 * dp - 6.0 * hv0 - 4.0 * hv1 - 1.5 * ha0 + 0.5 * ha1
            coef[4, c, a] = -15.0 * dp + 8.0 * hv0 + 7.0 * hv1 + 1.5 * ha0 - ha1
            coef[5, c, a] = 6.0 * dp - 3.0 * hv0 - 3.0 * hv1 - 0.5 * ha0 + 0.5 * ha1
    for r in range(times.shape[0]):
        t = times[r]
        s = (t - t0) / h
        sc = min(max(s, 0.0), 1.0)
        for c in range(C):
            if 0.0 <= s <= 1.0:
                for a in range(3):
                    c0, c1, c2 = coef[0, c, a], coef[1, c, a], coef[2, c, a]
                    c3, c4, c5 = coef[3, c, a], coef[4, c, a], coef[5, c, a]
                    position[r, c, a] = c0 + s * (c1 + s * (c2 + s * (c3 + s * (c4 + s * c5))))
                    velocity[r, c, a] = (c1 + s * (2.0 * c2 + s * (3.0 * c3 + s * (
                        4.0 * c4 + s * 5.0 * c5)))) / h
                    acceleration[r, c, a] = (2.0 * c2 + s * (6.0 * c3 + s * (
                        12.0 * c4 + s * 20.0 * c5))) / (h * h)
            else:
                e = 0 if s < 0.0 else 1
                tau = t - (t0 if s < 0.0 else t0 + h)
                for a in range(3):
                    p, v, acc = end_p[e, c, a], end_v[e, c, a], end_a[e, c, a]
                    position[r, c, a] = p + tau * (v + 0.5 * tau * acc)
                    velocity[r, c, a] = v + tau * acc
                    acceleration[r, c, a] = acc
            q = _slerp_at((q_ends[0, c, 0], q_ends[0, c, 1], q_ends[0, c, 2], q_ends[0, c, 3]),
                          (arc[c, 0], arc[c, 1], arc[c, 2]), sc)
            for a in range(4):
                orientation[r, c, a] = q[a]
            for a in range(3):
                angular_velocity[r, c, a] = (1.0 - sc) * w_ends[0, c, a] + sc * w_ends[1, c, a]


@njit(cache=True)
def point_kinematics(position, orientation, linear_velocity, angular_velocity,
                     linear_acceleration, angular_acceleration, body, r_local,
                     out_p, out_v, out_a, out_q, out_w):
    """Eq. 1–3 of ``head`` for ``C`` points fixed in kinematic bodies (``body`` ``(C,)``,
    ``r_local`` ``(C, 3)`` m in the body frame), into the ``(C, 3|4)`` outputs:
    ``p = R + r``, ``ṗ = Ṙ + ω × r``, ``p̈ = R̈ + α × r + ω × (ω × r)``, ``r = R_body r_local``,
    and the bodies' orientation and ω."""
    for c in range(body.shape[0]):
        k = body[c]
        q = (orientation[k, 0], orientation[k, 1], orientation[k, 2], orientation[k, 3])
        w = (angular_velocity[k, 0], angular_velocity[k, 1], angular_velocity[k, 2])
        al = (angular_acceleration[k, 0], angular_acceleration[k, 1], angular_acceleration[k, 2])
        r = qrotate(q, (r_local[c, 0], r_local[c, 1], r_local[c, 2]))
        wxr = cross(w, r)
        axr = cross(al, r)
        wxwxr = cross(w, wxr)
        for a in range(3):
            out_p[c, a] = position[k, a] + r[a]
            out_v[c, a] = linear_velocity[k, a] + wxr[a]
            # (p̈ + α × r) + ω × (ω × r): the order of head.py's NumPy form, bit for bit
            out_a[c, a] = (linear_acceleration[k, a] + axr[a]) + wxwxr[a]
            out_w[c, a] = w[a]
        for a in range(4):
            out_q[c, a] = q[a]


@njit(cache=True)
def frame_ends(p0, q0, v0, w0, a0, al0, p1, q1, v1, w1, a1, al1, body, r_local,
               end_p, end_v, end_a, end_q, end_w):
    """``point_kinematics`` of the points at both ends of a frame: the bodies' state at its
    start (``p0 … al0``) into row 0 of the ``(2, C, 3|4)`` outputs, at its end (``p1 … al1``)
    into row 1 (``AnchorTrack``'s ends; one call instead of two and the stacking)."""
    point_kinematics(p0, q0, v0, w0, a0, al0, body, r_local, end_p[0], end_v[0], end_a[0],
                     end_q[0], end_w[0])
    point_kinematics(p1, q1, v1, w1, a1, al1, body, r_local, end_p[1], end_v[1], end_a[1],
                     end_q[1], end_w[1])


@njit(cache=True)
def frame_tables(p0, q0, v0, w0, a0, al0, p1, q1, v1, w1, a1, al1, body, r_local, n_anchor,
                 t0, t1, t_base, k0, n_steps, dt, ends_a, ends_b, table_a, table_b):
    """A frame's head side in one call: whether both bodies' states (``p0 … al0`` at the
    frame's start ``t0``, ``p1 … al1`` at its end ``t1``) are finite, and, bit for bit as
    ``frame_ends`` then ``track_table`` compute them, into the output tuples (each the five
    arrays of an ``AnchorKinematics``: p, ṗ, p̈ ``(·, ·, 3)``, orientation ``(·, ·, 4)``,
    ω ``(·, ·, 3)``):

    * ``ends_a`` ``(2, n_anchor, ·)`` and ``ends_b`` ``(2, K, ·)``: the points ``body`` /
      ``r_local`` ``(n_anchor + K,)`` at both ends, the anchors' attachment points first,
      then the colliders' body origins;
    * ``table_a`` and ``table_b`` ``(2 n_steps + 2, ·, ·)``: their tracks (``AnchorTrack``,
      ``h = max(t1 - t0, 1e-12)``) at the stage times of steps ``k0 … k0 + n_steps - 1`` of
      ``dt`` from ``t_base`` (``Simulator._stage_times``: row ``2k`` at ``t_base + (k0 + k)
      dt``, ``2k + 1`` half a step later), and in the last row at ``t1`` (the frame's end,
      where the published chain is posed).
    """
    finite = True
    for arr in (p0, q0, v0, w0, a0, al0, p1, q1, v1, w1, a1, al1):
        for i in range(arr.shape[0]):
            for j in range(arr.shape[1]):
                if not math.isfinite(arr[i, j]):
                    finite = False
    n = body.shape[0]
    frame_ends(p0, q0, v0, w0, a0, al0, p1, q1, v1, w1, a1, al1, body[:n_anchor],
               r_local[:n_anchor], ends_a[0], ends_a[1], ends_a[2], ends_a[3], ends_a[4])
    frame_ends(p0, q0, v0, w0, a0, al0, p1, q1, v1, w1, a1, al1, body[n_anchor:n],
               r_local[n_anchor:n], ends_b[0], ends_b[1], ends_b[2], ends_b[3], ends_b[4])
    times = np.empty(2 * n_steps + 2)
    half = 0.5 * dt
    for k in range(n_steps + 1):
        t = t_base + float(k0 + k) * dt
        times[2 * k] = t
        if k < n_steps:
            times[2 * k + 1] = t + half
    times[2 * n_steps + 1] = t1
    h = max(t1 - t0, 1e-12)
    track_table(times, t0, h, ends_a[0], ends_a[1], ends_a[2], ends_a[3], ends_a[4],
                table_a[0], table_a[1], table_a[2], table_a[3], table_a[4])
    track_table(times, t0, h, ends_b[0], ends_b[1], ends_b[2], ends_b[3], ends_b[4],
                table_b[0], table_b[1], table_b[2], table_b[3], table_b[4])
    return finite


@njit(cache=True)
def sinusoid_table(coef, t_base, k0, n_steps, dt, body, r_local, out):
    """Points fixed in ``K`` bodies moving in closed form (``head.SinusoidMotion``) at the
    stage times of steps ``k0 … k0 + n_steps - 1`` of ``dt`` from ``t_base`` (row ``2k`` at
    ``t_base + (k0 + k) dt``, ``2k + 1`` half a step later, ``2 n_steps`` at the last step's
    end: ``head.stage_times``). Body ``b`` (row ``b`` of ``coef``, ``SINUSOID_COLUMNS``):

        p = p0 + A sin(ω t + φ),  ṗ = (A ω) cos(ω t + φ),  p̈ = (-A ω²) sin(ω t + φ)
        (per axis), turned about world Z by yaw = Y sin(ω_y t + φ_y), its rate
        (Y ω_y) cos(ω_y t + φ_y) and acceleration (-Y ω_y²) sin(ω_y t + φ_y)

    (each product as its column holds it, so that a motion's NumPy form and this give the
    same values bit for bit). Into ``out``, the points' table (``point_kinematics`` of
    ``body`` / ``r_local`` at each time): p, ṗ, p̈ ``(2 n_steps + 1, C, 3)``, the bodies'
    orientation ``(·, C, 4)`` and ω ``(·, C, 3)``."""
    K = coef.shape[0]
    out_p, out_v, out_a, out_q, out_w = out
    p, v, acc = np.empty((K, 3)), np.empty((K, 3)), np.empty((K, 3))
    q, om, al = np.zeros((K, 4)), np.zeros((K, 3)), np.zeros((K, 3))
    half = 0.5 * dt
    for row in range(2 * n_steps + 1):
        t = t_base + float(k0 + row // 2) * dt
        if row % 2 == 1:
            t = t + half
        for b in range(K):
            for a in range(3):
                arg = coef[b, 12 + a] * t + coef[b, 15 + a]
                s, c = _sin_cos(arg)
                p[b, a] = coef[b, a] + coef[b, 3 + a] * s
                v[b, a] = coef[b, 6 + a] * c
                acc[b, a] = coef[b, 9 + a] * s
            s, c = _sin_cos(coef[b, 21] * t + coef[b, 22])
            yaw = 0.5 * (coef[b, 18] * s)
            q[b, 2], q[b, 3] = _sin_cos(yaw)
            om[b, 2] = coef[b, 19] * c
            al[b, 2] = coef[b, 20] * s
        point_kinematics(p, q, v, om, acc, al, body, r_local, out_p[row], out_v[row],
                         out_a[row], out_q[row], out_w[row])


@njit(cache=True, inline='always')
def _sin_cos(x):
    """sin x, cos x; at ±0 (a still axis) exactly ±0 and 1 without the calls."""
    if x == 0.0:
        return x, 1.0
    return math.sin(x), math.cos(x)
