"""The controller's contract with its clients (the tuner, tools, a user's own script).

Topics, services and the refusal codes: every refusal ends with ``[code]``, which clients
match instead of the prose (docs/controller.md, "Services, topics").  Pure.
"""

from __future__ import annotations

import re

#: Topics (relative: they follow the controller's namespace).
LOSS_TOPIC = 'controller/loss'
INTERNALS_TOPIC = 'controller/internals'
#: Services (private: ``<controller node>/<name>``), both std_srvs/srv/Trigger.
START_SERVICE = 'start_experiment'
RESET_SERVICE = 'reset_fault'
#: A client's heartbeat (private: ``<controller node>/heartbeat``, std_msgs/msg/Header:
#: stamp = the client's wall time, frame_id = the client's node name), published every
#: ``HEARTBEAT_PERIOD`` s, best effort; stamped zero, the client's goodbye, sent
#: ``HEARTBEAT_GOODBYES`` times (docs/controller.md, "Tuner watchdog").
HEARTBEAT_TOPIC = 'heartbeat'
HEARTBEAT_PERIOD = 0.1  # [s]
HEARTBEAT_GOODBYES = 3

BUSY = 'busy'
FINISHING_MOVE = 'finishing_move'
NO_DRIVE_STATE = 'no_drive_state'
SAFETY_FAULT = 'safety_fault'
TUNER_LOST = 'tuner_lost'
STATE_NOT_FINITE = 'state_not_finite'
INVALID = 'invalid'
REFUSALS: frozenset[str] = frozenset(
    {BUSY, FINISHING_MOVE, NO_DRIVE_STATE, SAFETY_FAULT, TUNER_LOST, STATE_NOT_FINITE, INVALID}
)
#: Refusals that clear by themselves: a client retries them (within its own deadline).
TRANSIENT: frozenset[str] = frozenset({BUSY, FINISHING_MOVE, NO_DRIVE_STATE})

_CODE = re.compile(r' \[([a-z_]+)\]$')
_STARTED = re.compile(r'^experiment (\d+) started$')


def refusal(code: str, text: str) -> str:
    """A refusal message: ``text`` for people, then `` [code]`` for programs."""
    if code not in REFUSALS:
        raise ValueError(f'unknown refusal code {code!r}')
    return f'{text} [{code}]'


def refusal_code(message: str) -> str | None:
    """The code at the end of a refusal message, or None if it carries none."""
    m = _CODE.search(message)
    return m.group(1) if m and m.group(1) in REFUSALS else None


def started(experiment_id: int) -> str:
    """The success message of ``~/start_experiment``."""
    return f'experiment {experiment_id} started'


def started_id(message: str) -> int | None:
    """The experiment id of a ``started()`` message, or None."""
    m = _STARTED.match(message)
    return int(m.group(1)) if m else None
