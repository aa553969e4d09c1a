"""The head (and the extra frames with ``<frame>.tf_frame``) from TF, as the node and the replay
take it: ``/tf`` and ``/tf_static`` messages into one ``TFBuffer``, out of it head poses in
``fixed_frame`` at the stamps of the moving transforms (``tf_buffer.TFPoseSource``), each a
``ReceivedPose`` (a ``PoseStamped`` in ``fixed_frame``) that goes the way a head pose on
``head_pose`` goes: recorded as the head input, queued in the runner. What could not be
composed (a frame missing), and the transforms held past their samples (extrapolated, stale),
are counted for ``/diagnostics`` and said in words naming the frames (:meth:`TFInput.news`).
"""
from __future__ import annotations

from collections.abc import Iterable
from typing import Any, TypeAlias

from .messages import TF_TOPIC, ReceivedPose, Stamp
from .parameters import chain_param_name, frame_names
from .tf_buffer import TFBuffer, TFPoseSource, TFSample
from .wire import pose_stamped_cdr

__all__ = ['TFInput', 'TF_TOPIC', 'TF_STATIC_TOPIC', 'tf_frames']

#: The static transforms' topic (``/tf``'s is ``messages.TF_TOPIC``).
TF_STATIC_TOPIC = '/tf_static'

#: Look-ups failing this many TF messages in a row are said (fewer: the tree coming in).
FAILING_SAID = 10

#: A source: 'head' or the index of an extra frame in ``frames``.
Source: TypeAlias = str | int


def tf_frames(values) -> dict[Source, str]:
    """What comes from TF in a value set: ``{'head': head_frame, i: <frames[i]>.tf_frame}``
    for those set (empty when ``head_frame`` is '')."""
    if not values.get('head_frame'):
        return {}
    out: dict[Source, str] = {'head': str(values['head_frame']).lstrip('/')}
    for i, f in enumerate(frame_names(values)):
        frame = str(values.get(chain_param_name(f, 'tf_frame')) or '').lstrip('/')
        if frame:
            out[i] = frame
    return out


class TFInput:
    """The TF buffer and a pose source per input taken from TF (module docstring).

    ``values``: the node's parameters (``head_frame``, ``fixed_frame``, ``frames``,
    ``<frame>.tf_frame``; ``stale_timeout`` bounds the wait for a lagging transform and says
    when one is stale).
    """

    def __init__(self, values):
        self.fixed_frame = str(values['fixed_frame']).lstrip('/')
        self.frames = frame_names(values)
        wait_ns = int(round(float(values['stale_timeout']) * 1e9))
        self.buffer = TFBuffer()
        self.sources: dict[Source, TFPoseSource] = {
            source: TFPoseSource(self.buffer, self.fixed_frame, frame, wait_ns=wait_ns,
                                 stale_ns=wait_ns)
            for source, frame in tf_frames(values).items()}
        #: ``/tf`` messages that could not be read or held an invalid transform
        self.bad_messages = 0
        self.last_bad: str | None = None
        #: Child frames starting with these are skipped: the node's own segments, which it
        #: hears back on ``/tf`` (set by the node: ``<tf.prefix><chain>/``).
        self.ignore_prefixes: tuple[str, ...] = ()
        self._said: dict[str, Any] = {}

    def describe(self, source: Source) -> str:
        """``TF <fixed_frame> -> <frame>`` (log messages, the head's 'topic')."""
        return f'TF {self.fixed_frame} -> {self.sources[source].frame}'

    def add(self, transforms: Iterable[tuple[int, int, str, str, Any, Any]],
            static: bool) -> list[tuple[Source, ReceivedPose]]:
        """One ``TFMessage``'s transforms (``wire.tf_message_fields``) into the buffer; the poses
        now due, as ``(source, ReceivedPose)`` in stamp order per source."""
        if self.ignore_prefixes:
            transforms = [t for t in transforms if not t[3].startswith(self.ignore_prefixes)]
        try:
            added = self.buffer.add_transforms(transforms, static)
        except ValueError as err:
            self.bad_messages += 1
            self.last_bad = f'{"/tf_static" if static else "/tf"}: {err}'
            return []
        out = []
        for source, src in self.sources.items():
            src.note(added)
            out += [(source, self.pose(s)) for s in src.poll()]
        return out

    def bad_message(self, text: str) -> None:
        """A ``TFMessage`` that could not be read at all."""
        self.bad_messages += 1
        self.last_bad = text

    def pose(self, sample: TFSample) -> ReceivedPose:
        """A composed pose as the ``PoseStamped`` in ``fixed_frame`` a head topic would carry."""
        sec, nanosec = divmod(sample.stamp_ns, 1_000_000_000)
        cdr = pose_stamped_cdr(sec, nanosec, self.fixed_frame, sample.position,
                               sample.orientation)
        return ReceivedPose(cdr, Stamp(sec, nanosec), self.fixed_frame, sample.position,
                            sample.orientation)

    def name(self, source: Source) -> str:
        return 'head' if source == 'head' else f'frame {self.frames[int(source)]}'

    # -- what is counted and said ---------------------------------------------------------
    def diagnostics(self) -> tuple[list[str], list[tuple[str, str]]]:
        """``(problems, key-values)`` for the node's ``DiagnosticStatus``: per source its TF
        path's state, the poses given, the transforms held past their samples."""
        problems, kv = [], []
        for source, src in self.sources.items():
            name = self.name(source)
            state = 'ok' if src.error is None and src.last_ns is not None else (
                src.error or 'waiting for transforms')
            if src.error is not None:
                problems.append(f'TF {name}: {src.error}')
            kv += [(f'tf {name}', f'{self.fixed_frame} -> {src.frame}: {state}'),
                   (f'tf {name} lookups failed', str(src.missing)),
                   (f'tf {name} late stamps', str(src.late))]
            for edge, n in sorted(src.extrapolated.items()):
                kv.append((f'tf {name} extrapolated: {edge}', str(n)))
            for edge, n in sorted(src.stale.items()):
                kv.append((f'tf {name} stale: {edge}', str(n)))
            if any(ns > src.stale_ns for _, ns in src.last_held):
                problems.append(f'TF {name}: stale transform '
                                f'{", ".join(e for e, _ in src.last_held)}')
        kv += [('tf bad messages', str(self.bad_messages)),
               ('tf old samples dropped', str(self.buffer.old))]
        return problems, kv

    def news(self) -> list[tuple[str, str]]:
        """``(key, text)`` of what went wrong since the last call (a frame missing, a transform
        held past its samples, a bad message), in words naming the frames; the node says
        them on its terminal (throttled by key)."""
        out = []
        for source, src in self.sources.items():
            name = self.name(source)
            # (not while the first messages bring the tree in: a few polls in a row)
            if src.error is not None and src.failing >= FAILING_SAID \
                    and self._changed(f'missing:{source}', src.missing):
                out.append((f'tf:missing:{source}',
                            f'No {name} pose from TF ({self.fixed_frame} -> {src.frame}): '
                            f'{src.error}'))
            if self._changed(f'extrapolated:{source}', sum(src.extrapolated.values())) \
                    and src.last_held:
                held = ', '.join(f'{e} ({ns * 1e-9:.3f} s past its samples)'
                                 for e, ns in src.last_held)
                stale = any(ns > src.stale_ns for _, ns in src.last_held)
                out.append((f'tf:held:{source}',
                            f'The {name} pose from TF ({self.fixed_frame} -> {src.frame}) '
                            f'holds {held}: {"stale, " if stale else ""}no newer sample came '
                            f'within stale_timeout ({src.wait_ns * 1e-9:g} s) of the other '
                            f'transforms'))
        if self._changed('bad', self.bad_messages):
            out.append(('tf:bad', f'Ignored a TF message: {self.last_bad}'))
        return out

    def _changed(self, key: str, value: Any) -> bool:
        changed = self._said.get(key, 0) != value
        self._said[key] = value
        return changed and bool(value)
