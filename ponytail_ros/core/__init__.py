"""ROS-free chain dynamics core (imports neither rclpy nor mcap).

What runs, in order: ``scene`` (description and validation) → ``model`` (arrays) → ``head``
(the kinematic bodies; the anchors' tables, ``head_kernels``) → the compiled step (``step``,
``lanes`` for a crowd: applied forces, the joint solve A f_c = b by ``chain_solve``, the
integrator, the joints closed) → for colliders and joint limits the contact stage
(``step_unilateral``, ``collision``, ``contact_kernels``, ``limits``). ``simulator`` runs them
in fixed steps; ``chain_ops`` holds the operations on the state between steps (rest pose,
impulses). The NumPy reference of the step lives in the tests (``test/oracle``).
"""
# First: where numba caches the kernels, decided before any of them is defined.
from . import kernel_cache  # noqa: F401
from .head import AnchorKinematics, HeadMotion, KinematicState, StillMotion, SwayYawMotion
from .scene import ChainSpec, ColliderSpec, Scene, SceneError, SolverSpec
from .simulator import TUNABLE_PARAMETERS, Simulator, StepReport
from .state import ChainState

__all__ = ['AnchorKinematics', 'ChainSpec', 'ColliderSpec', 'ChainState', 'HeadMotion',
           'KinematicState', 'Scene', 'SceneError', 'Simulator', 'SolverSpec', 'StepReport',
           'StillMotion', 'SwayYawMotion', 'TUNABLE_PARAMETERS']
