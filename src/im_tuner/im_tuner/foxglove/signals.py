"""What each recorded signal means, by name: the meaning and unit a layout's label gives.

The index of every field comes from the contracts (``im_drive_sim.contract.STATE_FIELDS``,
``COMMAND_FIELDS``; ``im_controller.layout.INTERNALS_FIELDS``; the loss message's keys,
which the tuner's result message carries too, ``runlog.records.KINDS`` and
``im_controller.config.GAIN_NAMES``/``GAIN_UNITS``); this module adds only the words and
units a person reads, keyed by field name, and :func:`signal` refuses a field it has no
words for, so a field added to a contract cannot reach a layout unlabelled. Units as
docs/interfaces.md (drive topics) and docs/controller.md (controller internals) give them;
``-`` for a count or a code. Pure: no rclpy, no numba.
"""

from __future__ import annotations

from dataclasses import dataclass

from im_controller.config import GAIN_NAMES, GAIN_UNITS
from im_controller.contract import INTERNALS_TOPIC
from im_controller.layout import INTERNALS_FIELDS
from im_drive_sim.contract import COMMAND_FIELDS, COMMAND_TOPIC, STATE_FIELDS, STATE_TOPIC

from ..runlog.records import KINDS


@dataclass(frozen=True)
class Signal:
    """One plotted quantity: its contract name, what it is, and its SI unit."""

    name: str
    meaning: str
    unit: str


#: drive/state, by field (docs/interfaces.md, "drive/state").
_STATE: dict[str, tuple[str, str]] = {
    'step_index': ('drive step k', '-'),
    'time_ns': ('sim time k Ts', 'ns'),
    'theta_meas': ('measured shaft position (encoder)', 'rad'),
    'omega_meas': ('measured speed', 'rad/s'),
    'torque': ('electromagnetic torque', 'N m'),
    'isd': ('d-axis (flux) current', 'A'),
    'isq': ('q-axis (torque) current', 'A'),
    'i_alpha': ('stator current, alpha axis', 'A'),
    'i_beta': ('stator current, beta axis', 'A'),
    'load_torque': ('load torque applied by the load machine', 'N m'),
    'theta': ('true position (simulation)', 'rad'),
    'omega': ('true speed (simulation)', 'rad/s'),
    'applied_step': ('answers_step of the command applied over the period', '-'),
    'command_delay': ('declared command delay d', 'periods'),
}

#: drive/command, by field (docs/interfaces.md, "drive/command").
_COMMAND: dict[str, tuple[str, str]] = {
    'answers_step': ('step_index of the state this command answers', '-'),
    'isq_ref': ('q-axis current reference sent to the drive', 'A'),
    'load_torque': ('load machine torque command', 'N m'),
}

#: controller/internals, by field (docs/controller.md sections 2-4; im_controller.layout).
_INTERNALS: dict[str, tuple[str, str]] = {
    'step_index': ('drive step k answered', '-'),
    'theta_ref': ('position reference theta* (raw trajectory)', 'rad'),
    'theta_sm': ('smoothed position reference', 'rad'),
    'theta_m': ('model position reference tracked', 'rad'),
    'omega_ff': ('speed feed-forward', 'rad/s'),
    'omega_ref': ('speed reference omega*', 'rad/s'),
    'e_theta': ('position error theta_m - theta_meas', 'rad'),
    'e_omega': ('speed error omega* - omega_meas', 'rad/s'),
    'p_term': ('speed PI proportional term', 'A'),
    'i_term': ('speed PI integral term', 'A'),
    'isq_ref': ('current reference i*sq (speed PI output)', 'A'),
    'saturated': ('speed PI output clamped (0/1)', '-'),
    'isq_cmd': ('current reference commanded', 'A'),
    'load_cmd': ('load torque commanded', 'N m'),
    'status': ('runner status code (0 hold .. 4 fault)', '-'),
    'reason': ('stop reason code', '-'),
    'exp_step': ('local experiment step n (negative in the settle, -1 in hold)', '-'),
    'f1': ('loss integrand |theta* - theta_meas|', 'rad'),
    'f2': ('loss integrand |omega* - omega_meas|', 'rad/s'),
    'f3': ('loss integrand |isqF - i*sq|', 'A'),
    'isq_f': ('filtered current reference isqF', 'A'),
    'counted': ('step counted in the loss (0/1)', '-'),
    'term1': ('running loss term 1', '-'),
    'term2': ('running loss term 2', '-'),
    'term3': ('running loss term 3', '-'),
}

#: The tuned gains, by name (paper eq. 8; docs/controller.md section 1); units from
#: im_controller.config.GAIN_UNITS.
_GAINS: dict[str, str] = {
    'k_pw': 'speed PI proportional gain',
    'k_iw': 'speed PI integral gain',
    'k_pos': 'position P gain',
    'tau_sm': 'smoothing filter time constant',
    'tau_eq': 'position loop equivalent time constant',
}

#: The 5 kHz array topics (absolute, as a run without a namespace records them): their
#: field layouts and the words for each field.
ARRAY_TOPICS: dict[str, tuple[tuple[str, ...], dict[str, tuple[str, str]]]] = {
    '/' + STATE_TOPIC: (STATE_FIELDS, _STATE),
    '/' + COMMAND_TOPIC: (COMMAND_FIELDS, _COMMAND),
    '/' + INTERNALS_TOPIC: (INTERNALS_FIELDS, _INTERNALS),
}

#: The loss topic (``diagnostic_msgs/DiagnosticArray``, one status per experiment, values
#: as key/value strings: im_controller.messages) and the tuner's result topic (one status
#: per results.jsonl record, named by its kind: im_tuner.result_msg) carry these keys; a
#: layout plots them from the result topic.
LOSS_KEY = 'loss'
LOSS_ID_KEY = 'experiment_id'

#: The record kinds (``runlog.records.KINDS``, the result message's status name) as a
#: legend names them.
KIND_WORDS: dict[str, str] = {
    'reference': 'reference',
    'eval': 'evaluations',
    'remeasure': 're-measurements',
}
if tuple(KIND_WORDS) != KINDS:
    raise ValueError(f'foxglove.signals: words for the kinds {tuple(KIND_WORDS)}, not {KINDS}')


def signal(topic: str, index: int) -> Signal:
    """The signal at ``data[index]`` of an array topic (ValueError: no such field, or no
    words for it)."""
    if topic not in ARRAY_TOPICS:
        raise ValueError(f'{topic} is not one of the array topics {sorted(ARRAY_TOPICS)}')
    fields, words = ARRAY_TOPICS[topic]
    if not 0 <= index < len(fields):
        raise ValueError(f'{topic} has {len(fields)} fields, not data[{index}]')
    name = fields[index]
    if name not in words:
        raise ValueError(f'{topic} field {name!r} has no meaning and unit in foxglove.signals')
    meaning, unit = words[name]
    return Signal(name, meaning, unit)


def loss_signals() -> dict[str, Signal]:
    """The plotted values of the loss message and the tuner's result message, by key: the
    experiment's id, its loss and the five gains it ran with (units from
    im_controller.config); KeyError for a gain this module has no words for."""
    out = {
        LOSS_ID_KEY: Signal(LOSS_ID_KEY, 'controller experiment counter', '-'),
        LOSS_KEY: Signal(LOSS_KEY, 'loss of the experiment (paper eq. 4)', '-'),
    }
    for n in GAIN_NAMES:
        out[n] = Signal(n, _GAINS[n], GAIN_UNITS[n])
    return out


def label(s: Signal) -> str:
    """A plot series' label: ``name: meaning [unit]``."""
    return f'{s.name}: {s.meaning} [{s.unit}]'


def index_table() -> str:
    """The index table of docs/foxglove.md (Markdown): every array index of the 5 kHz
    topics with its name, meaning and unit, from the contracts."""
    rows = ['| message path | field | meaning | unit |', '|---|---|---|---|']
    for topic, (fields, _words) in ARRAY_TOPICS.items():
        for i in range(len(fields)):
            s = signal(topic, i)
            meaning = s.meaning.replace('|', '\\|')  # a literal bar inside a table cell
            rows.append(f'| `{topic}.data[{i}]` | `{s.name}` | {meaning} | {s.unit} |')
    return '\n'.join(rows) + '\n'
