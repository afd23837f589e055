"""safe's abort screen on a plant the drive file gets wrong: im7500w-j10 on the bench
profile whose plant has half the file's inertia (``study --plant-mismatch J=x0.5``, the
default row).  Its run 14 aborts at evaluation 2 without the screen (a candidate of
sigma 0.02 next to the identified model's first step, near the plant's stability edge);
with it, the identified model names that candidate, the search learns it as an abort
without an experiment, and no experiment of the run aborts."""

from __future__ import annotations

from im_tuner.first_step import IdentifiedFirstStep
from im_tuner.study import runs as R, spec as S
from im_tuner.tuning import TuningRun

SPEC = S.StudySpec(
    runs=15,
    budget=4,
    algos=('safe',),
    drives=('im7500w-j10',),
    full_grid=False,
    realism='bench',
    mismatch=(('J', 0.5),),
).for_drive('im7500w-j10')
CELL = next(i for i, c in enumerate(SPEC.cells) if c.algo == 'safe' and c.first == 'identify')
RUN = 14


def test_the_screen_names_the_candidate_that_aborts_on_the_plant(monkeypatch):
    runs: list[TuningRun] = []
    real_init = TuningRun.__init__

    def init(self, *a, **k):  # (to read the run's optimiser and records afterwards)
        real_init(self, *a, **k)
        runs.append(self)

    monkeypatch.setattr(TuningRun, '__init__', init)
    screened = R.run_one(SPEC, CELL, RUN)
    run = runs[-1]
    screen = run.first_step.screen(run.records)
    said = screen.screened
    ev = [r for r in run.records if r.kind == 'eval']
    # no false alarm on the start and the first step (neither aborts on the plant)
    assert not screen(ev[0].u) and not screen(ev[1].u)

    monkeypatch.setattr(IdentifiedFirstStep, 'screen', lambda self, records: None)
    plain = R.run_one(SPEC, CELL, RUN)
    # without the screen: evaluation 2 (the first candidate after the first step) aborts
    assert plain.aborted.tolist() == [False, False, True, False]
    assert plain.losses[1] == screened.losses[1]  # the same first step
    # with it: that candidate is named and not run, the step shrinks, nothing aborts
    assert not screened.aborted.any()
    assert run.opt.screened == said >= 1 and run.opt.aborts == 0
    plain_ev = [r for r in runs[-1].records if r.kind == 'eval']
    assert screen(plain_ev[2].u) and ev[2].u != plain_ev[2].u
    assert run.opt.sigma < 0.02 * 0.5
