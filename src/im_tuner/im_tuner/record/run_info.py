"""What a bag says of the run that recorded it, pure (no rclpy): the command, host, ROS
environment and package versions (the ``im_tuner.run`` metadata record), the recorder's
version, and the default bag directory name."""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import os
import platform
import shlex
import socket
import sys
from pathlib import Path

#: Packages whose versions go into the run metadata.
VERSIONED = (
    'im_drive_sim',
    'im_controller',
    'im_tuner',
    'ros-jazzy-rclpy',
    'ros-jazzy-rmw-fastrtps-cpp',
    'numpy',
    'numba',
    'mcap',
)


def default_out_dir(base: Path | str = 'bags', prefix: str = 'recording') -> Path:
    """``<base>/<prefix>_<UTC time>``: a new bag directory's default name."""
    stamp = _dt.datetime.now(_dt.UTC).strftime('%Y_%m_%d-%H_%M_%S')
    return Path(base) / f'{prefix}_{stamp}'


def run_metadata(command: list[str] | None = None) -> dict[str, str]:
    """What ran, where and with which versions: the bag's ``im_tuner.run`` record."""
    versions = {pkg: version(pkg, 'not installed') for pkg in VERSIONED}
    return {
        'command': shlex.join(command if command is not None else sys.argv),
        'started_utc': _dt.datetime.now(_dt.UTC).isoformat(timespec='seconds'),
        'host': socket.gethostname(),
        'python': platform.python_version(),
        'ros_distro': os.environ.get('ROS_DISTRO', 'jazzy'),
        'rmw_implementation': os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp'),
        'ros_domain_id': os.environ.get('ROS_DOMAIN_ID', '0'),
        'versions': json.dumps(versions, sort_keys=True),
    }


def version(pkg: str, missing: str) -> str:
    """The installed version of ``pkg`` (``missing`` when it is not installed)."""
    try:
        return importlib.metadata.version(pkg)
    except importlib.metadata.PackageNotFoundError:
        return missing
