"""What a replay feeds a controller and what it compares: read from a recorded bag of the
tuner's in-process benches (pure; docs/replay.md, "How it works").

:func:`load_plan` turns the bag into a :class:`ReplayPlan`: the states the recorded
controller answered, in order; the requests, each before the state it acted on (experiment
i's gains before state ``gains_step``, its start before its first state); the recorded
command answering each fed state, and whether the period it drove was fresh.
:func:`compare` sets replayed commands beside the recorded ones. The node side is
:mod:`im_tuner.replay.node`."""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from im_controller.config import GAIN_NAMES
from im_controller.contract import INTERNALS_TOPIC
from im_controller.layout import (
    INTERNALS_FIELDS,
    LINK_REASONS,
    SAFETY_REASONS,
    STATUS_ABORTED,
    STATUS_DONE,
    STATUS_FAULT,
    STATUS_RUNNING,
)
from im_drive_sim.contract import (
    COMMAND_FIELDS,
    COMMAND_TOPIC,
    STATE_FIELDS,
    STATE_INDEX,
    STATE_TOPIC,
)

from ..rundir import writer_of

#: The simulated clock's topic (absolute, as the drive publishes it).
CLOCK_TOPIC = '/clock'
#: The bag's topics the replay reads (the bench's root namespace).
STATE = '/' + STATE_TOPIC
COMMAND = '/' + COMMAND_TOPIC
INTERNALS = '/' + INTERNALS_TOPIC
#: Metadata record holding the controller's parameters at start (im_tuner.bench.inprocess).
CONTROLLER_RECORD = 'im_tuner.controller'
#: Command fields compared (``answers_step`` is the key, equal by construction).
COMPARED = ('isq_ref', 'load_torque')

_I_STATUS = INTERNALS_FIELDS.index('status')
_K_APPLIED = STATE_INDEX['applied_step']
_K_DELAY = STATE_INDEX['command_delay']


class ReplayError(Exception):
    """The bag cannot be replayed (bad input: one line, exit 2)."""


@dataclass(frozen=True)
class Experiment:
    """One recorded experiment on the drive's timeline."""

    eid: int  #: experiment id
    first_step: int  #: step index of its first state (the first of its settle)
    last_step: int  #: step index of the state that ended it (status done or aborted)
    gains: tuple[float, ...]  #: its gains, ``GAIN_NAMES`` order
    gains_step: int  #: the first state its gains acted on (``LossResult.gains_step``)
    reason: str = ''  #: why it stopped early ('' done)


@dataclass
class ReplayPlan:
    """What to feed, which requests to make when, and what to compare (see module doc)."""

    bag: Path
    mode: str  #: the recorded controller's ``mode``: ``lockstep`` or ``realtime``
    params: dict[str, object]  #: the controller's parameters at start, as recorded
    states: np.ndarray  #: (n, 14) the states to feed, in order
    recorded: np.ndarray  #: (n, 3) the recorded command answering each fed state
    fresh: np.ndarray  #: (n,) bool: the period that command drove was fresh
    experiments: list[Experiment]  #: every experiment with a result, in order
    target: Experiment | None  #: --experiment N, or None: every experiment
    clock_ns: np.ndarray  #: stamps [ns] of the recorded /clock messages, in order
    clock_raw: list[bytes] = field(default_factory=list)  #: their CDR bytes

    @property
    def window(self) -> tuple[int, int]:
        """Step indices [first, last] compared: the target's span, or every fed state."""
        if self.target is not None:
            return self.target.first_step, self.target.last_step
        return int(self.states[0, 0]), int(self.states[-1, 0])

    def compared_mask(self) -> np.ndarray:
        """Fed states whose answers are compared: inside :attr:`window` and, on a
        real-time bag, only those whose command drove a fresh period."""
        k = self.states[:, 0]
        a, b = self.window
        inside = (k >= a) & (k <= b)
        return inside & self.fresh if self.mode == 'realtime' else inside

    def requests(self) -> dict[int, list[tuple[str, object]]]:
        """Fed-state index -> the requests to make before feeding it, in order: the gains
        (``('gains', tuple)``) before the start (``('start', eid)``)."""
        k = self.states[:, 0]
        out: dict[int, list[tuple[str, object]]] = {}
        for e in self.experiments:
            # the first fed state at or after gains_step: the gains acted from there on
            i = int(np.searchsorted(k, e.gains_step))
            if i < len(k):
                out.setdefault(i, []).append(('gains', e.gains))
        for e in self.experiments:
            i = int(np.searchsorted(k, e.first_step))
            out.setdefault(i, []).append(('start', e.eid))
        return out


@dataclass
class Comparison:
    """Replayed commands beside the recorded ones (:func:`compare`)."""

    compared: int  #: commands compared
    differing: int  #: of those, how many differ in any compared field
    max_abs_diff: float  #: the largest |recorded - replayed| over compared fields [A, N m]
    first: dict[str, object] | None  #: the first differing: step, field, recorded, replayed

    @property
    def match(self) -> bool:
        return self.differing == 0


def compare(plan: ReplayPlan, replayed: np.ndarray) -> Comparison:
    """Compare ``replayed`` ((n, 3), the commands the live controller answered each fed
    state with; NaN rows for states it did not answer) with the recorded commands on
    :meth:`ReplayPlan.compared_mask`. Bit for bit: a difference of one ulp counts."""
    mask = plan.compared_mask()
    rec = plan.recorded[mask][:, 1:]
    rep = replayed[mask][:, 1:]
    # NaN-safe "differs": an unanswered state (NaN) differs from any command
    differs = ~(rec == rep)
    rows = np.flatnonzero(differs.any(axis=1))
    diff = np.abs(rec - rep)
    max_abs = float(np.nanmax(diff)) if diff.size and not np.all(np.isnan(diff)) else 0.0
    if rows.size and np.isnan(diff[rows]).any():
        max_abs = math.inf  # a command never came
    first: dict[str, object] | None = None
    if rows.size:
        r = int(rows[0])
        j = int(np.flatnonzero(differs[r])[0])
        first = {
            'step': int(plan.states[mask][r, 0]),
            'field': COMPARED[j],
            'recorded': float(rec[r, j]),
            'replayed': float(rep[r, j]),
        }
    return Comparison(int(mask.sum()), int(rows.size), max_abs, first)


# ---------------------------------------------------------------------------- reading
def _spans(internals: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) step of each experiment in the internals rows (one per answered
    state, in order): it starts at a running/done/aborted row not preceded by a running
    one and ends at its first done/aborted row."""
    k, st = internals[:, 0], internals[:, _I_STATUS]
    spans = []
    prev = -1.0
    start: int | None = None
    for i in range(len(k)):
        s = st[i]
        if start is None and s in (STATUS_RUNNING, STATUS_DONE, STATUS_ABORTED) and prev != 1:
            start = int(k[i])
        if start is not None and s in (STATUS_DONE, STATUS_ABORTED):
            spans.append((start, int(k[i])))
            start = None
        prev = s
    return spans


def load_plan(bag_dir: Path, experiment: int | None = None) -> ReplayPlan:
    """Read ``bag_dir`` and decide the replay (see the module docstring); ReplayError
    (one line) when the bag cannot be replayed or has no experiment ``experiment``."""
    from ..record.reader import BagReadError, find_mcap, read_bag

    try:
        mcap_file = find_mcap(bag_dir)
    except BagReadError as exc:
        hint = ''
        if bag_dir.is_dir() and sorted(bag_dir.glob('bag_*/*.mcap')):
            hint = f' (a run directory: give its bag, {sorted(bag_dir.glob("bag_*"))[0]})'
        raise ReplayError(f'{exc}{hint}') from None
    writer = writer_of(mcap_file)
    if writer is not None:  # its index is written when it closes: not a killed recorder's
        raise ReplayError(
            f'{bag_dir}: being recorded now by {writer}; replay it once its recorder has '
            'closed it (at the end of the run)'
        )
    try:
        data = read_bag(bag_dir, dict.fromkeys((STATE, COMMAND, INTERNALS)), raw=(CLOCK_TOPIC,))
    except (BagReadError, ValueError, OSError) as exc:
        raise ReplayError(f'{bag_dir}: not a readable bag ({exc})') from None
    if not data.complete:
        raise ReplayError(
            f'{mcap_file}: not closed (no end, no index); a bag left by a killed recorder: '
            '`ros2 run im_tuner recorder --repair DIR` first'
        )
    if data.damaged:
        more = f' (and {len(data.damaged) - 1} more)' if len(data.damaged) > 1 else ''
        raise ReplayError(
            f'{bag_dir}: DAMAGED: {data.damaged[0].describe()}{more}: its messages cannot '
            'be trusted, and a replay needs every state the controller saw'
        )
    for topic in (STATE, COMMAND, INTERNALS):
        if topic not in data.topics or not data.topics[topic].count:
            raise ReplayError(f'{bag_dir}: no {topic} messages: nothing to replay')
        lost = (data.recorder_counts or {}).get(topic, {})
        if lost.get('lost', 0) or lost.get('published_before_recording', 0):
            raise ReplayError(
                f'{bag_dir}: {topic} is incomplete ({lost.get("lost", 0)} lost, '
                f'{lost.get("published_before_recording", 0)} before recording): '
                'the controller saw messages the bag does not hold'
            )
    clock_raw = [m for _t, m in sorted(data.raw[CLOCK_TOPIC], key=lambda m: m[0])]
    # rosgraph_msgs/Clock CDR: encapsulation (4 bytes), int32 sec, uint32 nanosec
    sec_ns = np.array([struct.unpack_from('<iI', m, 4) for m in clock_raw], np.int64)
    clock_ns = (sec_ns.reshape(-1, 2) * [1_000_000_000, 1]).sum(axis=1)
    records = data.metadata  # the bag's metadata records, as the reader found them
    if CONTROLLER_RECORD not in records:
        raise ReplayError(
            f'{bag_dir}: no {CONTROLLER_RECORD} record (the controller parameters at start): '
            "only the tuner's in-process benches (inproc, realtime) write it"
        )
    params = json.loads(records[CONTROLLER_RECORD]['parameters'])
    if int(params.get('internals_decimation', 1)) != 1:
        raise ReplayError(
            f'{bag_dir}: internals_decimation is {params["internals_decimation"]}: '
            'the experiments cannot be found on every state'
        )
    mode = str(params.get('mode', 'lockstep'))

    S, Cm, Itn = data.arrays[STATE], data.arrays[COMMAND], data.arrays[INTERNALS]
    if S.shape[1] != len(STATE_FIELDS):
        raise ReplayError(f'{bag_dir}: drive states of {S.shape[1]} values, not the contract')
    if Cm.shape[1] != len(COMMAND_FIELDS) or Itn.shape[1] != len(INTERNALS_FIELDS):
        raise ReplayError(f'{bag_dir}: commands or internals not in the contract layout')
    # a lock-step drive re-sends a state nobody answered: keep each step's first copy
    _, first = np.unique(S[:, 0], return_index=True)
    S = S[np.sort(first)]
    if int(S[0, 0]) != 0:
        raise ReplayError(
            f'{bag_dir}: the drive states begin at step {int(S[0, 0])}, not 0: the controller '
            'saw states before the bag began'
        )
    # the recorded answer to each step (a -1 command answers no state: not fed)
    answers = Cm[Cm[:, 0] >= 0]
    _, last_copy = np.unique(answers[::-1, 0], return_index=True)
    answers = answers[len(answers) - 1 - last_copy]  # sorted by step; the newest copy

    spans = _spans(Itn)
    losses = sorted(data.losses, key=lambda d: int(d['experiment_id']))
    first_id = int(params.get('first_experiment_id', 0))
    experiments = []
    for i, loss in enumerate(losses):
        eid = int(loss['experiment_id'])
        if eid != first_id + i or i >= len(spans):
            raise ReplayError(
                f'{bag_dir}: experiment results {[int(d["experiment_id"]) for d in losses]} '
                f'do not follow the starts in the internals (first id {first_id})'
            )
        experiments.append(
            Experiment(
                eid,
                spans[i][0],
                spans[i][1],
                tuple(float(loss[g]) for g in GAIN_NAMES),
                int(loss['gains_step']),
                loss.get('reason', ''),
            )
        )
    if not experiments:
        raise ReplayError(f'{bag_dir}: no experiment result in the bag')
    target = None
    if experiment is not None:
        ids = [e.eid for e in experiments]
        if experiment not in ids:
            raise ReplayError(
                f'--experiment {experiment}: not in the bag (it holds experiments '
                f'{ids[0]}..{ids[-1]})'
            )
        target = experiments[ids.index(experiment)]
        experiments = experiments[: ids.index(experiment) + 1]
    # a FAULT before the last experiment replayed ends is refused: the fault reset that
    # followed it is a request made at a wall-clock moment the bag does not pin to a state
    end = experiments[-1].last_step
    for e in experiments[:-1]:
        if e.reason in (*SAFETY_REASONS, *LINK_REASONS):
            raise ReplayError(
                f'experiment {e.eid} ended in a safety fault ({e.reason}): a replay cannot '
                'place the fault reset that followed; replay an experiment up to it'
            )
    at = np.flatnonzero((Itn[:, _I_STATUS] == STATUS_FAULT) & (Itn[:, 0] < end))
    if at.size:
        raise ReplayError(
            f'the controller went to FAULT at step {int(Itn[at[0], 0])}: a replay cannot '
            'place the fault reset that followed; replay an experiment before it'
        )

    fed = answers[answers[:, 0] <= end]
    by_step = {int(k): i for i, k in enumerate(S[:, 0])}
    missing = [int(k) for k in fed[:, 0] if int(k) not in by_step]
    if missing:
        raise ReplayError(f'{bag_dir}: a command answers step {missing[0]}, a state not in the bag')
    states = S[[by_step[int(k)] for k in fed[:, 0]]]
    fresh = np.zeros(len(fed), bool)
    for i, k in enumerate(fed[:, 0]):
        row = by_step.get(int(k) + int(states[i, _K_DELAY]))
        fresh[i] = row is not None and S[row, _K_APPLIED] == k
    return ReplayPlan(
        bag=bag_dir,
        mode=mode,
        params=params,
        states=states,
        recorded=fed,
        fresh=fresh,
        experiments=experiments,
        target=target,
        clock_ns=clock_ns,
        clock_raw=clock_raw,
    )
