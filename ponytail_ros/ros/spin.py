"""The shared ``main()`` of the package's executables: init, spin one node, shut down cleanly.

``--help`` / ``-h`` (before ``--ros-args``) prints the executable's help and exits 0; invalid
parameters end with one line naming the parameter and what is allowed, exit status 2.
"""
import gc
import inspect
import os
import re
import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions
from rclpy.timer import TimerInfo

__all__ = ['run_node', 'make_executor', 'spin_until_signal', 'timer_callback', 'EXECUTORS']

#: ``PONYTAIL_EXECUTOR``'s values: rclpy's ``EventsExecutor`` (the default: its wait runs in
#: C++ and is not rebuilt in Python at every wake-up) or the ``SingleThreadedExecutor``.
EXECUTORS = ('events', 'single')
#: s: the longest one ``spin_once`` waits for work, so the longest Ctrl-C or SIGTERM waits
#: before the node stops.
SPIN_TIMEOUT = 0.1


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


def make_executor(name=None):
    """The executor the package's executables spin on: ``name`` (default: the
    ``PONYTAIL_EXECUTOR`` environment variable, else ``'events'``), one of ``EXECUTORS``.

    rclpy's default ``SingleThreadedExecutor`` rebuilds its wait set in Python at every
    wake-up (every timer tick and every message: ~240 a second for a 120 Hz node), which is
    most of an idle rclpy node's CPU; ``EventsExecutor`` (``rclpy.experimental``) waits in C++
    (``docs/bench``: ``node_cpu``). Raises ``ValueError`` naming the variable and the allowed
    values for anything else.
    """
    name = os.environ.get('PONYTAIL_EXECUTOR', 'events') if name is None else name
    if name == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    if name == 'single':
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor()
    raise ValueError(f'PONYTAIL_EXECUTOR = {name!r}: allowed {" or ".join(EXECUTORS)}')


def timer_callback(method):
    """``method(info)`` as a timer callback whose signature is looked up, not rebuilt: the
    executor inspects a timer callback's signature at every call to find a ``TimerInfo``
    parameter (``inspect.signature`` of a bound method: a visible share of an idle node's
    main thread); a plain function carrying its ``__signature__`` answers at once."""
    # The annotation is exactly ``TimerInfo`` (rclpy compares it with ``==``: not Optional).
    def callback(info: TimerInfo = None):  # type: ignore[assignment]
        return method(info)
    callback.__signature__ = inspect.signature(callback)
    return callback


def spin_until_signal(executor, node):
    """Spin ``node`` until SIGINT, SIGTERM or the context's shutdown, a signal taking effect
    between two callbacks; returns the signal handlers it replaced."""
    stop = []
    executor.add_node(node)
    previous = {sig: signal.signal(sig, lambda signum, frame: stop.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    # A finite timeout: EventsExecutor's spin_once without one (rclpy.spin's way) returns at
    # once, a busy loop that takes a whole core.
    while executor.context.ok() and not stop:
        executor.spin_once(timeout_sec=SPIN_TIMEOUT)
    return previous


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
        # The signals are handled here, not by rclpy: rclpy's handler shuts the context down at
        # once, and under EventsExecutor the KeyboardInterrupt lands inside the next callback,
        # e.g. between a tick's PoseArray and its /tf, leaving a half-recorded tick. Here a
        # signal only asks the loop to stop after the callback in progress.
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:          # malformed --ros-args, unreadable params file
        print(f'{program}: cannot start: {describe_error(err)}', file=sys.stderr)
        return 2
    try:
        executor = make_executor()
    except ValueError as err:
        print(f'{program}: cannot start: {err}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    previous: dict = {}
    node = None
    code = 0
    try:
        node = make_node()              # Ctrl-C here (a first start's compile) still interrupts
        # What start-up built (compiled kernels, rclpy, NumPy: ~130,000 objects) lives as long
        # as the process: frozen, the collector's full passes skip it (one took 64 ms, a
        # stalled tick) and the exit does not traverse it.
        gc.freeze()
        previous = spin_until_signal(executor, node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except tuple(bad_input) as err:
        print(f'{program}: invalid parameters: {describe_error(err)}', file=sys.stderr)
        code = 2
    except Exception:
        # An external shutdown of the context in the middle of a callback (a publish then
        # fails) is a clean shutdown, not an error.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return code
