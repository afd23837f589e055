"""The house stays in order. Inside each package no module imports another
that imports it back (lazy and ``TYPE_CHECKING`` imports included: a circle is a circle
whenever it runs), and no subpackage (``im_tuner.bench``, ``im_tuner.record``, ...) is both
above and below another module; no source file over 600 lines; no cache committed; the
top-level benchmarks and the tuner's benches do not share a name; the packages (their
code, tests and config), tests, benchmarks, docs, tools and requirements say what is, not
which issue asked for it (no issue numbers). Static: reads
the sources with ``ast`` and asks git what is tracked, imports nothing."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / 'src'
PACKAGES = ('im_drive_sim', 'im_controller', 'im_tuner')
#: the longest a source file may be (lines)
MAX_LINES = 600
#: the tracked files that name no issue: folders (the packages' code, tests and config
#: included), then single files
NO_ISSUE_DIRS = ('src/', 'test/', 'benchmarks/', 'research/', 'docs/', 'tools/', '.ci/')
NO_ISSUE_FILES = ('Makefile', 'README.md', 'conftest.py', 'requirements.txt', 'constraints.txt')
#: a reference to an issue by its number: "issue" or "issues", a space or a hyphen, the number
#: (a "#" before it allowed)
ISSUE_NUMBER = re.compile(r'\b[Ii]ssues?[ -]#?[0-9]+')


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package's ``__init__``)."""
    out: dict[str, tuple[Path, bool]] = {}
    for pkg in PACKAGES:
        for p in sorted((SRC / pkg / pkg).rglob('*.py')):
            if '__pycache__' in p.parts:
                continue
            parts = list(p.relative_to(SRC / pkg).with_suffix('').parts)
            init = parts[-1] == '__init__'
            out['.'.join(parts[:-1] if init else parts)] = (p, init)
    return out


def _targets(mod: str, init: bool, node: ast.AST, known: frozenset[str]) -> set[str]:
    """The project's modules an import statement in ``mod`` loads (a submodule named in
    ``from pkg import sub`` counts as the submodule, not its package)."""
    out: set[str] = set()
    if isinstance(node, ast.Import):
        out |= {a.name for a in node.names}
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            base = mod.split('.') if init else mod.split('.')[:-1]
            base = base[: len(base) - (node.level - 1)]
            origin = '.'.join(base + ([node.module] if node.module else []))
        else:
            origin = node.module or ''
        for a in node.names:
            out.add(f'{origin}.{a.name}' if f'{origin}.{a.name}' in known else origin)
    return out & known


def _graph(mods: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    g: dict[str, set[str]] = {}
    known = frozenset(mods)
    for m, (path, init) in mods.items():
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            edges |= _targets(m, init, node, known)
        g[m] = edges - {m}
    return g


def _cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(g):
        if root in index:
            continue
        work = [(root, iter(sorted(g[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(g.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _collapsed(g: dict[str, set[str]], mods: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """The graph with each subpackage (``pkg.sub``, a folder) as one node."""

    def node(m: str) -> str:
        head = '.'.join(m.split('.')[:2])
        return head if mods.get(head, (None, False))[1] else m

    out: dict[str, set[str]] = {}
    for m, edges in g.items():
        out.setdefault(node(m), set()).update(node(w) for w in edges)
    return {k: v - {k} for k, v in out.items()}


def test_no_module_circle() -> None:
    assert _cycles(_graph(_modules())) == []


def test_no_subpackage_both_above_and_below_a_module() -> None:
    mods = _modules()
    assert _cycles(_collapsed(_graph(mods), mods)) == []


def test_the_checks_find_a_circle() -> None:
    """The checks can fail: a made-up circle, and one the package had (im_tuner.family
    importing the offline bench from the bench layer, which imports family)."""
    assert _cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    mods = {
        'p.bench': (Path('bench/__init__.py'), True),
        'p.bench.spec': (Path('bench/spec.py'), False),
        'p.bench.offline': (Path('bench/offline.py'), False),
        'p.family': (Path('family.py'), False),
    }
    g = {'p.bench.spec': {'p.family'}, 'p.family': {'p.bench.offline'}, 'p.bench': set()}
    g['p.bench.offline'] = set()
    assert _cycles(g) == []
    assert _cycles(_collapsed(g, mods)) == [['p.bench', 'p.family']]


def _tracked() -> list[str]:
    git = shutil.which('git')
    if git is None or not (ROOT / '.git').exists():
        pytest.skip('not a git checkout: what is tracked cannot be asked')
    p = subprocess.run([git, 'ls-files'], cwd=ROOT, capture_output=True, text=True, check=True)
    return p.stdout.splitlines()


def test_no_source_file_over_600_lines() -> None:
    long = {}
    for pkg in PACKAGES:
        for p in (SRC / pkg).rglob('*.py'):
            if {'build', '__pycache__'} & set(p.parts):
                continue
            n = len(p.read_text().splitlines())
            if n > MAX_LINES:
                long[str(p.relative_to(ROOT))] = n
    assert long == {}


def test_no_cache_committed() -> None:
    caches = ('.cache/', '__pycache__/', '.pytest_cache/', '.mypy_cache/', '.ruff_cache/')
    assert [f for f in _tracked() if any(c in f'/{f}' for c in caches)] == []


def test_benchmarks_and_benches_have_two_names() -> None:
    """The benchmarks live in ``benchmarks/``; ``bench`` is the tuner's (``--bench``,
    ``im_tuner.bench``)."""
    assert [f for f in _tracked() if f.startswith('bench/')] == []
    assert (ROOT / 'benchmarks' / 'run_all.py').is_file()
    assert (SRC / 'im_tuner' / 'im_tuner' / 'bench' / 'spec.py').is_file()


def test_no_issue_numbers_in_the_tracked_tree() -> None:
    found = []
    for f in _tracked():
        path = ROOT / f
        if not (f.startswith(NO_ISSUE_DIRS) or f in NO_ISSUE_FILES) or not path.is_file():
            continue
        data = path.read_bytes()
        if b'\0' in data:  # a figure, not text
            continue
        for n, line in enumerate(data.decode('utf-8', 'replace').splitlines(), 1):
            if ISSUE_NUMBER.search(line):
                found.append(f'{f}:{n}: {line.strip()}')
    assert found == []


def test_the_issue_number_check_finds_them() -> None:
    """The examples are built at run time, so that this file names no issue either."""
    n = 26
    for text in (
        f'(issue {n})',
        f'Issue {n}, item 6:',
        f'issues {n}, 29',
        f'issue-{n}',
        f'issue #{n}',
    ):
        assert ISSUE_NUMBER.search(text), text
    for text in (f'rosbag2 #{n}', 'the issues ask', f'tissue {n}', '#1 SMP PREEMPT_DYNAMIC'):
        assert not ISSUE_NUMBER.search(text), text


#: where an algorithm may be named in a comparison: its own package, and the study, whose
#: Tables I-III compare the paper's two named algorithms (SPSA and neCGA)
ALGO_NAMED_IN = ('im_tuner/optim/', 'im_tuner/study/')


def _algorithm_tests(tree: ast.AST, names: frozenset[str]) -> list[int]:
    """Lines of ``tree`` that compare with an algorithm's name (``algo == 'safe'``,
    ``x in ('safe', ...)``) or probe an optimiser with ``getattr(opt, ...)``."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            consts = [node.left, *node.comparators]
            for c in list(consts):
                if isinstance(c, (ast.Tuple, ast.List, ast.Set)):
                    consts += c.elts
            if any(isinstance(c, ast.Constant) and c.value in names for c in consts):
                out.append(node.lineno)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == 'getattr'
            and node.args
            and 'opt' in ast.unparse(node.args[0]).split('.')[-1]
        ):
            out.append(node.lineno)
    return out


def test_no_algorithm_named_outside_the_optimisers() -> None:
    """An algorithm's special needs are declared in ``optim.options.ALGORITHMS`` and asked
    of the optimiser (``wants_first``): the tuning loop, the tuner's checks, the benches
    and the report never test its name."""
    names = frozenset(('spsa', 'necga', 'cga', 'pecga', 'rcga', 'cmaes', 'tpe', 'safe'))
    found = []
    for pkg in PACKAGES:
        for p in sorted((SRC / pkg / pkg).rglob('*.py')):
            rel = p.relative_to(SRC / pkg).as_posix()
            if '__pycache__' in p.parts or rel.startswith(ALGO_NAMED_IN):
                continue
            found += [f'{rel}:{n}' for n in _algorithm_tests(ast.parse(p.read_text()), names)]
    assert found == []


def test_the_algorithm_name_check_finds_them() -> None:
    names = frozenset(('safe',))
    for text in (
        "if algo != 'safe': pass",
        "ok = cli.algo in ('spsa', 'safe')",
        "w = getattr(self.opt, 'wants_first', False)",
    ):
        assert _algorithm_tests(ast.parse(text), names) == [1], text
    assert (
        _algorithm_tests(ast.parse("x = 'safe'\nif algo in optim.TAKES_FIRST: pass"), names) == []
    )
