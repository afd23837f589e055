"""The drive contract (docs/interfaces.md) as data: topics, QoS, field layouts, counters.

Every side of the drive interface reads these names from here: the simulator node, the
example drive, check_drive, the controller's drive client, the tuner, the recorder and the
report. The module is pure (neither numba nor rclpy), so a tool or a user's drive can read
the contract without compiling kernels or starting ROS; ``runtime.qos_profile`` turns a
:class:`QosSpec` into an rclpy ``QoSProfile``.

Units: times in ns (int), angles in rad, speeds in rad/s, currents in A, torques in N m.
"""

from __future__ import annotations

from dataclasses import dataclass

NS_PER_S = 1_000_000_000

#: Timing modes of a drive: paced by the controller's answers, or by the wall clock.
MODES: tuple[str, ...] = ('lockstep', 'realtime')

# ------------------------------------------------------------------------------ topics
#: Topic names, relative: they follow the drive node's namespace.
STATE_TOPIC = 'drive/state'
COMMAND_TOPIC = 'drive/command'
JOINT_STATE_TOPIC = 'drive/joint_states'
STATUS_TOPIC = 'drive/status'

#: The message type of each drive topic.
TOPIC_TYPES: dict[str, str] = {
    STATE_TOPIC: 'std_msgs/msg/Float64MultiArray',
    COMMAND_TOPIC: 'std_msgs/msg/Float64MultiArray',
    JOINT_STATE_TOPIC: 'sensor_msgs/msg/JointState',
    STATUS_TOPIC: 'diagnostic_msgs/msg/DiagnosticArray',
}

# ------------------------------------------------------------------------------ layouts
#: Layout of ``drive/state`` (Float64MultiArray.data), one sample per period k:
#: step_index k, time_ns = k Ts [ns], the measured position [rad] and speed [rad/s] the
#: controller uses, electromagnetic torque [N m], d/q and alpha/beta stator currents [A],
#: the load torque [N m], the true position [rad] and speed [rad/s], applied_step: the
#: ``answers_step`` of the command the drive applied over the period that ended at this
#: state (-1: none), and command_delay d, the drive's declared command delay (1 or 2): the
#: command answering state k acts over k + d - 1 -> k + d (docs/interfaces.md, "Timing").
STATE_FIELDS: tuple[str, ...] = (
    'step_index',
    'time_ns',
    'theta_meas',
    'omega_meas',
    'torque',
    'isd',
    'isq',
    'i_alpha',
    'i_beta',
    'load_torque',
    'theta',
    'omega',
    'applied_step',
    'command_delay',
)
STATE_INDEX: dict[str, int] = {n: i for i, n in enumerate(STATE_FIELDS)}

#: The command delays a drive can declare (periods; see STATE_FIELDS).
COMMAND_DELAYS: tuple[int, ...] = (1, 2)

#: Layout of ``drive/command``: the state step it answers, the q-axis current reference
#: [A] and the load torque [N m] the bench applies (the simulator's load machine).
COMMAND_FIELDS: tuple[str, ...] = ('answers_step', 'isq_ref', 'load_torque')
CMD_STEP, CMD_ISQ, CMD_LOAD = 0, 1, 2

#: ``drive/status`` counters (a DiagnosticStatus's key/values, in any order; the example
#: drive, real time only, has no ``republished``; meanings: docs/interfaces.md,
#: "drive/status").
STATUS_COUNTERS: tuple[str, ...] = (
    'steps',
    'commands',
    'fresh',
    'held',
    'late',
    'stale_ignored',
    'overruns',
    'missed',
    'republished',
    'max_lateness_us',
    'watchdog_trips',
    'watchdog_steps',
    'backpressure',
)


# --------------------------------------------------------------------------------- QoS
@dataclass(frozen=True)
class QosSpec:
    """A QoS profile as data (rclpy names, lower case): history 'keep_last'/'keep_all',
    depth (samples; 0 with keep_all), reliability 'reliable'/'best_effort', durability
    'volatile'/'transient_local'."""

    history: str
    depth: int
    reliability: str
    durability: str = 'volatile'


#: The 5 kHz lock-step readers: reliable, so no step is lost in transit; in real time a
#: depth of 64 periods (12.8 ms) bridges scheduling hiccups.
LOCKSTEP = QosSpec('keep_last', 64, 'reliable')

#: Every recorded topic's publisher: a reader that falls behind back-pressures it instead
#: of losing samples (docs/interfaces.md, "Topics").
RECORDED = QosSpec('keep_all', 0, 'reliable')

#: The same topics published by a composed real-time loop (``tuner --bench realtime``),
#: whose recorder takes them from the loop's outbox: never blocks, bounded memory.
LOOP_PUBLISHED = QosSpec('keep_last', 1000, 'reliable')

#: The controller's experiment services (start_experiment, reset_fault) and their
#: introspection events: reliable KEEP_LAST 100. rclpy's default (10) drops requests past
#: the tenth when many arrive before the executor takes them.
SERVICES = QosSpec('keep_last', 100, 'reliable')
