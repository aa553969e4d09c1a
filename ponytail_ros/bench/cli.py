"""``ponytail_bench``: the speed/accuracy trade of the chain solver, measured.

Subcommands (default ``all``):

``trade``    sweep integrator, internal step, stabilisation (projection, Baumgarte), head tick
             rate and segment count on the named scenes (``scenes``: moving, release, shake,
             rope); per setting the CPU cost per simulated
             second and per step, the tip error (RMS/max, mm) against a converged reference (this
             core's RK4 at a tiny step, itself checked against ``../shared/reference/`` and by
             Richardson), the joint gap and, on still heads, the energy drift. Writes
             ``trade.csv/json``, ``refcheck.csv/json``, ``pareto.png``; prints and stores the
             recommended default (``summary.json``).
``scaling``  cost per step vs segment count (1..1000), RK4 / symplectic Euler / RATTLE,
             MuJoCo if installed: ``scaling.csv/json``, ``scaling.png``.
``mujoco``   the same chain in MuJoCo (RK4, head driven exactly) side by side with this core for
             several segment counts and steps: ``mujoco.csv/json``, ``mujoco.png``.
``batch``    C = 1, 10, 100, 1000 chains of 20 segments in one scene (one banded solve) vs one
             chain alone and vs C separate simulators: ``batch.csv/json``.
``energy``   still anchor, no damping, 5 segments released 45° from vertical, 10 s: relative
             energy drift per integrator and step: ``energy.csv/json``, ``energy.png``.
``terms``    what each force term, collider and joint limit costs on a 20-segment ponytail
             (each added in turn; switched-off terms against the plain scene), and what each
             ready-made scene (``config/*.yaml``) costs: ``terms.csv/json``,
             ``scenes.csv/json``.
``refcheck`` this core's RK4 against every file of ``../shared/reference/``.
``report``   ``results.md``: all tables of the JSON files in the output directory, as markdown
             (also written at the end of ``all``).

Measurements of the product as it runs (each its own options; ``ponytail_bench <name> --help``):

``step``     the compiled step per RK4 step against MuJoCo's ``mj_step``, same run
``tick``     one tick of the core at 12 to 4096 segments (``--idle``: after sleeping)
``crowds``   N characters in one scene, one tick (``--runner``: as a node runs them)
``node``     ``ponytail_node``'s CPU share beside the head demo (``--floor``: rclpy's own floor;
             ``--characters``: a crowd in one node)
``replay``   ``ponytail_replay`` of a 300 s head bag, and where its time goes
``compile``  the cold and warm compile of a scene's kernels, per stage
``many``     a folder of head bags replayed with ``-j 1`` and ``-j 2`` (``ponytail_replay -j``)
``scale``    N characters as one node and as several in their namespaces: tick rate and CPU
``head``     the head pose fit's accuracy and cost

Profiles: ``--quick`` (the default; ~2–3 min on one core), ``--full`` (all of it; ~30–40 min),
``--tiny`` (seconds; for the tests). Timings are CPU seconds (``time.process_time``) with BLAS
pinned to one thread, median of repeats.

Layout: this module parses the arguments and dispatches (``COMMANDS``); each subcommand is a
module of ``commands/``; ``profiles`` holds the sizes, ``tables`` the CSV/JSON/markdown output
and the run metadata, ``recommend`` the choice of the default setting.
"""
# First, before anything imports NumPy: one BLAS thread (see ``blas_threads``).
from . import blas_threads

# isort: split
import argparse
import json
import os
import sys
import time
from types import ModuleType
from typing import Any

from ponytail_ros.core.compile import report_compile

from . import mujoco_chain as MJ
from .commands import (  # one line per command, as in COMMANDS
    batch,
    energy,
    mujoco,
    pose,
    refcheck,
    report,
    scaling,
    terms,
    trade,
)
from .profiles import PROFILES
from .scenes import EXTRA_SCENES, SCENES
from .tables import jsonable, make_meta

__all__ = ['ALL', 'COMMANDS', 'PROFILES', 'TOOLS', 'build_parser', 'main', 'run_tool']

# -- the subcommands, in --help order: name -> module of ``commands/`` (defines ``HELP`` and
# ``run``). A new command: its module, one line in the import above and one line here.
COMMANDS: dict[str, ModuleType] = {
    'trade': trade,
    'scaling': scaling,
    'mujoco': mujoco,
    'batch': batch,
    'energy': energy,
    'terms': terms,
    'refcheck': refcheck,
    'pose': pose,
    'report': report,
}
#: Measurements run as their own commands: name -> (module of ``bench/``, help, arguments
#: put before the user's).
TOOLS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    'step': ('step_cost', 'the compiled step against MuJoCo mj_step, per RK4 step', ()),
    'tick': ('tick_cost', 'one tick of the core at 12 to 4096 segments', ()),
    'crowds': ('tick_cost', 'N characters in one scene, one tick (--runner: as a node)',
               ('--characters', '1', '10', '100', '250')),
    'node': ('node_cpu', "ponytail_node's CPU share beside the head demo", ()),
    'replay': ('replay_cost', 'ponytail_replay of a 300 s head bag, and where it goes', ()),
    'compile': ('compile_cost', 'the cold and warm compile of a scene\'s kernels, per stage',
                ()),
    'many': ('replay_many', 'a folder of head bags replayed with -j 1 and -j 2', ()),
    'scale': ('scale_out', 'N characters as one node and as several, tick rate and CPU', ()),
    'head': ('head_estimation_bench', "the head pose fit's accuracy and cost", ()),
}
#: What ``all`` (the default) runs, before ``report``.
ALL = ('trade', 'scaling', 'mujoco', 'batch', 'energy', 'terms')
ALL_HELP = 'trade, scaling, mujoco, batch, energy, terms, then report (the default)'


def _common_options(suppress: bool = False) -> argparse.ArgumentParser:
    """The options, accepted before and after the subcommand. The subcommand's copy has no
    defaults (``SUPPRESS``), so that it does not overwrite options given before it."""
    def d(value: Any) -> Any:
        return argparse.SUPPRESS if suppress else value

    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument('--quick', dest='profile', action='store_const', const='quick', default=d(None),
                   help='the default: every subcommand in ~2-3 min')
    g.add_argument('--full', dest='profile', action='store_const', const='full', default=d(None),
                   help='the full sweep (~30-40 min)')
    g.add_argument('--tiny', dest='profile', action='store_const', const='tiny', default=d(None),
                   help='seconds; for tests (numbers meaningless)')
    common.add_argument('--out', default=d(None), help='output directory (default: docs/bench)')
    common.add_argument('--repeats', type=int, default=d(None), help='timing repeats (median)')
    common.add_argument('--no-mujoco', action='store_true', default=d(False),
                        help='skip MuJoCo even if installed')
    common.add_argument('--quiet', action='store_true', default=d(False),
                        help='no progress bar (there is none when stderr is not a terminal)')
    common.add_argument('--scenes', default=d(None),
                        help='comma-separated scenes for trade (default: the profile\'s; '
                             f'any of {", ".join(SCENES + EXTRA_SCENES)})')
    return common


def build_parser() -> argparse.ArgumentParser:
    """The parser: common options before or after the subcommand (default ``all``)."""
    common = _common_options()
    p = argparse.ArgumentParser(prog='ponytail_bench', parents=[common],
                                description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest='command')
    helps = {name: module.HELP for name, module in COMMANDS.items()}
    helps['all'] = ALL_HELP
    for name, text in helps.items():
        sub.add_parser(name, parents=[_common_options(suppress=True)], help=text)
    for name, (_, text, _) in TOOLS.items():
        sub.add_parser(name, help=text)
    return p


def run_tool(name: str, argv: list[str]) -> int:
    """Run the measurement ``name`` of ``TOOLS`` with its own command line ``argv``."""
    import importlib
    module, _, preset = TOOLS[name]
    main = importlib.import_module(f'{__package__}.{module}').main
    status = main([*preset, *argv])
    return status if isinstance(status, int) else 0


def main(argv: list[str] | None = None) -> int:
    """``ponytail_bench [options] [command] [options]``; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in TOOLS:
        return run_tool(argv[0], argv[1:])
    args = build_parser().parse_args(argv)
    report_compile()            # the cold compile is said, and not timed as a setting's cost
    profile = args.profile or 'quick'
    prof = dict(PROFILES[profile])
    if args.repeats:
        prof['repeats'] = prof['scaling_repeats'] = prof['batch_repeats'] = args.repeats
    if args.scenes:
        prof['scenes'] = tuple(x.strip() for x in args.scenes.split(',') if x.strip())
        prof['durations'] = dict(PROFILES['full']['durations'], **prof['durations'])
        prof['seg_counts'] = ()
    out = args.out or os.path.join('docs', 'bench')
    os.makedirs(out, exist_ok=True)
    command = args.command or 'all'
    todo = ALL if command == 'all' else (command,)
    saved_mujoco = MJ.mujoco
    if args.no_mujoco:
        MJ.mujoco = None
    try:
        _run_commands(todo, profile, prof, out, command, progress=not args.quiet)
    finally:
        MJ.mujoco = saved_mujoco
    return 0


class _Progress:
    """A tqdm bar over the commands, weighted by their wall times in the last run
    (``summary.json``) so that its ETA means something; silent when stderr is not a terminal,
    with ``--quiet`` or without tqdm."""

    def __init__(self, todo: tuple[str, ...], summary: dict[str, Any], enabled: bool):
        last = summary.get('wall_s', {})
        self.weights = {name: float(last.get(name, 30.0)) for name in todo}
        self.bar: Any = None
        if enabled and sys.stderr.isatty():
            try:
                from tqdm import tqdm
            except ImportError:
                return
            self.bar = tqdm(total=sum(self.weights.values()), unit='s', desc='ponytail_bench',
                            bar_format='{desc}: {percentage:3.0f}%|{bar}| {postfix} '
                                       '[{elapsed}<{remaining}]', file=sys.stderr)

    def start(self, name: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(name)

    def done(self, name: str) -> None:
        if self.bar is not None:
            self.bar.update(self.weights[name])

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _run_commands(todo: tuple[str, ...], profile: str, prof: dict[str, Any], out: str,
                  command: str, progress: bool = True) -> int:
    walls: dict[str, float] = {}
    t_all = time.perf_counter()
    summary_path = os.path.join(out, 'summary.json')
    summary: dict[str, Any] = {}
    if os.path.exists(summary_path):
        try:
            with open(summary_path) as f:
                summary = json.load(f)
        except ValueError:
            summary = {}
    print(f'ponytail_bench {command} --{profile} -> {out} '
          f'(BLAS threads pinned: {blas_threads.PINNED})')
    bar = _Progress(todo, summary, progress)
    for name in todo:
        t0 = time.perf_counter()
        print(f'\n== {name} ==', flush=True)
        bar.start(name)
        meta = make_meta(profile, name)
        res = COMMANDS[name].run(prof, out, meta, log=lambda *a: print(*a, flush=True))
        walls[name] = time.perf_counter() - t0
        bar.done(name)
        print(f'[{name}: {walls[name]:.1f} s wall]', flush=True)
        if name == 'trade':
            summary['recommendation'] = jsonable(res[2])
    bar.close()
    wall = time.perf_counter() - t_all
    if command == 'all':
        summary.update(dict(meta=make_meta(profile, command), wall_s=dict(walls, total=wall)))
    elif command != 'report':
        # One subcommand re-run: its wall time joins those of the last full run.
        summary['wall_s'] = {**summary.get('wall_s', {}), **walls}
    if command != 'report':
        with open(summary_path, 'w') as f:
            json.dump(jsonable(summary), f, indent=1, allow_nan=False)
        if command == 'all':
            report.run(prof, out, make_meta(profile, 'report'))
    each = ', '.join(f'{k} {v:.0f} s' for k, v in walls.items())
    print(f'\nTotal wall time {wall:.1f} s ({each})')
    return 0


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
