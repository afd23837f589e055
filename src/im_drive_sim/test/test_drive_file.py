"""A drive file's ``base``: a packaged drive, or a path relative to the file that names it
(``im_drive_sim.drive_file``; docs/real-drive.md). ``base: sub/motor.yaml`` raised
ValueError from pathlib in every executable that reads a drive file."""

from __future__ import annotations

import os

import pytest

from im_drive_sim.drive_file import load_config, packaged_base
from im_drive_sim.params import ConfigError, default_config_path


@pytest.fixture
def tree(tmp_path):
    """drives/my.yaml on drives/sub/motor.yaml; other/up.yaml on ../drives/sub/motor.yaml."""
    (tmp_path / 'drives' / 'sub').mkdir(parents=True)
    (tmp_path / 'other').mkdir()
    motor = default_config_path().read_text().replace('J: 2.5e-3', 'J: 4.0e-3')
    assert 'J: 4.0e-3' in motor
    (tmp_path / 'drives' / 'sub' / 'motor.yaml').write_text(motor)
    (tmp_path / 'drives' / 'my.yaml').write_text('base: sub/motor.yaml\nTs: 200.0e-6\n')
    (tmp_path / 'other' / 'up.yaml').write_text('base: ../drives/sub/motor.yaml\n')
    return tmp_path


def test_a_relative_base_is_found_beside_the_file_that_names_it(tree, monkeypatch):
    for cwd in (tree, tree / 'other', tree / 'drives' / 'sub'):
        monkeypatch.chdir(cwd)
        for f in (tree / 'drives' / 'my.yaml', tree / 'other' / 'up.yaml'):
            name = os.path.relpath(f, cwd)  # as a user types it, from where they are
            assert load_config(name).machine.J == 4.0e-3, (cwd, name)
    abs_base = tree / 'abs.yaml'
    abs_base.write_text(f'base: {tree / "drives" / "sub" / "motor.yaml"}\n')
    assert load_config(abs_base).machine.J == 4.0e-3
    assert packaged_base(tree / 'drives' / 'my.yaml') is None  # a base of its own


def test_a_missing_relative_base_is_one_line_naming_the_file(tree):
    bad = tree / 'drives' / 'bad.yaml'
    for base in ('sub/none.yaml', '../nowhere/m.yaml', 'sub'):
        bad.write_text(f'base: {base}\n')
        with pytest.raises(ConfigError) as err:
            load_config(bad)
        text = str(err.value)
        assert text.startswith(f"bad.yaml: base '{base}': cannot read "), text
        assert len(text.splitlines()) == 1 and "relative to bad.yaml's folder" in text
    bad.write_text('base: sub/motor.yaml\n')
    (tree / 'drives' / 'sub' / 'motor.yaml').write_text('machine: [\n')
    said = r"bad\.yaml: base 'sub/motor\.yaml': /\S+/sub/motor\.yaml: YAML syntax error at line 2"
    with pytest.raises(ConfigError, match=said) as e:
        load_config(bad)
    assert len(str(e.value).splitlines()) == 1  # (a YAML error's text spans lines)
    assert str(e.value).count('motor.yaml') == 2  # the base as written, then its path


def test_the_packaged_base_of_a_drive_file(tmp_path):
    assert packaged_base(None) == 'paper_750w'
    assert packaged_base('im7500w-j3') == 'im7500w-j3'
    for base in ('im7500w-j3', 'im7500w-j3.yaml', 'paper_750w'):
        f = tmp_path / 'mine.yaml'
        f.write_text(f'base: {base}\n')
        assert packaged_base(f) == base.removesuffix('.yaml')
    assert packaged_base(tmp_path / 'missing.yaml') is None
    assert packaged_base(default_config_path()) is None  # a complete file: no base
