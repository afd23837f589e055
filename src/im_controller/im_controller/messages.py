"""The loss topic's message: a :class:`LossResult` as ``diagnostic_msgs/DiagnosticArray``,
one ``DiagnosticStatus`` per experiment, floats written with ``repr`` so that they read
back bit for bit (docs/controller.md, "Services, topics").
"""

from __future__ import annotations

import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from im_drive_sim.contract import NS_PER_S

from .config import GAIN_NAMES, Gains
from .layout import SAFETY_REASONS
from .result import LossResult

#: Keys of ``DiagnosticStatus.values``, in order, with how each is written: ``int`` as
#: ``str``, ``float`` as ``repr``, ``bool`` as 'true' or 'false', each of the LossResult
#: field of its name (``_FIELD``: but these); None: by hand (terms, reason, gains, ripple,
#: motion).
_KINDS: dict[str, type | None] = {
    'experiment_id': int,
    'loss': float,
    'term1': None,
    'term2': None,
    'term3': None,
    'aborted': bool,
    'reason': None,
    'trip_step': int,
    'trip_time': float,
    **dict.fromkeys(GAIN_NAMES),
    't_start_ns': int,
    't_end_ns': int,
    'steps': int,
    'direction': int,
    'fresh': int,
    'held': int,
    'late': int,
    'timing': bool,
    'gains_step': int,
    'ripple': None,
    'motion': None,
}
LOSS_KEYS: tuple[str, ...] = tuple(_KINDS)
_INTS, _FLOATS, _BOOLS = (tuple(k for k, v in _KINDS.items() if v is t) for t in (int, float, bool))
_FIELD = {'t_start_ns': 't_start', 't_end_ns': 't_end'}


def _floats(text: str) -> tuple[float, ...]:
    """Space-separated floats (written with repr: they read back bit for bit)."""
    return tuple(float(x) for x in text.split())


def result_to_msg(result: LossResult, node_name: str) -> DiagnosticArray:
    """Pack a result (see module docstring)."""
    r = result
    values = {
        **{k: str(getattr(r, _FIELD.get(k, k))) for k in _INTS},
        **{k: repr(getattr(r, k)) for k in _FLOATS},
        **{k: 'true' if getattr(r, k) else 'false' for k in _BOOLS},
        **{f'term{j + 1}': repr(v) for j, v in enumerate(r.terms)},
        **{n: repr(v) for n, v in zip(GAIN_NAMES, r.gains.as_tuple(), strict=True)},
        'reason': r.reason,
        # the standstill ripple (rms, peak-to-peak [A] after the move, after the load)
        # and the motion sums (im_tuner.identify): space-separated reprs
        'ripple': ' '.join(repr(float(x)) for x in r.ripple),
        'motion': ' '.join(repr(float(x)) for x in r.motion),
    }
    st = DiagnosticStatus(
        name=f'{node_name}: experiment {r.experiment_id}',
        hardware_id=node_name,
        message=(r.reason if r.aborted else 'done')
        + (f' (timing: {r.held} held, {r.late} late periods)' if r.timing else ''),
    )
    if r.timing:
        st.level = DiagnosticStatus.WARN  # not the paper's timing: not a loss
    elif not r.aborted:
        st.level = DiagnosticStatus.OK
    elif r.reason in SAFETY_REASONS:
        st.level = DiagnosticStatus.ERROR
    else:
        st.level = DiagnosticStatus.WARN
    st.values = [KeyValue(key=k, value=values[k]) for k in LOSS_KEYS]
    msg = DiagnosticArray(status=[st])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(r.t_end), NS_PER_S)
    return msg


def msg_to_result(msg: DiagnosticArray) -> LossResult:
    """Unpack a loss message; raises ValueError if it is not one."""
    if len(msg.status) != 1:
        raise ValueError(f'a loss message has one status, got {len(msg.status)}')
    kv = {v.key: v.value for v in msg.status[0].values}
    missing = [k for k in LOSS_KEYS if k not in kv]
    if missing:
        raise ValueError(f'loss message lacks {missing}')
    fields: dict[str, Any] = {_FIELD.get(k, k): int(kv[k]) for k in _INTS}
    fields.update({k: float(kv[k]) for k in _FLOATS}, **{k: kv[k] == 'true' for k in _BOOLS})
    ripple = _floats(kv['ripple'])
    return LossResult(
        **fields,
        terms=(float(kv['term1']), float(kv['term2']), float(kv['term3'])),
        gains=Gains(*(float(kv[n]) for n in GAIN_NAMES)),
        reason=kv['reason'],
        ripple=ripple if len(ripple) == 4 else (math.nan,) * 4,
        motion=_floats(kv['motion']),
    )
