"""The standstill-ripple limit of the final choice (``--ripple-limit``):
the re-measured and applied gains are the best evaluated ones whose rms of isq* is within
the limit x the start's in both standstill windows, the start if none is.

A fake bench whose loss falls towards a point that ripples (rms grows with k_pw's
coordinate), so the unlimited choice breaks the limit; then the same run with the limit,
its summary, a resume, and the tuner's and study's options.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from test_tuning import fake_measurement

from im_controller.config import GAIN_NAMES, Gains
from im_drive_sim.cli import UsageError
from im_tuner import optim
from im_tuner.rundir import RunDir
from im_tuner.runlog import RunConfig
from im_tuner.runlog.ripple import (
    DEFAULT_RIPPLE_LIMIT,
    RIPPLE_TOLERANCE,
    default_ripple_limit,
    parse_ripple_limit,
)
from im_tuner.space import load_params
from im_tuner.tuner_args import parse_options
from im_tuner.tuner_cli import _check_run, _new_run_config
from im_tuner.tuning import Measurement, TuningRun

SPACE = load_params().space
U_START = SPACE.start_u


class RippleBench:
    """Loss = 1 + |u - u*|^2 (u* = the start + 0.15, but 0.9 in k_pw: the loss wants a
    fast speed loop), standstill
    rms of isq* = 0.15 A (after the move) and 0.20 A (after the load) x (1 + 8 max(0,
    u_kpw - u_kpw,start)): the faster speed loop hunts at standstill, as on the plant."""

    def __init__(self, ripple_gain: float = 8.0) -> None:
        self.n = 0
        self.k = ripple_gain
        self.applied: Gains | None = None

    def ripple_of(self, u: np.ndarray) -> tuple[float, float, float, float]:
        f = 1.0 + self.k * max(0.0, float(u[0]) - float(U_START[0]))
        return (0.15 * f, 1.2 * f, 0.20 * f, 1.5 * f)

    def measure(self, gains: Gains) -> Measurement:
        u = SPACE.to_u(gains)
        target = np.clip(U_START + 0.15, 0.0, 1.0)
        target[0] = 0.9
        loss = 1.0 + float(np.sum((u - target) ** 2)) + 1e-3 * (self.n % 3)
        eid, self.n = self.n, self.n + 1
        return fake_measurement(eid, gains, loss, ripple=self.ripple_of(u))

    def apply(self, gains: Gains) -> None:
        self.applied = gains


def run_with(path: Path, limit: float | None, bench: RippleBench | None = None, **kw):
    bench = bench or RippleBench()
    opt = optim.make_optimizer('safe', 5, 11, U_START)
    run = TuningRun(
        RunDir.create(path),
        SPACE,
        opt,
        budget=40,
        satisfactory_loss=0.5,
        remeasure=3,
        ripple_limit=limit,
        **kw,
    )
    assert run.run(bench) == 'done'
    return run, bench


def ratio(bench: RippleBench, gains: Gains) -> float:
    r, s = bench.ripple_of(SPACE.to_u(gains)), bench.ripple_of(U_START)
    return max(r[0] / s[0], r[2] / s[2])


def test_without_the_limit_the_choice_ripples_with_it_it_does_not(tmp_path):
    free, bench0 = run_with(tmp_path / 'free', None)
    assert bench0.applied is not None and ratio(bench0, bench0.applied) > 2.0
    s0 = free.summary(outcome='done', wall_s=1.0)
    assert s0.ripple['limit'] is None and s0.ripple['bound'] is None
    assert s0.ripple['changed'] is False and s0.ripple['applied_within'] is None

    told: list[tuple[float, float]] = []  # (measured, told) per evaluation
    bench = RippleBench()
    opt = optim.make_optimizer('safe', 5, 11, U_START)
    tell = opt.tell_measurement

    def spy(u, loss, aborted):
        told.append((float(u[0]), loss))
        return tell(u, loss, aborted)

    opt.tell_measurement = spy  # type: ignore[method-assign]
    lim = TuningRun(RunDir.create(tmp_path / 'lim'), SPACE, opt, budget=40,
                    satisfactory_loss=0.5, remeasure=3, ripple_limit=1.5)  # fmt: skip
    assert lim.run(bench) == 'done'
    g = bench.applied
    assert g is not None and g != Gains(*SPACE.start)
    assert ratio(bench, g) <= 1.5 < ratio(bench, bench0.applied)
    # above the limit's tolerance the optimiser is told max(L (1 + (r - 1)), the best L
    # so far within the limit), r = rms / (1.5 x the start's); up to it, L
    evals = [r for r in lim.records if r.kind == 'eval']
    assert len(told) == len(evals) == 40
    above, quiet = 0, math.inf
    for rec, (_, t) in zip(evals, told, strict=True):
        r = ratio(bench, Gains(*(rec.gains[n] for n in GAIN_NAMES))) / 1.5
        if r > RIPPLE_TOLERANCE:
            assert t == pytest.approx(max(rec.loss * r, quiet), rel=1e-12)
            above += 1
        else:
            assert t == rec.loss
        if r <= 1.0:
            quiet = min(quiet, rec.loss)
    assert above >= 3  # (it tried louder gains, and was told they cost)
    # so the search differs from the free one's, and stays within the limit at the end
    assert [r.loss for r in free.records if r.kind == 'eval'] != [r.loss for r in evals]
    rem1 = [r.eval for r in lim.records if r.kind == 'remeasure']
    assert len(rem1) == 3
    by = {r.eval: r for r in evals}
    for i in rem1:  # every re-measured point is within the limit
        assert ratio(bench, Gains(*(by[i].gains[n] for n in GAIN_NAMES))) <= 1.5
    s = lim.summary(outcome='done', wall_s=1.0)
    rip = s.ripple
    assert rip['limit'] == 1.5
    assert rip['bound'] == pytest.approx({'rms_after_move': 0.225, 'rms_after_load': 0.30})
    assert rip['start']['rms_after_move'] == pytest.approx(0.15)
    assert rip['applied']['rms_after_move'] <= 0.225 and rip['applied_within'] is True
    assert rip['fallback'] is False and s.applied['eval'] in rem1
    # the summary's and the report's line
    from im_tuner.progress import mechanics_lines

    kept = (
        '; it kept out evaluation' + 's' * (len(rip['excluded']) > 1) + ' '
        + ', '.join(str(i) for i in rip['excluded'])
        if rip['changed']
        else '; it changed nothing'
    )  # fmt: skip
    assert mechanics_lines(s)[-1] == (
        "  ripple limit 1.5x the start's (0.225/0.300 A rms): applied gains within it" + kept
    )
    assert mechanics_lines(s0)[-1] == '  ripple limit: off'
    # the price: the limited choice's loss is higher than the free one's
    assert s.applied['loss'] > s0.applied['loss']


class Everywhere(RippleBench):
    """The standstill rms grows with any change of the gains: only the start is within."""

    def ripple_of(self, u):
        f = 1.0 + 50.0 * float(np.sum(np.abs(u - U_START)))
        return (0.15 * f, 1.2 * f, 0.20 * f, 1.5 * f)


def test_with_no_point_within_the_limit_the_start_stays(tmp_path):
    # safe's evaluation 1 is the start itself (within); told the louder points' cost, it
    # stays near the start: what it re-measures is within, the start stays applied
    run, bench = run_with(tmp_path / 'safe', 1.2, Everywhere())
    assert bench.applied == Gains(*SPACE.start)
    rem = [r for r in run.records if r.kind == 'remeasure']
    assert rem and all(ratio(bench, Gains(*(r.gains[n] for n in GAIN_NAMES))) <= 1.2 for r in rem)
    s = run.summary(outcome='done', wall_s=1.0)
    assert s.ripple['fallback'] is False and s.ripple['applied_within'] is True
    assert s.ripple['applied']['rms_after_move'] == pytest.approx(0.15)
    # neCGA never measures the start: nothing is within, nothing re-measured, the start
    # stays and the summary says why
    opt = optim.make_optimizer('necga', 5, 11, None)
    run = TuningRun(RunDir.create(tmp_path / 'necga'), SPACE, opt, budget=30,
                    satisfactory_loss=0.5, remeasure=3, ripple_limit=1.2)  # fmt: skip
    bench = Everywhere()
    assert run.run(bench) == 'done'
    assert bench.applied == Gains(*SPACE.start)
    assert not [r for r in run.records if r.kind == 'remeasure']
    s = run.summary(outcome='done', wall_s=1.0)
    assert s.applied['source'] == 'reference' and s.ripple['fallback'] is True
    assert s.best['loss'] < s.reference['loss']  # (it found lower losses: all too loud)


def test_a_resumed_run_keeps_its_limit(tmp_path):
    """The limit goes from the command line to run.yaml and from run.yaml to the resumed
    run (``make_tuning``): killed after 25 evaluations, resumed, the same choice as the
    run left alone."""
    from im_tuner.tuner_cli import make_tuning

    new = _new('--seed', '11', '--opt', 'first=none', '--budget', '40')
    assert new.run.ripple_limit == 1.5
    whole = make_tuning(RunDir.create(tmp_path / 'whole'), new.run, new.params, None)
    assert whole.ripple_limit == 1.5 and whole.run(bench := RippleBench()) == 'done'
    part = make_tuning(RunDir.create(tmp_path / 'part'), new.run, new.params, None)
    b2 = RippleBench()
    assert part.run(b2, should_stop=lambda: part.state.evals >= 25) == 'interrupted'
    run = RunConfig.from_text(new.run.to_text())  # (run.yaml read back)
    again = make_tuning(RunDir(tmp_path / 'part'), run, new.params, None)
    assert again.ripple_limit == 1.5 and again.restore() > 25
    assert again.run(b2) == 'done'
    assert b2.applied == bench.applied and bench.applied != Gains(*SPACE.start)
    s = again.summary(outcome='done', wall_s=1.0)
    assert s.ripple['changed'] is True and s.ripple['applied_within'] is True


# -- the options -------------------------------------------------------------------------------
def _new(*args: str):
    argv = ['tuner', *args]
    return _new_run_config(parse_options(argv[1:]), argv)


def test_the_default_is_on_for_safe_off_for_the_papers_algorithms():
    assert DEFAULT_RIPPLE_LIMIT == 1.5
    assert default_ripple_limit('safe') == 1.5
    assert all(default_ripple_limit(a) is None for a in optim.ALGOS if a != 'safe')
    assert _new('--seed', '3', '--opt', 'first=none').run.ripple_limit == 1.5
    assert _new('--algo', 'necga', '--seed', '3').run.ripple_limit is None
    assert _new('--algo', 'spsa', '--seed', '3', '--ripple-limit', '2').run.ripple_limit == 2.0
    assert (
        _new('--seed', '3', '--opt', 'first=none', '--ripple-limit', 'off').run.ripple_limit is None
    )
    # without a reference the start's ripple is unknown: off by default, refused if given
    assert _new('--seed', '3', '--opt', 'first=none', '--no-reference').run.ripple_limit is None
    # written to run.yaml, off as null (a resume reads it back)
    text = _new('--algo', 'necga', '--seed', '3').run.to_text()
    assert 'ripple_limit: null' in text
    assert RunConfig.from_text(text).ripple_limit is None


@pytest.mark.parametrize(
    'args, expect',
    [
        (['--ripple-limit', '0.5'], "--ripple-limit: a ratio >= 1 or 'off', got '0.5'"),
        (['--ripple-limit', 'inf'], "--ripple-limit: a ratio >= 1 or 'off', got 'inf'"),
        (['--ripple-limit', 'loud'], "--ripple-limit: a ratio >= 1 or 'off', got 'loud'"),
        (['--ripple-limit', '1.5', '--no-reference'], 'not with --no-reference'),
    ],
)
def test_bad_limits_are_one_line(args, expect):
    with pytest.raises(UsageError) as exc:
        _new('--seed', '3', '--opt', 'first=none', *args)
    assert expect in str(exc.value) and '\n' not in str(exc.value)


def test_a_run_file_with_a_bad_limit_is_refused():
    run = _new('--algo', 'necga', '--seed', '3').run
    for bad in (0.5, 'x', True, math.inf):
        run.ripple_limit = bad
        with pytest.raises(UsageError, match='ripple_limit must be a ratio >= 1 or null'):
            _check_run(run, 'run.yaml')
    run.ripple_limit = 1.5
    _check_run(run, 'run.yaml')


def test_parse():
    assert parse_ripple_limit('off') is None and parse_ripple_limit('OFF') is None
    assert parse_ripple_limit('1') == 1.0 and parse_ripple_limit('2.5') == 2.5
    for bad in ('0.99', '-1', 'nan', '', '1.5x'):
        with pytest.raises(ValueError):
            parse_ripple_limit(bad)


def test_the_issues_necga_run_on_the_paper_drive():
    """The motivating run: the paper's drive (`ideal`), `--algo necga --budget 30 --seed 2`:
    its choice hunts at standstill (0.585/0.587 A rms, 4.6 A peak-to-peak: 3.8x the
    start's 0.155/0.198 A).  With --ripple-limit 1.5 the search is told its loud points'
    cost and nothing quiet beats the start in 30 evaluations: the start stays, the three
    best (loud) evaluations kept out.  With the paper's 200 evaluations it finds quiet
    gains: 0.071/0.167 A rms at a re-measured loss 0.504 (0.458 loud, without; 0.519
    before the search's RIPPLE_TOLERANCE, which lets it try gains near the bound)."""
    from im_drive_sim.drive_file import load_config
    from im_tuner.offline import OfflineBench
    from im_tuner.runlog import MemoryRecord
    from im_tuner.tuning import run_seeds

    drive = load_config(None)
    got = {}
    for budget, limit in ((30, None), (30, 1.5), (200, None), (200, 1.5)):
        opt_ss, drive_seed = run_seeds(2)
        opt = optim.make_optimizer('necga', SPACE.dim, opt_ss, None)
        run = TuningRun(MemoryRecord(), SPACE, opt, budget=budget, satisfactory_loss=0.85,
                        remeasure=3, ripple_limit=limit)  # fmt: skip
        assert run.run(OfflineBench(drive, drive_seed, None)) == 'done'
        got[budget, limit] = run.summary(outcome='done', wall_s=0.0)
    free, lim = got[30, None].ripple, got[30, 1.5].ripple
    start = free['start']
    assert start == lim['start']
    assert start['rms_after_move'] == pytest.approx(0.155, abs=0.001)
    assert start['rms_after_load'] == pytest.approx(0.198, abs=0.001)
    assert free['applied']['rms_after_move'] == pytest.approx(0.585, abs=0.001)
    assert free['applied']['pp_after_move'] == pytest.approx(4.595, abs=0.001)
    assert got[30, None].applied['eval'] == 25 and free['changed'] is False
    assert got[30, 1.5].applied['source'] == 'reference' and lim['applied'] == start
    assert lim['changed'] is True and lim['excluded'] == [24, 5, 26]
    free, lim = got[200, None], got[200, 1.5]
    assert free.applied['remeasured_loss'] == pytest.approx(0.4576, abs=1e-4)
    assert free.ripple['applied']['rms_after_load'] == pytest.approx(0.281, abs=0.001)
    assert lim.applied['remeasured_loss'] == pytest.approx(0.5040, abs=1e-4)
    for k in ('rms_after_move', 'rms_after_load'):
        assert lim.ripple['applied'][k] <= 1.5 * start[k]
    assert lim.ripple['applied']['rms_after_move'] == pytest.approx(0.071, abs=0.001)


def test_a_study_run_that_keeps_its_start_reports_the_starts_loss():
    """A study row with the limit (``study --ripple-limit``): a neCGA run of 4 evaluations
    on the paper's drive finds nothing within 1.0x the start's ripple, so the start stays:
    its re-measured column is the reference's loss (not left out of the mean), its ripple
    the start's; without the limit its best (louder) evaluation is re-measured."""
    from im_tuner.study.runs import run_one
    from im_tuner.study.spec import StudySpec

    lim = run_one(StudySpec(runs=1, budget=4, algos=('necga',), ripple_limit=1.0), 1, 0)
    assert lim.remeasured == lim.ref_loss == pytest.approx(0.9803, abs=1e-4)
    assert lim.ripple[2:] == lim.ripple[:2] and lim.ripple_changed
    assert lim.ripple[0] == pytest.approx(0.1546, abs=1e-4)
    free = run_one(StudySpec(runs=1, budget=4, algos=('necga',), ripple_limit=None), 1, 0)
    assert math.isfinite(free.remeasured) and free.remeasured != free.ref_loss
    assert not free.ripple_changed


def test_a_study_run_reports_the_loss_of_what_it_leaves_applied():
    """With a ripple limit the study's re-measured column is the applied gains' loss: a
    run whose re-measured point failed the limit on the mean of its experiments (its
    search ended among loud points: im750w-j1 on the per-drive bench, run 17 of 25, left
    its start applied after 200 evaluations while the column said 0.604) reports the
    applied evaluation's loss measured once more, or the reference's when the start stays;
    without a limit, and where the applied point is the re-measured one, the best's
    re-measurement."""
    from types import SimpleNamespace as NS

    from im_tuner.study.runs import applied_loss

    ref = NS(eval=-1, loss=1.04)
    rem = [NS(eval=23, loss=0.628)]
    at = {'eval': 23, 'loss': 0.60}
    other = {'eval': 40, 'loss': 0.59}
    start = {'eval': -1, 'loss': 1.04}
    assert applied_loss(at, ref, rem, limited=True) == 0.628  # applied = re-measured
    assert applied_loss(other, ref, rem, limited=False) == 0.628  # no limit: as before
    # the next best within it: one more experiment of it (its search loss is the least
    # of many, biased low), nan without one
    assert applied_loss(other, ref, rem, limited=True, again=0.605) == 0.605
    assert math.isnan(applied_loss(other, ref, rem, limited=True))
    assert applied_loss(start, ref, rem, limited=True) == 1.04  # the start stays
    assert applied_loss(start, ref, [], limited=True) == 1.04  # nothing within the limit
    assert math.isnan(applied_loss(other, ref, [], limited=False))  # nothing re-measured
    assert math.isnan(applied_loss(None, ref, [], limited=True))
    # a run with two re-measured points applies the second: its re-measurement
    two = [*rem, NS(eval=40, loss=0.61)]
    assert applied_loss(other, ref, two, limited=True) == 0.61


def test_one_loud_experiment_within_the_tolerance_is_told_its_loss_the_choice_stays_strict():
    """On ``bench`` one experiment's standstill rms scatters about its gains' mean (the
    random load, the current sensor's noise), so the search penalises an experiment only
    above RIPPLE_TOLERANCE x the bound; the floor L_quiet and the final choice keep the
    strict bound (the mean over the gains' experiments)."""
    from im_tuner.runlog.records import Evaluation, Reference
    from im_tuner.runlog.ripple import ripple_bound, told_loss, within_limit

    assert 1.0 < RIPPLE_TOLERANCE < DEFAULT_RIPPLE_LIMIT
    start = {'rms_after_move': 0.2, 'rms_after_load': 0.3}
    ref = Reference(eval=-1, status='ok', gains={'k': 0.0}, loss=1.0, terms=[1.0, 0, 0],
                    aborted=False, ripple=start)  # fmt: skip

    def ev(i: int, loss: float, r: float) -> Evaluation:
        """Evaluation i, its rms r x the bound (1.5 x the start's) after the load."""
        rip = {'rms_after_move': 0.2, 'rms_after_load': r * 1.5 * 0.3}
        return Evaluation(eval=i, status='ok', gains={'k': float(i + 1)}, u=[0.0] * 5,
                          loss=loss, terms=[loss, 0, 0], aborted=False, ripple=rip)  # fmt: skip

    tol = RIPPLE_TOLERANCE
    quiet, scattered, loud, louder = (
        ev(0, 0.8, 0.9),
        ev(1, 0.6, tol - 0.01),
        ev(2, 0.5, tol + 0.05),
        ev(3, 0.7, 2.0),
    )
    recs = [ref, quiet, scattered, loud, louder]
    bound = ripple_bound(recs, 1.5)
    assert bound == pytest.approx({'rms_after_move': 0.3, 'rms_after_load': 0.45})
    told = [told_loss(recs[: i + 1], x, 1.5) for i, x in enumerate(recs[1:])]
    # within the limit, and one experiment up to the tolerance over it: the loss measured
    assert told[:2] == [0.8, 0.6]
    # above the tolerance: L (1 + (r - 1)), not below the best loss within the limit (0.8;
    # the tolerated experiment is not within it)
    assert told[2] == pytest.approx(0.8) and told[3] == pytest.approx(1.4)
    # the choice: the tolerated gains' mean rms is over the bound, so they are no candidate
    assert within_limit(recs, quiet.gains, bound) and not within_limit(recs, scattered.gains, bound)
    # without a limit every experiment is told its loss
    assert [told_loss(recs[: i + 1], x, None) for i, x in enumerate(recs[1:])] == [
        0.8,
        0.6,
        0.5,
        0.7,
    ]
    # a window where the start rests at rms 0 bounds nothing (nothing to be louder than)
    still = Reference(eval=-1, status='ok', gains={'k': 0.0}, loss=1.0, terms=[1.0, 0, 0],
                      aborted=False, ripple={**start, 'rms_after_load': 0.0})  # fmt: skip
    assert ripple_bound([still], 1.5) == pytest.approx({'rms_after_move': 0.3})
    # (one louder than the bound after the move is still told so; after the load, none is)
    assert told_loss([still, quiet], loud, 1.5) == 0.5
    assert told_loss([still, quiet], louder, 1.5) == 0.7
