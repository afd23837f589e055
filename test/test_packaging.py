"""Packaging conventions of the three ament_python packages, on the sources and on the
tree ``make setup`` installed into ``.venv`` (see docs/building-with-colcon.md and
/work/shared/notes/ros2-on-pip.md).

The executable wrappers (``src/<pkg>/scripts/*``) are run from fake prefix trees in
``tmp_path`` with a fake interpreter that records its arguments, to check that they exec
the prefix's own ``bin/python`` when there is one and ``python3`` from PATH otherwise.
"""

from __future__ import annotations

import configparser
import os
import re
import shutil
import stat
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'
PACKAGES = ['im_drive_sim', 'im_controller', 'im_tuner']
TIMEOUT = 30

WRAPPERS = sorted((REPO / 'src').glob('*/scripts/*'))
WRAPPER_IDS = [f'{w.parents[1].name}/{w.name}' for w in WRAPPERS]


@pytest.fixture
def _installed():
    # make test always runs make setup first: a missing install is a failure, not a skip.
    assert (VENV / '.installed').exists(), 'run `make setup` first'


needs_install = pytest.mark.usefixtures('_installed')


# ------------------------------------------------------------------------- sources


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_xml_format_3_and_name(pkg):
    root = ET.parse(REPO / 'src' / pkg / 'package.xml').getroot()
    assert root.tag == 'package'
    assert root.get('format') == '3'
    assert root.findtext('name') == pkg
    assert root.findtext('export/build_type') == 'ament_python'


@pytest.mark.parametrize('pkg', PACKAGES)
def test_setup_cfg_install_scripts(pkg):
    cfg = configparser.ConfigParser(interpolation=None)
    assert cfg.read(REPO / 'src' / pkg / 'setup.cfg')
    assert cfg.get('install', 'install_scripts') == f'$base/lib/{pkg}'
    assert cfg.get('develop', 'script_dir') == f'$base/lib/{pkg}'


@pytest.mark.parametrize('pkg', PACKAGES)
def test_resource_marker(pkg):
    assert (REPO / 'src' / pkg / 'resource' / pkg).is_file()


@pytest.mark.parametrize('wrapper', WRAPPERS, ids=WRAPPER_IDS)
def test_wrapper_source_is_executable(wrapper):
    assert wrapper.stat().st_mode & stat.S_IXUSR, f'{wrapper} lacks the run bit (chmod +x)'


def wrapper_launch(wrapper: Path) -> list[str]:
    """What a wrapper runs after the interpreter: ``-m im_drive_sim.launch <exe>
    <module>:<function>``; both branches must run the same."""
    launches = set(
        re.findall(r'(-m\s+im_drive_sim\.launch\s+\w+\s+[\w.]+:\w+)', wrapper.read_text())
    )
    assert len(launches) == 1, f'{wrapper}: expected one launch line, found {launches}'
    return launches.pop().split()


@pytest.mark.parametrize('wrapper', WRAPPERS, ids=WRAPPER_IDS)
def test_wrapper_launches_a_main_of_its_own_package(wrapper):
    pkg = wrapper.parents[1].name
    _m, _launch, exe, target = wrapper_launch(wrapper)
    module, function = target.split(':')
    assert exe == wrapper.name and module.split('.')[0] == pkg
    path = REPO / 'src' / pkg / Path(*module.split('.'))
    source = path.with_suffix('.py')
    assert source.is_file(), f'{wrapper.name} runs {module}, which is not in src/{pkg}'
    assert re.search(rf'^def {function}\(', source.read_text(), re.M), (source, function)


# ------------------------------------------------------------------ installed tree


@needs_install
@pytest.mark.parametrize('pkg', PACKAGES)
def test_installed_ament_index_and_package_xml(pkg):
    assert (VENV / 'share' / 'ament_index' / 'resource_index' / 'packages' / pkg).is_file()
    installed = VENV / 'share' / pkg / 'package.xml'
    assert installed.is_file()
    assert ET.parse(installed).getroot().findtext('name') == pkg


@needs_install
@pytest.mark.parametrize('pkg', PACKAGES)
def test_installed_executables_carry_run_bit(pkg):
    libdir = VENV / 'lib' / pkg
    sources = sorted(p.name for p in (REPO / 'src' / pkg / 'scripts').glob('*'))
    installed = sorted(p.name for p in libdir.iterdir()) if libdir.is_dir() else []
    assert installed == sources
    for name in installed:
        assert os.access(libdir / name, os.X_OK), f'{libdir / name} is not executable'


# ----------------------------------------------------------- wrappers in fake prefixes

RECORDER = """#!/bin/sh
# a fake interpreter: records how it was called, then exits with 5
{{ printf 'SELF:%s\\n' "$0"; for a in "$@"; do printf 'ARG:%s\\n' "$a"; done; }} > '{log}'
exit 5
"""
ARGS = ['a b', '', '--ros-args', '-p', 'x:=1']


def make_prefix(tmp_path: Path, wrapper: Path, with_python: bool, via_symlink: bool = False):
    """``<tmp>/pre fix/lib/<pkg>/<exe>`` (a space on purpose), optional ``bin/python``."""
    pkg = wrapper.parents[1].name
    prefix = tmp_path / 'pre fix'
    exe = prefix / 'lib' / pkg / wrapper.name
    exe.parent.mkdir(parents=True)
    if via_symlink:  # colcon --symlink-install links lib/<pkg>/<exe> into the build dir
        target = tmp_path / 'build' / pkg / 'scripts' / wrapper.name
        target.parent.mkdir(parents=True)
        shutil.copy2(wrapper, target)
        exe.symlink_to(target)
    else:
        shutil.copy2(wrapper, exe)
    log = tmp_path / 'argv.log'
    if with_python:
        (prefix / 'bin').mkdir()
        (prefix / 'bin' / 'python').write_text(RECORDER.format(log=log))
        (prefix / 'bin' / 'python').chmod(0o755)
    return prefix, exe, log


def run_wrapper(exe: Path, env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(exe), *ARGS], env=env, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT
    )


def recorded(log: Path) -> tuple[str, list[str]]:
    lines = log.read_text().splitlines()
    return lines[0][len('SELF:') :], [line[len('ARG:') :] for line in lines[1:]]


@pytest.mark.parametrize('via_symlink', [False, True], ids=['copy', 'symlink'])
@pytest.mark.parametrize('wrapper', WRAPPERS, ids=WRAPPER_IDS)
def test_wrapper_uses_prefix_python(tmp_path, wrapper, via_symlink):
    prefix, exe, log = make_prefix(tmp_path, wrapper, with_python=True, via_symlink=via_symlink)
    # A python3 on PATH that must NOT be used.
    decoy = tmp_path / 'decoy'
    decoy.mkdir()
    (decoy / 'python3').write_text('#!/bin/sh\necho DECOY; exit 99\n')
    (decoy / 'python3').chmod(0o755)
    env = {'PATH': f'{decoy}:/usr/bin:/bin', 'HOME': str(tmp_path)}
    res = run_wrapper(exe, env, cwd=tmp_path)
    assert res.returncode == 5, res.stdout + res.stderr  # the fake's exit code comes back
    self_path, argv = recorded(log)
    assert Path(self_path) == prefix / 'bin' / 'python'
    assert argv == [*wrapper_launch(wrapper), *ARGS]


@pytest.mark.parametrize('wrapper', WRAPPERS, ids=WRAPPER_IDS)
def test_wrapper_falls_back_to_python3_on_path(tmp_path, wrapper):
    _prefix, exe, log = make_prefix(tmp_path, wrapper, with_python=False)
    fakebin = tmp_path / 'fakebin'
    fakebin.mkdir()
    (fakebin / 'python3').write_text(RECORDER.format(log=log))
    (fakebin / 'python3').chmod(0o755)
    env = {'PATH': f'{fakebin}:/usr/bin:/bin', 'HOME': str(tmp_path)}
    # Started by a relative path from another directory, as `ros2 run` would not do but
    # a user might.
    res = run_wrapper(
        Path(os.path.relpath(exe, tmp_path / 'fakebin')), env, cwd=tmp_path / 'fakebin'
    )
    assert res.returncode == 5, res.stdout + res.stderr
    self_path, argv = recorded(log)
    assert Path(self_path).name == 'python3' and Path(self_path).parent == fakebin
    assert argv == [*wrapper_launch(wrapper), *ARGS]
