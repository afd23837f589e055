"""The default algorithm is named in one place (im_tuner.optim.options.DEFAULT_ALGO), and
``make demo`` and the README's main command run it."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from im_tuner import optim

pytestmark = pytest.mark.unit
ROOT = Path(__file__).resolve().parents[1]


def _demo_command(*make_args: str) -> str:
    """The command ``make demo`` would run (make -n: printed, not run)."""
    out = subprocess.run(
        ['make', '-n', '--no-print-directory', 'demo', *make_args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    lines = [ln for ln in out.splitlines() if 'ros2 run im_tuner tuner' in ln]
    assert len(lines) == 1, out
    return lines[0]


def test_make_demo_runs_the_tuners_default() -> None:
    cmd = _demo_command()
    assert '--algo' not in cmd  # the tuner's own default, not a second name of it
    assert cmd.split('ros2 run im_tuner tuner', 1)[1].strip() == ''


def test_make_demo_algo_picks_another() -> None:
    assert _demo_command('ALGO=necga').split('ros2 run im_tuner tuner', 1)[1].split() == [
        '--algo',
        'necga',
    ]


def test_readme_main_command_and_default_name() -> None:
    readme = (ROOT / 'README.md').read_text()
    main = re.search(r'The main command:\n\n    (.+)\n', readme)
    assert main is not None and main.group(1).strip() == 'ros2 run im_tuner tuner'
    # where the README names the default, it is the code's
    named = set(re.findall(r'`--algo` defaults to `(\w+)`', readme))
    assert named == {optim.DEFAULT_ALGO}
    assert optim.DEFAULT_ALGO in optim.ALGOS
