"""docs/architecture.md's "How to add" recipes, applied as written: the worked example of
each is taken from the page, added to a copy of the installed package (never to the tree),
run end to end, and removed with the copy.  The recipe's promise is checked with numbers:
how many of the package's files it touched (the page's row of docs is the last), and that
the tuner then runs the new thing."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import im_drive_sim
import im_tuner

ROOT = Path(__file__).resolve().parents[1]
ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def _section_code(title: str) -> list[str]:
    """The ```python blocks of docs/architecture.md's "How to add" subsection ``title``."""
    text = (ROOT / 'docs' / 'architecture.md').read_text()
    body = text.split(f'### {title}\n', 1)[1]
    body = re.split(r'\n#{2,3} ', body, maxsplit=1)[0]
    return re.findall(r'```python\n(.*?)```', body, flags=re.S)


def _package_copy(dest: Path, package: object = im_tuner) -> Path:
    """A copy of an installed package under ``dest`` (caches left out: its numba kernels
    compile afresh from the copy's source)."""
    src = Path(package.__file__).parent  # type: ignore[attr-defined]
    out = dest / src.name
    shutil.copytree(src, out, ignore=shutil.ignore_patterns('__pycache__'))
    return out


def _insert(path: Path, edits: list[tuple[str, str, str]]) -> None:
    """Each (anchor, text, where) into ``path``: the anchor stands there once; ``text``
    goes 'after' or 'before' it, or 'replaces' it."""
    text = path.read_text()
    for anchor, new, where in edits:
        assert text.count(anchor) == 1, (path.name, anchor)
        repl = {'after': anchor + new, 'before': new + anchor, 'replaces': new}[where]
        text = text.replace(anchor, repl)
    path.write_text(text)


def _python(code: str, env: dict[str, str], timeout: float = 300) -> str:
    """``code`` run by this interpreter with ``env``; its stdout (the test fails on an
    exit code that is not 0, with the end of stderr)."""
    p = subprocess.run(
        [sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=timeout
    )
    assert p.returncode == 0, p.stderr[-3000:]
    return p.stdout


def _changed(a: Path, b: Path) -> list[str]:
    """Files of tree ``b`` that are new or differ from tree ``a``."""
    out = []
    for f in sorted(b.rglob('*.py')):
        rel = f.relative_to(b)
        if not (a / rel).is_file() or (a / rel).read_bytes() != f.read_bytes():
            out.append(rel.as_posix())
    return out


def test_an_optimiser_added_as_the_recipe_says_tunes_the_bench(tmp_path: Path) -> None:
    module, algorithm, options = _section_code('An optimiser')
    pkg = _package_copy(tmp_path / 'site')
    (pkg / 'optim' / 'toy.py').write_text(module)
    opt_file = pkg / 'optim' / 'options.py'
    text = opt_file.read_text()
    for anchor, entry in (
        ('ALGORITHMS: dict[str, Algorithm] = {\n', algorithm),
        ('OPTIONS: dict[str, dict[str, OptionSpec]] = {\n', options),
    ):
        assert text.count(anchor) == 1, anchor
        text = text.replace(anchor, anchor + entry)
    opt_file.write_text(text)
    # the recipe's files in the package: the module and the declaration (docs: the third)
    assert _changed(Path(im_tuner.__file__).parent, pkg) == ['optim/options.py', 'optim/toy.py']

    env = {**os.environ, 'PYTHONPATH': str(tmp_path / 'site')}
    # the optimiser's contract, from the template: a resumed state asks the same points
    probe = (
        'import json, numpy as np\n'
        'from im_tuner.optim import Optimizer, make_optimizer, describe_options\n'
        "o = make_optimizer('toy', 5, 3, np.full(5, 0.5), spread=0.2)\n"
        'for _ in range(6):\n'
        '    u = o.ask(); o.tell(u, float(np.sum((u - 0.3) ** 2)))\n'
        'r = Optimizer.from_state(json.loads(json.dumps(o.state_dict())))\n'
        "print(json.dumps([o.ask().tolist(), r.ask().tolist(), describe_options('toy')]))\n"
    )
    p = subprocess.run(
        [sys.executable, '-c', probe], env=env, capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0, p.stderr[-2000:]
    asked, resumed, described = json.loads(p.stdout)
    assert asked == resumed and all(0.0 <= v <= 1.0 for v in asked)
    assert 'spread=0.1: half-width of the uniform draws' in described

    # the tuner takes it by name, with its option, on the simulated bench
    args = ['--algo', 'toy', '--opt', 'spread=0.05', '--budget', '3', '--remeasure', '0']
    run = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args, '--bench', 'inproc', '--no-record'],
        env={**env, 'PYTHONUNBUFFERED': '1'},
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    summary = json.loads(next(tmp_path.glob('bags/tuner_toy_*/summary.json')).read_text())
    assert summary['evaluations'] == 3 and summary['outcome'] == 'done', summary
    run_yaml = next(tmp_path.glob('bags/tuner_toy_*/run.yaml')).read_text()
    assert 'algo: toy' in run_yaml and 'spread: 0.05' in run_yaml
    # removed: the tree and the installed package never had it
    assert not (Path(im_tuner.__file__).parent / 'optim' / 'toy.py').exists()
    assert not (ROOT / 'src' / 'im_tuner' / 'im_tuner' / 'optim' / 'toy.py').exists()


#: a loss of one experiment from rest, the hand-tuned start, on a drive file (None: the
#: packaged default) with overrides, stepped through the nodes' Python path
_LOSS = (
    'import json, sys\n'
    'from im_controller.config import Gains\n'
    'from im_drive_sim.drive_file import load_config\n'
    'from im_drive_sim.sim import DriveSim\n'
    'from im_tuner.offline import run_experiment_offline\n'
    'file, over = json.loads(sys.argv[1])\n'
    'cfg = load_config(file, overrides=over)\n'
    'sim = DriveSim(cfg, seed=3)\n'
    'sim.reset(omega=0.0, fluxed=True)\n'
    'r, _ = run_experiment_offline(sim, Gains(), record=False, python_loop=True)\n'
    'extra = {k: getattr(cfg.disturbance, k, None) for k in ("load_offset",)}\n'
    'print(json.dumps([r.loss.hex(), extra]))\n'
)


def _loss(env: dict[str, str], file: str | None, over: dict) -> tuple[str, dict]:
    code = _LOSS.replace('json.loads(sys.argv[1])', repr([file, over]))
    loss, extra = json.loads(_python(code, env).splitlines()[-1])
    return loss, extra


def test_a_bench_effect_added_as_the_recipe_says_acts_only_where_set(tmp_path: Path) -> None:
    key, estimate, word, source, term = _section_code('A bench effect')
    pkg = _package_copy(tmp_path / 'site', im_drive_sim)
    _insert(
        pkg / 'params.py',
        [
            ('\n\n_SECTIONS: dict[str, type] = {\n', key, 'before'),
            ('BENCH_ESTIMATES: dict[str, float] = {\n', estimate, 'after'),
        ],
    )
    _insert(
        pkg / 'model_layout.py',
        [
            ('N_PARAMS = 55\n', word + 'N_PARAMS = 56\n', 'replaces'),
            ('FROM_CONFIG: dict[int, str] = {\n', source, 'after'),
        ],
    )
    _insert(
        pkg / 'kernels.py',
        [
            ('from .model_layout import (\n', '    P_LOAD_OFF,\n', 'after'),
            ('    tl += v\n', term, 'after'),
        ],
    )
    assert _changed(Path(im_drive_sim.__file__).parent, pkg) == [
        'kernels.py',
        'model_layout.py',
        'params.py',
    ]
    env = {**os.environ, 'PYTHONPATH': str(tmp_path / 'site')}
    before, _ = _loss(dict(os.environ), None, {})
    ideal, told = _loss(env, None, {})
    assert ideal == before and told == {'load_offset': 0.0}  # off: not a bit changed
    drive = tmp_path / 'offset.yaml'
    drive.write_text('base: paper_750w\ndisturbance:\n  load_offset: 0.05\n')
    shifted, told = _loss(env, str(drive), {})
    assert told == {'load_offset': 0.05} and shifted != before
    _, told = _loss(env, None, {'realism': 'bench'})
    assert told == {'load_offset': 0.005}  # the bench profile gives it
    assert (
        not (Path(im_drive_sim.__file__).parent / 'model_layout.py').read_text().count('LOAD_OFF')
    )


def test_a_recorded_topic_added_as_the_recipe_says_is_in_the_bag(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    publisher, publish = _section_code('A recorded topic')
    pkg = _package_copy(tmp_path / 'site', im_drive_sim)
    _insert(
        pkg / 'drive_sim_node.py',
        [
            (
                'from rosgraph_msgs.msg import Clock\n',
                'from std_msgs.msg import Float64\n',
                'after',
            ),
            (
                "        self.clock_pub = self.create_publisher(Clock, '/clock', RECORDED_QOS)\n",
                publisher,
                'after',
            ),
            ('        self.send_status(st, values)\n', publish, 'before'),
        ],
    )
    assert _changed(Path(im_drive_sim.__file__).parent, pkg) == ['drive_sim_node.py']
    env = {**os.environ, 'PYTHONPATH': str(tmp_path / 'site'), 'PYTHONUNBUFFERED': '1'}
    args = ['--algo', 'necga', '--budget', '2', '--remeasure', '0', '--seed', '1']
    run = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args, '--bench', 'inproc'],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    values = []
    for bag in sorted(tmp_path.glob('bags/tuner_necga_*/**/*.mcap')):
        with bag.open('rb') as f:
            for schema, channel, message in make_reader(f).iter_messages():
                if channel.topic == '/drive/rotor_resistance':
                    assert schema is not None and schema.name == 'std_msgs/msg/Float64'
                    values.append(_cdr_double(message.data))
    assert values and all(v == 2.1 for v in values), values  # ideal: the file's Rr, no drift
    assert (
        not (Path(im_drive_sim.__file__).parent / 'drive_sim_node.py').read_text().count('rr_pub')
    )


def _cdr_double(cdr: bytes) -> float:
    """A std_msgs/Float64's value from its CDR bytes (the 4-byte encapsulation header,
    then the double)."""
    import struct

    return struct.unpack('<d' if cdr[1] == 1 else '>d', cdr[4:12])[0]


def test_a_named_drive_added_as_the_recipe_says_is_taken_by_name(tmp_path: Path) -> None:
    make, entry = _section_code('A drive form')
    pkg = _package_copy(tmp_path / 'site')
    _insert(pkg / 'bench' / 'drive_spec.py', [('def compiled_example(', make + '\n\n', 'before')])
    _insert(pkg / 'benches.py', [('}\n\n\ndef is_simulated(', entry, 'before')])
    assert _changed(Path(im_tuner.__file__).parent, pkg) == ['bench/drive_spec.py', 'benches.py']
    env = {**os.environ, 'PYTHONPATH': str(tmp_path / 'site')}
    probe = (
        'import json, rclpy\n'
        'from im_tuner.bench.drive_spec import make_drive, resolve\n'
        'from im_tuner.benches import drive_help, is_simulated\n'
        "c = resolve('python', None)\n"
        'ctx = rclpy.Context(); rclpy.init(context=ctx)\n'
        "node = make_drive('python', ctx, [])\n"
        'out = [c.spec, c.form, is_simulated("realtime", "python"), type(node).__name__,\n'
        '       type(node.hw).__name__, node.hw.__module__]\n'
        'node.destroy_node(); rclpy.shutdown(context=ctx)\n'
        'print(json.dumps([out, drive_help()]))\n'
    )
    out, text = json.loads(_python(probe, env).splitlines()[-1])
    assert out == ['python', '', True, 'ExampleDrive', 'Hardware', 'im_drive_sim.example_drive']
    assert "'python' (the example's stand-in plant as a Python class)" in text
    helped = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', '--help'], env=env, capture_output=True, text=True
    )
    assert "'python'" in helped.stdout.replace('\n', ' ')
    refused = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', '--bench', 'realtime', '--drive', 'pyton'],
        env=env,
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert refused.returncode == 2 and "'python'" in refused.stderr, refused.stderr
    assert 'python' not in __import__('im_tuner.benches').benches.NAMED_DRIVES
