"""The command a drive holds, and the power stage's latch: which command acts over the
coming period. With command delay d = 2 the command answering state k acts over k+1 ->
k+2 (docs/interfaces.md, "Timing model"); the latch here keeps the *labels* of the
commands -- ``applied_step`` and whether it was fresh -- so that each published state
says which command drove the period that ended at it. The values themselves are latched
by the model (``kernels.step_model``) or by the hardware.

Used by both drive nodes; a compiled copy of the same rule, for the GIL-free loop, is
``period_kernel.latch_labels``. Pure Python: no rclpy, no numba.
"""

from __future__ import annotations

#: the labels of no command (zero current: before the first command, a safe stop, the
#: watchdog): applied_step -1, not fresh
NO_COMMAND: tuple[int, bool] = (-1, False)


class CommandLatch:
    """The labels (applied_step, fresh) of the command latched for the next period.

    ``delay``: the drive's command delay d (1 or 2 periods). With 1 nothing waits and
    :meth:`latch` returns its argument."""

    def __init__(self, delay: int) -> None:
        self.delay = delay
        #: delay 2: (applied_step, fresh) of the command latched for the next period
        self.pending: tuple[int, bool] = NO_COMMAND

    def latch(self, applied: int, fresh: bool) -> tuple[int, bool]:
        """The labels of the command that acts over the coming period, given those of the
        command handed to the power stage now: the same with delay 1; with delay 2 the
        one latched a period earlier (and this one waits)."""
        if self.delay == 2:
            acting, self.pending = self.pending, (applied, fresh)
            return acting
        return applied, fresh

    def hold(self, applied: int) -> int:
        """A period the loop missed (it started late): nothing new was handed to the power
        stage, so it latched again the command it holds. Returns the applied_step of the
        command acting over that period: with delay 2 the pending one (``applied``, taken
        but not yet written, waits for the next period's write), with delay 1 ``applied``.
        Neither is fresh any more."""
        if self.delay == 2:
            acting = self.pending[0]
            self.pending = (acting, False)
            return acting
        return applied

    def drop(self) -> None:
        """Forget the latched command (a safe stop, the watchdog: zero current at once)."""
        self.pending = NO_COMMAND


class HeldCommand:
    """The command a drive holds between commands (zero before the first one)."""

    __slots__ = ('answers', 'applied', 'fresh', 'isq_ref', 'load')

    def __init__(self) -> None:
        self.isq_ref = 0.0  #: q-axis current reference [A]
        self.load = 0.0  #: load torque [N m]
        #: its answers_step: the new state's applied_step (-1: none, untagged, zeroed)
        self.applied = -1
        #: it answers the latest published state (or is untagged) and came since the last step
        self.fresh = False
        self.answers = -1  #: answers_step of the newest tagged command taken

    def zero(self) -> None:
        """Zero current and no load, labelled as no command (a safe stop, the watchdog)."""
        self.isq_ref = self.load = 0.0
        self.applied = -1
