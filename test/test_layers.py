"""The package's layers point one way: checked on the source, by walking every module's imports.

Nothing is imported or executed: each file under ``ponytail_ros/`` is parsed (``ast``) and
every ``import`` statement in it is collected, at module level or inside a function (a lazy
import is still a dependency), relative imports resolved against the file's package.

- ``ponytail_ros.core`` is ROS-free: it imports neither rclpy, nor mcap, nor a ROS message
  package, nor any other part of ``ponytail_ros``.
- ``ponytail_ros.app`` (the runner, the parameters, the node's behaviour as messages, the
  tick's output interface) imports no rclpy, and of the package only ``core`` (and the
  top-level ``resources``): the node (``ros``) and the offline tools (``recording``) both build
  on it.
- ``ros`` and ``recording`` do not import each other (the node records through a ``TickSink``
  it is given; ``ponytail_ros/node.py`` wires the two together).
- The top-level subpackages (``core``, ``app``, ``ros``, ``recording``, ``bench``, ``testing``
  and the top-level modules) form no cycle: core <- app <- (ros, recording) <- (node, testing,
  bench, demo).
"""
import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE = 'ponytail_ros'
ROOT = Path(__file__).resolve().parent.parent / PACKAGE

#: External packages the core must not import (top-level names; ``*_msgs`` are ROS messages).
ROS_OR_MCAP = ('rclpy', 'rosidl_runtime_py', 'ament_index_python', 'mcap', 'mcap_ros2')

#: What the application layer may import of the package.
APP_MAY_IMPORT = frozenset({'core', 'resources'})


def module_name(path: Path) -> str:
    """``ponytail_ros/core/scene.py`` -> ``ponytail_ros.core.scene`` (a package: its name)."""
    parts = list(path.relative_to(ROOT.parent).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def source_modules() -> dict[str, Path]:
    """Every module of the package, by dotted name."""
    return {module_name(p): p for p in sorted(ROOT.rglob('*.py'))}


def imports_of(name: str, path: Path, known: set[str]) -> Iterator[str]:
    """The dotted names ``path`` imports; ``from a import b`` yields ``a.b`` when ``b`` is a
    module of this package, else ``a``."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'), str(path))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split('.')
                base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = '.'.join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ''
            for alias in node.names:
                full = f'{base}.{alias.name}'
                yield full if full in known else base


def import_graph() -> dict[str, set[str]]:
    """Module -> the dotted names it imports (inside the package or not)."""
    modules = source_modules()
    known = set(modules)
    return {name: set(imports_of(name, path, known)) for name, path in modules.items()}


def unit(dotted: str) -> str:
    """The top-level part of the package a module belongs to: ``ponytail_ros.ros.node`` ->
    ``ros``, ``ponytail_ros.demo`` -> ``demo``; '' for the package's ``__init__``."""
    parts = dotted.split('.')
    return parts[1] if len(parts) > 1 else ''


def unit_graph() -> dict[str, set[str]]:
    """Top-level subpackage -> the other top-level subpackages it imports."""
    graph: dict[str, set[str]] = {}
    for module, targets in import_graph().items():
        src = unit(module)
        if not src:
            continue
        deps = graph.setdefault(src, set())
        for t in targets:
            if t.split('.')[0] == PACKAGE and unit(t) and unit(t) != src:
                deps.add(unit(t))
    return graph


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every node a path of one or more edges leads to from ``start``."""
    seen: set[str] = set()
    todo = [start]
    while todo:
        for w in graph.get(todo.pop(), ()):
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The cycles: each set of nodes that all reach one another (the graph is tiny)."""
    reach = {v: reachable(graph, v) for v in graph}
    found: list[frozenset[str]] = []
    for v in sorted(graph):
        if v in reach[v]:
            component = frozenset(w for w in reach[v] if v in reach.get(w, set()))
            if component not in found:
                found.append(component)
    return found


def test_the_walk_sees_the_imports() -> None:
    """The walk itself: modules found, relative and absolute imports resolved."""
    graph = import_graph()
    assert 'ponytail_ros.core.scene' in graph and 'ponytail_ros.bench.cli' in graph
    assert 'numpy' in graph['ponytail_ros.core.scene']
    assert 'ponytail_ros.core.head' in graph['ponytail_ros.core']            # from .head import
    assert 'ponytail_ros.bench.commands.trade' in graph['ponytail_ros.bench.cli']
    assert 'ponytail_ros.bench.measure' in graph['ponytail_ros.bench.commands.trade']  # from ..
    assert {'core'} <= unit_graph()['bench']


def test_cycles_are_found() -> None:
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [frozenset('abc')]
    assert cycles({'a': {'b'}, 'b': set()}) == []


def test_core_imports_neither_ros_nor_mcap() -> None:
    bad = {}
    for module, targets in import_graph().items():
        if unit(module) != 'core':
            continue
        found = sorted(t for t in targets
                       if t.split('.')[0] in ROS_OR_MCAP or t.split('.')[0].endswith('_msgs'))
        if found:
            bad[module] = found
    assert not bad, f'the core must stay ROS-free: {bad}'


def test_core_imports_no_other_part_of_the_package() -> None:
    bad = {}
    for module, targets in import_graph().items():
        if unit(module) != 'core':
            continue
        found = sorted(t for t in targets if t.split('.')[0] == PACKAGE and unit(t) != 'core')
        if found:
            bad[module] = found
    assert not bad, f'ponytail_ros.core imports only itself: {bad}'


def test_app_imports_no_rclpy() -> None:
    bad = {}
    for module, targets in import_graph().items():
        if unit(module) != 'app':
            continue
        found = sorted(t for t in targets if t.split('.')[0] in ('rclpy', 'rosidl_runtime_py'))
        if found:
            bad[module] = found
    assert 'ponytail_ros.app.runner' in import_graph()
    assert not bad, f'the application layer must not import rclpy: {bad}'


def test_app_builds_on_the_core_only() -> None:
    assert unit_graph()['app'] <= APP_MAY_IMPORT, unit_graph()['app']


def test_node_and_recording_do_not_import_each_other() -> None:
    graph = unit_graph()
    assert 'recording' not in graph['ros'] and 'ros' not in graph['recording'], graph
    assert {'app'} <= graph['ros'] and {'app'} <= graph['recording']


def test_no_cycle_between_subpackages() -> None:
    found = cycles(unit_graph())
    assert not found, f'import cycles between top-level subpackages: {found}'
