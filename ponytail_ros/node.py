"""``ponytail_node``: the ROS node (``ros/node.py``) with the run recorder
(``recording/recorder.py``) wired in as its recording ``TickSink``.

The node and the recorder sit side by side on the application layer (``app/``) and import
neither each other: this module, above both, is where they meet. Use ``PonytailNode`` from
here wherever ``record_path`` should record (the harness, the demo, the benchmarks).

Run: ``ponytail_node --ros-args --params-file config/ponytail.yaml`` or
``python -m ponytail_ros.node --ros-args ...``.
"""
import sys

from ponytail_ros.recording.recorder import RunRecorder
from ponytail_ros.ros import node as _ros_node

__all__ = ['PonytailNode', 'main']


class PonytailNode(_ros_node.PonytailNode):
    """``ros.node.PonytailNode`` recording to ``record_path`` (``RunRecorder.for_node``)."""

    def __init__(self, node_name='ponytail', *, context=None, **kwargs):
        kwargs.setdefault('recording_sink', RunRecorder.for_node)
        super().__init__(node_name, context=context, **kwargs)


def main(args=None):
    """Entry point of ``ponytail_node``; returns the exit code."""
    return _ros_node.main(args, node_class=PonytailNode)


if __name__ == '__main__':
    sys.exit(main())
