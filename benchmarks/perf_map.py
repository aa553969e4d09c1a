"""``python benchmarks/perf_map.py``: where the compiled step's time goes, by kernel,
with Linux ``perf``.

numba's machine code lives in anonymous memory, so ``perf report`` shows its samples as bare
addresses. This runs ``tick_cost.crowd_runner`` (``--characters`` characters through
``ChainRunner``, as a node runs them) and then writes ``/tmp/perf-<pid>.map``, the file
``perf`` reads to name code it cannot find in a binary: one line per compiled function
loaded in this process (its address, its size up to the next function, its name as
``module.function`` and, when a function has several compiled versions, numba's
specialisation number). Run it under ``perf record``::

    perf record -F 4000 -o /tmp/k.data python benchmarks/perf_map.py --characters 100
    perf report -i /tmp/k.data --no-children --sort sym

Functions that numba or LLVM inlined count in their caller (``inline='always'`` kernels
such as ``contact_stage.limit_stage``'s callees show up inside it); libm's
functions (``atan2``, ``sin``) are named by ``perf`` itself. The addresses come from numba's
execution engine (``codegen()._engine``, not a public API: a numba that changes it makes
this command say so, not mis-name samples).
"""
import argparse
import os
import re

from ponytail_ros.bench.tick_cost import crowd_runner
from ponytail_ros.core.compile import report_compile

__all__ = ['compiled_functions', 'write_map']

# numba's mangled names: _ZN<len>ponytail_ros<len>core<len><module><len><function>B<n>v<k>...
_NAME = re.compile(r'_ZN(?:\d+ponytail_ros\d+core)?\d+(?P<module>\w+?)\d+(?P<function>[A-Za-z_]'
                   r'\w*?)B\d+v(?P<version>\d+)')


def _short(name):
    """``module.function vK`` for numba's mangled ``name`` (the name itself if it is not)."""
    m = _NAME.match(name)
    if m is None:
        return name
    return f"{m['module']}.{m['function']} v{m['version']}"


def compiled_functions():
    """``[(address, name)]`` of every function compiled (or loaded from the cache) in this
    process, sorted by address. Raises ``RuntimeError`` if numba's engine does not expose
    them the way this reads them."""
    from numba.core.registry import cpu_target
    try:
        engine = cpu_target.target_context.codegen()._engine
        names, ee = engine._defined_symbols, engine._ee
    except AttributeError as err:
        raise RuntimeError(f'this numba does not expose its compiled symbols ({err})') from err
    out = []
    for name in names:
        address = ee.get_function_address(name)
        if address:
            out.append((address, name))
    return sorted(out)


def write_map(path=None):
    """Write ``perf``'s map of the compiled functions to ``path`` (default
    ``/tmp/perf-<pid>.map``); each function's size runs to the next one's start (at most
    1 MiB; the last, 64 KiB). Returns ``(path, number of functions)``."""
    path = path or f'/tmp/perf-{os.getpid()}.map'
    functions = compiled_functions()
    ends = [a for a, _ in functions[1:]] + [functions[-1][0] + 65536] if functions else []
    with open(path, 'w') as f:
        for (address, name), end in zip(functions, ends, strict=True):
            f.write(f'{address:x} {min(end - address, 1 << 20):x} {_short(name)}\n')
    return path, len(functions)


def main(argv=None):
    p = argparse.ArgumentParser(prog='python benchmarks/perf_map.py',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--characters', type=int, default=1)
    p.add_argument('--ticks', type=int, default=2000)
    args = p.parse_args(argv)
    report_compile()
    med = crowd_runner(args.params, args.characters, args.ticks)[0]
    path, n = write_map()
    print(f'{args.characters} character(s), {args.ticks} ticks: {1e3 * med:.3f} ms per tick '
          f'(median); {n} compiled functions named in {path}')


if __name__ == '__main__':
    main()
