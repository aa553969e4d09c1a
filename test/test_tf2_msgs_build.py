"""tf2_msgs for the PyPI install (``interfaces/tf2_msgs``, built by the ``pypi`` extra).

When it is built: ``TFMessage`` and ``TF2Error`` import, carry ros2/geometry2's type hashes (read
back from the graph, as a subscriber on another ROS 2 install sees them) and travel between
processes. When it is not (no compiler, or another ROS 2 installation provides tf2_msgs), these
tests skip saying why. The backend's no-build path is tested on its own: the set-up never fails
for want of a compiler.
"""
import importlib.util
import os
import subprocess
import sys
import time
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INTERFACE = ROOT / 'interfaces' / 'tf2_msgs'
#: The RIHS01 hashes of ros2/geometry2's tf2_msgs (Kilted), as its rosidl build prints them.
TFMESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'
TF2ERROR_HASH = 'RIHS01_db2485e7d6a0ec75bf087e058ee45df682acc3a621ca7780503d10aac141809a'


def _not_built_reason():
    if importlib.util.find_spec('tf2_msgs') is not None:
        return None
    try:
        why = metadata.distribution('ros-tf2-msgs').read_text('BUILD_SKIPPED')
    except metadata.PackageNotFoundError:
        why = 'ros-tf2-msgs is not installed (the `pypi` extra installs it)'
    return f'tf2_msgs is not importable: {why}'


needs_tf2_msgs = pytest.mark.skipif(_not_built_reason() is not None,
                                    reason=str(_not_built_reason()))


def _backend():
    spec = importlib.util.spec_from_file_location('tf2_msgs_build_backend',
                                                  INTERFACE / 'build_backend.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_interface_sources_are_colcon_ignored_and_declare_the_dependency():
    # A colcon workspace keeps its own tf2_msgs: this copy must never be picked up there.
    assert (INTERFACE / 'COLCON_IGNORE').exists()
    assert '<exec_depend>tf2_msgs</exec_depend>' in (ROOT / 'package.xml').read_text()
    assert (INTERFACE / 'msg' / 'TFMessage.msg').read_text() == \
        'geometry_msgs/TransformStamped[] transforms\n'


def test_no_compiler_gives_an_installable_wheel_without_tf2_msgs_and_the_reason(
        tmp_path, monkeypatch):
    backend = _backend()
    monkeypatch.setenv('PATH', str(tmp_path))         # no cc, no c++, no cmake
    monkeypatch.delenv('CC', raising=False)
    monkeypatch.delenv('CXX', raising=False)
    monkeypatch.delenv('PONYTAIL_TF2_MSGS_BUILD', raising=False)
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    assert backend.get_requires_for_build_wheel() == []     # nothing downloaded for nothing
    name = backend.build_wheel(str(tmp_path))
    with zipfile.ZipFile(tmp_path / name) as whl:
        names = whl.namelist()
        info = name.split('-')[0] + '-' + name.split('-')[1] + '.dist-info'
        assert not [n for n in names if not n.startswith(info)]
        assert 'compiler' in whl.read(f'{info}/BUILD_SKIPPED').decode()
        assert 'Requires-Dist' not in whl.read(f'{info}/METADATA').decode()
        # RECORD lists every other file with its hash
        record = whl.read(f'{info}/RECORD').decode().splitlines()
        assert sorted(line.split(',')[0] for line in record) == sorted(names)


def test_a_sourced_ros_with_tf2_msgs_is_not_built_over(tmp_path, monkeypatch):
    backend = _backend()
    index = tmp_path / 'opt' / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'tf2_msgs').write_text('')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'opt'))
    monkeypatch.delenv('PONYTAIL_TF2_MSGS_BUILD', raising=False)
    reason = backend._skip_reason()
    assert reason is not None and str(tmp_path / 'opt') in reason


@needs_tf2_msgs
def test_built_messages_have_geometry2s_type_hashes(ros_context):
    import rclpy
    from tf2_msgs.msg import TF2Error, TFMessage
    assert TF2Error.NO_ERROR == 0 and TF2Error.TRANSFORM_ERROR == 6
    node = rclpy.create_node('tf2_msgs_hash', context=ros_context)
    try:
        node.create_publisher(TFMessage, 'tf_hash_check', 1)
        node.create_publisher(TF2Error, 'tf2_error_hash_check', 1)
        hashes = {topic: str(node.get_publishers_info_by_topic(topic)[0].topic_type_hash)
                  for topic in ('tf_hash_check', 'tf2_error_hash_check')}
    finally:
        node.destroy_node()
    assert hashes == {'tf_hash_check': TFMESSAGE_HASH, 'tf2_error_hash_check': TF2ERROR_HASH}


PUBLISHER = '''
import sys, time, rclpy
from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage
rclpy.init()
node = rclpy.create_node('tf_publisher')
pub = node.create_publisher(TFMessage, 'tf_cross_process', 10)
for i in range(200):
    t = TransformStamped()
    t.header.frame_id = 'world'
    t.child_frame_id = f'frame/{i}'
    t.transform.translation.z = 0.25 * i
    t.transform.rotation.w = 1.0
    pub.publish(TFMessage(transforms=[t]))
    time.sleep(0.05)
'''


@needs_tf2_msgs
@pytest.mark.ros
def test_tfmessage_travels_between_processes(ros_context):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from tf2_msgs.msg import TFMessage
    node = rclpy.create_node('tf_subscriber', context=ros_context)
    got = []
    node.create_subscription(TFMessage, 'tf_cross_process', got.append, 10)
    proc = subprocess.Popen([sys.executable, '-c', PUBLISHER], env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 30
        while len(got) < 3 and time.monotonic() < deadline and proc.poll() is None:
            executor.spin_once(timeout_sec=0.1)
    finally:
        proc.kill()
        _, err = proc.communicate()
        node.destroy_node()
    assert len(got) >= 3, err
    for msg in got:
        (t,) = msg.transforms
        i = int(t.child_frame_id.split('/')[1])
        assert t.header.frame_id == 'world'
        assert t.transform.translation.z == 0.25 * i and t.transform.rotation.w == 1.0
