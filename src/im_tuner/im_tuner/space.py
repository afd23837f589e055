"""The search space of the tuner: box, start point and the map to normalised parameters.

Pure.  The optimisers work on u in [0, 1]^5, the controller takes the gains
theta_i = lo_i + (hi_i - lo_i) u_i (paper eq. 8, ``GAIN_UNITS``).  The box and the start
come from a YAML parameter file (``config/tuner.yaml``: the paper's motor), its errors
naming the file and the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from im_controller.config import GAIN_NAMES, GAIN_RANGES, GAIN_UNITS, Gains
from im_drive_sim.yaml_file import YamlFileError, read_yaml


class TunerParamsError(ValueError):
    """A bad tuner parameter file; the message names the file and the key."""


@dataclass(frozen=True)
class SearchSpace:
    """Box [lo, hi] per gain (in ``GAIN_NAMES`` order) and the start point."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    start: tuple[float, ...]

    @property
    def dim(self) -> int:
        return len(self.lo)

    def to_gains(self, u: np.ndarray) -> Gains:
        """Gains of normalised ``u`` (clipped to [0, 1] against rounding)."""
        u = np.asarray(u, dtype=float)
        if u.shape != (self.dim,) or not np.all(np.isfinite(u)):
            raise ValueError(f'u must be {self.dim} finite numbers, got {u!r}')
        return Gains(
            *(
                lo + (hi - lo) * min(max(float(x), 0.0), 1.0)
                for lo, hi, x in zip(self.lo, self.hi, u, strict=True)
            )
        )

    def to_u(self, gains: Gains | tuple[float, ...]) -> np.ndarray:
        """Normalised coordinates of ``gains`` (not clipped)."""
        g = gains.as_tuple() if isinstance(gains, Gains) else tuple(gains)
        return np.array(
            [(x - lo) / (hi - lo) for x, lo, hi in zip(g, self.lo, self.hi, strict=True)]
        )

    @property
    def start_u(self) -> np.ndarray:
        return self.to_u(self.start)

    def as_dict(self) -> dict[str, dict[str, float | str]]:
        return {
            n: {'lo': lo, 'hi': hi, 'start': s, 'unit': GAIN_UNITS[n]}
            for n, lo, hi, s in zip(GAIN_NAMES, self.lo, self.hi, self.start, strict=True)
        }


@dataclass(frozen=True)
class TunerParams:
    """Contents of a tuner parameter file."""

    space: SearchSpace
    satisfactory_loss: float
    source: str


def _num(src: str, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise TunerParamsError(f'{src}: {key} must be a finite number, got {v!r}')
    return float(v)


def parse_params(data: Any, src: str = '<dict>') -> TunerParams:
    """Validate the parsed YAML ``data`` (see config/tuner.yaml); ``src`` names it."""
    if not isinstance(data, dict):
        raise TunerParamsError(
            f'{src}: expected a mapping with search_box and '
            f'satisfactory_loss, got {type(data).__name__}'
        )
    extra = sorted(set(data) - {'search_box', 'satisfactory_loss'})
    if extra:
        raise TunerParamsError(
            f'{src}: unknown key(s) {extra}; expected search_box, satisfactory_loss'
        )
    for k in ('search_box', 'satisfactory_loss'):
        if k not in data:
            raise TunerParamsError(f'{src}: missing key {k}')
    box = data['search_box']
    if not isinstance(box, dict):
        raise TunerParamsError(
            f'{src}: search_box must be a mapping of the gains {list(GAIN_NAMES)}'
        )
    unknown = sorted(set(box) - set(GAIN_NAMES))
    missing = [n for n in GAIN_NAMES if n not in box]
    if unknown or missing:
        raise TunerParamsError(
            f'{src}: search_box must have exactly {list(GAIN_NAMES)}'
            + (f'; unknown {unknown}' if unknown else '')
            + (f'; missing {missing}' if missing else '')
        )
    lo, hi, start = [], [], []
    for n in GAIN_NAMES:
        entry = box[n]
        key = f'search_box.{n}'
        if not isinstance(entry, dict) or set(entry) != {'lo', 'hi', 'start'}:
            raise TunerParamsError(
                f'{src}: {key} must be {{lo: ..., hi: ..., start: ...}}, got {entry!r}'
            )
        a, b, s = (_num(src, f'{key}.{f}', entry[f]) for f in ('lo', 'hi', 'start'))
        rlo, rhi = GAIN_RANGES[n]
        unit = GAIN_UNITS[n]
        if not a < b:
            raise TunerParamsError(f'{src}: {key}: lo must be below hi, got [{a:g}, {b:g}]')
        if a < rlo or b > rhi:
            raise TunerParamsError(
                f'{src}: {key}: [{a:g}, {b:g}] {unit} leaves the '
                f"controller's accepted range [{rlo:g}, {rhi:g}] {unit}"
            )
        if not a <= s <= b:
            raise TunerParamsError(
                f'{src}: {key}.start {s:g} {unit} is outside the box [{a:g}, {b:g}]'
            )
        lo.append(a)
        hi.append(b)
        start.append(s)
    sat = _num(src, 'satisfactory_loss', data['satisfactory_loss'])
    if sat <= 0.0:
        raise TunerParamsError(f'{src}: satisfactory_loss must be > 0, got {sat:g}')
    return TunerParams(SearchSpace(tuple(lo), tuple(hi), tuple(start)), sat, src)


def load_params(path: str | Path | None = None) -> TunerParams:
    """Load and validate a tuner parameter file (None: the packaged default)."""
    p = Path(str(resources.files('im_tuner') / 'config' / 'tuner.yaml') if path is None else path)
    src = str(p)
    try:
        data, _ = read_yaml(p)
    except YamlFileError as exc:
        raise TunerParamsError(f'{src}: {exc}') from None
    return parse_params(data, src)
