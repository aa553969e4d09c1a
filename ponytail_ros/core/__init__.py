"""ROS-free chain dynamics core (imports neither rclpy nor mcap).

What runs, in order: ``scene`` (description and validation) → ``model`` (arrays) → ``head``
(the kinematic bodies; the anchors' tables, ``head_kernels``) → the compiled step (``step``,
``lanes`` for a crowd: applied forces, the joint solve A f_c = b by ``chain_solve``, the
integrator, the joints closed) → for colliders and joint limits the contact stage
(``step_unilateral``, ``collision``, ``contact_stage``, ``limits``). ``simulator`` runs them
in fixed steps; ``chain_ops`` holds the operations on the state between steps (rest pose,
impulses). The NumPy reference of the step lives in the tests (``test/oracle``).
"""
# First: where numba caches the kernels, decided before any of them is defined. The public
# names are imported at their first use (PEP 562), so that ``kernel_cache`` alone stays light:
# the commands say a cold cache at once, before the seconds of numba's import
# (``compile.say_if_cold``).
import importlib
from typing import TYPE_CHECKING

from . import kernel_cache  # noqa: F401

if TYPE_CHECKING:
    from .head import AnchorKinematics, HeadMotion, KinematicState, StillMotion, SwayYawMotion
    from .scene import ChainSpec, ColliderSpec, Scene, SceneError, SolverSpec
    from .simulator import TUNABLE_PARAMETERS, Simulator, StepReport
    from .state import ChainState

__all__ = ['AnchorKinematics', 'ChainSpec', 'ColliderSpec', 'ChainState', 'HeadMotion',
           'KinematicState', 'Scene', 'SceneError', 'Simulator', 'SolverSpec', 'StepReport',
           'StillMotion', 'SwayYawMotion', 'TUNABLE_PARAMETERS']

_HOME = {'AnchorKinematics': 'head', 'HeadMotion': 'head', 'KinematicState': 'head',
         'StillMotion': 'head', 'SwayYawMotion': 'head', 'ChainSpec': 'scene',
         'ColliderSpec': 'scene', 'Scene': 'scene', 'SceneError': 'scene', 'SolverSpec': 'scene',
         'TUNABLE_PARAMETERS': 'simulator', 'Simulator': 'simulator', 'StepReport': 'simulator',
         'ChainState': 'state'}


def __getattr__(name):
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'.{home}', __name__), name)
    globals()[name] = value
    return value
