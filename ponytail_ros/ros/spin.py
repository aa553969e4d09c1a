"""The shared ``main()`` of the package's executables: init, spin one node, shut down cleanly."""
import sys

import rclpy
from rclpy.executors import ExternalShutdownException

__all__ = ['run_node']


def run_node(program, make_node, args=None, bad_input=()):
    """Spin the node ``make_node()`` until Ctrl-C, SIGTERM or external shutdown; exit code.

    ``bad_input``: exception types meaning invalid parameters (exit 2, one line, no traceback).
    """
    try:
        rclpy.init(args=sys.argv if args is None else args)
    except Exception as err:          # malformed --ros-args, unreadable params file
        print(f'{program}: cannot start: {err}', file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except tuple(bad_input) as err:
        print(f'{program}: invalid parameters: {err}', file=sys.stderr)
        code = 2
    except Exception:
        # Ctrl-C/SIGTERM shut the context down from the signal handler, possibly in the middle
        # of a callback (a publish then fails): that is a clean shutdown, not an error.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
