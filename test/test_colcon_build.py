"""colcon builds the three ament_python packages without a ROS installation.

Uses ``.venv/bin/colcon`` (colcon-core, colcon-ros, ... pinned in requirements.txt; see
docs/building-with-colcon.md) on a copy of ``src/`` in a tmp dir, in both install modes,
then checks the install space (``lib/<pkg>/<exe>``, the ament index marker,
``share/<pkg>/package.xml``) and runs it the way a sourced ROS workspace would:
``source install/setup.bash``, then the wrapper (which, with no ``bin/python`` in a colcon
prefix, runs ``python3`` from PATH -- here the venv's, standing in for the system Python
of a ROS machine) and ``ros2 run``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'
COLCON = VENV / 'bin' / 'colcon'
PACKAGES = ['im_drive_sim', 'im_controller', 'im_tuner']
TIMEOUT = 180
ROS_DOMAIN_ID = os.environ.get('ROS_DOMAIN_ID') or str(20 + os.getpid() % 200)


@pytest.fixture(scope='module', autouse=True)
def _colcon_is_installed():
    # make setup installs colcon (requirements.txt); its absence is a failure, not a skip.
    assert COLCON.is_file(), (
        f'{COLCON} missing: run `make setup` (colcon is pinned in requirements.txt)'
    )


def plain_env(home: Path, **extra: str) -> dict[str, str]:
    """A plain shell with the venv's bin/ on PATH (its python3 plays the system's)."""
    env = {
        'PATH': f'{VENV / "bin"}:/usr/bin:/bin',
        'HOME': str(home),
        'LANG': 'C.UTF-8',
        'ROS_DOMAIN_ID': ROS_DOMAIN_ID,
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
    }
    env.update(extra)
    return env


def source_executables(pkg: str) -> list[str]:
    return sorted(p.name for p in (REPO / 'src' / pkg / 'scripts').glob('*'))


@pytest.fixture(scope='module', params=['copy', 'symlink'])
def workspace(request, tmp_path_factory):
    """A colcon workspace in tmp, built from a copy of src/ (never built in the repo)."""
    ws = tmp_path_factory.mktemp(f'colcon-{request.param}')
    for pkg in PACKAGES:
        shutil.copytree(
            REPO / 'src' / pkg,
            ws / 'src' / pkg,
            symlinks=True,
            ignore=shutil.ignore_patterns('build', 'install', 'log', '*.egg-info', '__pycache__'),
        )
    cmd = [
        str(COLCON),
        '--log-base',
        str(ws / 'log'),
        'build',
        '--base-paths',
        str(ws / 'src'),
        '--build-base',
        str(ws / 'build'),
        '--install-base',
        str(ws / 'install'),
        '--executor',
        'sequential',
    ]
    if request.param == 'symlink':
        cmd.append('--symlink-install')
    res = subprocess.run(
        cmd, env=plain_env(ws), cwd=ws, capture_output=True, text=True, timeout=TIMEOUT
    )
    assert res.returncode == 0, res.stdout + res.stderr
    return ws, request.param


def in_sourced_shell(ws: Path, script: str) -> subprocess.CompletedProcess:
    bash = shutil.which('bash')
    assert bash, 'bash is needed for this test'
    return subprocess.run(
        [bash, '-c', f'source install/setup.bash && {script}'],
        env=plain_env(ws),
        cwd=ws,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )


@pytest.mark.parametrize('pkg', PACKAGES)
def test_install_space_layout(workspace, pkg):
    ws, _ = workspace
    prefix = ws / 'install' / pkg
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / pkg).exists()
    assert (prefix / 'share' / pkg / 'package.xml').exists()
    libdir = prefix / 'lib' / pkg
    installed = sorted(p.name for p in libdir.iterdir()) if libdir.is_dir() else []
    assert installed == source_executables(pkg)
    for name in installed:
        assert os.access(libdir / name, os.X_OK), libdir / name


def test_sourced_workspace_imports_the_install_space(workspace):
    ws, mode = workspace
    res = in_sourced_shell(
        ws,
        'printf "AMENT:%s\\n" "$AMENT_PREFIX_PATH" && '
        'python3 -c "import im_drive_sim, im_controller, im_tuner; '
        'print(im_drive_sim.__file__); print(im_tuner.__file__)"',
    )
    assert res.returncode == 0, res.stderr
    out = res.stdout.splitlines()
    ament = out[0][len('AMENT:') :].split(':')
    assert sorted(ament) == sorted(str(ws / 'install' / p) for p in PACKAGES)
    # The copies in the workspace win over the ones pip installed into the venv.
    # (--symlink-install: build/<pkg> is on PYTHONPATH, its modules link into src/.)
    space = ws / ('build' if mode == 'symlink' else 'install')
    assert len(out) == 3
    for line in out[1:]:
        assert Path(line).is_relative_to(space), line


def test_wrapper_runs_from_install_space(workspace):
    ws, _ = workspace
    res = in_sourced_shell(ws, 'install/im_drive_sim/lib/im_drive_sim/drive_sim --help')
    assert res.returncode == 0, res.stderr
    assert 'usage' in res.stdout.lower()


def test_ros2_run_finds_the_overlay(workspace):
    ws, _ = workspace
    res = in_sourced_shell(
        ws,
        'ros2 pkg executables im_drive_sim --full-path && ros2 run im_drive_sim drive_sim --help',
    )
    assert res.returncode == 0, res.stderr
    first = Path(res.stdout.splitlines()[0])
    assert first == ws / 'install' / 'im_drive_sim' / 'lib' / 'im_drive_sim' / first.name
    assert 'usage' in res.stdout.lower()
