"""``python -m im_tuner.foxglove``: where the installed layouts are, or write them afresh.

Without options: the path of every installed layout, one a line (what Foxglove's "Import
from file..." takes); ``make foxglove-layouts`` regenerates the committed copies with
``--out``. Bad input: one line on stderr, exit 2, nothing written.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

from im_drive_sim.cli import Parser, UsageError, run_cli

from .layouts import LAYOUTS, build, definitions, render, render_sdk
from .signals import index_table

PROG = 'im_tuner.foxglove'
PACKAGE = 'im_tuner'
#: A ROS namespace: absolute, tokens of letters, digits and underscores, not starting
#: with a digit (rcl's rule), no trailing slash.
_NAMESPACE = re.compile(r'^(/[A-Za-z_][A-Za-z0-9_]*)+$')


def share_dir() -> Path:
    """``share/im_tuner/foxglove`` of the installed package: through the ament index when
    it is set up (``AMENT_PREFIX_PATH``), else this interpreter's prefix (a venv made by
    ``make setup``)."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    for prefix in prefixes:
        marker = Path(prefix) / 'share' / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
        if marker.is_file():
            return Path(prefix) / 'share' / PACKAGE / 'foxglove'
    raise UsageError(f'{PACKAGE} is not installed in {os.pathsep.join(prefixes)} (run make setup)')


def _parser() -> Parser:
    p = Parser(prog=f'python -m {PROG}', description=__doc__.splitlines()[0])
    p.add_argument(
        '--out', metavar='DIR', help='write the layouts into DIR (its parent must exist)'
    )
    p.add_argument(
        '--namespace',
        metavar='NS',
        default='',
        help='topics under a namespace, e.g. /bench1 (default: none; needs --out)',
    )
    p.add_argument(
        '--sdk',
        action='store_true',
        help="write the SDK's layout form (foxglove.layouts), not Foxglove's import file "
        '(needs --out)',
    )
    p.add_argument(
        '--table',
        action='store_true',
        help='print the index table of the 5 kHz topics (Markdown, as docs/foxglove.md has it)',
    )
    return p


def _body(argv: list[str]) -> int:
    a = _parser().parse_args(argv)
    if a.out == '':
        raise UsageError('--out: an empty path (give a directory)')
    if a.namespace == '' and any(x.startswith('--namespace') for x in argv):
        raise UsageError('--namespace: empty (leave it out for no namespace)')
    if a.namespace and not _NAMESPACE.match(a.namespace):
        raise UsageError(f'--namespace: not a ROS namespace (like /bench1): {a.namespace!r}')
    if a.table:
        if a.out is not None or a.namespace or a.sdk:
            raise UsageError('--table takes no other option')
        sys.stdout.write(index_table())
        return 0
    if a.out is None:
        if a.namespace:
            raise UsageError('--namespace needs --out DIR (the installed layouts have none)')
        if a.sdk:
            raise UsageError('--sdk needs --out DIR')
        d = share_dir()
        missing = [n for n in LAYOUTS if not (d / f'{n}.json').is_file()]
        if missing:
            raise UsageError(f'{d} lacks {", ".join(missing)} (run make setup)')
        for n in LAYOUTS:
            print(d / f'{n}.json')
        return 0
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f'--out: {out} exists and is not a directory')
    if not out.parent.is_dir():
        raise UsageError(f'--out: the parent directory {out.parent} does not exist')
    if a.sdk:
        texts = {n: render_sdk(layout) for n, layout in definitions(a.namespace).items()}
    else:
        texts = {name: render(layout) for name, layout in build(a.namespace).items()}
    try:
        out.mkdir(exist_ok=True)
        for name, text in texts.items():
            (out / f'{name}.json').write_text(text, encoding='ascii')
            print(out / f'{name}.json')
    except OSError as exc:
        raise UsageError(f'--out: cannot write {out}: {exc.strerror or exc}') from None
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = sys.argv[1:] if argv is None else argv
    return run_cli(PROG, lambda: _body(args))
