"""The wait for a replacement recorder (``bench.forms.Children._recorder_died``), without
ROS: a recorder whose subscriptions are on the graph is not ready until its own status
says every publisher is matched (the graph shows subscriptions before DDS matches them:
what a publisher sends in between reaches no bag), as the first recorder's wait does."""

from __future__ import annotations

from pathlib import Path

import pytest

from im_tuner.bench import forms


class Child:
    """A recorder child that lives (poll None) until ``dies_after`` polls (None: never)."""

    def __init__(self, dies_after: int | None = None) -> None:
        self.polls, self.dies_after = 0, dies_after

    def poll(self) -> int | None:
        self.polls += 1
        return -9 if self.dies_after is not None and self.polls > self.dies_after else None


class Watch:
    """The recorder's status as the tuner's watch follows it: matched after ``after``
    spins of the tuner's executor (None: never)."""

    def __init__(self, after: int | None) -> None:
        self.after, self.spins, self.readied, self.expected = after, 0, 0, []

    def matched(self, topics: list[str]) -> bool:
        return self.after is not None and self.spins >= self.after

    def ready(self, received=None) -> None:
        self.readied += 1

    def expect(self, bag: Path) -> None:
        self.expected.append(bag)


class Host:
    def __init__(self, new: Path) -> None:
        self.new, self.lines, self.replaced = new, [], []

    def warn(self, text: str) -> None:
        self.lines.append(text)

    def next_bag(self) -> Path:
        return self.new

    def bag_replaced(self, bag: Path) -> None:
        self.replaced.append(bag)


class Node:
    def get_logger(self):
        return self

    def error(self, _text: str) -> None:
        pass


def _children(tmp_path: Path, watch: Watch, child: Child):
    c = forms.Children.__new__(forms.Children)
    c.node, c.watch, c.host = Node(), watch, Host(tmp_path / 'bag_1')
    c.bag, c.rec_topics, c.recorder_restarts = tmp_path / 'bag_0', ['/l', '/s'], 0
    c.children = {}

    def start(out: Path) -> None:
        c.bag = out
        watch.expect(out)
        c.children['recorder'] = child

    c._start_recorder = start

    def spin_until(pred, timeout=None) -> bool:
        for _ in range(200):  # (a bounded fake executor: one spin per check)
            if pred():
                return True
            watch.spins += 1
        return pred()

    c.spin_until = spin_until
    return c


@pytest.fixture(autouse=True)
def _graph(monkeypatch):
    """The new recorder's subscriptions are on the graph at once; the dead bag repairs."""
    monkeypatch.setattr(forms, 'recorder_endpoints', lambda node, topics: {b'dead'})
    monkeypatch.setattr(forms, 'recorder_subscribed', lambda node, topics, ignore=(): True)

    class Report:
        def summary(self) -> str:
            return 'bag_0: repaired'

    import im_tuner.record.repair as repair

    monkeypatch.setattr(repair, 'repair_bag', lambda bag: Report())


def test_the_replacement_is_ready_once_its_status_says_matched(tmp_path):
    watch, child = Watch(after=7), Child()
    c = _children(tmp_path, watch, child)
    c._recorder_died('killed by signal 9')
    assert watch.expected == [tmp_path / 'bag_1'] and c.host.replaced == [tmp_path / 'bag_1']
    # it spun until the status matched (before the fix: ready on the graph, at 0 spins)
    assert watch.spins == 7 and watch.readied == 1
    assert c.host.lines[-1] == '  recording again into bag_1 (messages in between are in no bag)'
    assert c.recorder_restarts == 1


def test_a_replacement_that_never_matches_is_said(tmp_path, monkeypatch):
    watch, child = Watch(after=None), Child()
    c = _children(tmp_path, watch, child)
    c._recorder_died('exit code 1')
    assert watch.readied == 0 and watch.spins == 200
    assert c.host.lines[-1].startswith(
        '  warning: the new recorder (bag_1) did not subscribe to and match every recorded '
        f'topic within {forms.RECORDER_READY_TIMEOUT:g} s'
    )


def test_a_replacement_that_dies_while_awaited_is_not_ready(tmp_path):
    watch, child = Watch(after=50), Child(dies_after=3)
    c = _children(tmp_path, watch, child)
    c._recorder_died('killed by signal 9')
    assert watch.readied == 0 and watch.spins < 50
    assert 'did not subscribe to and match' in c.host.lines[-1]
