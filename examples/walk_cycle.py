"""My character's walk cycle, as a head motion: sim time t (s) -> head pose in the world frame
(REP 103): position (m) and orientation quaternion (x, y, z, w)."""
import math

STEP_FREQUENCY = 1.8      # Hz: steps per second
SPEED = 1.2               # m/s forward (+x)


def walk(t):
    phase = 2.0 * math.pi * STEP_FREQUENCY * t
    x = SPEED * t
    y = 0.03 * math.sin(0.5 * phase)              # sway from foot to foot
    z = 1.60 + 0.025 * math.cos(phase)            # bob, twice per stride
    yaw = 0.12 * math.sin(0.5 * phase)            # the head turns with the shoulders
    pitch = 0.05 * math.sin(phase)                # and nods with the steps
    # q = yaw about z, then pitch about y
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    return (x, y, z), (-sy * sp, cy * sp, sy * cp, cy * cp)


def walk_then_stop(t, stop=2.0):
    """The walk until ``stop`` s, then the head held where it stopped."""
    return walk(min(t, stop))
