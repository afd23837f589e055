"""The optimiser interface shared by SPSA and the compact-GA family.

Pure numpy (no rclpy): the tuner node, the offline study and the tests drive the same
objects.  One evaluation at a time (ask/tell), on parameters normalised to the search
box, u = (theta - lo)/(hi - lo) in [0, 1]^dim; the tuner maps u to gains and back.

Contract (every optimiser):

* ``ask() -> u``: the next candidate to measure (a fresh float64 array in [0, 1]^dim).
  Asking again before ``tell`` returns the SAME candidate: a lost evaluation is re-run
  with the same parameters, never resampled.
* ``tell(u, loss)``: the measured loss of the candidate just asked (``u`` must equal it
  bit for bit, else ValueError and nothing changes).  ``loss`` must be a finite float
  (a penalised/aborted experiment is just a large loss); NaN/inf -> ValueError.
* ``evaluations``: number of ``tell`` calls so far (loss evaluations, never iterations).
* ``state_dict()`` -> a JSON-serialisable dict holding everything, RNG state included;
  ``Optimizer.from_state(d)`` (any subclass, dispatched on ``d['algo']``) rebuilds an
  optimiser that continues exactly as the original would (bit-identical asks).
* ``converged()``: True when the algorithm has nothing left to do (a compact GA whose
  probability vector is all 0/1); the tuner stops on its budget regardless.
* ``config()``: the configuration as a JSON-serialisable dict (for the run files).

Randomness: each optimiser owns one ``numpy.random.Generator(PCG64)`` built from its
seed (an int or a SeedSequence); no global RNG.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

__all__ = [
    'NDARRAY',
    'Optimizer',
    'OptimizerError',
    'OptionSpec',
    'check_dim',
    'check_loss',
    'check_options',
    'check_seed',
    'check_start',
    'check_told',
    'check_version',
    'make_rng',
    'rebuild',
    'rng_state',
    'seed_from_json',
    'seed_json',
    'set_rng_state',
    'told_history',
    'told_loss',
    'zero_signs_match',
]

#: The array type, bound once (tell's fast path tests ``type(u) is NDARRAY``).
NDARRAY = np.ndarray


class OptimizerError(ValueError):
    """Bad optimiser configuration or misuse (the message says which and why)."""


def check_seed(seed: Any) -> int | np.random.SeedSequence:
    """An int seed (>= 0, bool refused) or a SeedSequence; returns it (ints as ``int``)."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(
        seed, (int, np.integer, np.random.SeedSequence)
    ):
        raise OptimizerError(f'seed must be an integer >= 0 or a SeedSequence, got {seed!r}')
    if not isinstance(seed, np.random.SeedSequence):
        if int(seed) < 0:
            raise OptimizerError(f'seed must be an integer >= 0, got {seed}')
        return int(seed)
    return seed


def make_rng(seed: int | np.random.SeedSequence) -> np.random.Generator:
    """A PCG64 generator from an int seed (>= 0) or a SeedSequence."""
    return np.random.Generator(np.random.PCG64(check_seed(seed)))


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


#: PCG64's underlying LCG has period 2^128: advancing by 2^128 - d steps goes back d draws.
_PCG64_PERIOD = 1 << 128


def rng_state(rng: np.random.Generator, unread: int = 0) -> dict[str, Any]:
    """JSON-serialisable state of a PCG64 generator (ints stay exact in JSON).

    ``unread``: how many of the doubles last drawn (one 64-bit output each) are still
    unused in the optimiser's random block; the state returned is the generator's as if
    they had never been drawn, i.e. exactly the state of a generator that drew one
    candidate's numbers at a time.  The optimisers draw their uniforms in blocks (one
    numpy call per many asks); with this the saved state does not depend on the block
    size, and ``set_rng_state`` + a fresh block continues the same stream.
    """
    st: dict[str, Any] = dict(rng.bit_generator.state)
    if unread:
        bg = np.random.PCG64(0)
        bg.state = st  # type: ignore[assignment]  # numpy's stub wants its TypedDict
        bg.advance(_PCG64_PERIOD - unread)
        st = dict(bg.state)
    return st


def set_rng_state(rng: np.random.Generator, state: dict[str, Any]) -> None:
    rng.bit_generator.state = state


def check_loss(loss: Any) -> float:
    """A told loss: a finite real number (bool and str refused)."""
    if isinstance(loss, (bool, np.bool_)) or not isinstance(
        loss, (int, float, np.integer, np.floating)
    ):
        raise OptimizerError(f'loss must be a finite number, got {loss!r}')
    x = float(loss)
    if not math.isfinite(x):
        raise OptimizerError(f'loss must be finite, got {x!r}')
    return x


def check_dim(dim: Any) -> int:
    """Number of parameters: an integer >= 1 (bool refused)."""
    if isinstance(dim, (bool, np.bool_)) or not isinstance(dim, (int, np.integer)) or dim < 1:
        raise OptimizerError(f'dim must be an integer >= 1, got {dim!r}')
    return int(dim)


def check_start(start: Any, dim: int) -> np.ndarray | None:
    """A start point: None, or ``dim`` finite numbers in [0, 1] (as a new float64 array)."""
    if start is None:
        return None
    try:
        x = np.array(start, dtype=np.float64)
        ok = (
            x.shape == (dim,)
            and np.asarray(start).dtype != np.bool_
            and bool(np.all(np.isfinite(x)))
            and bool(np.all((x >= 0.0) & (x <= 1.0)))
        )
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise OptimizerError(
            f'start must be None or {dim} finite numbers in [0, 1] '
            f'(normalised parameters), got {start!r}'
        )
    return x


@dataclass(frozen=True)
class OptionSpec:
    """One option of an optimiser: type, default, meaning, accepted values.

    ``type`` is ``float``, ``int`` or ``str``.  Numbers must lie in [low, high] (a bound
    is exclusive if ``low_strict``/``high_strict``; ``None`` = unbounded); ``+inf`` is
    accepted only where ``high`` is ``inf`` and not strict.  Strings must be one of
    ``choices``.  ``default`` None means "derived from other options" (``help`` says how).
    Floats accept int/float (numpy scalars too) but never bool; ints refuse floats.
    """

    type: type
    default: Any
    help: str
    low: float | None = None
    high: float | None = None
    low_strict: bool = False
    high_strict: bool = False
    choices: tuple[str, ...] | None = None

    def allowed(self) -> str:
        """The accepted values in words, e.g. 'a number in (0, 0.5)', "one of 'a', 'b'"."""
        if self.choices is not None:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        kind = 'an integer' if self.type is int else 'a number'
        fmt = (lambda v: str(int(v))) if self.type is int else (lambda v: f'{v:g}')
        lo, hi = self.low, self.high
        if lo is not None and hi is not None:
            return (
                f'{kind} in {"(" if self.low_strict else "["}{fmt(lo)}, '
                f'{fmt(hi)}{")" if self.high_strict else "]"}'
            )
        if lo is not None:
            return f'{kind} {">" if self.low_strict else ">="} {fmt(lo)}'
        if hi is not None:
            return f'{kind} {"<" if self.high_strict else "<="} {fmt(hi)}'
        return kind

    def check(self, where: str, value: Any) -> Any:
        """``value`` converted to the option's type, or OptimizerError naming ``where``."""
        bad = OptimizerError(f'{where} must be {self.allowed()}, got {value!r}')
        if self.choices is not None:
            if not isinstance(value, str) or value not in self.choices:
                raise bad
            return str(value)
        if isinstance(value, (bool, np.bool_)):
            raise bad
        if self.type is int:
            if not isinstance(value, (int, np.integer)):
                raise bad
            x: Any = int(value)
        else:
            if not isinstance(value, (int, float, np.integer, np.floating)):
                raise bad
            x = float(value)
            if math.isnan(x) or (
                math.isinf(x) and not (x > 0 and self.high == math.inf and not self.high_strict)
            ):
                raise bad
        if self.low is not None and (x <= self.low if self.low_strict else x < self.low):
            raise bad
        if self.high is not None and (x >= self.high if self.high_strict else x > self.high):
            raise bad
        return x


def check_options(
    algo: str, specs: dict[str, OptionSpec], options: dict[str, Any]
) -> dict[str, Any]:
    """Every option known and valid; returns them all, defaults filled in (None stays None)."""
    for name in options:
        if name not in specs:
            raise OptimizerError(
                f'unknown option {name!r} for {algo} (allowed: {", ".join(specs) or "none"})'
            )
    out = {}
    for name, spec in specs.items():
        if name in options and not (spec.default is None and options[name] is None):
            out[name] = spec.check(f'{algo} option {name}', options[name])
        else:
            out[name] = spec.default
    return out


def check_told(pending: list[float] | None, u: Any, loss: Any) -> float:
    """Validate a ``tell`` (the exact check, with the error messages): a pending candidate
    (``ask``'s values as a list of floats, None when nothing is pending), ``u`` equal to
    it bit for bit once converted to float64 (a list, or an int array of 0/1, is fine), a
    finite loss.

    The optimisers' ``tell`` first tries a fast path, written out in each (it runs once per
    evaluation, with cold caches; docs/optimisers.md "Speed") and accepting only::

        type(u) is ndarray and u.tolist() == pending   (Python's exact number comparison)
        and (no zero pending, or zero_signs_match(u.tolist(), pending))
        and type(loss) is float and loss - loss == 0.0   (finite)

    ``tolist`` gives a nested list for a 2-d array and a scalar for a 0-d one, so equality
    also checks the shape; numbers that compare equal convert to the same float64, whose
    bytes differ only in the sign of zero, hence the zero test.  Everything else (lists,
    numpy scalars as loss, mismatches, errors) comes here.
    """
    if pending is None:
        raise OptimizerError('tell without a pending candidate: call ask() first')
    try:
        a = np.asarray(u, dtype=np.float64)
        same = a.shape == (len(pending),) and a.tobytes() == np.array(pending).tobytes()
    except (TypeError, ValueError):
        same = False
    if not same:
        raise OptimizerError(
            'tell: u is not the pending candidate returned by ask() (it must be equal bit for bit)'
        )
    return check_loss(loss)


def zero_signs_match(values: list[Any], pending: list[float]) -> bool:
    """Equal lists (``==``) are equal float64 bytes unless a zero differs in sign."""
    try:
        return all(
            math.copysign(1.0, a) == math.copysign(1.0, b)
            for a, b in zip(values, pending, strict=True)
        )
    except TypeError:  # not real numbers (a complex zero...): the exact check
        return False


class Optimizer(ABC):
    """Base class: see the module docstring for the contract."""

    #: registry name ('spsa', 'cga', 'pecga', 'necga', 'rcga'); set by subclasses
    algo: ClassVar[str] = ''
    _registry: ClassVar[dict[str, type[Optimizer]]] = {}

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if cls.algo:
            Optimizer._registry[cls.algo] = cls

    #: the options the constructor takes (name -> spec); set by subclasses
    OPTIONS: ClassVar[Mapping[str, OptionSpec]] = {}

    dim: int
    evaluations: int

    if TYPE_CHECKING:
        # The constructor every subclass has (make_optimizer calls it through the registry).
        def __init__(
            self,
            dim: int,
            seed: int | np.random.SeedSequence,
            start: np.ndarray | None = None,
            **options: Any,
        ) -> None: ...

    @property
    @abstractmethod
    def iterations(self) -> int:
        """The paper's iterations completed so far: SPSA iterations, GA generations."""

    @abstractmethod
    def ask(self) -> np.ndarray: ...

    @abstractmethod
    def tell(self, u: np.ndarray, loss: float) -> None: ...

    @abstractmethod
    def state_dict(self) -> dict[str, Any]: ...

    @classmethod
    @abstractmethod
    def _from_state(cls, state: dict[str, Any]) -> Optimizer: ...

    @abstractmethod
    def config(self) -> dict[str, Any]: ...

    def converged(self) -> bool:
        return False

    def _init_checked(
        self, dim: int, seed: int | np.random.SeedSequence, start: Any, options: dict[str, Any]
    ) -> tuple[int | np.random.SeedSequence, np.ndarray | None]:
        """The checks every optimiser that takes a start runs first: sets ``dim``,
        ``_opts`` and ``_seed_json``; returns the checked seed and start (None: none)."""
        self.dim = check_dim(dim)
        seed = check_seed(seed)
        x0 = check_start(start, self.dim)
        self._opts = check_options(self.algo, dict(self.OPTIONS), options)
        self._seed_json = seed_json(seed)
        return seed, x0

    def tell_measurement(self, u: np.ndarray, loss: float, aborted: bool) -> None:
        """``tell`` with the experiment's aborted flag (the tuner calls this).  The default
        ignores the flag: the penalised loss says it; an optimiser that treats an aborted
        experiment as a constraint (safe) overrides it."""
        self.tell(u, loss)

    @staticmethod
    def from_state(state: dict[str, Any]) -> Optimizer:
        """Rebuild any optimiser from ``state_dict()`` output (dispatch on 'algo')."""
        try:
            cls = Optimizer._registry.get(state['algo'])
            if cls is None:  # its module not imported yet (im_tuner.optim loads them lazily)
                from .options import algorithm_class

                cls = algorithm_class(state['algo'])
        except (KeyError, TypeError):
            raise OptimizerError(
                f'not an optimiser state (algo {state.get("algo")!r})'
                if isinstance(state, dict)
                else 'not an optimiser state'
            ) from None
        return cls._from_state(state)


def told_loss(pending: list[float] | None, u: Any, loss: Any) -> float:
    """The loss of a ``tell``, after checking ``u`` is the pending candidate.

    Fast path (the tuner's case): an ndarray holding exactly the pending numbers (signs
    of zeros included) and a finite float.  Anything else goes through
    :func:`check_told`, the exact check with its error messages."""
    if (
        pending is None
        or type(u) is not NDARRAY
        or type(loss) is not float
        or loss - loss != 0.0
        or (tl := u.tolist()) != pending
        or (0.0 in pending and not zero_signs_match(tl, pending))
    ):
        return check_told(pending, u, loss)
    return loss


def check_version(cls: Any, state: dict[str, Any], version: int) -> None:
    """The state's format version is ``version``, else OptimizerError."""
    if state.get('version') != version:
        raise OptimizerError(
            f'{cls.algo} state version {state.get("version")!r} not supported (expected {version})'
        )


def seed_from_json(j: Any) -> int | np.random.SeedSequence:
    """The seed written by :func:`seed_json` (an int, or a SeedSequence's entropy and key)."""
    if isinstance(j, dict):
        return np.random.SeedSequence(j['entropy'], spawn_key=tuple(j['spawn_key']))
    return int(j)


def told_history(algo: str, state: dict[str, Any]) -> tuple[list[list[float]], list[float]]:
    """The candidates and losses told so far, saved by an optimiser whose state is its
    history (cmaes, tpe), checked for matching lengths."""
    us, losses = state['told_u'], state['told_loss']
    if len(us) != len(losses) or state['evaluations'] != len(losses):
        raise OptimizerError(f'{algo} state: told candidates and losses do not match')
    return [[float(x) for x in u] for u in us], [check_loss(v) for v in losses]


def rebuild(cls: Any, state: dict[str, Any], version: int) -> Any:
    """The first half of every ``_from_state``: check the state's version, build ``cls``
    from the saved configuration (seed 0, no start; the saved seed is what ``config()``
    reports) and put the saved RNG state in it.
    The caller then restores its own fields."""
    check_version(cls, state, version)
    cfg = dict(state['config'])
    dim = cfg.pop('dim')
    cfg.pop('algo'), cfg.pop('seed')
    opt = cls(dim, 0, None, **cfg)
    opt._seed_json = state['config']['seed']
    set_rng_state(opt._rng, state['rng'])
    return opt
