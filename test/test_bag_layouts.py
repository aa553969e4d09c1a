"""The bags ROS users have: what rosbag2 (here: the ``rosbags`` writer) writes -- a bag folder,
its ``metadata.yaml``, split files, sqlite3 storage, zstd compression of files, messages and
chunks -- replay to the same chain as a single ``.mcap`` file; several bags at once; and every
bad layout ends in a clear message, never in silence.
"""
import shutil

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')
pytest.importorskip('rosbags.rosbag2')

from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from ponytail_ros.recording.bag import BagError, BagReader  # noqa: E402

from ros_helpers import HEAD, N_POSES, head_samples, run  # noqa: E402

STORE = get_typestore(Stores.ROS2_KILTED)


def rosbags_folder(folder, samples, storage=StoragePlugin.MCAP, compression=None):
    """A rosbag2 bag folder written by rosbags; its folder."""
    writer = Writer(folder, version=9, storage_plugin=storage)
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection(HEAD, 'geometry_msgs/msg/PoseStamped', typestore=STORE)
        for log_ns, data in samples:
            writer.write(conn, log_ns, data)
    return folder


def split_folder(tmp_path, name, samples, storage=StoragePlugin.MCAP):
    """A bag split over two files as rosbag2 lays it out (``<name>_0``, ``<name>_1``, one
    ``metadata.yaml`` listing both), each file written by rosbags."""
    half = len(samples) // 2
    parts = [rosbags_folder(tmp_path / f'{name}_part{i}', chunk, storage)
             for i, chunk in enumerate((samples[:half], samples[half:]))]
    folder = tmp_path / name
    folder.mkdir()
    infos, names = [], []
    for i, part in enumerate(parts):
        info = yaml.safe_load((part / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        (data,) = [p for p in part.iterdir() if p.name != 'metadata.yaml']
        names.append(f'{name}_{i}{data.suffix}')
        shutil.move(data, folder / names[-1])
        infos.append(info)
    info = infos[0]
    start = info['starting_time']['nanoseconds_since_epoch']
    end = infos[1]['starting_time']['nanoseconds_since_epoch'] + infos[1]['duration'][
        'nanoseconds']
    info['relative_file_paths'] = names
    info['files'] = [dict(f['files'][0], path=n) for f, n in zip(infos, names, strict=True)]
    info['message_count'] = len(samples)
    info['duration'] = {'nanoseconds': end - start}
    info['topics_with_message_count'][0]['message_count'] = len(samples)
    (folder / 'metadata.yaml').write_text(yaml.safe_dump(
        {'rosbag2_bagfile_information': info}, sort_keys=False))
    return folder


def segment_poses(path):
    """[(stamp ns, (n, 3) positions)] of a replay output's segment_poses."""
    out = []
    for _, _, msg, _ in BagReader(path).messages('/segment_poses', order='file'):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        out.append((stamp, np.array([[p.position.x, p.position.y, p.position.z]
                                     for p in msg.poses])))
    return out


@pytest.fixture(scope='module')
def layouts(tmp_path_factory):
    """The same head motion in every layout; name -> the path a user gives."""
    root = tmp_path_factory.mktemp('layouts')
    samples = head_samples()
    single = rosbags_folder(root / 'single', samples)
    out = {
        'mcap file': next(single.glob('*.mcap')),
        'bag folder': single,
        'metadata.yaml': single / 'metadata.yaml',
        'split folder': split_folder(root, 'split', samples),
        'db3 folder': rosbags_folder(root / 'db3', samples, StoragePlugin.SQLITE3),
        'db3 file': next(rosbags_folder(root / 'db3b', samples,
                                        StoragePlugin.SQLITE3).glob('*.db3')),
        'split db3': split_folder(root, 'splitdb', samples, StoragePlugin.SQLITE3),
        'zstd files': rosbags_folder(root / 'zfile', samples, compression=CompressionMode.FILE),
        'zstd messages': rosbags_folder(root / 'zmsg', samples,
                                        compression=CompressionMode.MESSAGE),
        'zstd chunks': rosbags_folder(root / 'zchunk', samples,
                                      compression=CompressionMode.STORAGE),
    }
    return out


def test_every_layout_reads_the_same_messages_at_the_same_times(layouts):
    reference = [(t, bytes(d)) for _, _, d, t in BagReader(layouts['mcap file']).messages(
        raw=True)]
    assert len(reference) == N_POSES
    for name, path in layouts.items():
        reader = BagReader(path)
        got = [(t, bytes(d)) for _, _, d, t in reader.messages(raw=True)]
        assert got == reference, name
        assert reader.topics() == {HEAD: 'geometry_msgs/msg/PoseStamped'}, name
        assert reader.finished and reader.truncation is None, name
    assert len(BagReader(layouts['split folder']).files) == 2


def test_every_layout_replays_to_the_same_segment_poses(layouts, tmp_path, params, capsys):
    outputs = {}
    for i, (name, path) in enumerate(layouts.items()):
        out = tmp_path / f'{i}.mcap'
        code, _, err = run([path, '-o', out, '--params', params], capsys)
        assert code == 0 and err == [], (name, err)
        outputs[name] = segment_poses(out)
    reference = outputs['mcap file']
    assert len(reference) >= N_POSES - 5
    for name, poses in outputs.items():
        assert [t for t, _ in poses] == [t for t, _ in reference], name
        worst = max(np.abs(a - b).max() for (_, a), (_, b) in zip(poses, reference, strict=True))
        assert worst <= 1e-6, (name, worst)


def test_one_file_of_a_split_bag_replays_its_part_and_says_where_the_rest_is(
        layouts, tmp_path, params, capsys):
    folder = layouts['split folder']
    first = folder / 'split_0.mcap'
    code, _, err = run([first, '-o', tmp_path / 'half.mcap', '--params', params], capsys)
    assert code == 0
    assert len(err) == 1 and 'file 1 of the 2 files of bag' in err[0] and str(folder) in err[0]
    code, _, err = run([folder, '-o', tmp_path / 'whole.mcap', '--params', params], capsys)
    assert code == 0 and err == []
    half, whole = segment_poses(tmp_path / 'half.mcap'), segment_poses(tmp_path / 'whole.mcap')
    assert len(half) < 0.6 * len(whole)
    assert [t for t, _ in half] == [t for t, _ in whole[:len(half)]]


def test_a_metadata_yaml_listing_a_missing_file_is_refused_naming_it(layouts, tmp_path,
                                                                    params, capsys):
    folder = tmp_path / 'broken'
    shutil.copytree(layouts['split folder'], folder)
    (folder / 'split_1.mcap').unlink()
    code, _, err = run([folder, '-o', tmp_path / 'o.mcap', '--params', params], capsys)
    assert code == 2 and len(err) == 1
    assert str(folder) in err[0] and 'split_1.mcap' in err[0] and 'missing' in err[0]
    assert not (tmp_path / 'o.mcap').exists()


def test_a_folder_without_metadata_reads_its_numbered_files_in_order_with_a_note(
        layouts, tmp_path):
    folder = tmp_path / 'split'
    shutil.copytree(layouts['split folder'], folder)
    (folder / 'metadata.yaml').unlink()
    reader = BagReader(folder)
    assert [f.label.name for f in reader.files] == ['split_0.mcap', 'split_1.mcap']
    assert len(reader.notes) == 1 and 'no metadata.yaml' in reader.notes[0]
    assert sum(1 for _ in reader.messages()) == N_POSES


def test_what_is_not_a_bag_is_said(tmp_path, params, capsys):
    empty = tmp_path / 'empty'
    empty.mkdir()
    code, _, err = run([empty, '-o', tmp_path / 'o.mcap', '--params', params], capsys)
    assert code == 2 and len(err) == 1 and 'not a rosbag2 bag' in err[0] and str(empty) in err[0]
    odd = tmp_path / 'odd'
    odd.mkdir()
    (odd / 'metadata.yaml').write_text('something: else\n')
    with pytest.raises(BagError, match='no rosbag2_bagfile_information'):
        BagReader(odd)
    text = tmp_path / 'notes.txt'
    text.write_text('hello')
    code, _, err = run([text, '-o', tmp_path / 'o.mcap', '--params', params], capsys)
    assert code == 2 and len(err) == 1 and 'not an MCAP file' in err[0]


# -- many bags ------------------------------------------------------------------------------------


def test_a_folder_of_bags_replays_one_output_per_bag_in_parallel(layouts, tmp_path, params,
                                                                capsys):
    bags = tmp_path / 'bags'
    bags.mkdir()
    for name in ('single', 'split', 'db3'):
        shutil.copytree(layouts['split folder'].parent / name, bags / name)
    out = tmp_path / 'out'
    code, stdout, err = run([bags, '-o', out, '--params', params, '-j', '2'], capsys)
    assert code == 0 and err == []
    lines = stdout.splitlines()
    assert sum(' -> ' in line for line in lines) == 3
    assert sorted(p.name for p in out.iterdir()) == ['db3.mcap', 'single.mcap', 'split.mcap']
    reference = segment_poses(out / 'single.mcap')
    for name in ('db3', 'split'):
        poses = segment_poses(out / f'{name}.mcap')
        assert [t for t, _ in poses] == [t for t, _ in reference]
        assert max(np.abs(a - b).max()
                   for (_, a), (_, b) in zip(poses, reference, strict=True)) <= 1e-6


def test_one_bad_bag_among_many_fails_the_run_and_the_others_are_written(layouts, tmp_path,
                                                                        params, capsys):
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(b'not a bag at all')
    out = tmp_path / 'out'
    code, stdout, err = run([layouts['bag folder'], bad, layouts['db3 folder'], '-o', out,
                             '--params', params, '-j', '2'], capsys)
    assert code == 2
    assert any(str(bad) in e and 'not an MCAP file' in e for e in err), err
    assert any('3 bags, 2 replayed' in e and '1 failed' in e for e in err), err
    assert sorted(p.name for p in out.iterdir()) == ['db3.mcap', 'single.mcap']


def test_two_bags_of_one_name_are_refused_before_anything_runs(layouts, tmp_path, params,
                                                              capsys):
    other = tmp_path / 'x' / 'single'
    shutil.copytree(layouts['bag folder'], other)
    code, _, err = run([layouts['bag folder'], other, '-o', tmp_path / 'out', '--params',
                        params], capsys)
    assert code == 2 and len(err) == 1 and 'single.mcap' in err[0]
    assert not (tmp_path / 'out').exists()


def test_a_killed_recorders_folder_replays_what_was_written_and_says_so(tmp_path, params,
                                                                        capsys):
    """What a SIGKILLed ``ros2 bag record`` leaves: ``<bag>/<bag>_0.mcap`` cut short, no
    ``metadata.yaml``. Replayed up to the cut, with the missing metadata and the cut said."""
    from ponytail_ros.bench.head_bag import make_head_recording
    whole = make_head_recording(tmp_path / 'whole.mcap', 10.0)   # 100 Hz, many chunks
    folder = tmp_path / 'killed'
    folder.mkdir()
    raw = whole.read_bytes()
    (folder / 'killed_0.mcap').write_bytes(raw[:int(len(raw) * 0.6)])
    code, _, err = run([folder, '-o', tmp_path / 'o.mcap', '--params', params], capsys)
    assert code == 0
    assert any('no metadata.yaml' in e and 'ros2 bag reindex' in e for e in err), err
    assert any('cut short in killed_0.mcap' in e and 'truncated at byte' in e for e in err), err
    assert any('all that could be read' in e for e in err), err
    poses = segment_poses(tmp_path / 'o.mcap')
    assert 300 < len(poses) < 700
    code, _, err = run(['repair', folder, tmp_path / 'fixed.mcap'], capsys)
    assert code == 2 and len(err) == 1 and 'killed_0.mcap' in err[0]


def test_an_mcap_file_of_another_profile_is_read_as_rosbags_would_refuse_it(tmp_path):
    """rosbags refuses an MCAP file whose profile is not ``ros2``; the same messages with
    another profile read here as with it."""
    from mcap.writer import Writer as McapWriter

    from ponytail_ros.recording.bag import message_definition
    samples = head_samples(50)
    paths = {}
    for profile in ('ros2', ''):
        paths[profile] = tmp_path / f'profile_{profile or "none"}.mcap'
        with open(paths[profile], 'wb') as f:
            w = McapWriter(f)
            w.start(profile=profile, library='test')
            sid = w.register_schema('geometry_msgs/msg/PoseStamped', 'ros2msg',
                                    message_definition('geometry_msgs/msg/PoseStamped').encode())
            cid = w.register_channel(HEAD, 'cdr', sid)
            for k, (log_ns, data) in enumerate(samples):
                w.add_message(cid, log_ns, data, log_ns, k)
            w.finish()
    with pytest.raises(Exception, match='Profile is not ros2'):
        with rosbag2_reader(paths['']):
            pass
    read = {p: [(t, bytes(d)) for _, _, d, t in BagReader(path).messages(raw=True)]
            for p, path in paths.items()}
    assert read[''] == read['ros2'] == [(t, bytes(d)) for t, d in samples]


def rosbag2_reader(path):
    from rosbags.rosbag2 import Reader
    return Reader(path)
