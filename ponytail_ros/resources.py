"""Where the package's installed files are: ``share/ponytail_ros/`` or, in a checkout, the tree.

Under colcon the share folder is found through the ament index. The PyPI wheels do not set
``AMENT_PREFIX_PATH``, and an editable pip install does not copy ``data_files``, so the
environment prefix and the source checkout are searched too.
"""
import os
import sys
from pathlib import Path

__all__ = ['config_path']

PACKAGE = 'ponytail_ros'


def _candidates():
    if os.environ.get('AMENT_PREFIX_PATH'):
        try:
            from ament_index_python.packages import get_package_share_directory
            yield Path(get_package_share_directory(PACKAGE))
        except Exception:  # not in the index: fall through to the other places
            pass
    yield Path(sys.prefix) / 'share' / PACKAGE
    yield Path(__file__).resolve().parents[1]          # a source checkout


def config_path(name='ponytail.yaml'):
    """Path of a parameters file shipped in ``config/`` (``FileNotFoundError`` if none)."""
    tried = []
    for base in _candidates():
        path = base / 'config' / name
        if path.is_file():
            return path
        tried.append(str(path))
    raise FileNotFoundError(f'config file {name!r} not found; looked in: {", ".join(tried)}')
