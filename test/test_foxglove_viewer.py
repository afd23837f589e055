"""The shipped Foxglove layouts in Foxglove's own app: a run watched live, then its bag.

The viewer is Foxglove Studio 1.48's prebuilt app (the bundle of the npm package
``@foxglove/studio-base``), mounted by a small page of ours with React 17.0.2's UMD builds and
run in Debian's headless Chromium, driven by ``playwright-core``: tools/foxglove-view/
(``view.mjs`` says how). The app connects with its own data sources -- the
Foxglove WebSocket client and the MCAP local-file source -- and loads each installed layout;
what every Plot panel drew is read from the app's own state (the props of each panel's chart:
the points it plots).

1. Live: a short tuner run with its live server (:func:`start_live_run`); an app per view of
   every layout (a layout, or one tab of it) is connected while the run goes on. Every panel
   gets a finite point on every path, and Fig. 9's points are the losses and gains of
   results.jsonl, bit for bit, at their experiment ids.
2. After the fact: the run's bag holds every result (the mcap library, read by time as a
   viewer reads it); opened as a local file, every panel plots finite points on every path,
   and Fig. 9 every experiment of results.jsonl, bit for bit.

Marked ``viewer``: it runs where Chromium (/usr/bin/chromium, or $CHROMIUM), Node.js and npm
are (``.ci/run`` installs them), and skips saying which is missing elsewhere.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest
from ament_index_python.packages import get_package_share_directory

from im_controller.config import GAIN_NAMES
from im_drive_sim.runtime import stop_child
from im_tuner.names import RESULT_TOPIC

REPO = Path(__file__).resolve().parents[1]
VIEW = REPO / 'tools' / 'foxglove-view'
ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
CHROMIUM = Path(os.environ.get('CHROMIUM', '/usr/bin/chromium'))
#: the live run: the lock-step bench, the reference, six evaluations and the re-measurements
RUN_ARGS = ('--budget', '6', '--seed', '1', '--quiet')
#: the longest the viewer waits for a view's panels to fill, and for the app to connect [s]
VIEW_TIMEOUT_S = 120
#: the longest the live run and its viewer may take together, and the bag's viewer [s]
LIVE_DEADLINE_S = 300
BAG_DEADLINE_S = 360
#: the result topic in the bag
RESULT = '/' + RESULT_TOPIC
#: Fig. 9's series path: a result of one kind, one value of it by its key
#: (``/tuner/result.status[:]{name=="eval"}.values[:]{key=="loss"}.value``)
RESULT_PATH = re.compile(r'\{name=="(\w+)"\}\.values\[:\]\{key=="(\w+)"\}\.value$')


def _missing() -> str | None:
    """What this machine lacks to run the viewer, or None."""
    if not CHROMIUM.exists():
        return f'no Chromium at {CHROMIUM} (Debian: apt-get install chromium)'
    for tool in ('node', 'npm'):
        if shutil.which(tool) is None:
            return f'no {tool} on PATH (Node.js and npm run the viewer)'
    return None


# serial: Chromium with six apps of Foxglove takes a core of its own; beside another test
# its pages can take longer than their deadlines to load
pytestmark = [
    pytest.mark.viewer,
    pytest.mark.serial,
    pytest.mark.skipif(_missing() is not None, reason=str(_missing())),
]


def _child(argv: list[str], **kwargs: Any) -> subprocess.Popen:
    """A child whose stdout and stderr go to files (read by :func:`finish`), never a pipe
    nobody reads while the test waits."""
    out = tempfile.TemporaryFile('w+')  # noqa: SIM115 (closed with the test's tmp files)
    err = tempfile.TemporaryFile('w+')  # noqa: SIM115
    proc = subprocess.Popen(argv, stdout=out, stderr=err, text=True, **kwargs)
    proc.files = (out, err)  # type: ignore[attr-defined]
    return proc


#: The WebSocket subprotocol the live server speaks, which the viewer's app then offers: the
#: stand-in's ``foxglove.websocket.v1`` is Studio 1.48's own; foxglove-sdk's server accepts only
#: ``foxglove.sdk.v1``, and the app offers that with this one constant rewritten (view.mjs
#: ``--subprotocol``). With the tuner's own server (foxglove-sdk): ``'foxglove.sdk.v1'``.
LIVE_SUBPROTOCOL = 'foxglove.websocket.v1'


def start_live_run(port: int, out: Path, bench: str = 'inproc') -> subprocess.Popen:
    """A short tuner run (:data:`RUN_ARGS`, on ``bench``) recording to ``out``, its topics
    served live on ws://127.0.0.1:``port`` (``tuner --live``) while it goes on."""
    args = [*RUN_ARGS, '--bench', bench, '--live', str(port), '--out', str(out)]
    return _child([ROS2, 'run', 'im_tuner', 'tuner', *args])


def view(*args: str) -> subprocess.Popen:
    """tools/foxglove-view/view.mjs with ``args`` (its report: one JSON line on stdout)."""
    argv = ['node', str(VIEW / 'view.mjs'), '--timeout', str(VIEW_TIMEOUT_S), *args]
    return _child(argv, cwd=VIEW)


def _read(proc: subprocess.Popen) -> tuple[str, str]:
    texts = []
    for f in proc.files:  # type: ignore[attr-defined]
        f.seek(0)
        texts.append(f.read())
    return texts[0], texts[1]


def finish(proc: subprocess.Popen, deadline_s: float, what: str) -> str:
    """``proc``'s stdout once it exited 0 within ``deadline_s``; its stderr's end if not."""
    try:
        proc.wait(timeout=deadline_s)
    except subprocess.TimeoutExpired:
        stop_child(proc)
        pytest.fail(
            f'{what} still running after {deadline_s} s; stderr ends:\n{_read(proc)[1][-3000:]}'
        )
    out, err = _read(proc)
    assert proc.returncode == 0, f'{what} exited {proc.returncode}:\n{err[-3000:]}'
    return out


def watch(viewer: subprocess.Popen, run: subprocess.Popen, deadline_s: float) -> dict:
    """The live viewer's report, once it and the run ended (within ``deadline_s``); a run
    that fails ends the wait at once."""
    deadline = time.monotonic() + deadline_s
    while viewer.poll() is None and time.monotonic() < deadline:
        if run.poll() not in (None, 0):
            pytest.fail(f'the live run exited {run.returncode}:\n{_read(run)[1][-3000:]}')
        time.sleep(0.2)
    report = json.loads(finish(viewer, max(1.0, deadline - time.monotonic()), 'the live viewer'))
    finish(run, max(1.0, deadline - time.monotonic()), 'the live run')
    return report


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


# -- what a layout shows --------------------------------------------------------------------
def leaves(node: Any) -> list[str]:
    return [node] if isinstance(node, str) else leaves(node['first']) + leaves(node['second'])


def plot_panels(layout: dict) -> list[str]:
    """Every Plot panel of a layout, inside its tabs too."""
    ids = leaves(layout['layout'])
    for pid in list(ids):
        if pid.startswith('Tab!'):
            for tab in layout['configById'][pid]['tabs']:
                ids += leaves(tab['layout'])
    return [p for p in ids if p.startswith('Plot!')]


@pytest.fixture(scope='module')
def layouts_dir() -> Path:
    return Path(get_package_share_directory('im_tuner')) / 'foxglove'


@pytest.fixture(scope='module')
def layouts(layouts_dir: Path) -> dict[str, dict]:
    return {
        f.stem: json.loads(f.read_text(encoding='utf-8'))
        for f in sorted(layouts_dir.glob('*.json'))
    }


@pytest.fixture(scope='module')
def viewer_installed() -> None:
    """tools/foxglove-view's npm packages, installed from its lock file when absent."""
    if (VIEW / 'node_modules' / '@foxglove' / 'studio-base' / 'assets' / 'index.js').exists():
        return
    p = subprocess.run(
        ['npm', 'ci', '--no-audit', '--no-fund'],
        cwd=VIEW,
        capture_output=True,
        text=True,
        timeout=600,
    )
    # (npm is there: a failed install is a failure, not a reason to skip)
    assert p.returncode == 0, f'npm ci in tools/foxglove-view failed: {p.stderr.strip()[-300:]}'


def watch_live_run(layouts_dir: Path, out: Path, *view_args: str, bench: str = 'inproc') -> dict:
    """The viewer's report of a live run (:func:`start_live_run` into ``out``): the viewer
    first, the run once every app of it has loaded (it is then seen from its first
    experiment: the apps retry their connection every 3 s until the server is up)."""
    port = free_port()
    ws = ('--ws', f'ws://127.0.0.1:{port}', '--subprotocol', LIVE_SUBPROTOCOL)
    ready = out.parent / f'{out.name}.viewer_ready'
    viewer = view('--layouts', str(layouts_dir), *ws, '--ready', str(ready), *view_args)
    run = None
    try:
        deadline = time.monotonic() + LIVE_DEADLINE_S
        while not ready.exists() and viewer.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert ready.exists(), f'the viewer did not load its apps: {_read(viewer)[1][-3000:]}'
        run = start_live_run(port, out, bench)
        return watch(viewer, run, LIVE_DEADLINE_S)
    finally:
        for proc in (viewer, run):
            if proc is not None and proc.poll() is None:
                stop_child(proc)


@pytest.fixture(scope='module')
def live(tmp_path_factory, layouts_dir, layouts, viewer_installed) -> tuple[dict, Path]:
    """The viewer's report of a live run, and the run's directory."""
    out = tmp_path_factory.mktemp('foxglove_view') / 'run'
    return watch_live_run(layouts_dir, out), out


def results_by_id(run: Path) -> dict[int, dict]:
    rows = [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]
    return {r['experiment_id']: r for r in rows if r.get('experiment_id') is not None}


def fig9_points(panels: dict) -> dict[tuple[str, str], list[list[float]]]:
    """Fig. 9's series: (record kind, key: ``loss`` or a gain's name) -> its [experiment
    id, value] points in id order, from every path plotted against a custom x axis."""
    out: dict[tuple[str, str], list[list[float]]] = {}
    for series in panels.values():
        for path, s in (series or {}).items():
            if 'points' in s:
                m = RESULT_PATH.search(path)
                assert m, path
                out.setdefault((m.group(1), m.group(2)), []).extend(s['points'])
    return {k: sorted(v) for k, v in out.items()}


def bag_result_ids(bag: Path) -> list[tuple[int, str]]:
    """The bag's tuner/result messages as (experiment id, kind), read with the mcap library
    as a viewer reads a time range: each message found again by a read of its own log time
    (the chunk indexes that a viewer's block reads go by)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    with bag.open('rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, _c, m, msg in reader.iter_decoded_messages(topics=[RESULT]):
            (st,) = msg.status
            key = (int({kv.key: kv.value for kv in st.values}['experiment_id']), st.name)
            again = reader.iter_messages(
                topics=[RESULT], starting_at=m.log_time, ending_at=m.log_time
            )
            assert any(a.data == m.data for _s, _c, a in again), f'{key}: not found at its time'
            out.append(key)
    return out


def expected(row: dict, key: str) -> float | None:
    return row.get('loss') if key == 'loss' else row['gains'][key]


#: Fig. 9's series: each record kind by each of the loss and the five gains
FIG9_SERIES = sorted(
    (kind, key) for kind in ('reference', 'eval', 'remeasure') for key in ('loss', *GAIN_NAMES)
)


# -- the tests ------------------------------------------------------------------------------
def _every_panel_drew(report: dict, layouts: dict) -> None:
    """Every path of every Plot panel of every layout got a finite point while connected."""
    assert report['errors'] == []
    assert sorted(report['layouts']) == sorted(layouts)
    for name, layout in layouts.items():
        seen = report['layouts'][name]
        for pid in plot_panels(layout):
            paths = [p['value'] for p in layout['configById'][pid]['paths']]
            panel = seen['panels'][pid]
            assert panel is not None, f'{name}: {pid} not drawn'
            assert sorted(panel) == sorted(paths), f'{name}: {pid}'
            for path, s in panel.items():
                # a point on every path, while connected: the app left the server after
                assert s['n'] >= 1 and s['finite'], f'{name}: {pid} {path}: {s}'
                assert seen['at'][pid] <= seen['disconnected'], f'{name}: {pid}'


def test_every_panel_of_every_layout_shows_a_live_run_as_it_goes(live, layouts):
    report, run = live
    _every_panel_drew(report, layouts)
    # Fig. 9 live: each point it drew is its experiment's loss or gain, bit for bit, in
    # the series of the experiment's kind
    rows = results_by_id(run)
    points = fig9_points(report['layouts']['fig9_loss_gains']['last'])
    assert sorted(points) == FIG9_SERIES
    for (kind, key), pts in points.items():
        assert len(pts) >= 1, (kind, key)
        for x, y in pts:
            assert x in rows, f'{kind} {key}: experiment id {x} not in results.jsonl'
            assert rows[int(x)]['kind'] == kind, f'{kind} {key}: experiment {x}'
            assert y == expected(rows[int(x)], key), f'{kind} {key} at experiment {x}'


def test_the_runs_bag_opened_as_a_file_shows_every_panel_and_every_experiment(
    live, layouts, layouts_dir
):
    _report, run = live
    bag = sorted((run / 'bag_0').glob('*.mcap'))[0]
    rows = results_by_id(run)
    # the bag itself holds every result, found where a viewer's time-range read looks
    assert bag_result_ids(bag) == [(i, r['kind']) for i, r in sorted(rows.items())]
    report = json.loads(
        finish(
            view('--layouts', str(layouts_dir), '--bag', str(bag)), BAG_DEADLINE_S, 'the bag viewer'
        )
    )
    assert report['errors'] == []
    for name, layout in layouts.items():
        panels = report['layouts'][name]['panels']
        for pid in plot_panels(layout):
            assert panels[pid] is not None, f'{name}: {pid} not drawn'
            for path, s in panels[pid].items():
                assert s['n'] >= 1 and s['finite'], f'{name}: {pid} {path}: {s}'
    # Fig. 9 after the fact: every experiment of results.jsonl in the series of its kind,
    # in id order, bit for bit
    fig9 = report['layouts']['fig9_loss_gains']
    points = fig9_points(fig9['panels'])
    assert sorted(points) == FIG9_SERIES
    for (kind, key), pts in points.items():
        want = [
            [float(i), expected(r, key)]
            for i, r in sorted(rows.items())
            if r['kind'] == kind and expected(r, key) is not None
        ]
        # (the app's player state then: the blocks read for Fig. 9, those not read, problems)
        assert pts == want, (kind, key, fig9['state'])


def test_every_panel_shows_a_real_time_run_live(tmp_path, layouts_dir, layouts, viewer_installed):
    """The same live view of a run on the real-time bench (the 5 kHz topics from the loop's
    outbox tap, at 250 Hz of wall-clock time)."""
    report = watch_live_run(layouts_dir, tmp_path / 'run', bench='realtime')
    _every_panel_drew(report, layouts)
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    assert summary['outcome'] == 'done' and summary['sessions'][-1]['live']['sent'] > 0
