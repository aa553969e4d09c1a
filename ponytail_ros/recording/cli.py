"""``ponytail_replay``, the command line: re-simulate a recording offline, compare two runs,
or play a recording's head poses into a running graph.

Usage::

    ponytail_replay BAG -o OUTPUT.mcap [--params FILE.yaml] [--head-topic /head_pose]
                    [--ticks auto|recorded|nominal] [--look-ahead] [--overwrite] [--quiet]
    ponytail_replay BAG BAG... -o OUT_DIR [-j N] [...]   (or a folder of bags: one output each)
    ponytail_replay compare A.mcap B.mcap [--plot out.png]      (or --compare A B)
    ponytail_replay --live INPUT.mcap [--rate 1.0] [--no-clock] [--restamp] [--loop]
    ponytail_replay repair IN.mcap OUT.mcap [--overwrite]    (a killed or damaged recording)

A BAG is what rosbag2 writes: a bag folder (``metadata.yaml`` and the ``.mcap`` or ``.db3``
files it lists, split or not, compressed or not), its ``metadata.yaml``, or a single ``.mcap``
(``.db3``) file (``bag/layout.py``).

Offline replay (no ROS graph, no sleeping; as fast as the machine allows): the head poses
(``geometry_msgs/msg/PoseStamped`` or ``TransformStamped``) of any rosbag2 bag -- one
written by the node (``record_path``) or by ``ros2 bag record`` -- are pushed into a
``ChainRunner`` at their log times (receive times), the runner is ticked on the recorded clock
and the output is written exactly as the node records a run (same topics, types, metadata).

* Extra frames (``frames``): each frame's poses are read from the recorded node's topic for it
  (``frame_topics`` in the recording's metadata), else from its ``<frame>.topic`` resolved in
  the node's namespace (default ``/<frame>_pose``), and pushed like the head's, in file order.
  A frame the scene uses whose topic is not in the file is an error.

* Parameters: ``--params`` (a node params file, ``/**: ros__parameters:``), else the input's
  ``ponytail_ros/parameters`` metadata (then the live changes recorded on
  ``/parameter_events`` are applied at their times too), else the package's
  ``config/ponytail.yaml``.
* Ticks (``--ticks``): ``recorded`` ticks at the node's own tick times (the header stamps of its
  first ``segment_poses`` topic) and feeds every head pose and parameter change in the file
  order, i.e. exactly as the node interleaved them with its ticks; ``nominal`` ticks every
  ``1/rate`` s from the first head pose, a head pose counting for a tick if its log time is <=
  the tick time. ``auto`` (default): ``recorded`` if the input has the node's ticks and the
  replay's ``rate`` equals the recorded one, else ``nominal``.
  File order rather than time decides what came before a tick: under ``use_sim_time`` a pose
  received just after a tick carries the same clock time as the tick.
* Deterministic: the same input, parameters and output path give a byte-identical output file
  (the output's chunks are cut by size only, never by wall time, and the CDR is canonical, see
  ``cdr.py``). Replaying a node's recording with its recorded parameters and ticks reproduces
  its ``segment_poses`` and ``segment_markers`` bit for bit: ``ReplayNode`` makes exactly the
  node's ``ChainRunner`` calls with the same floats (the node's ``NodeCore``, its output to a
  ``TickSink`` as the node's recorder gets it, ``replay_node.py``; ``test_replay.py`` checks
  the two stay in step).
* Look-ahead (``--look-ahead``): every head pose is known ahead of time, so each tick is run
  only once ``LOOK_AHEAD_SAMPLES`` head poses logged after it, and ``LOOK_AHEAD_SPAN_NS`` of
  them, have been pushed (the frames' poses and the parameter changes in between are applied
  in file order), and the head is estimated at the tick time itself (no delay) by a centred
  fit through the poses on both sides: where poses are sparse (at most 10 within ±0.05 s:
  below ~100 Hz, and near the ends of the history) a global degree-11 interpolating spline
  through all the stored poses (``LOOK_AHEAD_SPLINE_DEGREE``, ``core/head_spline.py``), else
  the estimator settings of ``LOOK_AHEAD_VALUES`` (degree 9 over ±0.05 s, at least the 10
  nearest poses: it smooths float rounding at high rates; for animation, noisy tracker data
  wants the default replay) and ``output_stamp: simulated``. The output's parameters record
  them. Input resets (a teleport, a frame change) then take effect up to that look-ahead
  early. Not bit-exact with the live run, by design: the default replay is.
* Diagnostics are written every ``diagnostics_period`` s of the recorded clock with the node's
  keys; wall-time measurements (solve time, timer lateness) are ``n/a`` offline.

Many bags (several BAGs, or a folder of bags): one output per bag, ``OUT_DIR/<bag>.mcap``, in
parallel worker processes (``-j N``, default the number of cores; ``many.py``), one line per
bag as it ends, exit status the worst of them.

Interrupted (SIGINT, SIGTERM): the replay stops between two input messages, its output is
finalised (every MCAP reader opens it) and marked partial in its metadata (``partial``,
``partial_reason``, ``complete_until_ns`` in ``ponytail_ros/recording``; the same in rosbag2's
``custom_data``); one line says so; exit 130 (SIGINT) or 143 (SIGTERM). Replaying into it again
needs ``--overwrite``; reading it says it is partial.

Compare: per chain, the tip (last segment's far end; segment length from the recorded
parameters, else the joint spacing) of two runs at the same stamps (each run's ``output_stamp``
is read from its parameters and printed: ``tick`` stamps label a chain simulated ``delay``
earlier, ``simulated`` ones its own time; recordings without it are ``tick``) -- or, when the
tick times differ (a nominal replay of a live run), at the nearest stamps within half a tick --
printed as RMS / max / final distance with the parameters that differ; ``--plot`` draws the
distance over time and both tips' coordinates.

Live: the head poses (and the recorded frames' poses, on their topics) are published at the
recorded pace (``--rate`` scales it) on the recorded head topic, with ``/clock`` from the
recorded log times before each pose and at ``--clock-rate`` Hz in between, for nodes with
``use_sim_time:=true``. For a node on the system clock use ``--no-clock --restamp`` (or its
``stamp_source:=receive``).

Nothing is lost or wrong in silence:

* a **damaged** input (changed bytes: a chunk or data-section CRC mismatch, a record that does
  not fit its length) is refused with the byte offset and the problem (``BagReader``); ``repair``
  keeps every intact record in a new file;
* a **truncated** input (a recording whose writer was killed) replays what can be read, with a
  warning saying where it is cut; ``repair`` makes it a complete, indexed file (``repair.py``);
* a bag not written by the node is replayed in **log-time order** (as ``ros2 bag play``), with a
  warning if it was stored out of that order; the node's own recordings in file order (the order
  the node handled the messages);
* head stamps on **another clock** than the log times (median offset over 5 s) are refused
  (exit 2) with the fix, ``--stamp-source receive``; with ``--stamp-source header`` (or
  ``stamp_source`` in the ``--params`` file, or a node recording's own) they are used, with a
  warning; in such a bag a first stamp of exactly 0 is a stamp, not "no stamp";
* one file of a split bag given alone is replayed with a warning naming the folder that holds
  the whole bag;
* unknown ``--params`` names are warned with the closest known name; dropped input poses are
  counted on the terminal; the last (partial) diagnostics period is written; a run in which
  nothing could be simulated (every pose dropped) is an error saying why.

Every recording and replay output also holds the segments as TF frames on ``/tf``
(``--tf-prefix``, ``--no-tf``; ``tf.py``). On a terminal a progress bar (tqdm) shows the
simulated time and the ETA; ``--quiet`` silences it, the summary and the warnings.

Exit status: 0 on success (warnings on stderr), 2 on bad or damaged input (one line on stderr
naming the file and the problem: not a bag, a listed file missing, damaged, truncated before the
head topic, no such topic, not a head pose type, head stamps on another clock, invalid
parameters, nothing simulated), 1 on an unexpected error, 130 / 143 when interrupted by SIGINT /
SIGTERM (the output finalised and marked partial). With many bags: the worst of them.
"""
from __future__ import annotations

import argparse
import gc
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from ponytail_ros.core.compile import say_compiles

from .compare import compare, format_comparison, plot_comparison
from .inputs import ReplayError
from .interrupt import EXIT_CODES, StopRequest
from .live import live_replay
from .offline import Progress, replay

__all__ = ['main']


def _parser():
    p = argparse.ArgumentParser(
        prog='ponytail_replay',
        description='Re-simulate a recording offline (-o), compare two runs (compare / '
                    '--compare), play its head poses into a running graph (--live), or repair a '
                    'cut-short or damaged recording (repair IN OUT).',
        epilog='Examples:  ponytail_replay run.mcap -o replayed.mcap --params config/ponytail.yaml'
               '   |   ponytail_replay compare run.mcap replayed.mcap --plot diff.png'
               '   |   ponytail_replay --live run.mcap'
               '   |   ponytail_replay repair killed.mcap fixed.mcap.  Exit status: 0 done, 2 bad '
               'or damaged input (one line naming the file and the problem), 1 unexpected error.')
    p.add_argument('inputs', nargs='+', metavar='BAG',
                   help='the recording: a bag folder, its metadata.yaml, or a .mcap/.db3 file '
                        '(two with --compare; several, or a folder of bags, for replay -o DIR)')
    p.add_argument('-o', '--output', metavar='OUTPUT',
                   help='replay: the new recording (.mcap), or a folder (one <bag>.mcap per '
                        'bag) for several bags')
    p.add_argument('-j', '--jobs', type=int, default=None, metavar='N',
                   help='several bags: replay N at a time in worker processes (default: the '
                        'number of cores)')
    p.add_argument('--params', metavar='FILE.yaml',
                   help='node parameters (default: the recorded ones, else the package config)')
    p.add_argument('--head-topic', help='head pose topic (default: the recorded node\'s, '
                                        'else /head_pose)')
    p.add_argument('--head-frame', metavar='FRAME',
                   help='take the head from the bag\'s /tf and /tf_static: the TF frame of the '
                        'head (the parameter head_frame, over --params and the recorded one)')
    p.add_argument('--fixed-frame', metavar='FRAME',
                   help='with --head-frame: the inertial frame the chain is simulated in '
                        '(the parameter fixed_frame; default as the parameters say, world)')
    p.add_argument('--ticks', choices=('auto', 'recorded', 'nominal'), default='auto',
                   help='tick at the node\'s recorded tick times or every 1/rate s (default '
                        'auto: recorded when available and the rate is unchanged)')
    p.add_argument('--stamp-source', choices=('header', 'receive'),
                   help='time head poses by their header stamps or their log (receive) times, '
                        'over the parameters\' stamp_source (receive: stamps on another clock)')
    p.add_argument('--no-tf', action='store_true',
                   help='replay: do not record the segments as TF frames on /tf')
    p.add_argument('--tf-prefix', metavar='PREFIX',
                   help='replay: TF frames are PREFIX<chain>/<i> (default: as recorded, else '
                        'none)')
    p.add_argument('--look-ahead', action='store_true',
                   help='estimate the head from poses on both sides of each tick (no delay, '
                        'simulated-time stamps): the most accurate re-simulation of recorded '
                        'animation')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUTPUT')
    p.add_argument('-q', '--quiet', action='store_true',
                   help='no progress bar, no summary, no warnings')
    p.add_argument('--compare', action='store_true', help='compare two recordings A B')
    p.add_argument('--plot', metavar='OUT.png', help='compare: also plot (matplotlib)')
    p.add_argument('--live', action='store_true',
                   help='publish the head poses (and /clock) into the ROS graph at recorded pace')
    p.add_argument('--rate', type=float, default=1.0, help='live: pace factor (default 1)')
    p.add_argument('--no-clock', action='store_true', help='live: do not publish /clock')
    p.add_argument('--clock-rate', type=float, default=100.0, help='live: /clock Hz between '
                                                                   'poses (default 100)')
    p.add_argument('--restamp', action='store_true',
                   help='live: stamp the poses with this process\'s clock (nodes without '
                        'use_sim_time)')
    p.add_argument('--loop', action='store_true', help='live: loop (times keep increasing)')
    return p


def _repair_parser():
    p = argparse.ArgumentParser(
        prog='ponytail_replay repair',
        description='Rewrite a recording cut short (a killed writer: no summary, index or '
                    'footer) or damaged (changed bytes) as a complete, indexed MCAP file that '
                    'every reader opens (rosbags, mcap, ros2 bag), keeping every intact record '
                    'and saying what was lost.')
    p.add_argument('input', metavar='IN.mcap')
    p.add_argument('output', metavar='OUT.mcap')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUT')
    p.add_argument('-q', '--quiet', action='store_true', help='no summary')
    return p


def _check_plot_path(path) -> str | None:
    """Why ``--plot`` cannot be written there, or None."""
    out = Path(path)
    if out.is_dir():
        return f'--plot {out}: is a directory, give a file name (e.g. diff.png)'
    if not out.parent.is_dir():
        return f'--plot {out}: folder {out.parent} does not exist'
    if not os.access(out.parent, os.W_OK):
        return f'--plot {out}: folder {out.parent} is not writable'
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ponytail_replay``; returns the exit code. Called without ``argv``
    (the console script: the process ends next), it freezes the garbage collector's objects
    first: the interpreter's final collection over the loaded compiled kernels took 0.3-0.8 s
    of a replay's wall time (``bench/replay_cost``)."""
    code = _main(list(sys.argv[1:] if argv is None else argv))
    if argv is None:
        gc.freeze()
    return code


def _main(argv) -> int:

    def error(text):
        print(f'ponytail_replay: error: {text}', file=sys.stderr)
        return 2

    if argv and argv[0] == 'repair':
        return _main_repair(argv[1:], error)
    parser = _parser()
    args, ros_args = _parse(parser, argv)

    def warn(text):
        if not args.quiet:
            print(f'ponytail_replay: warning: {text}', file=sys.stderr)

    try:
        if args.compare:
            return _main_compare(args, parser, error)
        if args.live:
            if len(args.inputs) != 1:
                parser.error('--live plays one bag')
            return _main_live(args, ros_args, warn, error)
        return _main_replay(args, warn, error, parser)
    except ReplayError as exc:
        return error(exc)
    except KeyboardInterrupt:
        return EXIT_CODES[signal.SIGINT]


def _parse(parser, argv):
    """``(args, ros_args)``: ``compare A B`` as ``--compare A B``; exactly one mode; the
    arguments left over are ROS arguments, for ``--live`` only."""
    if argv and argv[0] == 'compare':
        argv = ['--compare'] + argv[1:]
    args, ros_args = parser.parse_known_args(argv)
    if ros_args and not args.live:
        parser.error(f'unrecognized arguments: {" ".join(ros_args)}')
    modes = sum((args.compare, args.live, args.output is not None))
    if modes != 1:
        parser.error('give exactly one of -o OUTPUT (replay), --compare A B, --live INPUT')
    return args, ros_args


def _main_compare(args, parser, error) -> int:
    """``compare A B [--plot out.png]``."""
    if len(args.inputs) != 2:
        parser.error('--compare takes two recordings: A B')
    if args.plot:
        problem = _check_plot_path(args.plot)
        if problem:
            return error(problem)
    comps, *_, values_a, values_b = compare(*args.inputs)
    print(format_comparison(args.inputs[0], args.inputs[1], comps, values_a, values_b))
    if args.plot:
        try:
            print(f'plot: {plot_comparison(comps, args.plot)}')
        except ImportError:
            return error('--plot needs matplotlib (pip install matplotlib)')
        except (OSError, ValueError) as exc:
            return error(f'--plot {args.plot}: cannot write it: '
                         f'{getattr(exc, "strerror", None) or exc}')
    return 0


def _replay_options(args) -> dict:
    return dict(params_file=args.params, head_topic=args.head_topic, ticks=args.ticks,
                overwrite=args.overwrite, stamp_source=args.stamp_source, tf=not args.no_tf,
                tf_prefix=args.tf_prefix, look_ahead=args.look_ahead,
                head_frame=args.head_frame, fixed_frame=args.fixed_frame)


def _main_replay(args, warn, error, parser) -> int:
    """``BAG -o OUTPUT`` (a progress bar on a terminal), or many bags ``-o DIR -j N``."""
    from .many import expand_inputs
    if args.jobs is not None and args.jobs < 1:
        parser.error(f'-j must be at least 1, not {args.jobs}')
    bags = expand_inputs(args.inputs)
    output = Path(args.output)
    if len(bags) > 1 or len(args.inputs) > 1:
        return _main_replay_many(args, bags, output, error)
    if output.is_dir() or args.output.endswith(('/', os.sep)):
        from .many import bag_name
        output = output / f'{bag_name(bags[0])}.mcap'
    progress = Progress(sys.stderr) if not args.quiet and sys.stderr.isatty() else None
    # The kernels the scene uses compile before the first tick, said.
    say_compiles((lambda m: None) if args.quiet else None, progress=not args.quiet)
    try:
        with StopRequest() as stop:
            result = replay(bags[0], output, progress=progress,
                            warn=None if args.quiet else warn, stop=stop,
                            **_replay_options(args))
    finally:
        if progress is not None:
            progress.close()
    if result.interrupted:
        print(f'ponytail_replay: {result.interrupted_line(bags[0])}', file=sys.stderr)
        return stop.exit_code
    if not args.quiet:
        print(result.summary(bags[0]))
    return 0


def _main_replay_many(args, bags, out_dir: Path, error) -> int:
    """Several bags into ``out_dir``, ``-j`` at a time; one line per bag; the worst exit."""
    from .many import output_paths, replay_many
    outputs = output_paths(bags, out_dir)
    jobs = args.jobs or os.cpu_count() or 1
    # each worker compiles (or loads) the stages its bag's scene uses, and says so
    say_compiles((lambda m: None) if args.quiet else None, progress=False)
    codes: list = []

    def report(outcome) -> None:
        codes.append(_bag_line(outcome, args.quiet, error))

    with StopRequest() as stop:
        outcomes = replay_many(bags, outputs, _replay_options(args), jobs=jobs, report=report,
                               stop=stop)
    if stop:
        return stop.exit_code
    failed = sum(1 for o in outcomes if o.status not in ('ok',))
    if not args.quiet or failed:
        print(f'ponytail_replay: {len(bags)} bags, {len(bags) - failed} replayed into '
              f'{out_dir}, {failed} failed', file=sys.stderr if failed else sys.stdout)
    return max(codes, default=0)


def _bag_line(outcome, quiet: bool, error) -> int:
    """The line (and warnings) of one bag of many; its exit code."""
    if not quiet:
        for text in outcome.warnings:
            print(f'ponytail_replay: warning: {text}', file=sys.stderr)
    if outcome.status == 'ok':
        if not quiet:
            print(outcome.result.summary(outcome.bag), flush=True)
        return 0
    if outcome.status == 'interrupted':
        print(f'ponytail_replay: {outcome.result.interrupted_line(outcome.bag)}',
              file=sys.stderr, flush=True)
        return 0            # (the exit code is the signal's)
    if outcome.status == 'not started':
        print(f'ponytail_replay: {outcome.bag}: not replayed (interrupted before it started)',
              file=sys.stderr, flush=True)
        return 0
    if outcome.status == 'error':
        return error(outcome.text)
    print(f'ponytail_replay: error: {outcome.bag}: unexpected error:\n{outcome.text}',
          file=sys.stderr, flush=True)
    return 1


def _main_repair(argv, error) -> int:
    from .repair import RepairError, repair
    args = _repair_parser().parse_args(argv)
    try:
        result = repair(args.input, args.output, overwrite=args.overwrite)
    except RepairError as exc:
        return error(exc)
    for problem in result.damage:
        print(f'ponytail_replay: warning: {args.input}: skipped a damaged part: '
              f'{problem.describe(result.input_size)}', file=sys.stderr)
    if not args.quiet:
        print(result.summary(args.input))
    return 0


def _main_live(args, ros_args, warn, error) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    try:
        rclpy.init(args=['ponytail_replay'] + ros_args)
    except Exception as exc:  # noqa: BLE001 - malformed --ros-args
        return error(f'cannot start: {exc}')
    try:
        n = live_replay(args.inputs[0], head_topic=args.head_topic, rate=args.rate,
                        clock=not args.no_clock, clock_hz=args.clock_rate,
                        restamp=args.restamp, loop=args.loop, warn=warn)
        if not args.quiet:
            print(f'published {n} head poses from {args.inputs[0]}')
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except ReplayError as exc:
        return error(exc)
    except Exception:
        if rclpy.ok():
            raise
        return 0  # shut down by a signal in the middle of a publish
    finally:
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
