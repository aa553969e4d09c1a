"""``bag/mcap_out.py``'s ``McapOut`` writes the bytes of ``mcap``'s own ``Writer`` (as
``BagWriter`` configures it) for the same calls: chunks cut by ``flush``, schemas and channels
added between chunks, metadata before and after, channels without messages, times out of
order, a run with no message at all."""
import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from ponytail_ros.recording.bag.mcap_out import McapOut


def _calls(seed):
    rng = random.Random(seed)
    calls = [('start', 'ros2', 'lib x'), ('add_metadata', 'rosbag2', {'a': 'b', 'é': 'ü'}),
             ('add_metadata', 'other', {})]
    schemas = channels = 0
    for _ in range(rng.randrange(1, 6)):
        schemas += 1
        calls.append(('register_schema', f'pkg/msg/T{schemas}', 'ros2msg',
                      b'int32 x\n' * schemas))
        for _ in range(rng.randrange(1, 4)):
            channels += 1
            calls.append(('register_channel', f'/t{channels}', 'cdr', schemas,
                          {'offered_qos_profiles': 'q', 'n': str(channels)}))
    t = 1_000
    for i in range(rng.randrange(0, 400)):
        r = rng.random()
        if r < 0.03:
            calls.append(('flush',))
        elif r < 0.04:
            channels += 1
            calls.append(('register_channel', f'/late{channels}', 'cdr', 1, {}))
        else:
            t += rng.randrange(-50, 1000)
            calls.append(('add_message', rng.randrange(1, channels + 1), max(t, 0),
                          bytes(rng.randrange(256) for _ in range(rng.randrange(0, 90))),
                          rng.randrange(0, 2**40), i % 7))
    calls.append(('add_metadata', 'rosbag2', {'a': 'c'}))
    calls.append(('finish',))
    return calls


def _run(writer, calls):
    for name, *args in calls:
        if name == 'add_message':
            channel_id, log_time, data, publish_time, sequence = args
            writer.add_message(channel_id, log_time, data, publish_time, sequence=sequence)
        elif name == 'register_channel':
            writer.register_channel(*args[:3], metadata=args[3])
        else:
            getattr(writer, name)(*args)


@pytest.mark.parametrize('seed', range(12))
def test_same_bytes_as_mcap_writer(seed):
    calls = _calls(seed)
    ours, theirs = io.BytesIO(), io.BytesIO()
    _run(McapOut(ours), calls)
    _run(Writer(theirs, chunk_size=2**62, compression=CompressionType.NONE), calls)
    assert ours.getvalue() == theirs.getvalue()
    n = sum(1 for c in calls if c[0] == 'add_message')
    ours.seek(0)
    assert sum(1 for _ in make_reader(ours).iter_messages(log_time_order=False)) == n
