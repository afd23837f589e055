"""Configuration loading and validation (docs/drive-model.md, "Parameter file reference")."""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
from pathlib import Path

import pytest
import yaml

try:  # source checkout without an installed package (the lead's packaging installs it)
    import im_drive_sim  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from im_drive_sim.drive_file import load_config
from im_drive_sim.params import ConfigError, DriveConfig, config_from_dict, default_config_path


@pytest.fixture(scope='module')
def default_dict() -> dict:
    return yaml.safe_load(default_config_path().read_text())


def _write(tmp_path: Path, data: dict, name: str = 'bad.yaml') -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_default_loads_with_paper_values() -> None:
    cfg = load_config()
    assert isinstance(cfg, DriveConfig)
    assert default_config_path().name == 'paper_750w.yaml'
    assert cfg.model == 'full' and cfg.Ts == 200e-6 and cfg.Ts_ns == 200_000 and cfg.seed == 0
    m = cfg.machine
    assert (m.Rs, m.Rr, m.Lls, m.Llr, m.Lm, m.pole_pairs) == (3.7, 2.1, 0.0125, 0.0125, 0.205, 1)
    assert m.Ls == pytest.approx(0.2175) and m.Lr == pytest.approx(0.2175)
    assert m.sigma == pytest.approx(0.11164, abs=1e-5)
    assert m.tau_r == pytest.approx(0.10357, abs=1e-5)
    assert m.rated_flux == pytest.approx(0.50225)
    assert m.Kt == pytest.approx(0.7101, abs=1e-4)
    assert m.u_max == pytest.approx(179.556, abs=1e-3)
    assert cfg.sensors.encoder_counts == 4096 and cfg.sensors.speed_filter_tau == 1e-3
    assert cfg.control.current_bandwidth == 1500.0 and cfg.control.computation_delay_steps == 0
    assert cfg.source == 'paper_750w.yaml'


def test_every_key_has_a_unit_comment() -> None:
    for line in default_config_path().read_text().splitlines():
        s = line.strip()
        if s and not s.startswith('#') and not s.endswith(':'):
            assert '#' in s and '[' in s.split('#', 1)[1], f'key without unit comment: {s}'


def test_round_trip_and_file_copy(tmp_path: Path, default_dict: dict) -> None:
    cfg = load_config()
    assert config_from_dict(cfg.to_dict()) == cfg
    assert load_config(_write(tmp_path, default_dict, 'copy.yaml')) == cfg
    assert load_config(str(_write(tmp_path, default_dict, 'copy2.yaml'))) == cfg


def test_overrides_nested_and_dotted() -> None:
    a = load_config(overrides={'machine': {'J': 1.0}, 'model': 'reduced'})
    b = load_config(overrides={'machine.J': 1.0, 'model': 'reduced'})
    assert a == b and a.machine.J == 1.0 and a.model == 'reduced'
    assert a.machine.Rs == 3.7
    with pytest.raises(ConfigError, match=r'unknown override key machine\.Jx'):
        load_config(overrides={'machine.Jx': 1.0})
    with pytest.raises(ConfigError, match=r'machine\.J must be a finite number > 0, got -1'):
        load_config(overrides={'machine.J': -1})


BAD_VALUES = [
    ('machine.Rs', -3.7, 'machine.Rs must be a finite number > 0, got -3.7'),
    ('machine.Rs', float('nan'), 'machine.Rs must be a finite number > 0, got nan'),
    ('machine.Lm', float('inf'), 'machine.Lm must be a finite number > 0, got inf'),
    ('machine.Lls', 0.0, 'machine.Lls must be a finite number > 0'),
    ('machine.J', 'heavy', "machine.J must be a finite number > 0, got 'heavy'"),
    ('machine.Udc', True, 'machine.Udc must be a finite number > 0, got True'),
    ('machine.B', -1e-4, 'machine.B must be a finite number >= 0'),
    ('machine.isq_max', 0, 'machine.isq_max must be a finite number > 0'),
    ('machine.rated_flux_current', -2.45, 'machine.rated_flux_current must be'),
    ('machine.pole_pairs', 1.5, 'machine.pole_pairs must be an integer >= 1, got 1.5'),
    ('machine.pole_pairs', 0, 'machine.pole_pairs must be an integer >= 1, got 0'),
    ('machine.pole_pairs', True, 'machine.pole_pairs must be an integer >= 1, got True'),
    ('sensors.encoder_counts', 4096.0, 'sensors.encoder_counts must be an integer >= 1'),
    ('sensors.encoder_counts', '4096', 'sensors.encoder_counts must be an integer >= 1'),
    ('sensors.speed_filter_tau', -1e-3, 'sensors.speed_filter_tau must be a finite number >= 0'),
    ('control.computation_delay_steps', 2, 'control.computation_delay_steps must be an integer'),
    ('disturbance.ripple_phase', float('nan'), 'disturbance.ripple_phase must be a finite number'),
    ('model', 'half', "model must be one of full, reduced, got 'half'"),
    ('Ts', 0.0, 'Ts must be a finite number > 0'),
    ('Ts', 1.5e-10, 'Ts must be an integer number of nanoseconds'),
    ('seed', -1, 'seed must be an integer >= 0'),
    ('seed', 1.0, 'seed must be an integer >= 0'),
    # consistency
    ('machine.Udc', 10.0, 'machine.Udc too low'),
    ('control.flux_floor', 1.0, 'control.flux_floor'),
    ('control.current_bandwidth', 10000.0, 'control.current_bandwidth too high'),
    ('Ts', 5e-3, 'Ts = 0.005 s too large'),
    # the clamp against the rated torque current Tn/Kt = 3.52 A: 700 A is a typo
    (
        'machine.isq_max',
        700.0,
        'machine.isq_max 700 A is implausible: 199x the rated torque current 3.52 A',
    ),
    ('machine.isq_max', 14.5, 'at most 4x (14.1 A) is accepted'),
]


@pytest.mark.parametrize('key,value,msg', BAD_VALUES, ids=[f'{k}={v!r}' for k, v, _ in BAD_VALUES])
def test_bad_values_name_file_and_key(
    tmp_path: Path, default_dict: dict, key: str, value: object, msg: str
) -> None:
    data = copy.deepcopy(default_dict)
    parts = key.split('.')
    if len(parts) == 1:
        data[key] = value
    else:
        data[parts[0]][parts[1]] = value
    p = _write(tmp_path, data, 'mymotor.yaml')
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    text = str(ei.value)
    assert text.startswith('mymotor.yaml: '), text
    assert msg in text, text
    assert isinstance(ei.value, ValueError)


def test_missing_and_unknown_keys(tmp_path: Path, default_dict: dict) -> None:
    d = copy.deepcopy(default_dict)
    del d['disturbance']
    with pytest.raises(ConfigError, match=r'^m\.yaml: missing key disturbance$'):
        load_config(_write(tmp_path, d, 'm.yaml'))
    d = copy.deepcopy(default_dict)
    del d['machine']['J']
    with pytest.raises(ConfigError, match=r'^m\.yaml: missing key machine\.J$'):
        load_config(_write(tmp_path, d, 'm.yaml'))
    d = copy.deepcopy(default_dict)
    d['machine']['Rss'] = 1.0
    with pytest.raises(ConfigError, match=r'^m\.yaml: unknown key machine\.Rss$'):
        load_config(_write(tmp_path, d, 'm.yaml'))
    d = copy.deepcopy(default_dict)
    d['extra'] = 1
    with pytest.raises(ConfigError, match=r'^m\.yaml: unknown key extra'):
        load_config(_write(tmp_path, d, 'm.yaml'))
    d = copy.deepcopy(default_dict)
    d['sensors'] = [1, 2]
    with pytest.raises(ConfigError, match=r'^m\.yaml: sensors must be a mapping'):
        load_config(_write(tmp_path, d, 'm.yaml'))


def test_yaml_syntax_error_and_empty_and_missing_file(tmp_path: Path) -> None:
    p = tmp_path / 'broken.yaml'
    p.write_text('model: full\nmachine: [1, 2\nTs: 2e-4\n')
    with pytest.raises(
        ConfigError, match=r'^broken\.yaml: YAML syntax error at line \d+, column \d+'
    ):
        load_config(p)
    # no settings: said as it is (a comments-only file is not "empty"), on one line
    for text, what in (
        ('', 'the file is empty'),
        ('\n  \n', 'the file is empty'),
        ('# nothing\n# Ts: 2e-4\n', 'the file holds only comments'),
        ('---\n# a document of comments\n...\n', 'the file holds only comments'),
        ('~\n', 'the YAML document is null'),
        ('null # nothing\n', 'the YAML document is null'),
    ):
        p = tmp_path / 'empty.yaml'
        p.write_text(text)
        with pytest.raises(ConfigError) as exc:
            load_config(p)
        msg = str(exc.value)
        assert msg.startswith(f'empty.yaml: no settings ({what}); a drive file is a mapping')
        assert '\n' not in msg
    p = tmp_path / 'list.yaml'
    p.write_text('- 1\n- 2\n')
    with pytest.raises(ConfigError, match=r'^list\.yaml: top level must be a mapping'):
        load_config(p)
    # a file that is not there: named once, by the path where it was looked for
    with pytest.raises(ConfigError) as exc:
        load_config(tmp_path / 'nope.yaml')
    said = 'nope.yaml: cannot read the file (No such file or directory)'
    assert str(exc.value) == f'{tmp_path}/{said}'

    p = tmp_path / 'binary.yaml'
    p.write_bytes(b'model: \xff\xfe\x00\n')
    with pytest.raises(ConfigError, match=r'^binary\.yaml: not a text \(UTF-8\) file'):
        load_config(p)
    # a clamp up to 4x the rated torque current is a drive's business
    assert load_config(overrides={'machine.isq_max': 14.0}).machine.isq_max == 14.0


def test_frozen() -> None:
    cfg = load_config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.machine.Rs = 1.0  # type: ignore[misc]
    assert math.isclose(cfg.machine.R_sigma, 3.7 + (0.205 / 0.2175) ** 2 * 2.1)
