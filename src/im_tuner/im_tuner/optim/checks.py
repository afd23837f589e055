"""What a caller hands an optimiser, checked: dim, seed, start, options, a told point and loss.

Every check raises :class:`OptimizerError` (a ``ValueError``) with one line naming what is
wrong and what is accepted, before anything is created or changed.  Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

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
    """One option of an optimiser: ``type`` (float, int or str), ``default`` (None:
    derived, ``help`` says how), meaning, and its accepted values: numbers in [low, high]
    (exclusive where ``*_strict``; None: unbounded; +inf only where ``high`` is an
    included inf), strings among ``choices``.  Never a bool; an int option refuses floats."""

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
    algo: str, specs: Mapping[str, OptionSpec], options: dict[str, Any]
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
    """The exact check of a ``tell``: a candidate pending, ``u`` equal to it bit for bit
    once converted to float64, a finite loss (what :func:`told_loss`'s fast path passes on)."""
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


def told_loss(pending: list[float] | None, u: Any, loss: Any) -> float:
    """The loss of a ``tell``, after checking ``u`` is the pending candidate: at once for
    the tuner's case (docs/optimisers.md, "Speed"), an ndarray equal to it (signs of zeros
    included) and a finite float; anything else through :func:`check_told`."""
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
