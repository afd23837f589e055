"""The drive model's first step for ``safe``: the controller tuned offline on the model.

:func:`model_prior` runs ``safe`` (first=none) on the *nominal model* (:func:`nominal_model`)
from the box's start, ``MODEL_EVALUATIONS`` experiments per seed of ``SEEDS``; re-measures
its ``CANDIDATES`` best distinct non-aborted points on the ``PERTURBATIONS`` of J and Rr
(the model is never the plant); and returns the point of the lowest worst-case loss ratio
to the start, or None when none beats the start on every perturbed model (or the start
aborts).  With a standstill-ripple limit R (``runlog.ripple``) the search runs on the
*noisy model* (:func:`noisy_model`) and a candidate's predicted rms (:func:`_ripple_check`)
must be within the bound B = R / (1 + ``RIPPLE_MARGIN``); up to ``RIPPLE_BATCHES`` batches
of candidates are checked.  The search is first told nothing of the ripple, so the step is
the model's best point whenever one of them is predicted within B; only when none is does
it run again told above B what a run is told above its limit (one experiment's rms
scatters by about 25 %, so a search told the bound also turns from good points whose mean
is within it: research/NOTES.md, "The first step: the model's best points first").
Deterministic, cached per key in the process and, with ``IM_TUNER_PRIOR_CACHE`` set, in
that directory (the key also holds a digest of the code and numeric baseline).  Pure.
"""

from __future__ import annotations

import dataclasses
import fcntl
import functools
import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from im_controller.config import ExperimentConfig, Gains
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim.params import DriveConfig

from .identify import Identified
from .space import SearchSpace

#: experiments of the offline search on the nominal model
MODEL_EVALUATIONS = 150
#: best points of that search checked on the perturbed models
CANDIDATES = 8
#: (J factor, Rr factor) of the perturbed models the chosen point must improve on
PERTURBATIONS: tuple[tuple[float, float], ...] = (
    (0.7, 0.8),
    (0.7, 1.2),
    (1.4, 0.8),
    (1.4, 1.2),
    (0.7, 1.0),
    (1.4, 1.0),
)
#: the searches' seeds (fixed numbers: the prior is a function of the drive alone)
SEEDS: tuple[int, ...] = (0, 1, 2, 3)
#: With a ripple limit, batches of ``CANDIDATES`` checked at most
RIPPLE_BATCHES = 4
#: With a ripple limit, the start's experiments on the search's model after the one from
#: rest: their mean rms is the limit's bound there (one experiment's scatters).
START_EXPERIMENTS = 4
#: With a ripple limit, experiments of each candidate in the ripple check (per model)
RIPPLE_EXPERIMENTS = 6
#: With a ripple limit R the first step's predicted rms must be within R / (1 + this): the
#: prediction's error on the plant (research/NOTES.md, "The first step predicted within
#: the limit").
RIPPLE_MARGIN = 0.10


@dataclass(frozen=True)
class Prior:
    """The model's first step: ``u`` in [0, 1]^dim; its loss over the start's on the model
    (``model_ratio``) and the worst over the perturbed models (``worst_ratio``); the
    offline ``experiments`` and wall ``seconds`` it cost; with a ripple limit, its
    predicted standstill rms over the start's (``ripple_ratio``, else None)."""

    u: tuple[float, ...]
    model_ratio: float
    worst_ratio: float
    experiments: int
    seconds: float
    ripple_ratio: float | None = None


def nominal_model(drive: DriveConfig) -> DriveConfig:
    """The drive file as a nameplate model: every bench effect at its off value (the
    ``ideal`` profile), no speed noise; the machine constants, control and sensors as
    written."""
    sections: dict[str, Any] = {}
    for name in ('machine', 'control', 'sensors', 'disturbance'):
        sec = getattr(drive, name)
        off = {
            f.name: f.metadata['off']
            for f in dataclasses.fields(sec)
            if f.metadata.get('off') is not None
        }
        if name == 'sensors':
            off['speed_noise_std'] = 0.0
        sections[name] = dataclasses.replace(sec, **off)
    return dataclasses.replace(drive, realism='ideal', **sections)


def _perturbed(model: DriveConfig, j: float, rr: float) -> DriveConfig:
    m = model.machine
    return dataclasses.replace(model, machine=dataclasses.replace(m, J=m.J * j, Rr=m.Rr * rr))


class _ModelBench:
    """The offline bench on a model with the run's experiment (a fresh drive at rest)."""

    def __init__(self, drive: DriveConfig, experiment: ExperimentConfig | None) -> None:
        from .offline import OfflineBench  # (numba: imported when a prior is built)

        self.bench = OfflineBench(drive, drive.seed)
        if experiment is not None:
            sim = self.bench.sim
            self.bench.runner = ExperimentRunner(config_for_drive(experiment, sim), Gains())
            self.bench.runner.reset(sim.theta_meas)
        self.experiments = 0
        #: per measured point, each non-aborted experiment's (rms after move, after load) [A]
        self.rms: dict[tuple[float, ...], list[tuple[float, float]]] = {}
        #: the last experiment's (rms after move, after load) [A] (nan: aborted)
        self.last = (math.nan, math.nan)

    def loss(self, space: SearchSpace, u: np.ndarray) -> tuple[float, bool]:
        m = self.bench.measure(space.to_gains(u))
        self.experiments += 1
        # the standstill rms of isq* [A] after the move and after the load (LIMIT_KEYS)
        self.last = (math.nan, math.nan) if m.aborted else (m.ripple[0], m.ripple[2])
        if not m.aborted:
            self.rms.setdefault(tuple(u.tolist()), []).append(self.last)
        return m.loss, m.aborted

    def start_rms(self, start: tuple[float, ...]) -> tuple[float, float]:
        """The mean rms of the start's experiments here, per window [A] (nan: none)."""
        ref = self.rms.get(start, [])
        if not ref:
            return (math.nan, math.nan)
        return (sum(x[0] for x in ref) / len(ref), sum(x[1] for x in ref) / len(ref))

    def ratios(self, u: tuple[float, ...], start: tuple[float, ...]) -> list[tuple[float, float]]:
        """Each experiment of ``u`` here: its rms over the start's mean, per window."""
        s0 = self.start_rms(start)
        return [(_over(r[0], s0[0]), _over(r[1], s0[1])) for r in self.rms.get(u, [])]


def _over(r: float, s0: float) -> float:
    """``r / s0``; 0 / 0 = 0 (both at rest within an encoder count), x / 0 = inf."""
    if s0 > 0.0 or math.isnan(s0):
        return r / s0
    return 0.0 if r == 0.0 else math.inf


def _over_limit(rms: tuple[float, float], start: tuple[float, float], limit: float) -> float | None:
    """One experiment's largest rms over ``limit`` x the start's mean, over the windows
    where the start's rms is > 0; None: no such window, or one without samples."""
    r = [rms[w] / (limit * start[w]) for w in range(2) if start[w] > 0.0]
    if not r or any(math.isnan(x) for x in r):
        return None
    return max(r)


def _search(
    model: DriveConfig,
    experiment: ExperimentConfig | None,
    space: SearchSpace,
    evaluations: int = MODEL_EVALUATIONS,
    ripple_limit: float | None = None,
) -> tuple[list[tuple[float, bool, tuple[float, ...]]], _ModelBench]:
    """``safe`` on the model, ``evaluations`` experiments per seed: the measured points
    (the first is the start's) and the bench.  With ``ripple_limit`` the start is measured
    ``START_EXPERIMENTS`` times more (its mean rms: the bound) and the search is told what
    a run is told (``runlog.ripple.told``) with no tolerance, so it ranks quiet points first."""
    from .optim import make_optimizer
    from .runlog.ripple import told

    bench = _ModelBench(model, experiment)
    bench.loss(space, space.start_u)  # the first experiment from rest (not a measure)
    start = tuple(space.start_u.tolist())
    if ripple_limit is not None:
        for _ in range(START_EXPERIMENTS):
            bench.loss(space, space.start_u)
        s0 = bench.start_rms(start)
    seen: list[tuple[float, bool, tuple[float, ...]]] = []
    for seed in SEEDS:
        opt = make_optimizer('safe', space.dim, seed, space.start_u)
        quiet = -math.inf  # the smallest loss within the limit so far (none: -inf)
        for _ in range(evaluations):
            u = opt.ask()
            loss, aborted = bench.loss(space, u)
            said = loss
            if ripple_limit is not None and not aborted:
                over = _over_limit(bench.last, s0, ripple_limit)
                said = told(loss, over, quiet, tolerance=1.0)
                if over is not None and over <= 1.0:
                    quiet = loss if quiet == -math.inf else min(quiet, loss)
            opt.tell_measurement(u, said, aborted)
            seen.append((loss, aborted, tuple(u.tolist())))
    return seen, bench


def _compute(
    model: DriveConfig,
    experiment: ExperimentConfig | None,
    space: SearchSpace,
    perturbations: tuple[tuple[float, float], ...] = PERTURBATIONS,
    evaluations: int = MODEL_EVALUATIONS,
    ripple_limit: float | None = None,
    ripple_models: tuple[DriveConfig, ...] = (),
) -> Prior | None:
    """The first step (module docstring); with ``ripple_limit`` (the run's ratio) the ripple
    is checked on ``model`` and each of ``ripple_models``: first among the best points of
    the search told nothing of the ripple, then, when none of them is predicted within the
    bound, among those of the search told the bound."""
    t0 = time.perf_counter()
    bound = None if ripple_limit is None else ripple_limit / (1.0 + RIPPLE_MARGIN)
    experiments = 0
    start = tuple(space.start_u.tolist())
    for told in (None,) if bound is None else (None, bound):
        seen, bench = _search(model, experiment, space, evaluations, told)
        experiments += bench.experiments
        f0 = next((loss for loss, ab, u in seen if u == start and not ab), None)
        if f0 is None:  # the box's start is unstable on the model: no ratio to beat, no prior
            return None
        ranked: dict[tuple[float, ...], float] = {}  # distinct points better than the start
        for loss, aborted, u in sorted(seen):
            if aborted or u == start or u in ranked or not loss < f0:
                continue
            # told the bound: only the points the search measured within it
            if told is None or _predicted(bench.ratios(u, start)) <= told:
                ranked[u] = loss
        chosen, n = _choose(model, experiment, space, perturbations, ranked, bound, ripple_models)
        experiments += n
        if chosen is not None:
            u, worst, loud = chosen
            return Prior(
                u=u,
                model_ratio=ranked[u] / f0,
                worst_ratio=worst,
                experiments=experiments,
                seconds=time.perf_counter() - t0,
                ripple_ratio=loud,
            )
    return None


def _choose(
    model: DriveConfig,
    experiment: ExperimentConfig | None,
    space: SearchSpace,
    perturbations: tuple[tuple[float, float], ...],
    ranked: dict[tuple[float, ...], float],
    bound: float | None,
    ripple_models: tuple[DriveConfig, ...],
) -> tuple[tuple[tuple[float, ...], float, float | None] | None, int]:
    """Of ``ranked`` (point: loss on the model, best first), in batches of ``CANDIDATES``
    (``RIPPLE_BATCHES`` with a ``bound``, else one): the point of the lowest worst loss
    ratio over the perturbed models, below 1, and with a bound predicted within it; with
    that ratio and its prediction (None: no bound), and the experiments it cost."""
    order = list(ranked)
    experiments = 0
    for b in range(1 if bound is None else RIPPLE_BATCHES):
        best = {u: ranked[u] for u in order[b * CANDIDATES : (b + 1) * CANDIDATES]}
        if not best:
            break
        worst = dict.fromkeys(best, 0.0)
        for j, rr in perturbations:
            pb = _ModelBench(_perturbed(model, j, rr), experiment)
            pb.loss(space, space.start_u)  # from rest
            ref, ref_aborted = pb.loss(space, space.start_u)
            if not ref_aborted:  # (else the start is unstable there: that model says nothing)
                for u in best:
                    loss, aborted = pb.loss(space, np.array(u))
                    worst[u] = max(worst[u], np.inf if aborted else loss / ref)
            experiments += pb.experiments
        ok = [u for u in best if worst[u] < 1.0]
        loud = dict.fromkeys(best, 0.0)
        if bound is not None:
            for m in (model, *ripple_models):
                said, n = _ripple_check(m, experiment, space, ok)
                experiments += n
                loud.update({u: max(loud[u], said[u]) for u in ok})
            ok = [u for u in ok if loud[u] <= bound]
        if ok:
            u = min(ok, key=lambda u: (worst[u], best[u]))
            return (u, float(worst[u]), None if bound is None else float(loud[u])), experiments
    return None, experiments


def _ripple_check(
    model: DriveConfig,
    experiment: ExperimentConfig | None,
    space: SearchSpace,
    points: list[tuple[float, ...]],
) -> tuple[dict[tuple[float, ...], float], int]:
    """Each point's predicted standstill rms over the start's on ``model`` (the start
    measured ``START_EXPERIMENTS`` times after one from rest, each point
    ``RIPPLE_EXPERIMENTS`` times; aborted: inf), and the experiments it cost."""
    mb = _ModelBench(model, experiment)
    start = tuple(space.start_u.tolist())
    for _ in range(1 + START_EXPERIMENTS):
        mb.loss(space, space.start_u)
    out = {}
    for u in points:
        aborted = any(mb.loss(space, np.array(u))[1] for _ in range(RIPPLE_EXPERIMENTS))
        out[u] = math.inf if aborted else _predicted(mb.ratios(u, start))
    return out, mb.experiments


def _predicted(ratios: list[tuple[float, float]]) -> float:
    """A point's predicted rms over the start's: the larger window's mean of its
    experiments' ratios (inf: none, or a window without samples)."""
    if not ratios:
        return math.inf
    means = [sum(r[w] for r in ratios) / len(ratios) for w in range(2)]
    return max(m if math.isfinite(m) else math.inf for m in means)


_CACHE: dict[str, Prior | None] = {}
#: a directory where computed first steps are kept across processes
CACHE_ENV = 'IM_TUNER_PRIOR_CACHE'


@functools.cache
def _code_digest() -> str:
    """sha256 of the three packages' sources, numpy's version and the numeric baseline's
    bits: what decides a point besides its key (a cache outlives no change of them)."""
    import im_controller
    import im_drive_sim
    import im_tuner
    from im_drive_sim import numeric

    h = hashlib.sha256()
    for root in (Path(str(p.__file__)).parent for p in (im_drive_sim, im_controller, im_tuner)):
        for f in sorted(root.rglob('*.py')):
            h.update(f.relative_to(root).as_posix().encode() + b'\0' + f.read_bytes())
    st = numeric.status()
    bits = {k: st[k] for k in ('state', 'numpy', 'openblas')}
    h.update(json.dumps([np.__version__, bits], sort_keys=True).encode())
    return h.hexdigest()


def _read(path: Path) -> tuple[bool, Prior | None]:
    """(found, value) of a cache file (not found: missing or unreadable)."""
    try:
        data = json.loads(path.read_text())
        return True, None if data is None else Prior(**{**data, 'u': tuple(data['u'])})
    except (OSError, ValueError, TypeError, KeyError):
        return False, None


def _cached(key: str, compute: Callable[[], Prior | None]) -> Prior | None:
    """``compute()`` once per ``key``: from this process's cache, else ``CACHE_ENV``'s
    directory, else computed and kept in both (atomic rename).  Processes that miss one key
    at once compute it once: the first holds the key's ``flock``, the others wait."""
    if key in _CACHE:
        return _CACHE[key]
    where = os.environ.get(CACHE_ENV, '')
    if not where:
        _CACHE[key] = value = compute()
        return value
    name = hashlib.sha256((_code_digest() + key).encode()).hexdigest()
    path = Path(where) / f'prior-{name}.json'
    found, value = _read(path)
    if found:
        _CACHE[key] = value
        return value
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = os.open(path.with_suffix('.lock'), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        lock = -1  # a cache that cannot be written costs time, not a result
    try:
        if lock >= 0:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another process computing it: wait for it
            found, value = _read(path)
        if not found:
            value = compute()
            if lock >= 0:
                try:
                    tmp = path.with_name(f'{path.name}.{os.getpid()}.tmp')
                    tmp.write_text(json.dumps(None if value is None else dataclasses.asdict(value)))
                    os.replace(tmp, path)
                except OSError:
                    pass
    finally:
        if lock >= 0:
            os.close(lock)  # (releases the lock)
    _CACHE[key] = value
    return value


def model_prior(
    drive: DriveConfig, space: SearchSpace, experiment: ExperimentConfig | None = None
) -> Prior | None:
    """``safe``'s first step from the nominal model of ``drive`` (module docstring) for the
    box ``space`` and ``experiment`` (None: the default one); None when the model finds
    nothing better than the start."""
    model = nominal_model(drive)
    key = json.dumps([model.to_dict(), repr(experiment), dataclasses.asdict(space)], sort_keys=True)
    return _cached(key, lambda: _compute(model, experiment, space))


#: The identified model's J and Kt ratio are rounded to this relative step, Tc to ROUND_TC
#: of the rated torque: a study's runs on one plant share a few cached models.
ROUND_J = 0.01
ROUND_TC = 0.005
#: The identified model's perturbations: J within +-(the larger of this and 3 standard
#: deviations of the identified J), Rr as for the file's model (not identified).
IDENTIFIED_J_SPREAD = 0.1
#: Experiments per seed of the offline search on the identified model: it is close to the
#: plant, so its optimum is worth finding (research/NOTES.md, "The identified model's
#: search").
IDENTIFIED_MODEL_EVALUATIONS = 300


def identified_model(
    drive: DriveConfig, experiment: ExperimentConfig | None, idf: Identified
) -> tuple[DriveConfig, ExperimentConfig]:
    """The nominal model with the identified mechanics in the file's current units: Kt_f
    stays, so J, B, Tc and the load torque are scaled by Kt_f / Kt (the same acceleration
    and isq); J rounded to ``ROUND_J``, Tc to ``ROUND_TC`` of the rated torque."""
    model = nominal_model(drive)
    m = model.machine
    k = idf.Kt_file / idf.Kt if idf.Kt > 0 else 1.0
    k = round(k / ROUND_J) * ROUND_J
    jr = math.exp(round(math.log(max(idf.J * k, 1e-12) / m.J) / ROUND_J) * ROUND_J)
    tc_step = ROUND_TC * m.rated_torque
    tc = max(0.0, round(idf.Tc * k / tc_step) * tc_step)
    b = max(0.0, idf.B * k)
    b = float(f'{b:.2g}') if b > 0 else 0.0
    machine = dataclasses.replace(m, J=m.J * jr, B=b, coulomb_torque=tc)
    exp = ExperimentConfig() if experiment is None else experiment
    tr = dataclasses.replace(exp.trajectory, load_torque=exp.trajectory.load_torque * k)
    return dataclasses.replace(model, machine=machine), dataclasses.replace(exp, trajectory=tr)


def noisy_model(drive: DriveConfig, model: DriveConfig, friction: bool = True) -> DriveConfig:
    """The drive file as written (bench effects, speed noise) with ``model``'s J and, with
    ``friction``, its B and Coulomb torque: the model whose standstill ripple is the
    plant's (the friction at rest decides the limit cycle and is barely identified)."""
    mm = model.machine
    machine = dataclasses.replace(drive.machine, J=mm.J)
    if friction:
        machine = dataclasses.replace(machine, B=mm.B, coulomb_torque=mm.coulomb_torque)
    return dataclasses.replace(drive, machine=machine)


#: The abort screen: experiments of a candidate from rest on each model, and the models'
#: J over the identified (the lower one puts the same gains nearer the stability edge)
SCREEN_EXPERIMENTS = 2
SCREEN_J = (1.0, 0.85)


class AbortScreen:
    """Whether gains abort on the identified drive: ``SCREEN_EXPERIMENTS`` experiments
    from rest on :func:`noisy_model` at each J factor of ``SCREEN_J``, True when one
    aborts.  A fresh bench per call, so the answer is a function of the point (a resumed
    run is given the same answers).  On the bench profile it named every plant abort of
    the default's runs (research/NOTES.md, "The abort screen")."""

    def __init__(
        self,
        drive: DriveConfig,
        space: SearchSpace,
        experiment: ExperimentConfig | None,
        idf: Identified,
    ) -> None:
        model, self.experiment = identified_model(drive, experiment, idf)
        noisy = noisy_model(drive, model)
        self.models = tuple(_perturbed(noisy, j, 1.0) for j in SCREEN_J)
        self.space = space
        self.experiments = 0  #: offline experiments run so far
        self.screened = 0  #: points predicted to abort so far

    def __call__(self, u: list[float]) -> bool:
        x = np.array(u, dtype=np.float64)
        for m in self.models:
            bench = _ModelBench(m, self.experiment)
            for _ in range(SCREEN_EXPERIMENTS):
                aborted = bench.loss(self.space, x)[1]
                if aborted:
                    break
            self.experiments += bench.experiments
            if aborted:
                self.screened += 1
                return True
        return False


def identified_prior(
    drive: DriveConfig,
    space: SearchSpace,
    experiment: ExperimentConfig | None,
    idf: Identified,
    ripple_limit: float | None = None,
) -> Prior | None:
    """``model_prior`` on :func:`identified_model`, robust over J's uncertainty
    (``IDENTIFIED_J_SPREAD``) and Rr's; with ``ripple_limit`` on :func:`noisy_model`
    with and without the identified friction (module docstring)."""
    model, exp = identified_model(drive, experiment, idf)
    others: tuple[DriveConfig, ...] = ()
    if ripple_limit is not None:  # the friction at rest is the least identified: both
        model, others = noisy_model(drive, model), (noisy_model(drive, model, friction=False),)
    spread = max(IDENTIFIED_J_SPREAD, 3.0 * idf.J_sd / idf.J if idf.J > 0 else 1.0)
    spread = round(spread, 2)
    lo, hi = 1.0 - min(spread, 0.5), 1.0 + spread
    perturbations = ((lo, 0.8), (lo, 1.2), (hi, 0.8), (hi, 1.2), (lo, 1.0), (hi, 1.0))
    key = json.dumps(
        [
            'identified',
            model.to_dict(),
            repr(exp),
            dataclasses.asdict(space),
            spread,
            IDENTIFIED_MODEL_EVALUATIONS,
            ripple_limit,
        ],
        sort_keys=True,
    )
    return _cached(
        key,
        lambda: _compute(
            model, exp, space, perturbations, IDENTIFIED_MODEL_EVALUATIONS, ripple_limit, others
        ),
    )


def model_drive_mismatch(mine: str | None, theirs: str | None, option: str = 'model') -> str | None:
    """Why a first step computed on ``mine`` (``--drive-config``; None: the default) does
    not fit a controller whose ``drive_config_file`` is ``theirs``: one line naming the
    fix, or None when both have the same machine and period.  A file unreadable here is a
    mismatch only when the names differ (the drive's host may keep it elsewhere)."""
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.params import ConfigError

    mine, theirs = mine or None, theirs or None
    try:
        same = _drive_key(load_config(mine)) == _drive_key(load_config(theirs))
    except ConfigError:
        same = mine == theirs
    if same:
        return None
    said = '(none)' if mine is None else mine
    return (
        f'--opt first={option}: the controller drives {theirs or "paper_750w (its default)"} '
        f'(its drive_config_file), but the first step would be the model of --drive-config '
        f'{said}; give --drive-config {theirs or "paper_750w"} (or --opt first=none)'
    )


def _drive_key(drive: DriveConfig) -> tuple[Any, ...]:
    """What the model of a drive depends on: its machine and its period."""
    return (drive.machine, drive.Ts)
