"""``ros2 run im_tuner study --plant ... --plant-mismatch ...``: the plant and
its mismatch recorded in study.json, printed in tables.txt, reproduction.md, family.txt
and family.md, kept by ``--from``; bad input refused in one line, exit 2, nothing written.
(The runs themselves: src/im_tuner/test/test_study_plant.py.)"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
STUDY = [ROS2, 'run', 'im_tuner', 'study']
SMALL = ('--algos', 'cmaes', '--runs', '2', '--budget', '4', '--jobs', '1', '--quiet')


def study(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*STUDY, *args], capture_output=True, text=True, timeout=timeout)


def _plant_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if 'plant' in ln]


def test_a_plant_study_records_and_prints_its_plant_and_from_keeps_it(tmp_path):
    out = tmp_path / 's'
    p = study(
        '--drive-config', 'im750w-j1', '--plant', 'im750w-j3', '--plant-mismatch',
        'Rr=x1.3 delay=2',
        *SMALL, '--out', str(out),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    meta = json.loads((out / 'study.json').read_text())
    assert meta['spec']['plant'] == ['im750w-j3']
    assert meta['spec']['mismatch'] == [['Rr', 1.3], ['delay', 2]]
    assert meta['l_ref_told'] > 0 and meta['l_ref'] != meta['l_ref_told']
    txt = (out / 'tables.txt').read_text()
    ratio = meta['l_ref'] / meta['l_ref_told']
    want = (
        'plant: im750w-j3 with Rr x1.3, command delay 2 periods; the tuner told im750w-j1 '
        '(its experiment, search box, start and model for the first step); L_ref is the '
        f'hand-tuned start on the plant, {ratio:.3f} x its {meta["l_ref_told"]:.5f} on the '
        'told drive'
    )
    assert _plant_lines(txt) == [want] and txt.splitlines()[2] == want
    assert p.stdout.startswith(txt)
    md = (out / 'reproduction.md').read_text()
    assert f'**The plant is not the drive the tuner is told.** P{want[1:]}.' in md
    # a run on another plant cannot be repeated by a tuner command on the ROS bench yet
    with (out / 'runs.csv').open() as f:
        assert {row['tuner_command'] for row in csv.DictReader(f)} == {''}
    # --from re-tabulates it: the same plant line, no new experiments
    npz = (out / 'study.npz').read_bytes()
    (out / 'tables.txt').unlink()
    (out / 'reproduction.md').unlink()
    p = study('--from', str(out), '--quiet')
    assert p.returncode == 0, p.stderr
    assert (out / 'tables.txt').read_text() == txt and (out / 'study.npz').read_bytes() == npz
    assert f'P{want[1:]}.' in (out / 'reproduction.md').read_text()
    # the plant is the one it ran on: --from takes no other
    p = study('--from', str(out), '--plant', 'im750w-j10', '--quiet')
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and '--from re-tabulates' in lines[0]


def test_a_family_with_a_plant_per_drive(tmp_path):
    out = tmp_path / 'fam'
    p = study(
        '--drives', 'im750w-j1,im750w-j3', '--plant', 'im750w-j3,im750w-j10',
        '--plant-mismatch', 'J=x1.5', *SMALL, '--out', str(out),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    plants = {}
    for d in ('im750w-j1', 'im750w-j3'):
        meta = json.loads((out / d / 'study.json').read_text())
        plants[d] = meta['spec']['plant']
        assert meta['spec']['mismatch'] == [['J', 1.5]] and meta['l_ref_told'] > 0
    assert plants == {'im750w-j1': ['im750w-j3'], 'im750w-j3': ['im750w-j10']}
    txt = (out / 'family.txt').read_text()
    head = (
        'the plant is not the drive the tuner is told: told im750w-j1, plant im750w-j3 with '
        "J x1.5; told im750w-j3, plant im750w-j10 with J x1.5 (each drive's losses "
        'normalised by its hand-tuned start on the plant)'
    )
    assert txt.splitlines()[1] == head
    per_drive = [ln for ln in txt.splitlines() if ln.startswith('plant: ')]
    assert [ln.split(';')[0] for ln in per_drive] == [
        'plant: im750w-j3 with J x1.5',
        'plant: im750w-j10 with J x1.5',
    ]
    md = (out / 'family.md').read_text()
    assert '**The plant is not the drive the tuner is told.** Told im750w-j1, plant' in md
    assert md.count('**The plant is not the drive the tuner is told.** Plant: ') == 2
    (out / 'family.txt').unlink()
    p = study('--from', str(out), '--quiet')
    assert p.returncode == 0, p.stderr
    assert (out / 'family.txt').read_text() == txt


def test_without_a_plant_nothing_says_plant(tmp_path):
    """A study of the told drive writes what it wrote before --plant existed (the digests:
    test_study_drives.test_without_drives_the_files_are_unchanged)."""
    out = tmp_path / 's'
    p = study('--drive-config', 'im750w-j1', *SMALL, '--out', str(out))
    assert p.returncode == 0, p.stderr
    meta = json.loads((out / 'study.json').read_text())
    assert not {'plant', 'mismatch'} & set(meta['spec']) and 'l_ref_told' not in meta
    for name in ('tables.txt', 'reproduction.md'):
        text = (out / name).read_text()
        assert (
            'the tuner told' not in text
            and 'L_ref is the hand-tuned start on the plant' not in text
        )
        assert 'The plant is not the drive' not in text, name


@pytest.mark.parametrize(
    ('args', 'expect'),
    [
        (['--plant-mismatch', 'J=2'], "--plant-mismatch 'J=2': a machine key takes a factor"),
        (['--plant-mismatch', 'delay=x2'], 'delay is the command delay in periods, 1 or 2'),
        (['--plant-mismatch', 'coulomb=-1%'], 'coulomb takes a percentage of rated torque'),
        (['--plant-mismatch', 'isq_max=x1.1'], 'isq_max takes no factor'),
        (['--plant-mismatch', 'rated_flux_current=x10'], 'the plant is not a valid drive'),
        (['--plant-mismatch', 'J=x0.0001'], 'with 0.1 <= F <= 10, e.g. J=x1.5'),
        (['--plant-mismatch', 'J=x1e6'], 'is another drive: give it as --plant'),
        (['--plant', 'nosuch'], '--plant: nosuch: no such drive file'),
        (['--plant', ','], '--plant: no drive named'),
        (['--plant', 'im3700w-j1'], 'machine.isq_max 17.66 A, the told drive 7 A'),
        (['--plant', 'FAST'], 'Ts 100 us, the told drive 200 us'),
        (['--plant', 'im750w-j3,im750w-j10'], '--plant: 2 plants for 1 told drive(s)'),
        (
            ['--drives', 'im750w-j1,im3700w-j1', '--plant', 'im750w-j3'],
            'the told drive 17.66 A: the experiment',
        ),
        (
            ['--drives', 'im750w-j1,im750w-j3', '--plant', 'a,b,c'],
            '--plant: 3 plants for 2 told drive(s)',
        ),
    ],
)
def test_bad_plant_one_line_exit_2_nothing_written(tmp_path, args, expect):
    fast = tmp_path / 'fast.yaml'
    fast.write_text('base: paper_750w\nTs: 1.0e-4\n')
    out = tmp_path / 'out'
    p = study(*[str(fast) if a == 'FAST' else a for a in args], '--out', str(out))
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, p.stderr
    assert lines[0].startswith('error: study: ') and expect in lines[0], lines[0]
    assert not out.exists() and p.stdout == ''
