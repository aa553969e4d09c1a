"""Many bags replayed at once: ``ponytail_replay BAG... -o DIR -j N``.

Every bag is replayed by ``offline.replay`` in a worker process of its own (at most ``N`` at a
time; scale-out is processes, as ROS 2's), into ``DIR/<bag name>.mcap``. The parent prints one
line per bag as it ends (its summary, or its error) and returns the worst outcome.

Signals: every worker runs in a process group of its own, so a terminal's Ctrl-C reaches the
parent only, which passes the first SIGINT or SIGTERM on to every running worker once; each
worker then ends its replay where it is, finalises its output marked partial, and reports.
Bags not started yet are not started. A second signal to the parent ends the workers at once.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

from .bag import BagError
from .bag.layout import bags_in, is_one_bag
from .inputs import ReplayError
from .interrupt import StopRequest

__all__ = ['expand_inputs', 'output_paths', 'replay_many', 'BagOutcome']


def expand_inputs(inputs: Sequence[str]) -> list[Path]:
    """The bags named on the command line: a folder that is not one bag itself (no
    ``metadata.yaml``) stands for the bags in it (``layout.bags_in``).

    Raises:
        ReplayError: an input does not exist, or a folder holds no bag.
    """
    out: list[Path] = []
    for given in inputs:
        path = Path(given)
        if not path.exists():
            raise ReplayError(f'cannot read bag {path}: No such file or directory')
        if path.is_dir() and not is_one_bag(path):
            inner = bags_in(path)
            if not inner:
                raise ReplayError(f'{path} is not a rosbag2 bag: no metadata.yaml and no .mcap '
                                  f'or .db3 file or bag folder in it')
            out.extend(inner)
        else:
            out.append(path)
    return out


def bag_name(path: Path) -> str:
    """A bag's name: its folder's (for ``metadata.yaml``, the folder holding it), else the
    file's name without its storage and compression suffixes."""
    if path.name == 'metadata.yaml':
        return path.parent.resolve().name
    if path.is_dir():
        return path.resolve().name
    name = path.name
    for suffix in ('.zstd', '.mcap', '.db3'):
        if name.endswith(suffix):
            name = name[:-len(suffix)]
    return name


def output_paths(bags: Sequence[Path], out_dir: Path) -> list[Path]:
    """``out_dir/<bag name>.mcap`` per bag (the folder made if missing).

    Raises:
        ReplayError: two bags with one name, or ``out_dir`` is a file or cannot be made.
    """
    names = [bag_name(b) for b in bags]
    seen: dict[str, Path] = {}
    for name, bag in zip(names, bags, strict=True):
        if name in seen:
            raise ReplayError(f'{seen[name]} and {bag} would both be replayed into '
                              f'{out_dir / (name + ".mcap")}: replay them into different '
                              f'folders')
        seen[name] = bag
    if out_dir.exists() and not out_dir.is_dir():
        raise ReplayError(f'-o {out_dir}: with several bags the output is a folder (one '
                          f'<bag>.mcap per bag), and {out_dir} is a file')
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReplayError(f'-o {out_dir}: cannot make the folder: {exc.strerror or exc}') \
            from None
    return [out_dir / f'{name}.mcap' for name in names]


@dataclass
class BagOutcome:
    """How one bag's replay ended: ``status`` ``'ok'``, ``'interrupted'``, ``'error'`` (bad
    input, exit 2) or ``'crash'`` (an unexpected error, exit 1; ``text`` the traceback)."""

    bag: Path
    status: str
    text: str = ''
    result: Any = None
    warnings: list[str] = field(default_factory=list)


def _worker(bag: Path, output: Path, options: dict[str, Any], conn) -> None:
    """In a worker process: replay one bag, send its ``BagOutcome``."""
    os.setpgid(0, 0)        # Ctrl-C reaches the parent only; it passes the signal on once
    from .offline import replay
    warnings: list[str] = []
    try:
        with StopRequest() as stop:
            result = replay(bag, output, warn=warnings.append, stop=stop, **options)
        status = 'interrupted' if result.interrupted else 'ok'
        outcome = BagOutcome(bag, status, result=result, warnings=warnings)
    except (ReplayError, BagError) as exc:
        outcome = BagOutcome(bag, 'error', str(exc), warnings=warnings)
    except BaseException:  # noqa: BLE001 - reported by the parent, one bag's failure
        outcome = BagOutcome(bag, 'crash', traceback.format_exc(), warnings=warnings)
    conn.send(outcome)
    conn.close()


def replay_many(bags: Sequence[Path], outputs: Sequence[Path], options: dict[str, Any], *,
                jobs: int, report: Callable[[BagOutcome], None],
                stop: StopRequest | None = None) -> list[BagOutcome]:
    """Replay ``bags`` into ``outputs`` in at most ``jobs`` worker processes; ``report`` is
    called with each bag's outcome as it ends (in the parent). ``options``: keyword arguments
    of ``offline.replay``. Bags not started when ``stop`` becomes true get status
    ``'not started'``."""
    ctx: Any = multiprocessing.get_context(
        'fork' if 'fork' in multiprocessing.get_all_start_methods() else 'spawn')
    pending = list(zip(bags, outputs, strict=True))
    running: dict[Any, tuple[Any, Path]] = {}       # connection -> (process, bag)
    outcomes: list[BagOutcome] = []
    outcome: BagOutcome
    forwarded = False
    try:
        while pending or running:
            while pending and len(running) < jobs and not stop:
                bag, output = pending.pop(0)
                receive, send = ctx.Pipe(duplex=False)
                process = ctx.Process(target=_worker, args=(bag, output, options, send),
                                      name=f'ponytail_replay {bag_name(bag)}')
                process.start()
                send.close()
                running[receive] = (process, bag)
            if stop and not forwarded:
                forwarded = True
                for process, _ in running.values():
                    _signal(process, stop.signum or signal.SIGTERM)
                for bag, _ in pending:
                    outcome = BagOutcome(bag, 'not started')
                    outcomes.append(outcome)
                    report(outcome)
                pending.clear()
            if not running:
                break
            ready: list[Any] = wait(list(running), timeout=0.2)
            for conn in ready:
                process, bag = running.pop(conn)
                try:
                    outcome = conn.recv()
                except (EOFError, OSError):
                    process.join()
                    outcome = BagOutcome(bag, 'crash', f'its worker process ended with exit '
                                                       f'status {process.exitcode}')
                process.join()
                conn.close()
                outcomes.append(outcome)
                report(outcome)
    finally:
        for process, _ in running.values():      # a second signal, or an error here
            _signal(process, signal.SIGTERM)
            _signal(process, signal.SIGTERM)
            process.join()
    return outcomes


def _signal(process, signum: int) -> None:
    try:
        if process.pid is not None and process.exitcode is None:
            os.kill(process.pid, signum)
    except ProcessLookupError:
        pass
