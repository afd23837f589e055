"""Tree-structured Parzen estimator (optuna's ``TPESampler``) behind the ask/tell contract.

One trial of an in-memory optuna study per evaluation; a start point is the first trial.
The state is the told trials and the sampler's two ``RandomState`` streams, inside the
tuner's checkpoint (no optuna journal to keep consistent with it).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import optuna
from optuna.distributions import BaseDistribution, FloatDistribution
from optuna.trial import TrialState, create_trial

from .base import (
    HISTORY,
    INT,
    SAVED,
    Field,
    Optimizer,
    OptimizerError,
    told_history,
)

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
    """optuna's TPE on [0, 1]^dim; ``start`` (optional) is enqueued as the first trial."""

    algo: ClassVar[str] = 'tpe'
    REPLAYS: ClassVar[bool] = True
    STATE: ClassVar[tuple[Field, ...]] = (
        *HISTORY,
        Field('rng_tpe', SAVED),
        Field('rng_random', SAVED),
        Field('evaluations', INT),
    )
    BAD_STATE: ClassVar[str] = 'not a tpe state ({error!r:.80})'
    STATE_ERRORS: ClassVar[tuple[type[Exception], ...]] = (
        KeyError,
        TypeError,
        ValueError,
        IndexError,
    )

    def _setup(self, x0: np.ndarray | None) -> None:
        opts = self._opts
        self._x0 = x0
        # optuna seeds numpy RandomStates with a 32-bit int: one drawn from our stream
        self._sampler_seed = int(self._rng.integers(0, 2**32 - 1))
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

    @property
    def iterations(self) -> int:
        """Trials completed (one evaluation each)."""
        return self.evaluations

    def _propose(self) -> list[float]:
        """The next trial's parameters (optuna's study.ask)."""
        self._trial = self._study.ask(self._dists)
        return [float(self._trial.params[n]) for n in self._names]

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """The trial completed with its loss."""
        if self._trial is not None:
            self._study.tell(self._trial, loss)
        else:  # a candidate restored from a state: the same trial, completed
            self._study.add_trial(self._frozen(u, loss))
        self._trial = None

    def _frozen(self, u: list[float], loss: float) -> optuna.trial.FrozenTrial:
        return create_trial(
            params=dict(zip(self._names, u, strict=True)),
            distributions=self._dists,
            value=loss,
            state=TrialState.COMPLETE,
        )

    def _settings(self) -> dict[str, Any]:
        return {
            **self._opts,
            'start': None if self._x0 is None else self._x0.tolist(),
            'optuna': optuna.__version__,
        }

    @property
    def rng_tpe(self) -> dict[str, Any]:
        """The state of TPE's own RandomState."""
        return _rs_state(self._sampler._rng.rng)

    @property
    def rng_random(self) -> dict[str, Any]:
        """The state of the start-up random sampler's RandomState."""
        return _rs_state(self._sampler._random_sampler._rng.rng)

    @classmethod
    def _restore(cls, state: dict[str, Any]) -> TPE:
        """The study rebuilt from the told trials, the sampler's streams put back."""
        start = state['config']['start']
        pending = state['pending']
        us, losses = told_history(cls.algo, state)
        # the start is enqueued only while it has not been asked yet
        opt = cls._replica(state, start if not us and pending is None else None)
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
        return opt
