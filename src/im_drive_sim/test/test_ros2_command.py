"""A command printed for the user runs as printed: ``cli.ros2_command`` is ``ros2`` when
the user's shell finds this installation's, else the path of this prefix's own."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from im_drive_sim.cli import ros2_command

pytestmark = pytest.mark.unit

MINE = Path(sys.prefix) / 'bin' / 'ros2'


@pytest.mark.skipif(not MINE.exists(), reason='this prefix has no ros2 of its own (colcon)')
def test_ros2_is_named_as_the_shell_would_find_it(monkeypatch, tmp_path):
    monkeypatch.delenv('IM_TUNER_SHELL_PATH', raising=False)
    monkeypatch.setenv('PATH', f'{MINE.parent}{os.pathsep}/usr/bin:/bin')
    assert ros2_command() == 'ros2'
    # started by this venv's ros2 from a shell without it on PATH: the shell's PATH counts
    monkeypatch.setenv('IM_TUNER_SHELL_PATH', '/usr/bin:/bin')
    monkeypatch.chdir(tmp_path)
    assert ros2_command() == str(MINE)
    monkeypatch.delenv('IM_TUNER_SHELL_PATH')
    monkeypatch.setenv('PATH', '/usr/bin:/bin')  # make demo: the venv is not on PATH
    monkeypatch.chdir(tmp_path)
    cmd = ros2_command()
    assert cmd == str(MINE), cmd
    # and what it names runs, from a shell without the venv on PATH
    p = subprocess.run(
        f'{cmd} run im_tuner report --help',
        shell=True,
        env={'PATH': '/usr/bin:/bin', 'HOME': str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0 and 'usage' in p.stdout, p.stderr[-2000:]
