"""Would the identified model have predicted the plant's aborted candidates?  The default
row's runs with the screen off; then each evaluation on the noisy identified model at J
and 0.85 J (``prior.SCREEN_J``), K experiments each (benches continuing over the run):
how many plant aborts it names, and how many candidates that did not abort.

    python research/abort_screen.py im7500w-j10 J=x0.5 30 2 [FIRST]
"""

import im_drive_sim  # noqa: F401, I001  (the numeric baseline, before numpy is imported)

import sys
import time

import numpy as np

from im_tuner import first_step
from im_tuner.prior import SCREEN_J, _ModelBench, _perturbed, identified_model, noisy_model
from im_tuner.runlog.records import Evaluation
from im_tuner.study import cli as C, runs as R


def main(argv: list[str]) -> None:
    drive, mismatch, runs = argv[0], argv[1], int(argv[2])
    k = int(argv[3]) if len(argv) > 3 else 2
    first = int(argv[4]) if len(argv) > 4 else 0
    args = ['--drives', drive, '--algos', 'safe', '--runs', str(runs), '--budget', '200']
    args += ['--realism', 'bench']
    if mismatch != '-':
        args += ['--plant-mismatch', mismatch]
    spec = C._spec(C._build_parser().parse_args(args)).for_drive(drive)
    cell = next(i for i, c in enumerate(spec.cells) if c.algo == 'safe' and c.first == 'identify')
    first_step.IdentifiedFirstStep.screen = lambda self, records: None  # type: ignore[method-assign]
    seen: list[R.TuningRun] = []
    init = R.TuningRun.__init__

    def keep(self: R.TuningRun, *a: object, **kw: object) -> None:
        init(self, *a, **kw)  # type: ignore[arg-type]
        seen.append(self)

    R.TuningRun.__init__ = keep  # type: ignore[method-assign]
    setup = spec.setup()
    total = np.zeros((2, 2), int)
    for r in range(first, runs):
        t0 = time.time()
        res = R.run_one(spec, cell, r)
        t = seen[-1]
        idf = t.first_step.identified(t.records)
        model, exp = identified_model(setup.drive, setup.experiment, idf)
        noisy = noisy_model(setup.drive, model)
        benches = [_ModelBench(_perturbed(noisy, j, 1.0), exp) for j in SCREEN_J]
        m = np.zeros((2, 2), int)
        named = []
        for e in (x for x in t.records if isinstance(x, Evaluation)):
            u = np.array(e.u)
            pred = any(b.loss(t.space, u)[1] for b in benches for _ in range(k))
            m[int(e.aborted), int(pred)] += 1
            if e.aborted or pred:
                named.append((e.eval, int(e.aborted), int(pred)))
        total += m
        print(
            f'run {r}: plant aborts {int(res.aborted.sum())}; not aborted: named {m[0, 1]} '
            f'of {m[0].sum()}; aborted: named {m[1, 1]} of {m[1].sum()}; (eval, aborted, '
            f'named) {named}; {time.time() - t0:.0f} s',
            flush=True,
        )
    print(
        f'not aborted: named {total[0, 1]} of {total[0].sum()}; '
        f'aborted: named {total[1, 1]} of {total[1].sum()}'
    )


if __name__ == '__main__':
    main(sys.argv[1:])
