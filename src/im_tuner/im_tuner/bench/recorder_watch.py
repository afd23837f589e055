"""The tuner's side of the recorder child's status topic (``record/status.py``).

:class:`RecorderWatch` follows the status of the recorder child writing the run's bag
and gives ``bench.forms.Children`` its two waits: before the first experiment, until the
recorder has matched every publisher of the recorded topics (the graph shows its
subscriptions earlier: over a network, seconds earlier); before the recorder is stopped,
until the bag holds every message the tuner itself received on those topics since the
recorder became ready (a reliable message lost on the network reaches the recorder only
after the writer's next heartbeat, though the tuner had its own copy at once).
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..record.status import CATCH_UP_S, TopicStatus, from_msg

#: the recorder child's status (its node is ``recorder``, in no namespace)
RECORDER_STATUS_TOPIC = '/recorder/status'
#: ``spin_until(pred, timeout)``: serve the node until ``pred()`` or the timeout
SpinUntil = Callable[[Callable[[], bool], float | None], bool]


class RecorderWatch:
    """The last status of the recorder child writing :attr:`bag`, and the tuner's own
    counts of received messages (per topic) to hold it to."""

    #: longest wait for the bag to hold what the tuner received, before the stop [s]
    catch_up_s = CATCH_UP_S

    def __init__(self, node: Node) -> None:
        self.bag = ''  #: the bag directory (absolute) whose recorder is followed
        self.status: dict[str, TopicStatus] = {}
        self._received: Callable[[], dict[str, int]] | None = None
        self._at_ready: dict[str, int] = {}
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=10,  # a replaced recorder's last status may still be on the graph
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        node.create_subscription(DiagnosticArray, RECORDER_STATUS_TOPIC, self._on_status, qos)

    def expect(self, bag: Path) -> None:
        """A recorder child is started on ``bag``: follow its status from now on."""
        self.bag = str(bag.resolve())
        self.status = {}

    def _on_status(self, msg: DiagnosticArray) -> None:
        try:
            bag, topics = from_msg(msg)
        except ValueError:
            return  # not a recorder's status
        if bag == self.bag:
            self.status = topics

    def matched(self, topics: list[str]) -> bool:
        """The recorder's own word: every publisher of every topic of ``topics`` matched."""
        return all(t in self.status and self.status[t].matched for t in topics)

    def ready(self, received: Callable[[], dict[str, int]] | None = None) -> None:
        """The recorder is ready: the tuner's counts from here on must be in its bag
        (``received``: the tuner's counts; None: the ones given before, if any)."""
        if received is not None:
            self._received = received
        if self._received is not None:
            self._at_ready = self._received()

    def recorded(self, topic: str) -> int:
        st = self.status.get(topic)
        return 0 if st is None else st.recorded

    def catch_up(self, spin_until: SpinUntil, warn: Callable[[str], None]) -> bool:
        """Wait (at most :attr:`catch_up_s`) until the bag holds every message the tuner
        received since :meth:`ready`; False, after a warning naming the topics, if not."""
        if self._received is None:
            return True
        need = {t: n - self._at_ready.get(t, 0) for t, n in self._received().items()}
        wait = self.catch_up_s
        if spin_until(lambda: all(self.recorded(t) >= n for t, n in need.items()), wait):
            return True
        short = ', '.join(
            f'{t} {self.recorded(t)} of {n}' for t, n in need.items() if self.recorded(t) < n
        )
        warn(
            f'warning: the bag holds fewer messages than the tuner received ({short}) '
            f'{wait:g} s after the last one: lost on the way to the recorder; '
            'results.jsonl has every loss'
        )
        return False


#: [s] a stopped recorder is given to close its bag (a loaded machine can need tens of
#: seconds to shut rclpy down): waiting costs time, a kill costs the bag
RECORDER_CLOSE_TIMEOUT = 120.0
RECORDER_EXIT_AFTER_CLOSE = 5.0  # [s] to exit once its bag is closed (then it is killed)


def recorder_endpoints(node: Node, topics: list[str]) -> set[bytes]:
    """GIDs of the subscriptions a node named ``recorder`` has on ``topics``."""
    return {
        bytes(i.endpoint_gid)
        for t in topics
        for i in node.get_subscriptions_info_by_topic(t)
        if i.node_name == 'recorder'
    }


#: longest wait for a dead recorder's subscriptions to leave the graph [s] (its DDS
#: lease is 1 s: config/recorder_fastdds.xml)
DEAD_RECORDER_GONE_S = 5.0


def wait_recorder_gone(
    node: Node, topics: list[str], timeout: float = DEAD_RECORDER_GONE_S
) -> frozenset[bytes]:
    """Wait until no node named ``recorder`` subscribes to ``topics`` (a killed
    recorder's subscriptions stay on the graph until its DDS lease runs out), at most
    ``timeout`` s. Returns the GIDs of those still there (empty: all gone).

    A replacement waits for it: one whose participant appeared while the reliable writers
    still held samples for the dead one's readers could stall the lock-step bench
    (research/NOTES.md, "A killed recorder's replacement")."""
    deadline = time.monotonic() + timeout
    while (left := recorder_endpoints(node, topics)) and time.monotonic() < deadline:
        time.sleep(0.05)  # graph queries need no spinning
    return frozenset(left)


def recorder_subscribed(
    node: Node, topics: list[str], ignore: frozenset[bytes] = frozenset()
) -> bool:
    """Does a recorder subscribe to every topic of ``topics``? ``ignore``: GIDs of a dead
    recorder's subscriptions, which stay on the graph until its DDS lease runs out
    (about a second): a replacement must not be taken for ready on them."""
    return all(recorder_endpoints(node, [t]) - ignore for t in topics)


def stop_recorder(p: subprocess.Popen, bag: Path | None, warn: Callable[[str], None]) -> int:
    """Stop the recorder child ``p`` recording ``bag``: SIGINT, then wait while it closes
    its bag (a line to ``warn`` every 10 s after the first 5 s); once the bag is closed it
    has RECORDER_EXIT_AFTER_CLOSE s to exit; killed only after RECORDER_CLOSE_TIMEOUT s
    without a closed bag. Its exit code."""
    from ..record.repair import bag_is_closed

    if p.poll() is not None:
        return p.returncode
    p.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    closed_at = None
    said = 5.0
    while p.poll() is None:
        now = time.monotonic() - t0
        if closed_at is None and bag is not None and bag_is_closed(bag):
            closed_at = now
        if (closed_at is not None and now - closed_at > RECORDER_EXIT_AFTER_CLOSE) or (
            closed_at is None and now > RECORDER_CLOSE_TIMEOUT
        ):
            p.kill()
            break
        if closed_at is None and now >= said:
            warn(
                f'  waiting for the recorder to close its bag: {now:.0f} s '
                f'(a loaded machine; killed after {RECORDER_CLOSE_TIMEOUT:g} s)'
            )
            said += 10.0
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=0.2)
    return p.wait()
