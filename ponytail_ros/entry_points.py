"""The console commands (``setup.py``'s ``console_scripts``): each says at once when the
simulation kernels will compile (a cold cache: the first start after an install or an
upgrade, ``core.compile.say_if_cold``), then imports its command, whose imports (numba, rclpy)
take seconds before it can say more."""
import sys

__all__ = ['demo', 'node', 'replay']


def _say_if_cold():
    if not any(a in ('-h', '--help') for a in sys.argv[1:]):
        from ponytail_ros.core.compile import say_if_cold
        say_if_cold()


def node():
    """``ponytail_node`` (``ponytail_ros.node.main``)."""
    _say_if_cold()
    from ponytail_ros.node import main
    return main()


def demo():
    """``ponytail_demo`` (``ponytail_ros.demo.main``)."""
    _say_if_cold()
    from ponytail_ros.demo import main
    return main()


def replay():
    """``ponytail_replay`` (``ponytail_ros.recording.cli.main``)."""
    _say_if_cold()
    from ponytail_ros.recording.cli import main
    return main()
