"""Tree-structured Parzen estimator (optuna's ``TPESampler``) behind the ask/tell contract.

One optuna trial per evaluation: ``ask`` asks an in-memory optuna study for the five
normalised parameters (each a ``FloatDistribution(0, 1)`` named ``u0..u4``), ``tell``
completes the trial with the measured loss.  A start point (the hand-tuned gains) is
enqueued as the first trial, as optuna's ``enqueue_trial`` does for a known-good
configuration.  No torch: TPE needs numpy/scipy only.

State: the trials told so far (parameters and loss), the pending candidate and the
sampler's two numpy ``RandomState`` streams (TPE's and its start-up random sampler's),
in JSON.  ``from_state`` rebuilds the study from the trials (``add_trials``) and puts the
streams back, so the next asks are the ones the original would have made, bit for bit.
The study itself lives in memory, inside the checkpoint the tuner writes atomically to
its run directory; a separate optuna journal or SQLite file would be a second file to
keep consistent with the checkpoint across a SIGKILL.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import optuna
from optuna.distributions import BaseDistribution, FloatDistribution
from optuna.trial import TrialState, create_trial

from .base import (
    Optimizer,
    OptimizerError,
    OptionSpec,
    check_version,
    make_rng,
    seed_from_json,
    told_history,
    told_loss,
)
from .options import TPE_OPTIONS

__all__ = ['TPE']

_STATE_VERSION = 1
optuna.logging.set_verbosity(optuna.logging.WARNING)


def _rs_state(rs: np.random.RandomState) -> dict[str, Any]:
    st = rs.get_state(legacy=False)
    assert isinstance(st, dict)
    return {
        'key': [int(k) for k in st['state']['key']],
        'pos': int(st['state']['pos']),
        'has_gauss': int(st['has_gauss']),
        'gauss': float(st['gauss']),
    }


def _set_rs_state(rs: np.random.RandomState, st: dict[str, Any]) -> None:
    rs.set_state(
        {
            'bit_generator': 'MT19937',
            'state': {'key': np.array(st['key'], dtype=np.uint32), 'pos': int(st['pos'])},
            'has_gauss': int(st['has_gauss']),
            'gauss': float(st['gauss']),
        }
    )


class TPE(Optimizer):
    """optuna's TPE on [0, 1]^dim.

    ``TPE(dim, seed, start=None, *, n_startup_trials=10, n_ei_candidates=24,
    multivariate='yes')``; ``start`` (optional) is enqueued as the first trial.
    """

    algo: ClassVar[str] = 'tpe'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = TPE_OPTIONS

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        start: np.ndarray | None = None,
        **options: Any,
    ) -> None:
        seed, x0 = self._init_checked(dim, seed, start, options)
        opts = self._opts
        self._x0 = x0
        # optuna seeds numpy RandomStates with a 32-bit int: one drawn from our stream
        self._sampler_seed = int(make_rng(seed).integers(0, 2**32 - 1))
        self._names = [f'u{i}' for i in range(self.dim)]
        self._dists: dict[str, BaseDistribution] = {
            n: FloatDistribution(0.0, 1.0) for n in self._names
        }
        self._sampler = optuna.samplers.TPESampler(
            seed=self._sampler_seed,
            n_startup_trials=opts['n_startup_trials'],
            n_ei_candidates=opts['n_ei_candidates'],
            multivariate=opts['multivariate'] == 'yes',
        )
        self._study = optuna.create_study(sampler=self._sampler, direction='minimize')
        if x0 is not None:
            self._study.enqueue_trial(dict(zip(self._names, x0.tolist(), strict=True)))
        self._trial: optuna.Trial | None = None
        self._pending: list[float] | None = None
        self._told_u: list[list[float]] = []
        self._told_loss: list[float] = []
        self.evaluations = 0

    @property
    def iterations(self) -> int:
        """Trials completed (one evaluation each)."""
        return self.evaluations

    def ask(self) -> np.ndarray:
        if self._pending is None:
            self._trial = self._study.ask(self._dists)
            self._pending = [float(self._trial.params[n]) for n in self._names]
        return np.array(self._pending)

    def tell(self, u: np.ndarray, loss: float) -> None:
        loss = told_loss(self._pending, u, loss)
        pending = self._pending
        assert pending is not None  # told_loss checked it
        if self._trial is not None:
            self._study.tell(self._trial, loss)
        else:  # a candidate restored from a state: the same trial, completed
            self._study.add_trial(self._frozen(pending, loss))
        self._told_u.append(pending)
        self._told_loss.append(loss)
        self._trial, self._pending = None, None
        self.evaluations += 1

    def _frozen(self, u: list[float], loss: float) -> optuna.trial.FrozenTrial:
        return create_trial(
            params=dict(zip(self._names, u, strict=True)),
            distributions=self._dists,
            value=loss,
            state=TrialState.COMPLETE,
        )

    def config(self) -> dict[str, Any]:
        return {
            'algo': self.algo,
            'dim': self.dim,
            'seed': self._seed_json,
            **self._opts,
            'start': None if self._x0 is None else self._x0.tolist(),
            'optuna': optuna.__version__,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            'algo': self.algo,
            'version': _STATE_VERSION,
            'config': self.config(),
            'told_u': [list(u) for u in self._told_u],
            'told_loss': list(self._told_loss),
            'pending': None if self._pending is None else list(self._pending),
            'rng_tpe': _rs_state(self._sampler._rng.rng),
            'rng_random': _rs_state(self._sampler._random_sampler._rng.rng),
            'evaluations': self.evaluations,
        }

    @classmethod
    def _from_state(cls, state: dict[str, Any]) -> TPE:
        check_version(cls, state, _STATE_VERSION)
        try:
            cfg = state['config']
            start = cfg['start']
            pending = state['pending']
            us, losses = told_history(cls.algo, state)
            # the start is enqueued only while it has not been asked yet
            opt = cls(
                int(cfg['dim']),
                seed_from_json(cfg['seed']),
                np.array(start, dtype=np.float64)
                if start is not None and not us and pending is None
                else None,
                **{k: cfg[k] for k in cls.OPTIONS},
            )
            opt._x0 = None if start is None else np.array(start, dtype=np.float64)
            opt._study.add_trials([opt._frozen(u, v) for u, v in zip(us, losses, strict=True)])
            opt._told_u, opt._told_loss = us, losses
            opt.evaluations = len(losses)
            _set_rs_state(opt._sampler._rng.rng, state['rng_tpe'])
            _set_rs_state(opt._sampler._random_sampler._rng.rng, state['rng_random'])
            if pending is not None:
                u = [float(x) for x in pending]
                if len(u) != opt.dim:
                    raise OptimizerError('tpe state: the pending candidate has the wrong size')
                opt._pending = u
        except OptimizerError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise OptimizerError(f'not a tpe state ({exc!r:.80})') from None
        return opt
