"""``ros2 run im_tuner study --drives ... --realism ...``: a table per drive, the
summary over drives, the Py-BOBYQA reference row with its evaluations counted, the
refusals; ``--beside`` (Tables I-III of two profiles side by side); and without
``--drives`` the study's files are those of the code before it existed, byte for byte.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
STUDY = [ROS2, 'run', 'im_tuner', 'study']


def study(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*STUDY, *args], capture_output=True, text=True, timeout=timeout)


#: sha256 of that study's tables.csv with safe's default ripple limit, retaken when the
#: identified first step or the statistics in tables.csv change (last: the first step from
#: the model's best points when one is predicted within the ripple limit)
DEFAULT_LIMIT_TABLES = '94a176c208967bb033ec583773946c2771a276542b943f0d6f624c7e6c5bc823'


def _without_new_columns(runs_csv: bytes) -> bytes:
    """runs.csv without the columns added since (the ripple, the identified drive)."""
    from im_tuner.study.files import RIPPLE_COLUMNS

    rows = list(csv.reader(io.StringIO(runs_csv.decode(), newline='')))
    keep = [
        i
        for i, name in enumerate(rows[0])
        if name not in RIPPLE_COLUMNS and not name.startswith('identified_')
    ]
    text = io.StringIO(newline='')
    csv.writer(text).writerows([row[i] for i in keep] for row in rows)
    return text.getvalue().encode()


def test_without_drives_the_files_are_unchanged(tmp_path):
    """Digests of the tables and runs of a small study made with the code before ``--drives``
    existed (main at a897583): the same study now gives the same bytes (out directory and
    the one new row of safe's grid aside)."""
    out = tmp_path / 's'
    # (--ripple-limit off: safe's ripple limit is on by default, which
    # steers its rows here: the tables' digest with it is DEFAULT_LIMIT_TABLES below)
    p = study(
        '--runs', '2', '--budget', '6', '--algos', 'spsa,necga,cmaes,safe', '--jobs', '1',
        '--quiet', '--out', str(out), '--ripple-limit', 'off',
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    # safe's grid has one row more (its first step from the drive model): every
    # other line is the bytes of before, the new row is there
    # (and one more: its first step from the identified drive)
    new_rows = (b',first step from the drive model,', b',first step from the identified drive,')

    def before(name: str) -> bytes:
        lines = (out / name).read_bytes().splitlines(keepends=True)
        for new_row in new_rows:
            assert sum(new_row in ln for ln in lines) >= 2
        # (and two statistics: the choice's standstill ripple)
        return b''.join(
            ln
            for ln in lines
            if not any(r in ln for r in new_rows) and not ln.startswith(b'ripple_')
        )

    tables = hashlib.sha256(before('tables.csv')).hexdigest()
    # and safe's commands now say its first step (the tuner's default depends on its bench)
    runs = (
        _without_new_columns(before('runs.csv'))
        .replace(str(out).encode(), b'OUT')
        .replace(b' --opt first=none', b'')
        .replace(b' --ripple-limit off', b'')
    )
    # (and the algorithm options as --opt KEY=VALUE, not a flag each)
    runs = re.sub(
        rb'--opt (\w+)=([^ ,"]+)', lambda m: b'--' + m[1].replace(b'_', b'-') + b' ' + m[2], runs
    )
    assert tables == 'e6de7e9d59bf6fcc6065ec2bffd83244c6b3c77c1e58f103707d6b3b4e4adc0b'
    assert (
        hashlib.sha256(runs).hexdigest()
        == '50d76073ebfaaa9884526a5da5bb61fca3e88eb1f223e49fd94ead851bbbd47f'
    )
    assert 'drives' not in json.loads((out / 'study.json').read_text())['spec']
    # the same study with safe's default ripple limit: only safe's rows differ
    dflt = tmp_path / 'default'
    p = study(
        '--runs', '2', '--budget', '6', '--algos', 'spsa,necga,cmaes,safe', '--jobs', '1',
        '--quiet', '--out', str(dflt),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    a, b = ((d / 'tables.csv').read_text().splitlines() for d in (out, dflt))
    differ = {x.split(',')[1] for x, y in zip(a, b, strict=True) if x != y}
    # (only safe's rows may differ; here none does: no experiment of these short runs is
    # over RIPPLE_TOLERANCE x the limit, and no choice over it; test_ripple_limit.py has
    # the runs the limit steers)
    assert differ <= {'safe'}
    assert hashlib.sha256((dflt / 'tables.csv').read_bytes()).hexdigest() == DEFAULT_LIMIT_TABLES
    assert not (out / 'family.json').exists()
    # beside it, the same grid on the bench profile: Tables I-III side by side
    bench = tmp_path / 'b'
    p = study(
        '--runs', '2', '--budget', '6', '--algos', 'spsa,necga', '--realism', 'bench',
        '--jobs', '1', '--quiet', '--out', str(bench), '--beside', str(out),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    md = (bench / 'beside.md').read_text()
    assert '## Tables I-III on the `bench` realism profile, beside `ideal` and the paper' in md
    assert md.count('(ideal ') == 4 * 12 and '; paper 0.81)' in md
    assert "### The paper's conclusions on `bench` and on `ideal`" in md
    assert json.loads((bench / 'study.json').read_text())['spec']['realism'] == 'bench'


def test_drives_a_table_per_drive_the_summary_and_bobyqa(tmp_path):
    out = tmp_path / 'fam'
    drive_file = tmp_path / 'mine.yaml'
    from im_drive_sim.params import default_config_path

    drive_file.write_text(default_config_path().read_text())
    p = study(
        '--drives', f'paper_750w,{drive_file}', '--realism', 'bench', '--algos', 'safe,bobyqa',
        '--runs', '2', '--budget', '12', '--jobs', '1', '--quiet', '--out', str(out),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    fam = json.loads((out / 'family.json').read_text())
    assert fam['drives'] == ['paper_750w', str(drive_file)] and fam['dirs'] == [
        'paper_750w',
        'mine',
    ]
    for d in fam['dirs']:
        assert (out / d / 'study.npz').is_file() and (out / d / 'tables.txt').is_file()
        with np.load(out / d / 'study.npz') as z:
            # four rows (safe blind, from the model, from the identified drive, bobyqa)
            # x 2 runs x 12 evaluations, every one measured
            assert z['losses'].shape == (4, 2, 12) and np.isfinite(z['losses']).all()
            assert np.isfinite(z['remeasured']).all()
            # the same drive file twice: the same losses (seeded, deterministic)
            if d == 'mine':
                with np.load(out / 'paper_750w' / 'study.npz') as z0:
                    assert np.array_equal(z['losses'], z0['losses'])
        meta = json.loads((out / d / 'study.json').read_text())
        assert meta['spec']['realism'] == 'bench' and meta['spec']['full_grid'] is False
    txt = (out / 'family.txt').read_text()
    assert p.stdout.startswith(txt)
    assert txt.count('Beyond the paper: every configuration') == 2
    assert txt.count('Py-BOBYQA rhobeg=0.08 (hand-tuned start)') == 3  # 2 drives + summary
    assert 'Summary over the drives' in txt
    assert (
        txt.count(': the default (safe first step from the identified drive) m') == 2
    )  # meets / misses, per drive
    md = (out / 'family.md').read_text()
    assert (
        md.count('## Drive ') == 2 and '![paper_750w comparison](paper_750w/comparison.png)' in md
    )
    # --from re-tabulates the family: the same text, no new experiments
    npz = (out / 'mine' / 'study.npz').read_bytes()
    (out / 'family.txt').unlink()
    p = study('--from', str(out), '--quiet')
    assert p.returncode == 0, p.stderr
    assert (out / 'family.txt').read_text() == txt and (
        out / 'mine' / 'study.npz'
    ).read_bytes() == npz


@pytest.mark.parametrize(
    ('args', 'expect'),
    [
        (
            ['--drives', 'paper_750w,nosuch'],
            '--drives: nosuch: no such drive file, and not a packaged drive',
        ),
        (['--drives', 'paper_750w', '--realism', 'noisy'], 'argument --realism: invalid choice'),
        (['--drives', 'paper_750w,paper_750w'], "--drives: 'paper_750w' given twice"),
        (['--drives', ','], '--drives: no drive named'),
        (['--drives', 'paper_750w', '--drive-config', 'x.yaml'], 'exclude each other'),
        (['--full-grid'], '--full-grid needs --drives'),
        (['--drives', 'paper_750w', '--beside', '.'], '--beside compares'),
        (['--beside', '/nonexistent'], '--beside /nonexistent: not a study directory'),
    ],
)
def test_bad_drives_one_line_exit_2_nothing_written(tmp_path, args, expect):
    out = tmp_path / 'out'
    p = study(*args, '--out', str(out))
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, p.stderr
    assert lines[0].startswith('error: study: ') and expect in lines[0], lines[0]
    assert not out.exists() and p.stdout == ''


def test_runs_csv_has_each_runs_ripple_and_identified_drive(tmp_path):
    """runs.csv gives each run's standstill ripple of isq* (the start's and the applied
    gains', rms about the mean and peak to peak, after the move and after the load: what
    study.npz holds) and, for the rows whose first step is identified, the drive identified
    from the start's experiments with its sd: here the plant is the told drive, so J and Kt
    are its file's within 2 sd and 3 %."""
    from im_drive_sim.drive_file import load_config
    from im_tuner.identify import FIGURES
    from im_tuner.study.files import RIPPLE_COLUMNS
    from im_tuner.study.results import load

    out = tmp_path / 's'
    p = study('--runs', '2', '--budget', '3', '--algos', 'safe', '--jobs', '1', '--quiet',
              '--out', str(out))  # fmt: skip
    assert p.returncode == 0, p.stderr
    with (out / 'runs.csv').open() as f:
        rows = list(csv.DictReader(f))
    res = load(out)
    assert len(rows) == len(res.cells) * 2
    machine = load_config(None).machine  # (the study's drive: the packaged default)
    identified_rows = 0
    for i, row in enumerate(rows):
        c, r = divmod(i, 2)
        assert (row['config'], int(row['run'])) == (res.cells[c].label, r)
        rms = [float(row[k]) for k in RIPPLE_COLUMNS[:4]]
        pp = [float(row[k]) for k in RIPPLE_COLUMNS[4:]]
        assert rms == list(res.ripple[c, r]) and pp == list(res.ripple_pp[c, r])
        assert all(0 < a <= b for a, b in zip(rms, pp, strict=True)), row
        figures = [row[f'identified_{f}'] for f in FIGURES]
        if res.cells[c].first != 'identify':
            assert figures == [''] * len(FIGURES), row
            continue
        identified_rows += 1
        v = dict(zip(FIGURES, map(float, figures), strict=True))
        assert list(v.values()) == list(res.identified[c, r])
        assert v['J_sd'] > 0 and v['Kt_sd'] > 0 and v['Tc_sd'] > 0
        for name, file_value in (('J', machine.J), ('Kt', machine.Kt)):
            err = abs(v[name] - file_value)
            assert err <= max(2 * v[f'{name}_sd'], 0.03 * file_value), (name, v, file_value)
    assert identified_rows == 2
