"""Does the identified model see the standstill ripple the plant shows? (issue 40 part 6)

For each run of the study's default row (safe, first step from the identified drive) on a
told drive and a mismatched plant: the drive the start's two experiments identify, the
offline search on that model (``prior._search``, as ``identified_prior``), and for each of
its candidates (``prior.CANDIDATES`` best distinct points) its loss and standstill rms on
the model over the start's there, its worst ratios over the perturbed models, and what
the plant then measures (loss over the start's, rms over the start's, in the two windows
of ``runlog.tally.LIMIT_KEYS``).  The chosen point is marked.

    python benchmarks/prior_ripple.py --drive im750w-j1 --mismatch J=x1.5 [--runs 8]
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

from im_controller.config import ExperimentConfig
from im_tuner import first_step as FS
from im_tuner import prior as P
from im_tuner.offline import OfflineBench
from im_tuner.study import runs as R
from im_tuner.study.plant import parse_mismatch
from im_tuner.study.spec import StudySpec


def _rms(rip: tuple[float, ...]) -> tuple[float, float]:
    return (rip[0], rip[2])


def _measure_all(bench: Any, space: Any, points: list[tuple[float, ...]]) -> dict[Any, Any]:
    """Each point twice (both directions), after the start from rest: (loss, rms pair)."""
    out: dict[Any, Any] = {}
    bench.measure(space.to_gains(space.start_u))
    for u in [tuple(space.start_u.tolist()), *points]:
        ms = [bench.measure(space.to_gains(np.array(u))) for _ in range(2)]
        ok = [m for m in ms if not m.aborted]
        if not ok:
            out[u] = (math.inf, (math.nan, math.nan))
            continue
        loss = sum(m.loss for m in ok) / len(ok)
        rms = tuple(sum(_rms(m.ripple)[w] for m in ok) / len(ok) for w in range(2))
        out[u] = (loss, rms)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drive', default='im750w-j1')
    ap.add_argument('--mismatch', default='J=x1.5')
    ap.add_argument('--runs', type=int, default=8)
    a = ap.parse_args()
    spec = StudySpec(
        runs=a.runs,
        budget=3,
        algos=('safe',),
        drives=(a.drive,),
        full_grid=False,
        mismatch=parse_mismatch(a.mismatch),
    )
    cell = next(i for i, c in enumerate(spec.cells) if c.first == 'identify')
    seen_keys: dict[str, list[int]] = {}
    calls: list[Any] = []
    orig = FS.identified_prior

    def capture(drive: Any, space: Any, experiment: ExperimentConfig | None, idf: Any) -> Any:
        calls.append((drive, space, experiment, idf))
        return None

    FS.identified_prior = capture  # type: ignore[assignment]
    try:
        for r in range(a.runs):
            R.run_one(spec, cell, r)
    finally:
        FS.identified_prior = orig  # type: ignore[assignment]
    plant, _params, experiment = spec.loaded()
    for r, (drive, space, exp, idf) in enumerate(calls):
        model, mexp = P.identified_model(drive, exp, idf)
        k = repr((model.machine, mexp))
        seen_keys.setdefault(k, []).append(r)
    print(f'{a.drive}, plant {a.mismatch}: {len(seen_keys)} identified model(s)')
    done: set[str] = set()
    for r, (drive, space, exp, idf) in enumerate(calls):
        model, mexp = P.identified_model(drive, exp, idf)
        k = repr((model.machine, mexp))
        if k in done:
            continue
        done.add(k)
        print(f'\nruns {seen_keys[k]}: J model {model.machine.J:.6g} (file {drive.machine.J:.6g})')
        seen, _ = P._search(model, mexp, space, P.IDENTIFIED_MODEL_EVALUATIONS)
        start = tuple(space.start_u.tolist())
        f0 = next(loss for loss, ab, u in seen if u == start and not ab)
        best: dict[tuple[float, ...], float] = {}
        for loss, aborted, u in sorted(seen):
            if not aborted and u != start and u not in best and loss < f0:
                best[u] = loss
            if len(best) == P.CANDIDATES:
                break
        cands = list(best)
        mb = P._ModelBench(model, mexp)
        on_model = _measure_all(mb.bench, space, cands)
        pb = OfflineBench(plant, 0, experiment)
        on_plant = _measure_all(pb, space, cands)
        chosen = orig(drive, space, exp, idf)
        l0m, r0m = on_model[start]
        l0p, r0p = on_plant[start]
        print(f'start: model rms {r0m[0]:.3f}/{r0m[1]:.3f} A, plant rms {r0p[0]:.3f}/{r0p[1]:.3f} A')
        print('  u | model loss/start | model rms/start (move, load) | plant loss/start | plant rms/start')
        for u in cands:
            lm, rm = on_model[u]
            lp, rp = on_plant[u]
            mark = '*' if chosen is not None and tuple(chosen.u) == u else ' '
            print(
                f'{mark} {", ".join(f"{x:.3f}" for x in u)} | {lm / l0m:.3f} | '
                f'{rm[0] / r0m[0]:.2f}, {rm[1] / r0m[1]:.2f} | {lp / l0p:.3f} | '
                f'{rp[0] / r0p[0]:.2f}, {rp[1] / r0p[1]:.2f}'
            )


if __name__ == '__main__':
    main()
