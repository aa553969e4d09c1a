"""The shared ``main()`` of the package's executables: init, spin one node, shut down cleanly.

``--help`` / ``-h`` (before ``--ros-args``) prints the executable's help and exits 0; invalid
parameters end with one line naming the parameter and what is allowed, exit status 2.
"""
import re
import sys

import rclpy
from rclpy.executors import ExternalShutdownException

__all__ = ['run_node']


_OUT_OF_RANGE = re.compile(r'Parameter (\S+) out of range Min: (\S+), Max: (\S+), value: (\S+)')
_WRONG_TYPE = re.compile(r"Trying to set parameter '([^']*)' to '(.*)' of type '(\w+)', "
                         r"expecting type '(\w+)'")


def describe_error(err) -> str:
    """rclpy's parameter errors in words: "rate = -1.0 is out of range: allowed 1.0 to 2000.0"
    instead of "Invalid parameter value (-1.0) for parameter. Reason: ..."."""
    text = str(err)
    match = _OUT_OF_RANGE.search(text)
    if match:
        name, lo, hi, value = match.groups()
        value = value.rstrip(':')
        return f'{name} = {value} is out of range: allowed {lo} to {hi}'
    match = _WRONG_TYPE.search(text)
    if match:
        name, value, got, want = match.groups()
        return (f'{name} = {value!r} has the wrong type: expected a {want.lower()}, got a '
                f'{got.lower()}')
    return ' '.join(text.split())


def wants_help(argv) -> bool:
    """``-h``/``--help`` among the arguments before ``--ros-args``."""
    args = list(argv[1:])
    if '--ros-args' in args:
        args = args[:args.index('--ros-args')]
    return '-h' in args or '--help' in args


def run_node(program, make_node, args=None, bad_input=(), help_text=None):
    """Spin the node ``make_node()`` until Ctrl-C, SIGTERM or external shutdown; exit code.

    ``bad_input``: exception types meaning invalid parameters (exit 2, one line, no traceback).
    ``help_text``: printed for ``--help`` (exit 0) instead of starting the node.
    """
    argv = sys.argv if args is None else args
    if wants_help(argv):
        print(help_text or f'usage: {program} [--ros-args -p name:=value '
                           f'--params-file FILE -r __ns:=/ns]')
        return 0
    try:
        rclpy.init(args=argv)
    except Exception as err:          # malformed --ros-args, unreadable params file
        print(f'{program}: cannot start: {describe_error(err)}', file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except tuple(bad_input) as err:
        print(f'{program}: invalid parameters: {describe_error(err)}', file=sys.stderr)
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
