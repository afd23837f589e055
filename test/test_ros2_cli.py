"""Tests of the installed ``ros2`` command (``.venv/bin/ros2``, made by ``make setup``).

Every call runs it as a subprocess from a scrubbed, plain-shell environment (no
``AMENT_PREFIX_PATH``, no ``VIRTUAL_ENV``, ``PATH=/usr/bin:/bin``, ``HOME`` in a tmp dir),
except one that goes through ``source .venv/bin/activate``. Behaviour of ``ros2 run``
(argument passing, exit codes, ``--prefix``, prefix priority) is checked against
throwaway ament prefixes built in ``tmp_path``; the hand-over to a real ``ros2cli`` is
checked with a fake ``ros2cli`` module on ``PYTHONPATH``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'
ROS2 = VENV / 'bin' / 'ros2'
TIMEOUT = 60  # seconds, for every subprocess (they normally take well under one)
# The run's own DDS domain (set by conftest.py) for anything that may start a node.
ROS_DOMAIN_ID = os.environ.get('ROS_DOMAIN_ID') or str(20 + os.getpid() % 200)


@pytest.fixture(autouse=True)
def _ros2_installed():
    # make test always runs make setup first: a missing command is a failure, not a skip.
    assert ROS2.is_file(), f'{ROS2} missing: run `make setup` first'


# ---------------------------------------------------------------------------- helpers


def plain_env(tmp_path: Path, **extra: str) -> dict[str, str]:
    """A plain shell's environment: nothing of the venv or of ROS, HOME in tmp."""
    home = tmp_path / 'home'
    home.mkdir(exist_ok=True)
    env = {'PATH': '/usr/bin:/bin', 'HOME': str(home), 'LANG': 'C.UTF-8'}
    env.update(extra)
    return env


def ros2(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(ROS2), *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT
    )


def lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def write_exe(path: Path, text: str, mode: int = 0o755) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(mode)
    return path


ECHO_ARGS = """#!/bin/sh
# prints where it runs from, each argument on its own line, and the environment it got
echo "WHO:{who}"
for a in "$@"; do printf 'ARG:%s\\n' "$a"; done
printf 'AMENT:%s\\n' "$AMENT_PREFIX_PATH"
printf 'FOO:%s\\n' "${{FOO-unset}}"
"""


def fake_prefix(root: Path, pkg: str = 'fakepkg', who: str = 'A') -> Path:
    """An ament prefix holding ``pkg`` with executables echo_args and exit3."""
    marker = root / 'share' / 'ament_index' / 'resource_index' / 'packages' / pkg
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    libdir = root / 'lib' / pkg
    write_exe(libdir / 'echo_args', ECHO_ARGS.format(who=who))
    write_exe(libdir / 'exit3', '#!/bin/sh\nexit 3\n')
    write_exe(libdir / 'not_executable', '#!/bin/sh\necho no\n', mode=0o644)
    return root


def field(out: str, key: str) -> list[str]:
    return [line[len(key) + 1 :] for line in out.splitlines() if line.startswith(key + ':')]


def source_executables(pkg: str) -> list[str]:
    scripts = REPO / 'src' / pkg / 'scripts'
    return (
        sorted(p.name for p in scripts.iterdir() if p.is_file() and not p.name.startswith('.'))
        if scripts.is_dir()
        else []
    )


# ------------------------------------------------------------------ ros2 pkg executables


def test_pkg_executables_lists_drive_sim(tmp_path):
    res = ros2(['pkg', 'executables'], plain_env(tmp_path), tmp_path)
    assert res.returncode == 0, res.stderr
    assert 'im_drive_sim drive_sim' in res.stdout.splitlines()


@pytest.mark.parametrize('pkg', ['im_drive_sim', 'im_controller', 'im_tuner'])
def test_pkg_executables_of_one_package(tmp_path, pkg):
    res = ros2(['pkg', 'executables', pkg], plain_env(tmp_path), tmp_path)
    assert res.returncode == 0, res.stderr
    assert lines(res.stdout) == [f'{pkg} {exe}' for exe in source_executables(pkg)]
    if pkg == 'im_drive_sim':
        assert 'im_drive_sim drive_sim' in res.stdout.splitlines()


def test_pkg_executables_full_path(tmp_path):
    res = ros2(['pkg', 'executables', 'im_drive_sim', '--full-path'], plain_env(tmp_path), tmp_path)
    assert res.returncode == 0, res.stderr
    paths = [Path(line) for line in lines(res.stdout)]
    assert paths, res.stdout
    libdir = (VENV / 'lib' / 'im_drive_sim').resolve()
    for path in paths:
        assert path.is_absolute() and path.is_file() and os.access(path, os.X_OK), path
        assert path.resolve().parent == libdir, path
    assert 'drive_sim' in [p.name for p in paths]


@pytest.mark.parametrize(
    'args', [['pkg', 'executables', 'x'], ['pkg', 'prefix', 'x'], ['run', 'x', 'drive_sim']]
)
def test_unknown_package(tmp_path, args):
    res = ros2(args, plain_env(tmp_path), tmp_path)
    assert res.returncode != 0
    assert res.stdout == ''
    assert lines(res.stderr) == ["Package 'x' not found"]


def test_unknown_executable(tmp_path):
    res = ros2(['run', 'im_drive_sim', 'no_such_exe'], plain_env(tmp_path), tmp_path)
    assert res.returncode != 0
    assert res.stdout == ''
    [line] = lines(res.stderr)
    assert "'no_such_exe'" in line and "'im_drive_sim'" in line


def test_pkg_prefix_is_the_venv(tmp_path):
    res = ros2(['pkg', 'prefix', 'im_drive_sim'], plain_env(tmp_path), tmp_path)
    assert res.returncode == 0, res.stderr
    assert Path(res.stdout.strip()).resolve() == VENV.resolve()


# ----------------------------------------------------------------- verbs and usage errors


@pytest.mark.parametrize(
    'args,provider',
    [
        (['topic', 'list'], 'ros2topic'),
        (['bag', 'record', '-a'], 'ros2bag'),
        (['launch', 'im_tuner', 'x.launch.py'], 'ros2launch'),
        (['param', 'list'], 'ros2param'),
    ],
)
def test_missing_verb_names_its_package(tmp_path, args, provider):
    res = ros2(args, plain_env(tmp_path), tmp_path)
    assert res.returncode != 0
    assert res.stdout == ''
    [line] = lines(res.stderr)
    assert f"'{provider}'" in line
    # `ros2 bag info` is what a ROS user tries first on a run's bag: the line names ours
    assert ('report --bag-info BAG_DIR' in line) == (args[0] == 'bag'), line


def test_gibberish_verb_is_a_usage_error(tmp_path):
    res = ros2(['frobnicate', 'now'], plain_env(tmp_path), tmp_path)
    assert res.returncode == 2
    [line] = lines(res.stderr)
    assert 'frobnicate' in line


@pytest.mark.parametrize('args', [['run'], ['run', 'im_drive_sim'], ['run', '--prefix']])
def test_run_missing_arguments(tmp_path, args):
    res = ros2(args, plain_env(tmp_path), tmp_path)
    assert res.returncode == 2
    assert 'usage' in res.stderr.lower() or '--prefix' in res.stderr
    assert len(lines(res.stderr)) == 1


def test_no_arguments_prints_usage(tmp_path):
    res = ros2([], plain_env(tmp_path), tmp_path)
    assert res.returncode == 2
    assert 'run' in res.stdout and 'pkg' in res.stdout


# ------------------------------------------------------------------------- activation


def test_works_after_activation(tmp_path):
    bash = shutil.which('bash')
    assert bash, 'bash is needed for this test'
    script = (
        'source .venv/bin/activate && command -v ros2 && '
        'printf "AMENT:%s\\n" "$AMENT_PREFIX_PATH" && ros2 pkg executables im_drive_sim'
    )
    res = subprocess.run(
        [bash, '-c', script],
        env=plain_env(tmp_path),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert res.returncode == 0, res.stderr
    out = res.stdout.splitlines()
    assert Path(out[0]).resolve() == ROS2.resolve()
    assert Path(field(res.stdout, 'AMENT')[0].split(':')[0]).resolve() == VENV.resolve()
    assert lines('\n'.join(out[2:])) == [
        f'im_drive_sim {e}' for e in source_executables('im_drive_sim')
    ]


# ----------------------------------------------- ros2 run against a fake ament prefix


def test_run_passes_arguments_and_ros_args_through(tmp_path):
    prefix = fake_prefix(tmp_path / 'pfx A')  # a space in the path on purpose
    args = [
        'a',
        'b c',
        '',
        '--flag',
        '-x=1',
        '--ros-args',
        '-p',
        'gain:=0.5',
        '-r',
        '__node:=n1',
        '--params-file',
        'p.yaml',
        '--',
        'tail',
    ]
    res = ros2(
        ['run', 'fakepkg', 'echo_args', *args],
        plain_env(tmp_path, AMENT_PREFIX_PATH=str(prefix)),
        tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert field(res.stdout, 'ARG') == args
    assert field(res.stdout, 'FOO') == ['unset']
    # The child sees the given prefix first and the venv (added by ros2) after it.
    ament = [Path(p) for p in field(res.stdout, 'AMENT')[0].split(':')]
    assert ament[0] == prefix
    assert VENV.resolve() in [p.resolve() for p in ament]


def test_run_propagates_exit_code(tmp_path):
    prefix = fake_prefix(tmp_path / 'pfx')
    res = ros2(
        ['run', 'fakepkg', 'exit3'], plain_env(tmp_path, AMENT_PREFIX_PATH=str(prefix)), tmp_path
    )
    assert res.returncode == 3


def test_run_ignores_non_executable_files(tmp_path):
    prefix = fake_prefix(tmp_path / 'pfx')
    env = plain_env(tmp_path, AMENT_PREFIX_PATH=str(prefix))
    res = ros2(['run', 'fakepkg', 'not_executable'], env, tmp_path)
    assert res.returncode != 0
    assert len(lines(res.stderr)) == 1
    res = ros2(['pkg', 'executables', 'fakepkg'], env, tmp_path)
    assert res.returncode == 0, res.stderr
    assert lines(res.stdout) == ['fakepkg echo_args', 'fakepkg exit3']


@pytest.mark.parametrize(
    'prefix_args,expected',
    [
        (['--prefix', 'env FOO=1'], '1'),
        (['--prefix=env FOO=2'], '2'),
        (['--prefix', "env 'FOO=with space'"], 'with space'),
    ],
)
def test_run_prefix_command(tmp_path, prefix_args, expected):
    prefix = fake_prefix(tmp_path / 'pfx')
    res = ros2(
        ['run', *prefix_args, 'fakepkg', 'echo_args', 'x', '--ros-args', '-p', 'a:=1'],
        plain_env(tmp_path, AMENT_PREFIX_PATH=str(prefix)),
        tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert field(res.stdout, 'FOO') == [expected]
    assert field(res.stdout, 'ARG') == ['x', '--ros-args', '-p', 'a:=1']


@pytest.mark.parametrize('order,winner', [(('A', 'B'), 'A'), (('B', 'A'), 'B')])
def test_first_prefix_wins(tmp_path, order, winner):
    prefixes = {who: fake_prefix(tmp_path / who, who=who) for who in 'AB'}
    env = plain_env(tmp_path, AMENT_PREFIX_PATH=':'.join(str(prefixes[w]) for w in order))
    res = ros2(['run', 'fakepkg', 'echo_args'], env, tmp_path)
    assert res.returncode == 0, res.stderr
    assert field(res.stdout, 'WHO') == [winner]
    res = ros2(['pkg', 'prefix', 'fakepkg'], env, tmp_path)
    assert res.stdout.strip() == str(prefixes[winner])
    res = ros2(['pkg', 'executables', 'fakepkg'], env, tmp_path)
    assert lines(res.stdout) == ['fakepkg echo_args', 'fakepkg exit3']  # listed once


def test_overlay_prefix_shadows_the_venv(tmp_path):
    """A package on AMENT_PREFIX_PATH (a sourced overlay) wins over the venv's copy."""
    overlay = tmp_path / 'overlay'
    (overlay / 'share/ament_index/resource_index/packages').mkdir(parents=True)
    (overlay / 'share/ament_index/resource_index/packages/im_drive_sim').touch()
    write_exe(overlay / 'lib/im_drive_sim/drive_sim', '#!/bin/sh\necho OVERLAY "$@"\n')
    env = plain_env(tmp_path, AMENT_PREFIX_PATH=str(overlay))
    res = ros2(['run', 'im_drive_sim', 'drive_sim', '--help'], env, tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == 'OVERLAY --help'
    res = ros2(['pkg', 'executables'], env, tmp_path)
    assert res.stdout.splitlines().count('im_drive_sim drive_sim') == 1


# ---------------------------------------------------------- hand-over to the real ros2cli


def test_hands_over_to_ros2cli_when_importable(tmp_path):
    fake = tmp_path / 'fake_site' / 'ros2cli'
    fake.mkdir(parents=True)
    (fake / '__init__.py').write_text('')
    (fake / 'cli.py').write_text(
        'import sys\n\n\ndef main():\n    print("FAKE-ROS2CLI", repr(sys.argv))\n    return 7\n'
    )
    env = plain_env(tmp_path, PYTHONPATH=str(tmp_path / 'fake_site'))
    for args in (
        ['topic', 'list'],
        ['run', 'im_drive_sim', 'drive_sim', 'a b', '--ros-args', '-p', 'x:=1'],
        [],
    ):
        res = ros2(args, env, tmp_path)
        assert res.returncode == 7, res.stderr
        assert res.stdout.strip() == f'FAKE-ROS2CLI {["ros2", *args]!r}'


# --------------------------------------------------------------------- the real node


def test_drive_sim_help_starts_and_exits_0(tmp_path):
    node = REPO / 'src' / 'im_drive_sim' / 'im_drive_sim' / 'drive_sim_node.py'
    env = plain_env(
        tmp_path, ROS_DOMAIN_ID=ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST'
    )
    res = ros2(['run', 'im_drive_sim', 'drive_sim', '--help'], env, tmp_path)
    assert res.returncode == 0, (
        f'{node} missing (the node has not landed yet)' if not node.is_file() else res.stderr
    )
    assert 'usage' in res.stdout.lower()
