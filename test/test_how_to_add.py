"""docs/architecture.md's "How to add" recipes, applied as written: the worked example of
each is taken from the page, added to a copy of the installed package (never to the tree),
run end to end, and removed with the copy.  The recipe's promise is checked with numbers:
how many of the package's files it touched, and that the tuner then runs the new thing."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import im_tuner

ROOT = Path(__file__).resolve().parents[1]
ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def _section_code(title: str) -> list[str]:
    """The ```python blocks of docs/architecture.md's "How to add" subsection ``title``."""
    text = (ROOT / 'docs' / 'architecture.md').read_text()
    body = text.split(f'### {title}\n', 1)[1]
    body = re.split(r'\n#{2,3} ', body, maxsplit=1)[0]
    return re.findall(r'```python\n(.*?)```', body, flags=re.S)


def _package_copy(dest: Path) -> Path:
    """A copy of the installed im_tuner package under ``dest`` (caches left out)."""
    src = Path(im_tuner.__file__).parent
    out = dest / 'im_tuner'
    shutil.copytree(src, out, ignore=shutil.ignore_patterns('__pycache__'))
    return out


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
