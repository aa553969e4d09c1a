"""``python benchmarks/first_start.py``: a user's first start and second start of the node.

The package is built as a wheel and installed with ``pip --target`` into a read-only
directory (no editable install, no cache beside the sources), then ``ponytail_node`` with
``config/ponytail.yaml`` is started beside ``ponytail_head_demo`` as an ordinary user would run
it: unable to write the install (as root, ``setpriv`` drops the file-mode override), with a
``HOME`` where nothing can be made and a fresh temporary directory (``TMPDIR``), so the kernel
cache falls back to ``<tmp>/ponytail_ros-<uid>/numba`` (``core/kernel_cache.py``).

Prints, per start: seconds from the node's start to its first line on stdout or stderr, and to
the first ``PoseArray`` a listener receives; whether the node printed a traceback. Then the
same again (the second start loads the cache the first one wrote). The dependencies (numpy,
numba, rclpy, …) come from this Python's environment.
"""
import argparse
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_DROP_DAC = ['--bounding-set=-dac_override,-dac_read_search',
             '--inh-caps=-dac_override,-dac_read_search']

_LISTENER = """
import sys, time, rclpy
from geometry_msgs.msg import PoseArray
from rclpy.qos import QoSProfile
rclpy.init()
node = rclpy.create_node('first_start_listener')
def got(msg):
    print('POSE', flush=True)
    raise SystemExit
node.create_subscription(PoseArray, sys.argv[1], got, QoSProfile(depth=10))
print('READY', flush=True)
try:
    rclpy.spin(node)
except SystemExit:
    pass
"""


def _install(dest):
    """A non-editable install of the package (no dependencies) into ``dest``, read-only."""
    wheels = dest / 'wheels'
    subprocess.run([sys.executable, '-m', 'pip', 'wheel', '-q', '--no-deps', '-w', str(wheels),
                    str(ROOT)], check=True)
    site = dest / 'site'
    wheel = next(wheels.glob('ponytail_ros-*.whl'))
    subprocess.run([sys.executable, '-m', 'pip', 'install', '-q', '--no-deps', '--target',
                    str(site), str(wheel)], check=True)
    for d, _, files in os.walk(site):
        for f in files:
            os.chmod(os.path.join(d, f), 0o444)
        os.chmod(d, 0o555)
    return site


def _prefix():
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which('setpriv')
    if setpriv is None:
        sys.exit('running as root needs setpriv (util-linux) to drop the file-mode override')
    return [setpriv, *_DROP_DAC]


def _start(site, tmp, home, params, timeout):
    env = {k: v for k, v in os.environ.items()
           if k not in ('NUMBA_CACHE_DIR', 'XDG_CACHE_HOME', 'PYTHONPATH')}
    env.update(ROS_DOMAIN_ID=str(random.randint(120, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', TMPDIR=str(tmp), HOME=str(home),
               ROS_LOG_DIR=str(tmp / 'ros_log'))
    run_env = dict(env, PYTHONPATH=str(site))
    head = subprocess.Popen([sys.executable, '-c', 'from ponytail_ros.ros.head_demo import main; '
                             'main()', '--ros-args', '-r', '__ns:=/alice'],
                            env=run_env, cwd=tmp, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    listener = subprocess.Popen([sys.executable, '-c', _LISTENER, '/alice/segment_poses'],
                                env=env, cwd=tmp, text=True, stdout=subprocess.PIPE)
    assert listener.stdout.readline().strip() == 'READY'
    t0 = time.monotonic()
    node = subprocess.Popen([*_prefix(), sys.executable, '-c',
                             'from ponytail_ros.entry_points import node; node()', '--ros-args',
                             '-r', '__ns:=/alice', '--params-file', str(params)],
                            env=run_env, cwd=tmp, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    lines, first = [], []

    def read():
        for line in node.stdout:
            if not first:
                first.append(time.monotonic() - t0)
            lines.append(line.rstrip())
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    pose = None
    try:
        listener.stdout.readline()          # 'POSE', or '' when it dies
        if listener.poll() is None or listener.returncode == 0:
            pose = time.monotonic() - t0
    finally:
        for p in (node, head, listener):
            if p.poll() is None:
                p.terminate()
        for p in (node, head, listener):
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                p.kill()
        reader.join(timeout=5)
    return first[0] if first else None, pose, lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default=str(ROOT / 'config' / 'ponytail.yaml'))
    p.add_argument('--starts', type=int, default=2)
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix='ponytail_first_start_'))
    try:
        site = _install(work)
        tmp = work / 'tmp'
        tmp.mkdir(mode=0o777)
        tmp.chmod(0o1777)
        home = work / 'ro'
        home.mkdir()
        home.chmod(0o555)
        for k in range(args.starts):
            first, pose, lines = _start(site, tmp, home / 'home', args.params, 10)
            tb = any('Traceback' in line for line in lines)
            print(f'start {k + 1}: first line after {first:.2f} s, first PoseArray after '
                  f'{pose:.1f} s, traceback: {"yes" if tb else "no"}' if pose is not None else
                  f'start {k + 1}: no PoseArray; output:\n' + '\n'.join(lines[-30:]))
            for line in lines[:6]:
                print(f'    | {line}')
            sys.stdout.flush()
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == '__main__':
    main()
