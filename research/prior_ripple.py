"""Does the identified model see the standstill ripple the plant shows?

For the first run of the study's default row (safe, first step from the identified drive)
on a told drive and a mismatched plant: the drive its start's two experiments identify,
the offline search on that model (``prior._search``, as ``identified_prior`` runs it) and
its ``--candidates`` best distinct points.  Per candidate: its loss over the start's on
the model, its worst loss ratio over the perturbed models, its standstill rms over the
start's (``_ModelBench.ripple_ratio``: the largest over its experiments, per window of
``runlog.ripple.LIMIT_KEYS``) in the nominal search and over the perturbed models, and
what the plant measures in six experiments of it (every other one after the start's, so
that they start from different rest positions): loss and the largest and mean rms, over
the start's; and the same rms on the *noisy model* (the identified mechanics on the told
drive file with its own effects and noise, its realism profile).  ``*`` the first step
without a ripple limit, ``+`` with ``--limit``.

    python research/prior_ripple.py --drive im750w-j1 --mismatch J=x1.5 [--limit 1.5]
        [--realism bench]

With ``--same D1,D2,...`` instead: per drive (its own file as the plant), whether the
first step of run 0 with the limit is the point without it, and its largest rms ratio
on the models.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np

from im_tuner import first_step as FS, prior as P
from im_tuner.offline import OfflineBench
from im_tuner.study import runs as R
from im_tuner.study.plant import parse_mismatch
from im_tuner.study.spec import StudySpec


def _ratio(bench: Any, u: tuple[float, ...], start: tuple[float, ...]) -> tuple[float, float]:
    """The largest rms of ``u`` over the start's mean on ``bench``, per window."""
    s0 = np.mean(bench.rms[start], axis=0)
    r = np.max(bench.rms.get(u, [(0.0, 0.0)]), axis=0)
    return (float(r[0] / s0[0]), float(r[1] / s0[1]))


def _six(bench: Any, start: Any, gains: Any) -> list[Any]:
    """Six experiments of ``gains`` on ``bench``, every other one after the start's (so
    that they begin from different rest positions)."""
    out = []
    for i in range(6):
        if i % 2 == 0:
            bench.measure(start)
        out.append(bench.measure(gains))
    return out


def _identified(spec: StudySpec) -> tuple[Any, ...]:
    """(told drive, space, experiment, identification) of run 0 of the default row."""
    cell = next(i for i, c in enumerate(spec.cells) if c.first == 'identify')
    calls: list[Any] = []
    orig = FS.identified_prior
    FS.identified_prior = lambda *args: calls.append(args)
    try:
        R.run_one(spec, cell, 0)  # the run's start: its two experiments identify the drive
    finally:
        FS.identified_prior = orig
    return tuple(calls[0][:4])


def _same(drives: list[str], limit: float) -> None:
    print('| drive | first step with the limit | its largest rms / start on the models |')
    print('|---|---|---|')
    for d in drives:
        spec = StudySpec(runs=1, budget=3, algos=('safe',), drives=(d,), full_grid=False)
        drive, space, exp, idf = _identified(spec)
        a = P.identified_prior(drive, space, exp, idf)
        b = P.identified_prior(drive, space, exp, idf, limit)
        same = (a is None) == (b is None) and (a is None or b is None or a.u == b.u)
        rr = '-' if b is None or b.ripple_ratio is None else f'{b.ripple_ratio:.2f}'
        print(f'| {d} | {"the same point" if same else "another point"} | {rr} |', flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drive', default='im750w-j1')
    ap.add_argument('--mismatch', default='J=x1.5')
    ap.add_argument('--limit', type=float, default=1.5)
    ap.add_argument('--candidates', type=int, default=16)
    ap.add_argument('--realism', default=None, help="the plant's profile (default its file's)")
    ap.add_argument('--same', default='', help='drives: is the limited first step the same?')
    a = ap.parse_args()
    if a.same:
        _same(a.same.split(','), a.limit)
        return
    spec = StudySpec(
        runs=1,
        budget=3,
        algos=('safe',),
        drives=(a.drive,),
        full_grid=False,
        mismatch=parse_mismatch(a.mismatch) if a.mismatch else (),
        realism=a.realism,
    )
    drive, space, exp, idf = _identified(spec)
    plant, _params, experiment = spec.loaded()
    model, mexp = P.identified_model(drive, exp, idf)
    seen, bench = P._search(model, mexp, space, P.IDENTIFIED_MODEL_EVALUATIONS)
    start = tuple(space.start_u.tolist())
    f0 = next(loss for loss, ab, u in seen if u == start and not ab)
    best: dict[tuple[float, ...], float] = {}
    for loss, aborted, u in sorted(seen):
        if not aborted and u != start and u not in best and loss < f0:
            best[u] = loss
        if len(best) == a.candidates:
            break
    spread = round(max(P.IDENTIFIED_J_SPREAD, 3.0 * idf.J_sd / idf.J), 2)
    lo, hi = 1.0 - min(spread, 0.5), 1.0 + spread
    worst = dict.fromkeys(best, 0.0)
    loud = dict.fromkeys(best, (0.0, 0.0))
    order = list(best)
    for b in range(0, len(order), P.CANDIDATES):  # as _compute: a batch per fresh model
        for j, rr in ((lo, 0.8), (lo, 1.2), (hi, 0.8), (hi, 1.2), (lo, 1.0), (hi, 1.0)):
            pb = P._ModelBench(P._perturbed(model, j, rr), mexp)
            pb.loss(space, space.start_u)
            ref, _ = pb.loss(space, space.start_u)
            for u in order[b : b + P.CANDIDATES]:
                loss, aborted = pb.loss(space, np.array(u))
                worst[u] = max(worst[u], np.inf if aborted else loss / ref)
                r = _ratio(pb, u, start)
                loud[u] = (max(loud[u][0], r[0]), max(loud[u][1], r[1]))
    pl = OfflineBench(plant, 0, experiment)
    g0 = space.to_gains(space.start_u)
    pl.measure(g0)
    ms0 = [pl.measure(g0) for _ in range(2)]
    l0 = np.mean([m.loss for m in ms0])
    r0 = np.mean([(m.ripple[0], m.ripple[2]) for m in ms0], axis=0)
    # the identified mechanics on the told drive file with its own effects and noise (its
    # realism profile), not the nominal model's: what a prediction of the ripple would use
    mm = model.machine
    noisy = dataclasses.replace(
        drive,
        machine=dataclasses.replace(
            drive.machine, J=mm.J, B=mm.B, coulomb_torque=mm.coulomb_torque
        ),
    )
    nb = OfflineBench(noisy, 1, mexp)
    nb.measure(g0)
    n0 = np.mean([(m.ripple[0], m.ripple[2]) for m in (nb.measure(g0) for _ in range(3))], axis=0)
    plain = P.identified_prior(drive, space, exp, idf)
    limited = P.identified_prior(drive, space, exp, idf, a.limit)
    print(
        f'{a.drive}, plant {a.mismatch}: identified J {idf.J:.6g} (file {drive.machine.J:.6g}); '
        f"start's rms on the model {np.mean(bench.rms[start], axis=0).round(3)} A, "
        f'on the plant {r0.round(3)} A, on the noisy model {n0.round(3)} A (after the move, '
        f'after the load; the noisy model: {drive.realism} effects)'
    )
    print(
        '| | model loss / start | worst over perturbed | model rms / start: nominal '
        '| perturbed, max | plant loss / start | plant rms / start, max | mean '
        '| noisy model rms / start, max | mean |'
    )
    print('|---|---|---|---|---|---|---|---|---|---|')
    for k, u in enumerate(best):
        gains = space.to_gains(np.array(u))
        ms = _six(pl, g0, gains)
        pr = np.array([(m.ripple[0], m.ripple[2]) for m in ms]) / r0
        nr = np.array([(m.ripple[0], m.ripple[2]) for m in _six(nb, g0, gains)]) / n0
        mark = ('*' if plain is not None and plain.u == u else '') + (
            '+' if limited is not None and limited.u == u else ''
        )
        nom = _ratio(bench, u, start)
        print(
            f'| {k}{mark} | {best[u] / f0:.3f} | {worst[u]:.3f} | {nom[0]:.2f}, {nom[1]:.2f} '
            f'| {loud[u][0]:.2f}, {loud[u][1]:.2f} | {np.mean([m.loss for m in ms]) / l0:.3f} '
            f'| {pr[:, 0].max():.2f}, {pr[:, 1].max():.2f} '
            f'| {pr[:, 0].mean():.2f}, {pr[:, 1].mean():.2f} '
            f'| {nr[:, 0].max():.2f}, {nr[:, 1].max():.2f} '
            f'| {nr[:, 0].mean():.2f}, {nr[:, 1].mean():.2f} |'
        )


if __name__ == '__main__':
    main()
