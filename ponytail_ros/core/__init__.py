"""ROS-free chain dynamics core (imports neither rclpy nor mcap).

Stages, one module each: ``scene`` (description and validation) → ``model`` (arrays) →
``head`` (kinematic bodies) → ``forces`` (applied) → ``solver`` (constraint forces, A f_c = b)
→ ``integrators`` → ``stabilization``; ``simulator`` runs them in fixed steps.
"""
# First: where numba caches the kernels, decided before any of them is defined.
from . import kernel_cache  # noqa: F401
from .head import AnchorKinematics, HeadMotion, KinematicState, StillMotion, SwayYawMotion
from .scene import ChainSpec, ColliderSpec, Scene, SceneError, SolverSpec
from .simulator import Simulator, StepReport, TUNABLE_PARAMETERS
from .state import ChainState

__all__ = ['AnchorKinematics', 'ChainSpec', 'ColliderSpec', 'ChainState', 'HeadMotion', 'KinematicState', 'Scene',
           'SceneError', 'Simulator', 'SolverSpec', 'StepReport', 'StillMotion', 'SwayYawMotion',
           'TUNABLE_PARAMETERS']
