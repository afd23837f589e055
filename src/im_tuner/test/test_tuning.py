"""The pure tuning loop (im_tuner.tuning), search space and run directory, with a fake bench.

The fake bench is deterministic (loss = a quadratic of the gains plus an experiment
counter term, so the plant history matters like on the real bench), can lose results
and abort experiments on demand, and records every call.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from im_controller.config import GAIN_NAMES, Gains
from im_tuner import optim
from im_tuner.rundir import RunDir, RunDirError
from im_tuner.runlog import Record, RunConfig
from im_tuner.space import TunerParamsError, load_params, parse_params
from im_tuner.tuning import (
    BenchFailure,
    LostEvaluation,
    Measurement,
    ResumeError,
    StopRequested,
    TuningRun,
    replay,
)

PARAMS = load_params()
SPACE = PARAMS.space


def fake_measurement(eid: int, gains: Gains, loss: float, **kw) -> Measurement:
    """Experiment ``eid`` of a fake bench: a completed 5625-period experiment of ``gains``
    every period fresh, one a second of sim time, directions alternating; ``kw`` overrides."""
    return Measurement(
        **{
            'loss': loss,
            'terms': (loss, 0.0, 0.0),
            'aborted': False,
            'reason': '',
            'fault': False,
            'experiment_id': eid,
            'direction': 1 - 2 * (eid % 2),
            'steps': 5625,
            'trip_step': -1,
            't_start_ns': eid * 10**9,
            't_end_ns': eid * 10**9 + 1125 * 10**6,
            'wall_s': 0.001,
            'gains': gains.as_tuple(),
            'fresh': 5625,
            **kw,
        }
    )


class FakeBench:
    """Loss = |u - u*|^2 + 1e-3 * (experiments so far mod 3): history-dependent."""

    def __init__(
        self, lose: set[int] = frozenset(), abort_above: float = 0.9, stop_at: int | None = None
    ) -> None:
        self.calls: list[tuple[float, ...]] = []
        self.lose = set(lose)  # call indices whose result is lost
        self.off_timing: set[int] = set()  # call indices holding 7 periods
        self.tolerance = 0  # held periods an experiment may have (the controller's)
        self.abort_above = abort_above
        self.stop_at = stop_at
        self.applied: Gains | None = None
        self.experiments = 0

    def measure(self, gains: Gains) -> Measurement:
        k = len(self.calls)
        if self.stop_at is not None and k == self.stop_at:
            raise StopRequested()
        self.calls.append(gains.as_tuple())
        eid = self.experiments
        self.experiments += 1
        if k in self.lose:
            raise LostEvaluation('no loss', experiment_id=eid)
        u = SPACE.to_u(gains)
        loss = float(np.sum((u - 0.3) ** 2)) + 1e-3 * (eid % 3)
        aborted = loss > self.abort_above
        return fake_measurement(
            eid,
            gains,
            loss * (10.0 if aborted else 1.0),
            terms=(loss, 0.0, 0.0),
            aborted=aborted,
            reason='term1' if aborted else '',
            fresh=5625 - 7 * (k in self.off_timing),
            held=7 * (k in self.off_timing),
            timing=k in self.off_timing and self.tolerance < 7,
        )

    def apply(self, gains: Gains) -> None:
        self.applied = gains


def make_run(path: Path, algo: str = 'necga', budget: int = 30, **kw) -> TuningRun:
    rd = RunDir.create(path)
    start = SPACE.start_u if algo in optim.TAKES_START else None
    opt = optim.make_optimizer(algo, 5, 7, start)
    return TuningRun(rd, SPACE, opt, budget=budget, satisfactory_loss=0.2, **kw)


def records(path: Path) -> list[Record]:
    return RunDir(path).read_results()


@pytest.mark.parametrize('algo', ['necga', 'spsa'])
def test_run_counts_evaluations_and_tracks_the_best(tmp_path, algo):
    bench = FakeBench()
    run = make_run(tmp_path / 'r', algo)
    assert run.run(bench) == 'done'
    recs = records(tmp_path / 'r')
    evals = [r for r in recs if r.kind == 'eval']
    assert len(evals) == 30 == run.state.evals == run.opt.evaluations
    assert recs[0].kind == 'reference' and recs[0].gains == dict(
        zip(GAIN_NAMES, SPACE.start, strict=True)
    )
    ok = [r for r in evals if not r.aborted]
    assert any(r.aborted for r in evals) or algo == 'spsa'
    best = min(ok, key=lambda r: r.loss)
    assert run.state.best['eval'] == best.eval and run.state.best['loss'] == best.loss
    # the best is never an aborted one, even when its penalised loss would be smaller
    assert all(not evals[i].aborted for i in [run.state.best['eval']])
    rem = [r for r in recs if r.kind == 'remeasure']
    assert [r.eval for r in rem] == [r.eval for r in sorted(ok, key=lambda r: r.loss)[:3]]
    pick = min(rem, key=lambda r: r.loss)
    assert bench.applied == Gains(*(pick.gains[n] for n in GAIN_NAMES))
    s = run.summary(outcome='done', wall_s=1.0)
    assert s.evaluations == 30 and s.experiments == len(recs)
    assert s.sim_s == pytest.approx(1.125 * len(recs))
    sat = next(i + 1 for i, r in enumerate(evals) if not r.aborted and r.loss <= 0.2)
    assert s.evaluations_to_satisfactory == sat
    assert len(run.state.opt_us) == 30
    json.loads(s.to_text())  # (to_text: no NaN/inf)


def test_lost_result_is_rerun_with_the_same_gains(tmp_path):
    bench = FakeBench(lose={3, 4})  # calls 3 and 4 = evaluation 2, attempts 1 and 2
    run = make_run(tmp_path / 'r', budget=5, remeasure=0)
    assert run.run(bench) == 'done'
    # calls: 0 the reference, 1 evaluation 0, 2 evaluation 1, 3-5 evaluation 2
    assert bench.calls[3] == bench.calls[4] == bench.calls[5] != bench.calls[6]
    recs = records(tmp_path / 'r')
    assert [(r.kind, r.eval, r.attempt, r.status) for r in recs[2:5]] == [
        ('eval', 1, 1, recs[2].status),
        ('eval', 2, 1, 'lost'),
        ('eval', 2, 2, 'lost'),
    ]
    assert recs[5].attempt == 3 and recs[5].status in ('ok', 'aborted')
    assert run.state.lost == 2 and run.state.evals == 5 and run.opt.evaluations == 5
    assert run.state.experiments == len(recs)  # lost ones ran on the bench too


def test_off_timing_result_is_rerun_never_told_and_counted(tmp_path):
    bench = FakeBench()
    bench.off_timing = {3, 4}  # evaluation 2, attempts 1 and 2
    run = make_run(tmp_path / 'r', budget=5, remeasure=0)
    assert run.run(bench) == 'done'
    assert bench.calls[3] == bench.calls[4] == bench.calls[5] != bench.calls[6]
    recs = records(tmp_path / 'r')
    off = [r for r in recs if r.status == 'timing']
    assert [(r.eval, r.attempt) for r in off] == [(2, 1), (2, 2)]
    for r in off:
        # the measured number is kept under another name, never as the loss
        assert r.loss is None and isinstance(r.off_timing_loss, float)
        assert r.periods == {'fresh': 5618, 'held': 7, 'late': 0}
        assert r.reason == 'timing: 7 held and 0 late of 5625 drive periods'
    assert recs[5].status in ('ok', 'aborted') and recs[5].periods['held'] == 0
    # the optimiser was told 5 losses, none of them off timing; the summary counts them
    assert run.state.timing == 2 and run.state.evals == 5 and run.opt.evaluations == 5
    assert run.summary(outcome='done', wall_s=1.0).timing == 2
    # a resume rebuilds the same counters from results.jsonl
    again = make_run_from(RunDir(tmp_path / 'r'), budget=5, remeasure=0)
    assert again.restore() == len(recs) and again.state.timing == 2


def test_an_attempt_off_timing_asks_for_the_tolerance_before_the_next(tmp_path):
    """``off_timing`` (``--timing-tolerance auto``: the host checked again) is called after
    each attempt off the timing, before the next; the tolerance it returns judges the next
    attempts (on the controller: here the fake bench) and is the summary's."""
    bench = FakeBench()
    bench.off_timing = {3, 4, 6}  # evaluation 2's attempts 1 and 2, evaluation 3
    run = make_run(tmp_path / 'r', budget=5, remeasure=0)
    run.timing_tolerance = 5
    asked: list[int] = []

    def louder() -> int | None:
        asked.append(len(run.records))
        bench.tolerance = 10  # (the controller, told)
        return 10

    run.off_timing = louder
    assert run.run(bench) == 'done'
    recs = records(tmp_path / 'r')
    assert [(r.eval, r.attempt, r.status) for r in recs if r.status == 'timing'] == [
        (2, 1, 'timing')
    ]
    assert asked == [4]  # after the 4th record (the reference, evaluations 0-1, the off one)
    assert recs[4].eval == 2 and recs[4].attempt == 2 and recs[4].periods['held'] == 7
    assert run.timing_tolerance == 10 and run.state.timing == 1
    assert run.summary(outcome='done', wall_s=1.0).timing_tolerance == 10


def test_results_lost_beyond_retries_end_the_run_with_best_applied(tmp_path):
    bench = FakeBench(lose={5, 6, 7})
    run = make_run(tmp_path / 'r', budget=10, retries=2)
    out = run.run(bench)
    assert out.startswith('failed: evaluation 5: no result after 3 attempts')
    assert run.state.evals == 4
    assert bench.applied is not None  # best so far (or the start) applied
    # the pending candidate is still pending: a resume re-runs it
    rd = RunDir(tmp_path / 'r')
    again = make_run_from(rd)
    again.restore()
    assert np.array_equal(again.opt.ask(), np.array(records(tmp_path / 'r')[-1].u))


def make_run_from(rd: RunDir, algo: str = 'necga', budget: int = 10, **kw) -> TuningRun:
    start = SPACE.start_u if algo in optim.TAKES_START else None
    opt = optim.make_optimizer(algo, 5, 7, start)
    return TuningRun(rd, SPACE, opt, budget=budget, satisfactory_loss=0.2, **kw)


@pytest.mark.parametrize('algo', ['necga', 'spsa', 'rcga', 'cmaes', 'tpe'])
def test_interrupted_then_resumed_equals_uninterrupted(tmp_path, algo):
    whole = make_run(tmp_path / 'whole', algo, budget=20)
    assert whole.run(FakeBench()) == 'done'
    part = make_run(tmp_path / 'part', algo, budget=20)
    bench = FakeBench(stop_at=9)
    assert part.run(bench) == 'interrupted'
    # a fresh process: new objects, restore from the files, replay the plant history
    rd = RunDir(tmp_path / 'part')
    resumed = make_run_from(rd, algo, budget=20)
    resumed.restore()
    bench2 = FakeBench()
    assert replay(bench2, resumed.records) == 9
    assert resumed.run(bench2) == 'done'
    key = lambda r: [getattr(r, k) for k in ('kind', 'eval', 'u', 'gains', 'loss', 'experiment_id')]  # noqa: E731
    assert [key(r) for r in records(tmp_path / 'whole')] == [
        key(r) for r in records(tmp_path / 'part')
    ]
    assert resumed.state.best == whole.state.best


def test_resume_catches_up_records_written_after_the_checkpoint(tmp_path):
    whole = make_run(tmp_path / 'whole', budget=12, remeasure=0)
    whole.run(FakeBench())
    # the same run killed between appending record 8 and 9 and writing their checkpoint
    part = make_run(tmp_path / 'part', budget=12, remeasure=0)
    bench = FakeBench(stop_at=7)
    part.run(bench)
    ck = (tmp_path / 'part' / 'checkpoint.json').read_text()
    extra = records(tmp_path / 'whole')[7:9]
    for r in extra:
        RunDir(tmp_path / 'part').append_result(r)
    (tmp_path / 'part' / 'checkpoint.json').write_text(ck)
    with open(tmp_path / 'part' / 'results.jsonl', 'a') as f:
        f.write('{"kind": "eval", "ev')  # torn line of a kill mid-write
    resumed = make_run_from(RunDir(tmp_path / 'part'), budget=12, remeasure=0)
    assert resumed.restore() == 9
    # restoring writes nothing: the caller cuts the torn line once it goes on
    assert (tmp_path / 'part' / 'results.jsonl').read_text().endswith('"ev')
    RunDir(tmp_path / 'part').cut_torn_tail()
    assert not (tmp_path / 'part' / 'results.jsonl').read_text().endswith('"ev')
    bench2 = FakeBench()
    replay(bench2, resumed.records)
    resumed.run(bench2)
    assert [r.loss for r in records(tmp_path / 'whole')] == [
        r.loss for r in records(tmp_path / 'part')
    ]


def test_resume_refuses_results_that_do_not_match_the_checkpoint(tmp_path):
    part = make_run(tmp_path / 'part', budget=12)
    part.run(FakeBench(stop_at=5))
    path = tmp_path / 'part' / 'results.jsonl'
    recs = records(tmp_path / 'part')
    ck = json.loads((tmp_path / 'part' / 'checkpoint.json').read_text())
    ck['records'] = 2  # pretend the checkpoint is older: records 2.. are caught up
    (tmp_path / 'part' / 'checkpoint.json').write_text(json.dumps(ck))
    lines = [r.to_dict() for r in recs]
    lines[3]['u'][0] = 0.123456  # ... but one of them is not what the optimiser asks
    path.write_text(''.join(json.dumps(r) + '\n' for r in lines))
    with pytest.raises(ResumeError, match='not what the checkpointed optimiser asks'):
        make_run_from(RunDir(tmp_path / 'part'), budget=12).restore()


def test_replay_detects_a_different_bench(tmp_path):
    part = make_run(tmp_path / 'part', budget=12)
    part.run(FakeBench(stop_at=5))
    other = FakeBench()
    other.experiments = 1  # a bench whose history differs: losses differ
    with pytest.raises(ResumeError, match='not the one of the run'):
        replay(other, records(tmp_path / 'part'))


def test_reference_stays_applied_when_nothing_beats_it(tmp_path):
    class StartIsBest(FakeBench):
        def measure(self, gains):
            m = super().measure(gains)
            start = gains.as_tuple() == SPACE.start
            return Measurement(**{**m.__dict__, 'loss': 0.01 if start else 5.0, 'aborted': False})

    bench = StartIsBest()
    run = make_run(tmp_path / 'r', budget=6)
    run.run(bench)
    assert bench.applied == Gains(*SPACE.start)
    assert run.summary(outcome='done', wall_s=1).applied['source'] == 'reference'


def test_a_fault_in_the_settle_is_re_run_and_never_told(tmp_path):
    """An experiment stopped by a safety fault in its standstill settle (before step 0:
    the fallback gains held, not one step of the candidate ran) measured nothing: it is
    recorded ``lost`` with the reason, the same gains run again, and the optimiser is
    told only the re-run's loss (its penalised loss, 0, would otherwise be the best)."""

    class SettleFault(FakeBench):
        def measure(self, gains):
            m = super().measure(gains)
            if len(self.calls) == 3:  # the 2nd evaluation's first attempt
                return Measurement(
                    **{
                        **m.__dict__,
                        'loss': 0.0,
                        'terms': (0.0, 0.0, 0.0),
                        'aborted': True,
                        'reason': 'max_speed',
                        'fault': True,
                        'steps': 0,
                        'fresh': 0,
                        'held': 0,
                    }
                )
            return m

    bench = SettleFault()
    run = make_run(tmp_path / 'r', budget=4)
    assert run.run(bench) == 'done'
    recs = records(tmp_path / 'r')
    lost = [r for r in recs if r.status == 'lost']
    assert len(lost) == 1 and lost[0].kind == 'eval' and lost[0].eval == 1
    assert lost[0].loss is None and 'settle, before step 0 (max_speed)' in lost[0].reason
    again = [r for r in recs if r.kind == 'eval' and r.eval == 1]
    assert again[0].status == 'lost' and again[1].attempt == 2
    assert again[1].status in ('ok', 'aborted')  # measured: told to the optimiser
    assert again[0].gains == again[1].gains  # the same gains, not a new candidate
    assert bench.calls[2] == bench.calls[3]
    assert run.opt.evaluations == 4 and run.state.best['loss'] > 0.0


def test_bench_failure_ends_the_run_cleanly(tmp_path):
    class Breaks(FakeBench):
        def measure(self, gains):
            if len(self.calls) == 4:
                raise BenchFailure('controller refused the gains')
            return super().measure(gains)

    bench = Breaks()
    run = make_run(tmp_path / 'r', budget=10)
    assert run.run(bench) == 'failed: controller refused the gains'
    assert bench.applied is not None and run.state.evals == 3


# -- search space ---------------------------------------------------------------------------
def test_default_params_are_the_papers_motor():
    assert PARAMS.space.start == (0.53, 20.0, 30.0, 0.005, 0.007)
    assert PARAMS.space.lo == (0.05, 0.0, 1.0, 0.0, 0.0)
    assert PARAMS.space.hi == (3.0, 200.0, 150.0, 0.05, 0.05)
    u = SPACE.start_u
    assert SPACE.to_gains(u).as_tuple() == pytest.approx(SPACE.start, rel=1e-15)
    assert SPACE.to_gains(np.ones(5)).as_tuple() == SPACE.hi


def _box(**over):
    box = {
        n: {'lo': lo, 'hi': hi, 'start': s}
        for n, lo, hi, s in zip(GAIN_NAMES, SPACE.lo, SPACE.hi, SPACE.start, strict=True)
    }
    for k, v in over.items():
        box[k] = v
    return {'search_box': box, 'satisfactory_loss': 0.85}


@pytest.mark.parametrize(
    'data, msg',
    [
        ([], 'expected a mapping'),
        ({'search_box': {}}, 'missing key satisfactory_loss'),
        ({**_box(), 'extra': 1}, "unknown key(s) ['extra']"),
        (_box(k_pw={'lo': 1.0, 'hi': 0.5, 'start': 0.7}), 'search_box.k_pw: lo must be below hi'),
        (_box(k_pw={'lo': 0.1, 'hi': 900, 'start': 0.7}), "leaves the controller's accepted range"),
        (_box(k_iw={'lo': 0.0, 'hi': 100.0, 'start': 150.0}), 'search_box.k_iw.start 150'),
        (_box(tau_eq={'lo': 0.0, 'hi': float('nan'), 'start': 0.0}), 'search_box.tau_eq.hi'),
        (_box(k_pos={'lo': True, 'hi': 10.0, 'start': 5.0}), 'search_box.k_pos.lo'),
        (_box(k_pos={'lo': 1.0, 'hi': 10.0}), 'search_box.k_pos must be'),
        ({**_box(), 'satisfactory_loss': -1}, 'satisfactory_loss must be > 0'),
    ],
)
def test_bad_parameter_files_name_the_key(data, msg):
    with pytest.raises(TunerParamsError, match=None) as ei:
        parse_params(data, 'f.yaml')
    assert msg in str(ei.value) and str(ei.value).startswith('f.yaml: ')


def test_parameter_file_read_errors(tmp_path):
    with pytest.raises(TunerParamsError, match='cannot read'):
        load_params(tmp_path / 'none.yaml')
    (tmp_path / 'bad.yaml').write_text('a: [1,\n')
    with pytest.raises(TunerParamsError, match='YAML syntax error at line 2'):
        load_params(tmp_path / 'bad.yaml')


# -- run directory ----------------------------------------------------------------------------
def test_run_directory_rules(tmp_path):
    rd = RunDir.create(tmp_path / 'a' / 'b')
    rd.write_run(RunConfig.from_dict({'algo': 'spsa', 'budget': 3, 'x': 1.5}))
    assert RunDir.open(rd.path).read_config().to_dict() == {'algo': 'spsa', 'budget': 3, 'x': 1.5}
    with pytest.raises(RunDirError, match='continue it with --resume'):
        RunDir.create(rd.path)
    (tmp_path / 'other').mkdir()
    (tmp_path / 'other' / 'f').write_text('x')
    with pytest.raises(RunDirError, match='not empty'):
        RunDir.create(tmp_path / 'other')
    with pytest.raises(RunDirError, match='not a tuning run'):
        RunDir.open(tmp_path / 'other')
    (tmp_path / 'file').write_text('x')
    with pytest.raises(RunDirError, match='cannot create'):
        RunDir.create(tmp_path / 'file' / 'run')
    # results: floats round-trip exactly; a torn last line is ignored (and cut on repair);
    # a bad line in the middle is an error
    x = 0.1 + 0.2

    def rec(loss: float, index: int = 0) -> dict:
        return {
            'kind': 'eval',
            'eval': index,
            'status': 'ok',
            'u': [0.5],
            'gains': {'k_pw': 1.0},
            'loss': loss,
            'terms': [loss, 0.0, 0.0],
            'aborted': False,
        }

    rd.append_result(Record.from_dict(rec(x)))
    rd.append_result(Record.from_dict(rec(1e-300, 1)))
    with open(rd.path / 'results.jsonl', 'a') as f:
        f.write('{"loss": 0.')
    got = rd.read_results()
    assert got == [Record.from_dict(rec(x)), Record.from_dict(rec(1e-300, 1))]
    assert [r.loss for r in got] == [x, 1e-300]  # floats read back bit for bit
    assert (rd.path / 'results.jsonl').read_text().endswith('0.')  # reading changes nothing
    rd.read_results(repair=True)
    assert (rd.path / 'results.jsonl').read_text().endswith('}\n')
    with open(rd.path / 'results.jsonl', 'a') as f:
        f.write('{"loss": 0.')
    assert rd.cut_torn_tail() == len('{"loss": 0.') and rd.cut_torn_tail() == 0
    with open(rd.path / 'results.jsonl', 'a') as f:
        f.write('garbage\n{"loss": 1}\n')
    with pytest.raises(RunDirError, match='line 3 is not a JSON record'):
        rd.read_results()
    # a record without what the tuner and the report read is named, with its line
    (rd.path / 'results.jsonl').write_text(
        json.dumps(rec(x))
        + '\n'
        + json.dumps({k: v for k, v in rec(x, 1).items() if k != 'loss'})
        + '\n'
    )
    with pytest.raises(RunDirError, match="line 2: record without 'loss'"):
        rd.read_results()
    assert rd.next_bag_dir().name == 'bag_0'
    (rd.path / 'bag_0').mkdir()
    (rd.path / 'bag_10').mkdir()
    (rd.path / 'bag_x').mkdir()
    assert [p.name for p in rd.bag_dirs()] == ['bag_0', 'bag_10']
    assert rd.next_bag_dir().name == 'bag_11'
