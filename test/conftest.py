"""Shared pytest set-up.

ROS isolation: tests that talk over DDS use a ROS domain of their own per test run, so parallel
runs on one machine (two checkouts, CI jobs, pytest-xdist workers) never hear each other.
``ROS_DOMAIN_ID`` is set here, before any ``rclpy.init``, from ``PONYTAIL_TEST_DOMAIN_ID`` if
given, else from the process id (1..101); child processes inherit it. Discovery is kept on this
host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``). (``ponytail_ros.testing.Harness``, which
most in-process tests use, goes further: discovery off for its own context.)

The public pytest plugin (``ponytail_ros.testing.plugin``: fixtures ``ponytail``,
``ponytail_params``, ``ponytail_offline``) is loaded here too, so the project's tests use the
same fixtures a user gets from the installed entry point (registered under the same name, it is
not loaded twice).
"""
import os

import pytest

pytest_plugins = ['ponytail_ros.testing.plugin']

TEST_DOMAIN_ID = int(os.environ.get('PONYTAIL_TEST_DOMAIN_ID', 1 + os.getpid() % 101))
os.environ['ROS_DOMAIN_ID'] = str(TEST_DOMAIN_ID)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def pytest_configure(config):
    """Compile the simulation step once, in the main process, before any xdist worker starts:
    the workers then load it from numba's cache instead of each paying the cold compile."""
    if not hasattr(config, 'workerinput'):
        from ponytail_ros.core.compile import report_compile
        report_compile()


@pytest.fixture
def params(tmp_path):
    """A node params file for the bag tests (``ros_helpers.PARAMS``: 100 Hz, 4 segments)."""
    from ros_helpers import PARAMS
    path = tmp_path / 'params.yaml'
    path.write_text(PARAMS)
    return path


@pytest.fixture(scope='session')
def live_run(tmp_path_factory):
    """The node's recorded live run (``ros_helpers.live_recording``), made once per session
    and read by ``test_recording.py`` and ``test_replay.py``."""
    from ros_helpers import live_recording
    return live_recording(tmp_path_factory.getbasetemp())


@pytest.fixture
def ros_context():
    """A fresh, initialised ``rclpy`` context on the test domain; shut down afterwards."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    context = Context()
    rclpy.init(context=context, domain_id=TEST_DOMAIN_ID)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
