"""The viewing and launch assets (``launch/``, ``rviz/``, ``foxglove/``) parse and name only
what the node really publishes.

RViz, Foxglove and ``ros2 launch`` are not on PyPI, so the files are checked as text: the launch
files parse as Python (``ast``) and start only executables this package installs; the RViz
config parses as YAML, the Foxglove layout as JSON. Their topics are checked against the
publishers of a real node started with the launch file's parameters in the launch file's
namespace (asked from the ROS graph), their frames against the TF frames the node names
(``<tf.prefix><chain>/<i>`` under ``fixed_frame``) and their segment indices against the scene.
"""
import ast
import json
import re
from pathlib import Path

import pytest
import yaml

from ponytail_ros.app.param_values import values_from_params_file

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'ponytail.yaml'
NAMESPACE = '/alice'            # launch/ponytail.launch.py's default
FIXED_FRAME = 'world'           # the node's fixed_frame default, the head demo's frame_id
TF_TOPICS = {'/tf', '/tf_static'}


def console_scripts():
    tree = ast.parse((ROOT / 'setup.py').read_text())
    scripts = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found = re.match(r'^(\w+) = ponytail_ros[\w.]*:\w+$', node.value)
            if found:
                scripts.add(found.group(1))
    return scripts


def launch_nodes(path):
    """``(package, executable, keywords)`` of every ``Node(...)`` in a launch file."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, 'id', None) == 'Node':
            kw = {k.arg: k.value for k in call.keywords}
            out.append((ast.literal_eval(kw['package']), ast.literal_eval(kw['executable']), kw))
    return out


def launch_defaults(path):
    """``DeclareLaunchArgument`` names -> default (a string, or None when computed)."""
    tree = ast.parse(path.read_text(), str(path))
    out = {}
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, 'id', None) == \
                'DeclareLaunchArgument':
            kw = {k.arg: k.value for k in call.keywords}
            default = kw.get('default_value')
            out[ast.literal_eval(call.args[0])] = (default.value if isinstance(
                default, ast.Constant) else None)
    return out


@pytest.mark.parametrize('name', ['ponytail.launch.py', 'crowd.launch.py'])
def test_launch_files_parse_and_start_only_installed_executables(name):
    path = ROOT / 'launch' / name
    nodes = launch_nodes(path)
    ours = {exe for pkg, exe, _ in nodes if pkg == 'ponytail_ros'}
    assert ours == {'ponytail_node', 'ponytail_head_demo'}
    assert ours <= console_scripts()
    assert {pkg for pkg, _, _ in nodes} <= {'ponytail_ros', 'rviz2'}
    # every node is namespaced: characters never share topic or frame names
    assert all('namespace' in kw for pkg, _, kw in nodes if pkg == 'ponytail_ros')
    tree = ast.parse(path.read_text())
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description'
               for n in tree.body)


def test_crowd_launch_builds_its_params_with_the_crowd_module():
    import importlib
    source = (ROOT / 'launch' / 'crowd.launch.py').read_text()
    crowd = importlib.import_module('ponytail_ros.app.crowd')
    used = set(re.findall(r'from ponytail_ros\.app\.crowd import ([\w, ]+)', source)[0]
               .replace(' ', '').split(','))
    assert used <= set(dir(crowd))
    defaults = launch_defaults(ROOT / 'launch' / 'crowd.launch.py')
    assert int(defaults['groups']) >= 2 and int(defaults['characters']) >= 1


def test_ponytail_launch_namespace_is_the_one_the_viewers_use():
    assert launch_defaults(ROOT / 'launch' / 'ponytail.launch.py')['namespace'] == \
        NAMESPACE.strip('/')


def rviz_config():
    return yaml.safe_load((ROOT / 'rviz' / 'ponytail.rviz').read_text())


def rviz_topics(cfg):
    return {d['Topic']['Value'] for d in cfg['Visualization Manager']['Displays']
            if 'Topic' in d}


def foxglove_layout():
    return json.loads((ROOT / 'foxglove' / 'ponytail.json').read_text())


def plot_paths(layout):
    return [p['value'] for key, panel in layout['configById'].items()
            if key.startswith('Plot!') for p in panel['paths']]


def test_rviz_config_shows_tf_markers_and_poses_in_world():
    cfg = rviz_config()
    assert cfg['Visualization Manager']['Global Options']['Fixed Frame'] == FIXED_FRAME
    classes = {d['Class'] for d in cfg['Visualization Manager']['Displays']}
    assert {'rviz_default_plugins/TF', 'rviz_default_plugins/MarkerArray',
            'rviz_default_plugins/PoseArray'} <= classes
    assert rviz_topics(cfg) == {f'{NAMESPACE}/segment_markers', f'{NAMESPACE}/segment_poses'}


def test_foxglove_layout_has_3d_with_tf_and_markers_and_a_tip_height_plot():
    layout = foxglove_layout()
    panels = layout['configById']
    (three_d,) = [p for k, p in panels.items() if k.startswith('3D!')]
    assert three_d['followTf'] == FIXED_FRAME
    assert {'/tf', f'{NAMESPACE}/segment_markers'} <= set(three_d['topics'])
    assert set(layout['layout'].values()) >= set(panels)    # every panel is placed
    n = int(values_from_params_file(CONFIG)['ponytail.n_segments'])
    (path,) = plot_paths(layout)
    found = re.fullmatch(r'(/[\w/]+)\.poses\[(\d+)\]\.position\.z', path)
    assert found and found.group(1) == f'{NAMESPACE}/segment_poses'
    assert int(found.group(2)) == n - 1                     # the last segment: the tip's


@pytest.mark.ros
def test_every_topic_the_viewers_name_is_published_by_the_node(ros_context):
    """The node started as the launch file starts it (config/ponytail.yaml, namespace alice):
    its publishers, read back from the ROS graph, include every topic the viewers subscribe."""
    import importlib.util

    from ponytail_ros.node import PonytailNode
    node = PonytailNode(context=ros_context, namespace=NAMESPACE,
                        cli_args=['--ros-args', '--params-file', str(CONFIG)])
    try:
        published = {name for name, _ in node.get_publisher_names_and_types_by_node(
            node.get_name(), node.get_namespace())}
    finally:
        node.destroy_node()
    layout = foxglove_layout()
    three_d = [p for k, p in layout['configById'].items() if k.startswith('3D!')][0]
    named = (rviz_topics(rviz_config()) | set(three_d['topics'])
             | {p.split('.')[0] for p in plot_paths(layout)})
    assert named - TF_TOPICS <= published, (named, published)
    if importlib.util.find_spec('tf2_msgs') is not None:      # live TF on
        assert '/tf' in published


def test_the_viewers_frames_are_frames_the_node_names():
    """RViz and Foxglove are fixed to ``world``, the parent of every segment frame (the node's
    ``fixed_frame`` default), and name no other frame; the segment frames of the launch file's
    character are ``alice/ponytail/<i>``."""
    from ponytail_ros.app.messages import segment_frame
    from ponytail_ros.ros.head_demo import namespace_prefix
    text = (ROOT / 'rviz' / 'ponytail.rviz').read_text() + \
        (ROOT / 'foxglove' / 'ponytail.json').read_text()
    frames = set(re.findall(r'(?:Fixed Frame|Reference Frame|Target Frame|"followTf"|'
                            r'"frameId")["]?:\s*"?([<>\w/ ]+?)"?\s*[,\n]', text))
    assert frames <= {FIXED_FRAME, '<Fixed Frame>'} and FIXED_FRAME in frames
    n = int(values_from_params_file(CONFIG)['ponytail.n_segments'])
    prefix = namespace_prefix(NAMESPACE)
    assert [segment_frame(prefix, 'ponytail', i) for i in (0, n - 1)] == \
        ['alice/ponytail/0', f'alice/ponytail/{n - 1}']
