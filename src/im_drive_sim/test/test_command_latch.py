"""The pieces both drive nodes share: the command latch and the held command,
the watchdog's trip state, and the compiled period's words (period_kernel.pack_words /
unpack_words) -- the same rule as the compiled copy, labels and counters through a round
trip unchanged."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np

from im_drive_sim import period_kernel as W
from im_drive_sim.command_latch import NO_COMMAND, CommandLatch, HeldCommand
from im_drive_sim.drive_sim_counters import Counters, counter_values
from im_drive_sim.pacing import CommandWatchdog


def test_delay_1_latch_passes_the_labels_through() -> None:
    latch = CommandLatch(1)
    assert latch.latch(7, True) == (7, True)
    assert latch.latch(8, False) == (8, False)
    assert latch.pending == NO_COMMAND


def test_delay_2_latch_runs_the_command_of_one_period_earlier() -> None:
    latch = CommandLatch(2)
    assert latch.latch(7, True) == (-1, False)  # nothing latched before the first command
    assert latch.latch(8, True) == (7, True)
    assert latch.latch(8, False) == (8, True)
    latch.drop()  # a safe stop: the latched command never runs
    assert latch.latch(9, True) == (-1, False)


def test_the_python_latch_and_its_compiled_copy_agree() -> None:
    for delay in (1, 2):
        latch = CommandLatch(delay)
        D = np.zeros(W.N_WORDS)
        D[W.D_DELAY] = delay
        D[W.D_PEND_APPLIED] = -1.0
        for applied, fresh in ((3, True), (4, False), (-1, False), (6, True), (7, True)):
            py = latch.latch(applied, fresh)
            nb = W.latch_labels(D, float(applied), float(fresh))
            assert (float(py[0]), float(py[1])) == nb


def test_held_command_zero_labels_no_command() -> None:
    held = HeldCommand()
    held.isq_ref, held.load, held.applied, held.fresh, held.answers = 2.5, 0.75, 41, True, 41
    held.zero()
    assert (held.isq_ref, held.load, held.applied) == (0.0, 0.0, -1)
    assert held.fresh and held.answers == 41  # a zeroed command keeps the newest answer


def test_period_words_round_trip() -> None:
    held, latch, counters = HeldCommand(), CommandLatch(2), Counters()
    held.isq_ref, held.load, held.applied, held.fresh, held.answers = -1.25, 0.5, 12, True, 12
    latch.pending = (11, True)
    counters.steps, counters.commands, counters.late, counters.missed = 13, 12, 2, 1
    constants = {
        'command_delay': 2,
        'wall_clock': True,
        'clock_decimation': 25,
        'joint_state_decimation': 10,
        'ts_ns': 200_000,
    }
    D, DC = W.pack_words(held, latch, True, constants, counters)
    assert D.shape == (W.N_WORDS,) and DC.dtype == np.int64
    assert D[W.D_ISQ] == -1.25 and D[W.D_PEND_APPLIED] == 11 and D[W.D_TS_NS] == 200_000
    assert list(DC) == [13, 12, 0, 0, 2, 0, 1]  # COUNTERS: steps ... stale_ignored, missed
    held2, latch2, counters2 = HeldCommand(), CommandLatch(2), Counters()
    assert W.unpack_words(D, DC, held2, latch2, counters2) is True
    assert vars(counters2) == vars(counters)
    assert latch2.pending == (11, True)
    assert [getattr(held2, n) for n in HeldCommand.__slots__] == [
        getattr(held, n) for n in HeldCommand.__slots__
    ]


def test_compiled_counters_are_the_status_counters_a_period_touches() -> None:
    assert W.COUNTERS == ('steps', 'commands', 'fresh', 'held', 'late', 'stale_ignored', 'missed')


def test_counter_values_text() -> None:
    c = Counters(steps=5, max_lateness_us=12.345)
    text = counter_values(c)
    assert text['steps'] == '5' and text['max_lateness_us'] == '12.3'
    assert list(text) == list(vars(c))


def test_watchdog_trips_once_and_resumes_once() -> None:
    wd = CommandWatchdog(timeout_s=10.0, ts=1.0)  # expires on periods: 10 of them
    assert not wd.expired()  # before the first command it never expires
    wd.command()
    periods = 0
    while not wd.expired():
        periods += 1
        assert periods < 20
    assert periods == 10  # the 11th period without a command is the first expired one
    assert wd.trip() and wd.tripped
    assert not wd.trip()  # said once
    assert wd.resume() and not wd.tripped
    assert not wd.resume()


def _imports(module: object) -> set[str]:
    """Top-level names of what a module's source imports (relative ones as 'im_drive_sim.x')."""
    tree = ast.parse(Path(module.__file__).read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names.add(str(node.module))
        elif isinstance(node, ast.ImportFrom):  # relative: the package's own modules
            names |= {f'im_drive_sim.{node.module or a.name}' for a in node.names}
    return names


def test_the_shared_pure_pieces_import_neither_rclpy_nor_numba() -> None:
    """The latch, the counters and the layout are pure; the QoS module needs rclpy.qos only
    (the controller and the tuner import it without the simulator node or numba)."""
    from im_drive_sim import command_latch, drive_sim_counters, model_layout, qos

    for m in (command_latch, drive_sim_counters, model_layout):
        foreign = {n for n in _imports(m) if n.split('.')[0] not in sys.stdlib_module_names}
        assert foreign <= {'im_drive_sim.contract'}, (m.__name__, foreign)
    assert _imports(qos) - {'__future__'} == {
        'rclpy.qos',
        'im_drive_sim.contract',
    }


def test_a_missed_period_latches_again_what_the_stage_holds() -> None:
    """``hold`` (a period a late loop missed on a power stage): with delay 2 the pending
    command acts again and the one taken meanwhile waits for its write; the compiled
    copy agrees and clears the held command's fresh flag."""
    for delay, want in ((1, 9), (2, 8)):
        latch = CommandLatch(delay)
        latch.latch(8, True)
        assert latch.hold(9) == want
        assert latch.pending == ((8, False) if delay == 2 else NO_COMMAND)
        D = np.zeros(W.N_WORDS)
        D[W.D_DELAY], D[W.D_APPLIED], D[W.D_FRESH] = delay, 9.0, 1.0
        D[W.D_PEND_APPLIED], D[W.D_PEND_FRESH] = 8.0, 1.0
        assert W.hold_labels(D) == want and D[W.D_FRESH] == 0.0
        assert D[W.D_PEND_FRESH] == (0.0 if delay == 2 else 1.0)


def test_the_simulator_counts_held_what_its_states_show_held_around_missed_periods() -> None:
    """A wall-clock simulator (``run_missed`` then ``run_period``), every state answered at
    once, loses 1, 2 and 3 whole periods to late starts: the held counter is what the
    published states show on the drive's timeline (the unseen periods, and every state
    whose ``applied_step`` is not k - d) -- what the controller counts, so a drive never
    counts fewer held periods than the experiments it ran."""
    from im_drive_sim import model_layout as L
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.sim import DriveSim

    for delay in (1, 2):
        sim = DriveSim(load_config(None), seed=0)
        sim.reset(omega=0.0)
        constants = {'command_delay': delay, 'wall_clock': True, 'clock_decimation': 25,
                     'joint_state_decimation': 10, 'ts_ns': 200_000}  # fmt: skip
        D, DC = W.pack_words(HeldCommand(), CommandLatch(delay), False, constants, Counters())
        state = np.zeros(len(L.RUN_FIELDS))
        i64 = [np.zeros(1, np.int64) for _ in range(4)]
        f64 = [np.zeros(1) for _ in range(3)]
        shown = 0
        for n in range(400):
            W.run_missed(sim.S, sim.P, sim._noise, D, DC, state, {100: 1, 200: 2, 300: 3}.get(n, 0))
            W.run_period(sim.S, sim.P, sim._noise, D, DC, state, (i64[0], i64[1]), (*i64[2:], *f64))
            k = int(state[0])
            applied = int(state[W.F_APPLIED])
            shown += applied < 0 or applied != k - delay  # (-1: no command)
            assert W.take_command(D, DC, k, float(k), 0.5, 0.0)  # answered at once: fresh
        steps, held, missed = (int(DC[i]) for i in (W.C_STEPS, W.C_HELD, W.C_MISSED))
        assert (steps, missed) == (406, 6)
        assert held == (steps - 400) + shown, (delay, held, shown)
        # the first d periods before any command; a gap of n: n unseen, then the states
        # of the command held over it (delay 2 after one missed period: on time, fresh)
        gaps = {1: (1 + 1) + (2 + 1) + (3 + 1), 2: (1 + 1) + (2 + 2) + (3 + 2)}
        assert held == delay + gaps[delay], delay
