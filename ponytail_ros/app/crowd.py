"""A crowd in one node: a params file's character copied N times, every copy but the first
hanging from its own extra frame, all those frames' poses in one ``PoseArray``.

Character 0 is the params file's scene as it is, on the head (``head_pose``). Character k
(1..N-1) is a copy of its chains and of its colliders fixed in the head, renamed
``<name>_<k>``, hanging from (and fixed in) the frame ``character_<k>``; every frame's pose
arrives on one topic, ``frames_topic`` (``frame_poses`` by default, what ``ponytail_head_demo
-p characters:=N`` publishes). Colliders static in the world (a floor) are shared, not copied.

``crowd_offsets(n)`` says where and when character k's head is: the same motion ``k *
CHARACTER_PHASE`` s later, ``k * CHARACTER_SPACING`` m along X (world frame, REP 103), so no
two characters move in lockstep and none reaches another's chains.

Run: ``python -m ponytail_ros.app.crowd config/ponytail.yaml 100 -o crowd.yaml``, then
``ponytail_node --ros-args --params-file crowd.yaml`` beside ``ponytail_head_demo --ros-args
-p characters:=100``. ROS-free.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from typing import Any

import numpy as np

from .param_values import values_from_params_file
from .parameters import MAX_FRAMES, ParameterError

__all__ = ['CHARACTER_SPACING', 'CHARACTER_PHASE', 'FRAMES_TOPIC', 'crowd_offsets',
           'crowd_values', 'params_file_text', 'main']

#: Distance between neighbouring characters' heads, m (along world X).
CHARACTER_SPACING = 1.0
#: How much later each next character's motion starts, s.
CHARACTER_PHASE = 0.37
#: The topic of the characters' frames (``frames_topic``), relative.
FRAMES_TOPIC = 'frame_poses'


def crowd_offsets(n: int) -> list[tuple[np.ndarray, float]]:
    """``(shift (3,) m, delay s)`` of characters 0..n-1: the head's motion delayed and
    shifted."""
    return [(np.array([k * CHARACTER_SPACING, 0.0, 0.0]), k * CHARACTER_PHASE)
            for k in range(n)]


def frame_name(k: int) -> str:
    """The extra frame character ``k`` (≥ 1) hangs from."""
    return f'character_{k}'


def crowd_values(partial: Mapping[str, Any], n: int,
                 frames_topic: str = FRAMES_TOPIC) -> dict[str, Any]:
    """The (partial, flat) parameter values of ``n`` characters from one character's
    ``partial`` (``values_from_params_file``). Raises ``ValueError`` for ``n`` < 1 or a scene
    with extra frames of its own (their copies would need poses nobody publishes)."""
    if n < 1:
        raise ValueError(f'characters = {n} is not allowed: at least 1')
    if partial.get('frames'):
        raise ValueError(f'the scene has extra frames ({list(partial["frames"])}): a crowd is '
                         f'built only of scenes whose chains and colliders are on the head')
    chains = [str(c) for c in partial.get('chains', ['ponytail'])]
    colliders = [str(c) for c in partial.get('colliders', [])]
    moving = [c for c in colliders if partial.get(f'{c}.frame', 'head') != 'world']
    out = dict(partial)
    if n == 1:
        return out
    frames = [frame_name(k) for k in range(1, n)]
    out['frames'] = frames
    out['frames_topic'] = frames_topic
    out['chains'] = chains + [f'{c}_{k}' for k in range(1, n) for c in chains]
    out['colliders'] = colliders + [f'{c}_{k}' for k in range(1, n) for c in moving]
    for k, frame in enumerate(frames, start=1):
        for name in chains + moving:
            prefix = f'{name}.'
            for key, value in partial.items():
                if key.startswith(prefix):
                    field = key[len(prefix):]
                    if field in ('anchor', 'frame') and value == 'head':
                        value = frame
                    out[f'{name}_{k}.{field}'] = value
            # (the default anchor / frame is the head: the copy's is its frame)
            field = 'frame' if name in moving else 'anchor'
            out.setdefault(f'{name}_{k}.{field}', frame)
    return out


def _nested(flat: Mapping[str, Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for key, value in flat.items():
        node = tree
        *groups, leaf = key.split('.')
        for g in groups:
            node = node.setdefault(g, {})
        node[leaf] = value
    return tree


def _scalar(value: Any) -> str:
    # (JSON's forms are YAML's too: true/false, numbers, double-quoted strings)
    return json.dumps(value)


def _block(tree: Mapping[str, Any], indent: int) -> list[str]:
    """Mappings as blocks, lists in flow style, no anchors or aliases (what ROS 2's params
    file parser reads)."""
    lines = []
    for key, value in tree.items():
        pad = ' ' * indent
        if isinstance(value, Mapping):
            lines.append(f'{pad}{key}:')
            lines += _block(value, indent + 2)
        elif isinstance(value, (list, tuple)):
            lines.append(f'{pad}{key}: [{", ".join(_scalar(v) for v in value)}]')
        else:
            lines.append(f'{pad}{key}: {_scalar(value)}')
    return lines


def params_file_text(flat: Mapping[str, Any], n: int, source: str) -> str:
    """A ROS 2 params file (``/**: ros__parameters:``) of the values ``flat``."""
    head = [f'# {n} characters in one ponytail node: {source} copied, characters 2..{n} on the',
            f'# frames of {flat.get("frames_topic", FRAMES_TOPIC)} (one PoseArray). Written by: '
            f'python -m ponytail_ros.app.crowd {source} {n}']
    return '\n'.join(head + _block({'/**': {'ros__parameters': _nested(flat)}}, 0)) + '\n'


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.app.crowd',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('params', help="one character's params file (e.g. config/ponytail.yaml)")
    p.add_argument('characters', type=int, help='how many characters (1 to frames\' limit, 256)')
    p.add_argument('-o', '--output', help='write the params file here (default: stdout)')
    p.add_argument('--frames-topic', default=FRAMES_TOPIC)
    args = p.parse_args(argv)
    if not 1 <= args.characters <= MAX_FRAMES:
        p.error(f'characters = {args.characters} is not allowed: must be in [1, {MAX_FRAMES}] '
                f'(frames: at most {MAX_FRAMES})')
    try:
        flat = crowd_values(values_from_params_file(args.params), args.characters,
                            args.frames_topic)
    except (ValueError, OSError, ParameterError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    text = params_file_text(flat, args.characters, args.params)
    if args.output:
        with open(args.output, 'w') as f:
            f.write(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
