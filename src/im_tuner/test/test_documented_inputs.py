"""The pure side of each case found broken on a documented path, checked at
the unit that decides it (the command-line side: test/test_documented_paths.py).

* a user's drive file on a packaged base takes that drive's gains, box and first step;
  ``--drive-config NAME --params FILE`` with another drive's box runs without a model step;
* a first step computed for one drive never goes to a controller of another;
* results.jsonl out of the tuner's order is refused, naming the line;
* a summary.json of a newer format is refused, not taken for a killed session;
* a study row whose runs all aborted is named, not averaged away (test_study_drives.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from im_drive_sim.drive_file import load_config
from im_tuner import family
from im_tuner.runlog.records import RecordError, parse_results

BIG = 'base: im7500w-j3\nmachine:\n  isq_max: 30.0  # [A] this drive clamps lower\n'


def _big(tmp_path: Path) -> Path:
    p = tmp_path / 'big.yaml'
    p.write_text(BIG)
    return p


def test_a_users_file_on_a_bigger_base_takes_that_drives_setup(tmp_path):
    """docs/drive-family.md's own example (``base: im7500w-j3``): before, the paper's box
    and experiment, the start aborted on the model and prior.py raised StopIteration."""
    from im_tuner.offline import OfflineBench

    mine, base = family.tuner_setup(_big(tmp_path)), family.tuner_setup('im7500w-j3')
    assert mine is not None and base is not None
    assert mine.params == base.params  # the box and the start of im7500w-j3
    assert mine.experiment.trajectory == base.experiment.trajectory
    assert mine.experiment.loss == base.experiment.loss
    assert mine.experiment.fallback_gains == base.experiment.fallback_gains
    assert mine.experiment.fallback_gains.k_pw > 5.0  # not the paper's 0.15 A s/rad
    assert (mine.experiment.control.isq_max, mine.drive.machine.isq_max) == (30.0, 30.0)
    assert family.controller_parameters(mine) == family.controller_parameters(base)
    # the start does not abort on that drive (it did with the paper's gains)
    bench = OfflineBench(mine.drive, 0, mine.experiment)
    ms = [bench.measure(mine.experiment.fallback_gains) for _ in range(2)]
    assert not any(m.aborted for m in ms) and all(0.9 < m.loss < 1.1 for m in ms)
    # a file on the paper's motor keeps the paper's defaults, as before
    small = tmp_path / 'small.yaml'
    small.write_text('base: paper_750w\nmachine:\n  isq_max: 5.0\n')
    s = family.tuner_setup(small)
    assert s is not None and family.controller_parameters(s) == ()
    # a file on a base of its own (no packaged drive under it): the defaults
    (tmp_path / 'motor.yaml').write_text(load_config(None).to_dict().__repr__())
    own = tmp_path / 'own.yaml'
    own.write_text('base: motor.yaml\n')
    (tmp_path / 'motor.yaml').write_text(json.dumps(load_config(None).to_dict()))
    assert load_config(own).machine.J == 2.5e-3 and family.tuner_setup(own) is None


def _new(*args: str):
    from im_tuner.tuner_args import parse_options
    from im_tuner.tuner_cli import _new_run_config

    argv = ['tuner', *args]
    return _new_run_config(parse_options(argv[1:]), argv)


def test_the_tuner_on_a_users_bigger_drive_takes_its_first_step_and_box(tmp_path):
    from im_tuner.prior import model_prior

    big = _big(tmp_path)
    setup = family.tuner_setup(big)
    assert setup is not None
    run = _new('--seed', '3', '--drive-config', str(big))
    assert run.run.options == {'first': 'identify'}  # the default: after the start
    prior = model_prior(load_config(big), setup.params.space, setup.experiment)
    assert prior is not None and prior.worst_ratio < 1.0
    model = _new('--seed', '3', '--drive-config', str(big), '--opt', 'first=model')
    assert model.run.options == {'first': list(prior.u)}
    assert run.params == setup.params  # the box the optimiser searches
    none = _new('--seed', '3', '--drive-config', str(big), '--opt', 'first=none')
    assert none.run.options == {'first': 'none'}


def test_a_box_of_another_drive_runs_without_a_model_step(tmp_path):
    """``--drive-config im7500w-j3 --params FILE`` with the paper's box: its start aborts
    on the 7.5 kW model; no first step from the model (it raised StopIteration)."""
    from im_drive_sim.params import default_config_path

    paper_box = default_config_path().parent.parent.parent / 'im_tuner' / 'config' / 'tuner.yaml'
    assert paper_box.is_file()
    args = ('--seed', '3', '--drive-config', 'im7500w-j3', '--params', str(paper_box))
    assert _new(*args, '--opt', 'first=model').run.options == {'first': 'none'}
    # identify decides after the start's experiments (an aborted start identifies nothing)
    assert _new(*args).run.options == {'first': 'identify'}


def test_a_first_step_of_one_drive_never_goes_to_another_drives_controller(tmp_path):
    from im_tuner.prior import model_drive_mismatch

    big = _big(tmp_path)
    assert model_drive_mismatch(None, '') is None
    assert model_drive_mismatch(None, 'paper_750w') is None
    assert model_drive_mismatch('im7500w-j3', 'im7500w-j3') is None
    same = tmp_path / 'same.yaml'
    same.write_text('base: im7500w-j3\nTs: 200.0e-6\n')
    assert model_drive_mismatch(str(same), 'im7500w-j3') is None  # the same machine
    assert model_drive_mismatch(str(big), 'im7500w-j3') is not None  # its clamp differs
    why = model_drive_mismatch(None, 'im7500w-j3')
    assert why is not None and len(why.splitlines()) == 1
    assert why.startswith('--opt first=model: the controller drives im7500w-j3')
    assert 'give --drive-config im7500w-j3 (or --opt first=none)' in why
    assert 'give --drive-config paper_750w' in str(model_drive_mismatch('im3700w-j1', ''))
    # a drive file the tuner cannot read here (a drive host's): judged by the names
    assert model_drive_mismatch('far.yaml', 'far.yaml') is None
    assert model_drive_mismatch(None, 'far.yaml') is not None


# -- results.jsonl in the tuner's order -------------------------------------------------------
def _line(kind: str, index: int, status: str = 'ok') -> dict:
    rec = {'kind': kind, 'eval': index, 'gains': {'k_pw': 1.0}, 'status': status}
    if kind == 'eval':
        rec['u'] = [0.5]
    if status in ('ok', 'aborted'):
        rec |= {'loss': 1.0, 'terms': [1.0, 0.0, 0.0], 'aborted': status == 'aborted'}
    return rec


def _raw(*recs: dict) -> bytes:
    return b''.join(json.dumps(r).encode() + b'\n' for r in recs)


GOOD = (
    _line('reference', -1, 'lost'),
    _line('reference', -1),
    _line('eval', 0),
    _line('eval', 1, 'lost'),
    _line('eval', 1, 'aborted'),
    _line('eval', 2),
    _line('remeasure', 2, 'lost'),
    _line('remeasure', 2),
    _line('remeasure', 0),
)


def test_results_in_the_tuners_order_are_read():
    recs, end = parse_results(_raw(*GOOD))
    assert [(r.kind, r.eval, r.status) for r in recs] == [
        (r['kind'], r['eval'], r['status']) for r in GOOD
    ]
    assert end == len(_raw(*GOOD))


@pytest.mark.parametrize(
    'recs, says',
    [
        ((*GOOD[:6], GOOD[5]), 'line 7: evaluation 2 again (it was measured on line 6)'),
        ((*GOOD[:3], GOOD[5]), 'line 4: evaluation 2, but evaluation 1 is missing'),
        ((*GOOD[:3], _line('remeasure', 7)), 'line 4: re-measurement of evaluation 7, which'),
        ((*GOOD[:5], _line('remeasure', 1)), 'line 6: re-measurement of evaluation 1, which'),
        ((*GOOD, GOOD[7]), 'line 10: evaluation 2 re-measured again (first on line 8)'),
        ((*GOOD[:2], GOOD[1]), 'line 3: a second measured reference (the first is line 2)'),
        ((_line('reference', 0),), 'line 1: a reference record with eval 0'),
        ((_line('eval', 1, 'lost'),), 'line 1: evaluation 1, but evaluation 0 is missing'),
    ],
    ids=['eval-twice', 'eval-skipped', 'remeasure-none', 'remeasure-aborted', 'remeasure-twice',
         'reference-twice', 'reference-index', 'lost-ahead'],
)  # fmt: skip
def test_results_out_of_order_are_refused_naming_the_line(recs, says):
    with pytest.raises(RecordError) as err:
        parse_results(_raw(*recs))
    assert str(err.value).startswith(says), str(err.value)
    assert len(str(err.value).splitlines()) == 1


def test_a_summary_of_a_newer_format_is_refused_not_taken_for_a_killed_session(tmp_path):
    from im_tuner.rundir import RunDir, RunDirError
    from im_tuner.runlog import Summary

    rd = RunDir(tmp_path)
    assert rd.read_summary() is None  # none: a killed session
    (tmp_path / 'summary.json').write_text('{"outcome": "done"')
    assert rd.read_summary() is None  # not one (the records are the truth)
    rd.write_summary(Summary(outcome='done', evaluations=3))
    assert rd.read_summary() == Summary(outcome='done', evaluations=3)
    (tmp_path / 'summary.json').write_text(json.dumps({'version': 99, 'outcome': 'done'}))
    with pytest.raises(RunDirError, match=r'summary\.json: format version 99: this im_tuner'):
        rd.read_summary()
