"""``python benchmarks/bag_read.py``: how fast a 300 s head bag is read, by this
package's ``BagReader`` (every MCAP record framed and CRC-checked, ``mcap_scan.py``) and by
``rosbags``' ``Reader``, each on the same messages written two ways: by this package's
``BagWriter`` (64 kB chunks) and by the ``rosbags`` writer (a bag folder). Prints the wall
time of one read (best of ``--repeat``) and messages per second; ``replay_cost`` gives the
replay of the same bag, for the reader's share of it.
"""
import argparse
import tempfile
import time
from pathlib import Path

from ponytail_ros.bench.head_bag import make_head_recording


def _best(fn, repeat):
    best, n = float('inf'), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        n = fn()
        best = min(best, time.perf_counter() - t0)
    return n, best


def _rosbags_copy(src: Path, folder: Path) -> Path:
    """The messages of ``src`` in a bag folder written by rosbags."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from ponytail_ros.recording.bag import BagReader
    store = get_typestore(Stores.ROS2_KILTED)
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/head_pose', 'geometry_msgs/msg/PoseStamped',
                                     typestore=store)
        for _, _, data, log_ns in BagReader(src).messages(raw=True):
            writer.write(conn, log_ns, data)
    return folder


def main(argv=None):
    p = argparse.ArgumentParser(prog="benchmarks/bag_read.py",
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--seconds', type=float, default=300.0, help='s of 100 Hz head poses')
    p.add_argument('--repeat', type=int, default=5)
    args = p.parse_args(argv)
    from rosbags.rosbag2 import Reader

    from ponytail_ros.recording.bag import BagReader
    with tempfile.TemporaryDirectory() as tmp:
        ours = make_head_recording(Path(tmp) / 'head.mcap', args.seconds)
        theirs = _rosbags_copy(ours, Path(tmp) / 'rosbags_bag')
        for label, path in (('BagWriter file', ours), ('rosbags bag folder', theirs)):
            readers = {
                'BagReader (raw CDR, checked)':
                    lambda path=path: sum(1 for _ in BagReader(path).messages(raw=True)),
                'BagReader (deserialised)':
                    lambda path=path: sum(1 for _ in BagReader(path).messages()),
                'rosbags Reader (raw CDR)':
                    lambda path=path: _rosbags_count(Reader, path),
            }
            for name, fn in readers.items():
                n, wall = _best(fn, args.repeat)
                print(f'{label:20s} {name:30s} {n} messages in {wall * 1e3:7.1f} ms '
                      f'({n / wall / 1e3:7.0f} k messages/s)', flush=True)


def _rosbags_count(reader_cls, path) -> int:
    with reader_cls(path) as reader:
        return sum(1 for _ in reader.messages())


if __name__ == '__main__':
    main()
