"""The optimiser template: the lifecycle every algorithm shares, written once.

Pure numpy.  The contract and how the template and an algorithm's hooks divide the work:
docs/optimisers.md, "The contract" and "How the code is cut".  A state is a snapshot (the
algorithm's variables and the PCG64 state, :func:`rng_state`) or, for ``REPLAYS``
algorithms whose libraries have no stable serialisation, the told history replayed.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, NamedTuple, Self

import numpy as np

from .checks import (
    OptimizerError,
    OptionSpec,
    check_dim,
    check_loss,
    check_options,
    check_seed,
    check_start,
    told_loss,
)
from .options import ALGORITHMS, OPTIONS


def seed_json(seed: int | np.random.SeedSequence) -> Any:
    """The seed as JSON (an int, or a SeedSequence's entropy and spawn key), for config()."""
    if isinstance(seed, np.random.SeedSequence):
        ent = seed.entropy
        return {
            'entropy': (
                None
                if ent is None
                else int(ent)
                if isinstance(ent, (int, np.integer))
                else [int(e) for e in ent]
            ),
            'spawn_key': [int(k) for k in seed.spawn_key],
        }
    return int(seed)


def seed_from_json(j: Any) -> int | np.random.SeedSequence:
    """The seed written by :func:`seed_json` (an int, or a SeedSequence's entropy and key)."""
    if isinstance(j, dict):
        return np.random.SeedSequence(j['entropy'], spawn_key=tuple(j['spawn_key']))
    return int(j)


#: PCG64's underlying LCG has period 2^128: advancing by 2^128 - d steps goes back d draws.
_PCG64_PERIOD = 1 << 128


def rng_state(rng: np.random.Generator, unread: int = 0) -> dict[str, Any]:
    """JSON-serialisable state of a PCG64 generator, as if the ``unread`` doubles last
    drawn (the unused rest of a random block) had never been drawn: the saved state does
    not depend on the block size."""
    st: dict[str, Any] = dict(rng.bit_generator.state)
    if unread:
        bg = np.random.PCG64(0)
        bg.state = st  # type: ignore[assignment]  # numpy's stub wants its TypedDict
        bg.advance(_PCG64_PERIOD - unread)
        st = dict(bg.state)
    return st


def told_history(algo: str, state: dict[str, Any]) -> tuple[list[list[float]], list[float]]:
    """The candidates and losses told so far, saved by an optimiser whose state is its
    history (``REPLAYS``), checked for matching lengths."""
    us, losses = state['told_u'], state['told_loss']
    if len(us) != len(losses) or state['evaluations'] != len(losses):
        raise OptimizerError(f'{algo} state: told candidates and losses do not match')
    return [[float(x) for x in u] for u in us], [check_loss(v) for v in losses]


class Codec(NamedTuple):
    """How one state field goes to JSON (``dump(opt, value)``) and back (``load(opt,
    json)``, converting and checking; None: written only, ``_restored`` recomputes it)."""

    load: Callable[[Any, Any], Any] | None
    dump: Callable[[Any, Any], Any]


class Field(NamedTuple):
    """One field of an algorithm's state: its JSON key, its codec, the attribute that holds
    it (the key unless named)."""

    key: str
    codec: Codec
    attr: str = ''


def _same(_opt: Any, v: Any) -> Any:
    return v


def _floats(_opt: Any, v: Any) -> list[float]:
    return [float(x) for x in v]


INT = Codec(lambda _o, v: int(v), _same)
FLOAT = Codec(lambda _o, v: float(v), _same)
STR = Codec(lambda _o, v: str(v), _same)
#: a list of floats (kept as a python list)
FLOATS = Codec(_floats, lambda _o, v: list(v))
FLOATS_OR_NONE = Codec(
    lambda o, v: None if v is None else _floats(o, v),
    lambda o, v: None if v is None else list(v),
)
#: a list of lists of floats (points)
ROWS = Codec(lambda o, v: [_floats(o, r) for r in v], lambda _o, v: [list(r) for r in v])
#: written, not read back (``_restored`` recomputes or checks it)
SAVED = Codec(None, _same)

#: the first fields of a replaying optimiser's state: the history the template keeps
#: (``REPLAYS``) and the pending candidate
HISTORY: tuple[Field, ...] = (
    Field('told_u', ROWS, '_told_u'),
    Field('told_loss', FLOATS, '_told_loss'),
    Field('pending', FLOATS_OR_NONE, '_pending'),
)


class Elitist:
    """``elite`` and ``elite_loss`` of an elitist optimiser (pe/neCGA, rcGA), from the
    subclass's ``_held_elite``: (u, stored loss), or None before its evaluation."""

    def _held_elite(self) -> tuple[list[float], float] | None:
        raise NotImplementedError

    @property
    def elite(self) -> np.ndarray | None:
        """The elite's normalised parameters (None before its evaluation)."""
        held = self._held_elite()
        return None if held is None else np.array(held[0])

    @property
    def elite_loss(self) -> float | None:
        """The elite's stored loss (measured once, when it was evaluated)."""
        held = self._held_elite()
        return None if held is None else held[1]


class Optimizer(ABC):
    """The template of every optimiser: ``Algo(dim, seed, start=None, **options)``, each
    argument checked in that order before anything is created (OptimizerError)."""

    #: registry name ('spsa', 'cga', ...; ``options.ALGOS``); set by subclasses
    algo: ClassVar[str] = ''
    _registry: ClassVar[dict[str, type[Optimizer]]] = {}

    #: the options the constructor takes (name -> spec): the algorithm's entry of
    #: ``options.OPTIONS``, set when its class is defined
    OPTIONS: ClassVar[Mapping[str, OptionSpec]] = {}

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if cls.algo:
            Optimizer._registry[cls.algo] = cls
            cls.OPTIONS = OPTIONS[cls.algo]

    #: why the algorithm refuses a start point ('': it takes one)
    NO_START: ClassVar[str] = ''
    #: tell_measurement's aborted flag reaches ``_update`` (else it is always False)
    ABORT_AWARE: ClassVar[bool] = False
    #: the state format: its version, its fields after the envelope (in JSON order)
    STATE_VERSION: ClassVar[int] = 1
    STATE: ClassVar[tuple[Field, ...]] = ()
    #: restored by replaying the told history from the seed (no 'rng' in the state)
    REPLAYS: ClassVar[bool] = False
    #: the refusal of a malformed state (``{algo}``, ``{error}``: the exception) and the
    #: exceptions it stands for
    BAD_STATE: ClassVar[str] = 'bad {algo} state: {error!r}'
    STATE_ERRORS: ClassVar[tuple[type[Exception], ...]] = (KeyError, TypeError, ValueError)
    #: samples (or iterations) per random block: one rng call per block
    _BLOCK: ClassVar[int] = 64

    dim: int
    evaluations: int

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        start: np.ndarray | None = None,
        **options: Any,
    ) -> None:
        self.dim = check_dim(dim)
        seed = check_seed(seed)
        x0 = check_start(start, self.dim)
        if x0 is not None and self.NO_START:
            raise OptimizerError(
                f'{self.algo} does not take a start point ({self.NO_START}); pass start=None'
            )
        self._opts = self._check_options(options)
        self._seed_json = seed_json(seed)
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self.evaluations = 0
        self._pending: list[float] | None = None  # the candidate asked and not yet told
        # the random block (``_block``'s values) and the next unused entry
        self._blk: list[Any] = []
        self._bi = 0
        if self.REPLAYS:
            self._told_u: list[list[float]] = []
            self._told_loss: list[float] = []
        self._setup(x0)

    def _check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        """Every option known and valid, defaults filled in; a subclass adds its
        cross-option checks (raising OptimizerError before anything is created)."""
        return check_options(self.algo, self.OPTIONS, options)

    @abstractmethod
    def _setup(self, x0: np.ndarray | None) -> None:
        """The initial state (options in ``self._opts``, the generator in ``self._rng``)."""

    @abstractmethod
    def _propose(self) -> list[float]:
        """The next candidate u, as python floats in [0, 1]."""

    @abstractmethod
    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """Learn from ``loss``, the measured loss of the pending candidate ``u``."""

    @property
    @abstractmethod
    def iterations(self) -> int:
        """The algorithm's iterations completed so far: SPSA iterations, GA generations."""

    def _block(self) -> list[Any]:
        """A new random block: uniforms for ``_BLOCK`` samples (the stream of one
        ``rng.random(dim)`` per sample)."""
        return self._rng.random(self._BLOCK * self.dim).tolist()

    def _draws(self, n: int) -> int:
        """The index in ``_blk`` of the next ``n`` unused entries (a new block when the
        current one is used up; n divides the block's length)."""
        i = self._bi
        if i == len(self._blk):
            self._blk, i = self._block(), 0
        self._bi = i + n
        return i

    def _unread(self) -> int:
        """How many doubles of the random block are drawn and not used yet."""
        return len(self._blk) - self._bi

    def _settings(self) -> dict[str, Any]:
        """The configuration after algo, dim and seed: the options (resolved)."""
        return self._opts

    def _restored(self, state: dict[str, Any]) -> None:  # noqa: B027  (optional hook)
        """After the fields are loaded: derived values and checks across fields."""

    def ask(self) -> np.ndarray:
        pu = self._pending
        if pu is None:
            self._pending = pu = self._propose()
        return np.array(pu)

    def tell(self, u: np.ndarray, loss: float) -> None:
        self.tell_measurement(u, loss, False)

    def tell_measurement(self, u: np.ndarray, loss: float, aborted: bool) -> None:
        """``tell`` with the experiment's aborted flag, which only an ``ABORT_AWARE``
        algorithm reads (for the others the penalised loss says it)."""
        pu = self._pending
        loss = told_loss(pu, u, loss)
        assert pu is not None  # told_loss refused a tell without an ask
        self._update(pu, loss, bool(aborted) if self.ABORT_AWARE else False)
        if self.REPLAYS:
            self._told_u.append(pu)
            self._told_loss.append(loss)
        self._pending = None
        self.evaluations += 1

    def converged(self) -> bool:
        return False

    @property
    def wants_first(self) -> bool:
        """Whether the tuning loop should give a model's point (:meth:`set_first`) before
        the next ``ask`` (an algorithm with the ``first`` policy, ``first='identify'``)."""
        return False

    def set_first(self, first: Any) -> None:
        """The model's point asked for by :attr:`wants_first` (None: none)."""
        raise OptimizerError(f'{self.algo} does not take a first point')

    #: a model's prediction of a candidate (u -> True: it would abort), given by the
    #: tuning loop when :attr:`wants_screen`; not state (the loop gives it again on resume)
    screen: Callable[[list[float]], bool] | None = None
    #: candidates the screen named (learnt as aborted, not measured)
    screened: int = 0

    @property
    def wants_screen(self) -> bool:
        """Whether the tuning loop should set :attr:`screen` now (an algorithm that skips
        candidates its model predicts to abort, once that model is identified)."""
        return False

    def config(self) -> dict[str, Any]:
        return {'algo': self.algo, 'dim': self.dim, 'seed': self._seed_json, **self._settings()}

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            'algo': self.algo,
            'version': self.STATE_VERSION,
            'config': self.config(),
        }
        if not self.REPLAYS:
            state['rng'] = rng_state(self._rng, self._unread())
        for f in self.STATE:
            state[f.key] = f.codec.dump(self, getattr(self, f.attr or f.key))
        return state

    @staticmethod
    def from_state(state: dict[str, Any]) -> Optimizer:
        """Rebuild any optimiser from ``state_dict()`` output (dispatch on 'algo')."""
        try:
            cls = Optimizer._registry.get(state['algo'])
            if cls is None:  # its module not imported yet (im_tuner.optim loads them lazily)
                cls = algorithm_class(state['algo'])
        except (KeyError, TypeError):
            raise OptimizerError(
                f'not an optimiser state (algo {state.get("algo")!r})'
                if isinstance(state, dict)
                else 'not an optimiser state'
            ) from None
        try:
            if state.get('version') != cls.STATE_VERSION:
                raise OptimizerError(
                    f'{cls.algo} state version {state.get("version")!r} not supported '
                    f'(expected {cls.STATE_VERSION})'
                )
            return cls._restore(state)
        except OptimizerError:
            raise
        except cls.STATE_ERRORS as e:
            raise OptimizerError(cls.BAD_STATE.format(algo=cls.algo, error=e)) from None

    @classmethod
    def _restore(cls, state: dict[str, Any]) -> Self:
        """A snapshot: built from the saved configuration (seed 0, no start; the saved
        seed is what ``config()`` reports), the saved RNG state put in, the fields loaded."""
        cfg = dict(state['config'])
        dim = cfg.pop('dim')
        cfg.pop('algo'), cfg.pop('seed')
        opt = cls(dim, 0, None, **cfg)
        opt._load(state)
        return opt

    def _load(self, state: dict[str, Any]) -> None:
        self._seed_json = state['config']['seed']
        self._rng.bit_generator.state = state['rng']
        for f in self.STATE:
            if f.codec.load is not None:
                setattr(self, f.attr or f.key, f.codec.load(self, state[f.key]))
        self._restored(state)

    @classmethod
    def _replica(cls, state: dict[str, Any], start: Any) -> Self:
        """A replaying optimiser's restore starts here: a new one from the saved seed,
        configuration and ``start`` (a saved start, or None)."""
        cfg = state['config']
        return cls(
            int(cfg['dim']),
            seed_from_json(cfg['seed']),
            None if start is None else np.array(start, dtype=np.float64),
            **{k: cfg[k] for k in cls.OPTIONS},
        )


def algorithm_class(algo: str) -> type[Optimizer]:
    """The class of ``algo`` (one of ``ALGOS``), its module imported now if it was not
    (the algorithms load lazily so that a run imports only its own library)."""
    d = ALGORITHMS[algo]
    cls: type[Optimizer] = getattr(importlib.import_module(f'{__package__}.{d.module}'), d.cls)
    return cls
