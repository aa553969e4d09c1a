"""The same chain in MuJoCo (optional: ``pip install mujoco``, the ``bench`` extra).

Model (MJCF, built from a ``BenchScene``):
- every segment is a body whose frame sits at its proximal joint with +X along the segment
  (this core's convention), a ``ball`` joint at the origin, a capsule geom for looks
  (``contype = conaffinity = 0``: no contacts; contacts are also disabled globally) and an
  explicit ``<inertial>``: the same mass, the centre at (l/2, 0, 0) and the same principal
  moments (axial first) as the core's ``Model``; no joint damping unless the scene has it, no
  armature, no limits;
- ``<option integrator="RK4" timestep=dt>``, the scene's gravity, no drag.

The head, "driven exactly": MuJoCo has no kinematic body whose acceleration can be prescribed
at every RK4 stage (a mocap body moves only between steps, and a weld to it is a soft
constraint). Every head motion in this benchmark is a sum of sinusoids per degree of freedom
(sway along X, yaw about Z), and a sinusoid is the free motion of a harmonic oscillator. So the
head is a body on ``slide``/``hinge`` joints (world X, Y, Z, then yaw about Z through its
origin: the core's head frame), of mass M = 1e10 kg and inertia 1e10 kg·m², each joint a spring
of stiffness ``M ω²`` (``I ω²``) at rest at 0 (for Z shifted to cancel gravity), started at
``A sin φ`` with velocity ``A ω cos φ``. MuJoCo's own RK4 then produces the exact head motion
at every stage up to its integration error of that oscillator, ~(ωh)⁴/120 per radian of phase
(at 1/240 s and 1.5 Hz: ~3e-8 m on the head, far below the chain's error), and the chain's pull
on the head moves it by F/M ~ 1e-10 m/s². It is the cheapest exact drive (no Python callback
per stage), so the timings are MuJoCo's own. ``head_error`` reports the head's actual deviation
from the formula over a run.

Initial state: the chain at rest relative to the head (ball ``qvel`` = 0, so it moves rigidly
with the head, as in the reference files), hanging along the scene's rest direction.
"""
import math
import time

import numpy as np

from ponytail_ros.app.motions import SinusoidHead
from ponytail_ros.core.head import StillMotion
from ponytail_ros.core.rotations import quat_from_two_vectors

try:  # optional dependency
    import mujoco
except ImportError:  # pragma: no cover - depends on the environment
    mujoco = None

__all__ = ['available', 'build_mjcf', 'MujocoChain', 'HEAD_MASS', 'quiet', 'warnings_seen']

HEAD_MASS = 1e10


def available():
    return mujoco is not None


_WARNINGS: list[str] = []


def _quiet_warning(msg):
    """Collect MuJoCo's warnings instead of printing them and writing MUJOCO_LOG.TXT."""
    _WARNINGS.append(str(msg))


def quiet():
    """Route MuJoCo's warnings (e.g. "simulation is unstable") to a list (``warnings_seen``)."""
    if mujoco is not None:
        mujoco.set_mju_user_warning(_quiet_warning)


def warnings_seen():
    return list(_WARNINGS)


def _fmt(v):
    return ' '.join(f'{x:.17g}' for x in np.atleast_1d(v))


def _head_dofs(motion):
    """[(joint type, axis index, amplitude, ω, phase)] of a one-body ``SinusoidHead``."""
    if isinstance(motion, StillMotion):
        return []
    if not isinstance(motion, SinusoidHead) or motion.n_bodies != 1:
        raise ValueError('MuJoCo driver supports StillMotion and one-body SinusoidHead')
    dofs = []
    for ax in range(3):
        if motion.A[0, ax] != 0.0:
            dofs.append(('slide', ax, motion.A[0, ax], motion.w[0, ax], motion.phi[0, ax]))
    if motion.Y[0] != 0.0:
        dofs.append(('hinge', 2, motion.Y[0], motion.wy[0], motion.phy[0]))
    return dofs


def _head_origin(motion):
    if isinstance(motion, StillMotion):
        s = motion.state_at(0.0)
        return s.position[0], s.orientation[0]
    return motion.p0[0], np.array([0.0, 0.0, 0.0, 1.0])


def build_mjcf(bench, dt):
    """MJCF text of ``bench`` (a ``BenchScene`` with one chain) at timestep ``dt``."""
    scene = bench.scene
    if len(scene.chains) != 1:
        raise ValueError('one chain per MuJoCo model')
    c = scene.chains[0]
    lengths, masses, inertia = c.lengths(), c.masses(), c.principal_inertia()
    g = np.asarray(scene.gravity, dtype=float)
    p0, q0 = _head_origin(bench.motion)
    dofs = _head_dofs(bench.motion)
    xml = [f'<mujoco model="chain_{c.n_segments}">',
           '<compiler angle="radian" autolimits="true" boundmass="0" boundinertia="0"/>',
           f'<option timestep="{dt:.17g}" integrator="RK4" gravity="{_fmt(g)}">',
           '<flag contact="disable"/>', '</option>',
           '<size nkey="0"/>', '<worldbody>']
    xml.append(f'<body name="head" pos="{_fmt(p0)}" quat="{_fmt([q0[3], q0[0], q0[1], q0[2]])}">')
    axes = ('1 0 0', '0 1 0', '0 0 1')
    for j, (kind, ax, _amp, w, _ph) in enumerate(dofs):
        k = HEAD_MASS * w * w
        ref = 0.0
        if kind == 'slide' and g[ax] != 0.0:
            ref = -g[ax] / (w * w)               # spring rest shifted to cancel the head's weight
        xml.append(f'<joint name="head{j}" type="{kind}" axis="{axes[ax]}" stiffness="{k:.17g}" '
                   f'springref="{ref:.17g}" damping="0" armature="0" limited="false"/>')
    xml.append(f'<inertial pos="0 0 0" mass="{HEAD_MASS:g}" '
               f'diaginertia="{_fmt([HEAD_MASS] * 3)}"/>')
    pos = np.asarray(c.attach, dtype=float)
    for i in range(c.n_segments):
        l = lengths[i]
        xml.append(f'<body name="s{i}" pos="{_fmt(pos)}">')
        xml.append(f'<joint name="j{i}" type="ball" damping="{c.damping:.17g}" armature="0"/>')
        xml.append(f'<inertial pos="{l / 2:.17g} 0 0" mass="{masses[i]:.17g}" '
                   f'diaginertia="{_fmt(inertia[i])}"/>')
        xml.append(f'<geom type="capsule" fromto="0 0 0 {l:.17g} 0 0" size="{c.radius:.17g}" '
                   f'contype="0" conaffinity="0" mass="0"/>')
        pos = np.array([l, 0.0, 0.0])
    xml.append(f'<site name="tip" pos="{lengths[-1]:.17g} 0 0"/>')
    xml.append('</body>' * c.n_segments)
    xml += ['</body>', '</worldbody>', '</mujoco>']
    return '\n'.join(xml), dofs


class MujocoChain:
    """A ``BenchScene`` in MuJoCo at step ``dt``; ``reset()`` puts it in the initial state."""

    def __init__(self, bench, dt):
        if mujoco is None:
            raise RuntimeError('mujoco is not installed (pip install mujoco)')
        self.bench = bench
        self.dt = float(dt)
        self.xml, self.dofs = build_mjcf(bench, dt)
        quiet()
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        self.data = mujoco.MjData(self.model)
        self.tip_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, 'tip')
        self.reset()

    def reset(self):
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        nh = len(self.dofs)
        for j, (_kind, _ax, amp, w, ph) in enumerate(self.dofs):
            d.qpos[j] = amp * math.sin(ph)
            d.qvel[j] = amp * w * math.cos(ph)
        c = self.bench.scene.chains[0]
        p0, q_head = _head_origin(self.bench.motion)
        if c.rest_direction is not None:
            d_local = np.asarray(c.rest_direction, dtype=float)
        else:
            # Along gravity, expressed in the head frame at t = 0.
            g = np.asarray(self.bench.scene.gravity, dtype=float)
            down = g / np.linalg.norm(g)
            R0 = self._head_rotation0(q_head)
            d_local = R0.T @ down
        q = quat_from_two_vectors(np.array([1.0, 0.0, 0.0]), d_local)
        d.qpos[nh:nh + 4] = [q[3], q[0], q[1], q[2]]           # MuJoCo: (w, x, y, z)
        d.time = 0.0
        mujoco.mj_forward(m, d)

    def _head_rotation0(self, q_head):
        yaw = 0.0
        for kind, _ax, amp, _w, ph in self.dofs:
            if kind == 'hinge':
                yaw = amp * math.sin(ph)
        cy, sy = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        x, y, z, w = q_head
        Rh = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return Rh @ Rz

    def tip(self):
        """World position of the tip (kinematics recomputed for the current qpos)."""
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.tip_id].copy()

    def head_error(self):
        """Largest deviation of the head joints from their formulas at the current time."""
        t = self.data.time
        return max((abs(self.data.qpos[j] - amp * math.sin(w * t + ph))
                    for j, (kind, ax, amp, w, ph) in enumerate(self.dofs)), default=0.0)

    def unstable(self):
        d = self.data
        bad = d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
        bad += d.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number
        bad += d.warning[mujoco.mjtWarning.mjWARN_BADQPOS].number
        return bool(bad) or not np.all(np.isfinite(d.qpos))

    def run(self, duration, sample_dt=0.01):
        """The tip after every ``sample_dt`` s: (times, tips, head error, unstable)."""
        self.reset()
        m, d = self.model, self.data
        n = int(math.floor(duration / sample_dt + 1e-9))
        ts, tips, head_err = [0.0], [self.tip()], 0.0
        steps = 0
        for k in range(1, n + 1):
            target = int(math.floor(k * sample_dt / self.dt + 1e-9))
            while steps < target:
                mujoco.mj_step(m, d)
                steps += 1
            ts.append(steps * self.dt)
            tips.append(self.tip())
            head_err = max(head_err, self.head_error())
        return np.array(ts), np.array(tips), head_err, self.unstable()

    def time_steps(self, n_steps, repeats=3):
        """CPU seconds per step (median over ``repeats`` runs of ``n_steps`` steps)."""
        m, d = self.model, self.data
        out = []
        for _ in range(repeats):
            self.reset()
            c0 = time.process_time()
            for _ in range(n_steps):
                mujoco.mj_step(m, d)
            out.append((time.process_time() - c0) / n_steps)
        return float(np.median(out))
