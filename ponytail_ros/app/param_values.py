"""The ponytail node's parameter values outside a running node: from a params file, from a
recording's metadata, to a recording's metadata -- the full set a node would have, so that a
replay builds exactly the node's ``Scene`` and ``RunnerSettings``.

Values are plain Python (float, int, bool, str, lists), as the node keeps them
(``PonytailNode._values``). In a recording every parameter is stored as a JSON string (JSON is
a subset of YAML; floats are written with ``repr``, so they round-trip bit for bit) in the
metadata record ``ponytail_ros/parameters``.

This module does not import rclpy.
"""
from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from ponytail_ros.app.parameters import (
    CHAIN_PARAMS,
    COLLIDER_PARAMS,
    DEFAULT_COLORS,
    FRAME_PARAMS,
    GLOBAL_PARAMS,
    REMOVED_PARAMS,
    ParameterError,
    build_runner_settings,
    chain_param_name,
    check_names,
    check_values,
    definition,
    removed_parameter_error,
)
from ponytail_ros.core.scene import REMOVED_SOLVER_FIELDS

__all__ = ['complete_values', 'values_from_params_file', 'values_from_metadata',
           'metadata_from_values', 'default_values', 'scene_and_settings', 'resolve_values',
           'unknown_names', 'unknown_parameter_warnings', 'unknown_parameter_warning',
           'closest_name', 'IGNORED_NAMES']

#: Parameters a node has that do not change the simulation (accepted and ignored offline).
IGNORED_NAMES = frozenset({'use_sim_time', 'record_path', 'start_type_description_service',
                           'tf.publish', 'tf.prefix'})


def default_values(chains, colliders=(), frames=()) -> dict[str, Any]:
    """Every parameter's default for these chain, collider and frame names, as the node
    declares them."""
    values = {p.name: _copy(p.default) for p in GLOBAL_PARAMS}
    values['chains'] = list(chains)
    values['colliders'] = list(colliders)
    values['frames'] = list(frames)
    for i, chain in enumerate(chains):
        for p in CHAIN_PARAMS:
            default = (list(DEFAULT_COLORS[i % len(DEFAULT_COLORS)]) if p.name == 'color'
                       else _copy(p.default))
            values[chain_param_name(chain, p.name)] = default
    for collider in colliders:
        for p in COLLIDER_PARAMS:
            values[chain_param_name(collider, p.name)] = _copy(p.default)
    for frame in frames:
        for p in FRAME_PARAMS:
            values[chain_param_name(frame, p.name)] = _copy(p.default)
    return values


def _copy(value):
    return list(value) if isinstance(value, (list, tuple)) else value


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_integer(v):
    return _is_number(v) and float(v).is_integer()


def _is_numbers(v):
    return isinstance(v, (list, tuple)) and all(_is_number(x) for x in v)


def _is_strings(v):
    return isinstance(v, (list, tuple)) and all(isinstance(x, str) for x in v)


def _floats(v):
    return [float(x) for x in v]


def _same(v):
    return v


#: kind -> (accepts(value), the value converted, what an error says was expected)
_KINDS = {
    'double': (_is_number, float, 'a number'),
    'int': (_is_integer, int, 'an integer'),
    'bool': (lambda v: isinstance(v, bool), _same, 'true or false'),
    'string': (lambda v: isinstance(v, str), _same, 'a string'),
    'double3': (_is_numbers, _floats, 'a list of numbers'),
    'double4': (_is_numbers, _floats, 'a list of numbers'),
    'doubles': (_is_numbers, _floats, 'a list of numbers'),
    'strings': (_is_strings, list, 'a list of strings'),
}


def _coerce(name, kind, value):
    """Type check and conversion as the node's declaration (plus its int→double coercion)
    does; raises ``ParameterError`` naming the parameter."""
    accepts, converted, expected = _KINDS.get(kind, (lambda v: False, _same, kind))
    if not accepts(value):
        raise ParameterError(name, f'{name} = {value!r} has the wrong type: expected {expected}')
    return converted(value)


def complete_values(partial: Mapping[str, Any]) -> dict[str, Any]:
    """The node's full parameter set given ``partial`` (name -> value; the rest defaults).

    Unknown names are ignored as the node ignores undeclared overrides (those in
    :data:`IGNORED_NAMES` silently, the others are returned by :func:`unknown_names`).

    Raises:
        ParameterError: a value of the wrong type or out of range, inconsistent values, a
            removed parameter (``REMOVED_PARAMS``); the message names the parameter.
    """
    for name in sorted(REMOVED_PARAMS & partial.keys()):
        raise removed_parameter_error(name, partial[name])
    chains = partial.get('chains', [p.default for p in GLOBAL_PARAMS if p.name == 'chains'][0])
    chains = _coerce('chains', 'strings', chains)
    colliders = _coerce('colliders', 'strings', partial.get('colliders', []))
    frames = _coerce('frames', 'strings', partial.get('frames', []))
    check_names(chains, colliders, frames)
    values = default_values(chains, colliders, frames)
    for name, value in partial.items():
        pdef = definition(name, chains, colliders, frames)
        if pdef is not None:
            values[name] = _coerce(name, pdef.kind, value)
    check_values(values, chains)
    return values


def unknown_names(partial: Mapping[str, Any]):
    """Names in ``partial`` that are not parameters of a node with its chains."""
    chains = list(partial.get('chains', ['ponytail']))
    colliders = list(partial.get('colliders', []))
    frames = list(partial.get('frames', []))
    return sorted(n for n in partial
                  if definition(n, chains, colliders, frames) is None and n not in IGNORED_NAMES)


def closest_name(name: str, known) -> str | None:
    """The known name most like ``name`` (a typo's intended name), or None."""
    import difflib
    match = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return match[0] if match else None


def unknown_parameter_warning(name: str, known) -> str:
    """"unknown parameter 'x' ignored (did you mean 'y'?)" for a name not in ``known``
    (for a removed parameter: that it was removed, and why)."""
    if name in REMOVED_PARAMS:
        why = REMOVED_SOLVER_FIELDS[name.rpartition('.')[2]]
        return f'parameter {name!r} ignored: it was removed ({why})'
    close = closest_name(name, known)
    hint = f' (did you mean {close!r}?)' if close else ''
    return f'unknown parameter {name!r} ignored{hint}'


def unknown_parameter_warnings(partial: Mapping[str, Any]) -> list[str]:
    """One warning per name in ``partial`` that no node with its chains, colliders and
    frames has, naming the closest known parameter."""
    unknown = unknown_names(partial) if partial else []
    if not unknown:
        return []
    try:
        known = default_values(list(partial.get('chains', ['ponytail'])),
                               list(partial.get('colliders', [])),
                               list(partial.get('frames', [])))
    except ParameterError:
        known = {}
    return [unknown_parameter_warning(n, known) for n in unknown]


def scene_and_settings(values: Mapping[str, Any]):
    """``(chains, Scene, RunnerSettings)`` of a full value set (see :func:`complete_values`)."""
    chains = list(values['chains'])
    return chains, check_values(values, chains), build_runner_settings(values)


# -- params files ------------------------------------------------------------------------------


def _flatten(tree: Mapping, prefix: str = '') -> dict[str, Any]:
    out = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(_flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def _section_matches(pattern: str, node_fqn: str) -> bool:
    """rcl's node name matching of a params file section (``/**``, ``/*``, a name with or
    without the leading slash, wildcards inside)."""
    pattern = pattern if pattern.startswith('/') else '/' + pattern
    regex = ''
    for part in re.split(r'(\*\*|\*)', pattern):
        regex += {'**': '.*', '*': '[^/]*'}.get(part, re.escape(part))
    return re.fullmatch(regex, node_fqn) is not None


def values_from_params_file(path: str | Path, node_fqn: str = '/ponytail') -> dict[str, Any]:
    """The parameters a node named ``node_fqn`` gets from a ROS 2 params file.

    Every section (``/**:``, ``ponytail:``, ``/alice/ponytail:``, wildcards) matching the node
    applies, in file order, later values winning; nested keys become dotted names.

    Raises:
        ParameterError: unreadable file, not a params file, no section for the node.
    """
    path = Path(path)
    try:
        tree = yaml.safe_load(path.read_text(encoding='utf-8'))
    except OSError as exc:
        raise ParameterError('params', f'cannot read params file {path}: '
                                       f'{exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise ParameterError('params', f'params file {path} is not valid YAML: '
                                       f'{str(exc).splitlines()[0]}') from None
    if not isinstance(tree, Mapping):
        raise ParameterError('params', f'params file {path} is not a ROS 2 params file '
                                       f'(expected "/**: ros__parameters: ...")')
    values: dict[str, Any] = {}
    found = False
    for section, body in tree.items():
        if not isinstance(body, Mapping) or 'ros__parameters' not in body:
            continue
        if _section_matches(str(section), node_fqn):
            found = True
            values.update(_flatten(body['ros__parameters'] or {}))
    if not found:
        raise ParameterError('params', f'params file {path} has no ros__parameters section for '
                                       f'node {node_fqn} (e.g. "/**:")')
    return values


# -- recording metadata ------------------------------------------------------------------------


def metadata_from_values(values: Mapping[str, Any]) -> dict[str, str]:
    """name -> JSON text of the value, every entry a str (an MCAP metadata record)."""
    return {name: json.dumps(_copy(value)) for name, value in values.items()}


def values_from_metadata(record: Mapping[str, str]) -> dict[str, Any]:
    """Inverse of :func:`metadata_from_values`; a hand-edited YAML value is accepted too.
    A removed parameter (``REMOVED_PARAMS``) that an older recording holds is left out: the
    replay runs what the node runs now.

    Raises:
        ParameterError: a value that is neither JSON nor YAML.
    """
    values = {}
    for name, text in record.items():
        if name in REMOVED_PARAMS:
            continue
        try:
            values[name] = json.loads(text)
        except ValueError:
            try:
                values[name] = yaml.safe_load(text)
            except yaml.YAMLError:
                raise ParameterError(name, f'{name}: recorded value {text!r} is neither JSON '
                                           f'nor YAML') from None
    return values


def resolve_values(params_file: str | Path | None, recorded: Mapping[str, str] | None,
                   node_fqn: str = '/ponytail') -> tuple[dict[str, Any], str]:
    """The full parameter set of a replay and where it came from: ``params_file`` if given,
    else the recording's ``recorded`` metadata, else the package's default config."""
    if params_file is not None:
        return complete_values(values_from_params_file(params_file, node_fqn)), str(params_file)
    if recorded:
        return complete_values(values_from_metadata(recorded)), 'the recording'
    from ponytail_ros.resources import config_path
    default = config_path('ponytail.yaml')
    return complete_values(values_from_params_file(default, node_fqn)), str(default)
