"""Golden runs of every optimiser: the asks, states and refusals, bit for bit.

For each algorithm (and a few option variants) and two seeds, a run of ``STEPS`` ask/tell
steps on a fixed deterministic loss writes one line per step: the asked point (``repr``
of each float), the loss, ``evaluations``, ``iterations``, ``converged()`` and the
``state_dict()`` JSON; every ``RESTORE_EVERY`` steps the state is restored
(``Optimizer.from_state``) and the restored optimiser's next ask and state are written.
Then the refusals: bad constructions, bad tells, and checkpoints with one field deleted or
replaced (the message of each, or the restored state).  The text of each block is hashed;
``GOLDEN`` holds the digests taken before the optimisers were restructured, so
any change of an ask, a state's JSON or a refusal message fails here.

``python test_optim_golden.py FILE`` writes the whole text (for ``cmp`` across a change).

Also: ``OLD_CHECKPOINTS`` (``golden_optim_checkpoints.json``) holds one mid-run state per
algorithm written by the code before that change, with its next asks: they must restore
and continue.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from im_tuner.optim import ALGOS, OPTIONS, TAKES_START, Optimizer, make_optimizer

STEPS = 60
RESTORE_EVERY = 13
SEEDS = (3, 11)
START = [0.16, 0.1, 0.19, 0.1, 0.14]

#: (algo, options, with the start point): the defaults of each algorithm and the variants
#: that take other paths (gray coding, newcomer replacement, pe elitism, tpe univariate...)
RUNS: list[tuple[str, dict[str, Any], bool]] = [
    ('spsa', {}, False),
    ('spsa', {'gains': 'spall', 'max_step': math.inf}, True),
    ('necga', {}, False),
    ('necga', {'elite_replacement': 'newcomer', 'n': 6, 'eta': 2}, False),
    ('necga', {'n': 6, 'eta': 2, 'coding': 'gray', 'bits': 7}, False),
    ('necga', {'n': 300, 'eta': 4}, False),  # two bytes per PV field
    ('cga', {}, False),
    ('cga', {'n': 4, 'bits': 3}, False),  # converges within the run
    ('pecga', {'n': 5}, False),
    ('rcga', {}, False),
    ('rcga', {'elitism': 'pe', 'sigma0': 0.5, 'n': 8}, False),
    ('cmaes', {}, False),
    ('cmaes', {'sigma0': 0.3, 'popsize': 5}, True),
    ('tpe', {'n_startup_trials': 4}, True),
    ('tpe', {'multivariate': 'no', 'n_startup_trials': 4}, False),
    ('safe', {}, True),
    ('safe', {'sigma0': 0.3, 'sigma_max': 0.5, 'remeasure_every': 3}, False),
    ('safe', {'model_every': 1, 'abort_shrink': 0.5}, True),
]
#: tpe costs ~20 ms an ask: fewer steps
TPE_STEPS = 24


def loss_of(u: np.ndarray, step: int) -> float:
    """A fixed deterministic loss on [0, 1]^5 (python float arithmetic only)."""
    v = [float(x) for x in u]
    q = sum((x - 0.1 - 0.2 * i) ** 2 for i, x in enumerate(v))
    return q + 0.05 * math.sin(7.0 * v[0] + 3.0 * v[-1]) + 1e-3 * (step % 5)


def aborted_at(step: int) -> bool:
    """Every 9th step is told as an aborted experiment (safe treats it as a constraint)."""
    return step % 9 == 8


def _floats(u: Any) -> str:
    return '[' + ', '.join(repr(float(x)) for x in np.asarray(u).ravel()) + ']'


def _state(opt: Optimizer) -> str:
    return json.dumps(opt.state_dict())


def run_lines(algo: str, opts: dict[str, Any], with_start: bool, seed: Any) -> Iterator[str]:
    """The golden text of one run (see the module docstring)."""
    start = np.array(START) if with_start else None
    opt = make_optimizer(algo, 5, seed, start=start, **opts)
    yield f'config {json.dumps(opt.config())}'
    steps = TPE_STEPS if algo == 'tpe' else STEPS
    for step in range(steps):
        u = opt.ask()
        again = opt.ask()
        assert again.tobytes() == u.tobytes()
        y = loss_of(u, step)
        opt.tell_measurement(u, y, aborted_at(step))
        yield (
            f'{step} ask {_floats(u)} loss {y!r} ev {opt.evaluations} it {opt.iterations} '
            f'conv {opt.converged()} state {_state(opt)}'
        )
        if step % RESTORE_EVERY == RESTORE_EVERY - 1:
            pending = opt.ask()  # a snapshot with a candidate pending
            twin = Optimizer.from_state(json.loads(_state(opt)))
            yield f'{step} restored-pending {_floats(twin.ask())} {_state(twin)}'
            assert twin.ask().tobytes() == pending.tobytes()


def _catch(fn: Callable[..., Any], *args: Any, **kw: Any) -> str:
    """``fn(*args, **kw)``'s refusal (whatever its type) as text, or 'ok' and its result."""
    try:
        out = fn(*args, **kw)
    except Exception as e:
        return f'{type(e).__name__}: {e}'
    return f'ok {out}'


def _config(cls: type[Optimizer], *args: Any, **options: Any) -> dict[str, Any]:
    return cls(*args, **options).config()


def _restored(state: dict[str, Any]) -> str:
    return _state(Optimizer.from_state(state))


def _corruptions(state: dict[str, Any]) -> Iterator[tuple[str, dict[str, Any]]]:
    """The state with one field deleted or replaced (top level and in its config)."""
    for key in list(state):
        for label, value in [
            ('del', None),
            ('x', 'x'),
            ('none', None),
            ('list', []),
            ('num', 0.5),
        ]:
            st = json.loads(json.dumps(state))
            if label == 'del':
                del st[key]
            else:
                st[key] = value
            yield f'{key}:{label}', st
    for key in list(state.get('config', {})):
        for label in ('del', 'x'):
            st = json.loads(json.dumps(state))
            if label == 'del':
                del st['config'][key]
            else:
                st['config'][key] = 'x'
            yield f'config.{key}:{label}', st


def refusal_lines(algo: str) -> Iterator[str]:
    """Refused constructions, tells and checkpoints of ``algo``: each message, or what
    was built instead."""
    cls = type(make_optimizer(algo, 5, 0))
    opts = make_optimizer(algo, 5, 0).config()
    yield f'start {_catch(_config, cls, 5, 0, np.full(5, 0.5))}'
    yield f'dim {_catch(cls, 0, 0)}'
    yield f'seed {_catch(cls, 5, -1)}'
    yield f'option {_catch(cls, 5, 0, None, nope=1)}'
    for name in opts:
        if name in ('algo', 'dim', 'seed', 'start', 'popsize_used', 'pycma', 'optuna'):
            continue
        for bad in ('x', -1, 0, 10**7, 1e9, None, True):
            yield f'option {name}={bad!r} {_catch(_config, cls, 5, 0, None, **{name: bad})}'
    for combo in (
        {'n': 4, 'eta': 4},
        {'n': 4, 'eta': 3},
        {'elitism': 'pe', 'n': 4, 'eta': 9},
        {'sigma0': 0.2},
        {'sigma0': 0.2, 'sigma_max': 0.2},
        {'bounded': 'yes'},
        {'bounded': False},
        {'gains': 'spall', 'alpha': 0.5},
    ):
        yield f'combo {combo} {_catch(_config, cls, 5, 0, None, **combo)}'
    opt = make_optimizer(algo, 5, 0)
    yield f'tell-first {_catch(opt.tell, np.full(5, 0.5), 1.0)}'
    for step in range(11):
        u = opt.ask()
        opt.tell(u, loss_of(u, step))
    states = [opt.state_dict()]
    u = opt.ask()
    states.append(opt.state_dict())
    for bad_u, loss in [(u[:4], 1.0), (u, math.nan), (u, '1'), ('x', 1.0)]:
        yield f'tell {_catch(opt.tell, bad_u, loss)}'
    for which, state in enumerate(states):
        for label, st in _corruptions(state):
            yield f'state{which} {label} {_catch(_restored, st)}'


def blocks(algos: tuple[str, ...] = ALGOS) -> Iterator[tuple[str, Callable[[], Iterator[str]]]]:
    """(name, the lines of the block) for every golden block, in order."""
    variant: dict[str, int] = {}
    for algo, opts, with_start in RUNS:
        variant[algo] = k = variant.get(algo, -1) + 1  # RUNS' k-th run of this algo
        if algo not in algos:
            continue
        ss = np.random.SeedSequence(123).spawn(2)[1]
        for label, seed in [*((str(s), s) for s in SEEDS), ('ss', ss)]:
            yield (
                f'{algo}#{k} seed {label}',
                lambda a=algo, o=opts, w=with_start, s=seed: run_lines(a, o, w, s),
            )
    for algo in algos:
        yield f'refusals {algo}', lambda a=algo: refusal_lines(a)
    yield 'options', option_lines


def option_lines() -> Iterator[str]:
    """The option table: every spec (type, default, help, bounds) and its allowed values."""
    for algo, specs in OPTIONS.items():
        for name, spec in specs.items():
            yield f'{algo} {name} {spec!r} {spec.allowed()}'


def digest(lines: Iterator[str]) -> str:
    h = hashlib.sha256()
    for line in lines:
        h.update(line.encode() + b'\n')
    return h.hexdigest()[:16]


#: block name -> digest of its text, taken before the optimisers were restructured.
GOLDEN: dict[str, str] = {
    'spsa#0 seed 3': '4a598d9546c71890',
    'spsa#0 seed 11': '049ce1365be22946',
    'spsa#0 seed ss': 'b81ce7fd0d66f52f',
    'spsa#1 seed 3': '1eb367ec701e2def',
    'spsa#1 seed 11': '32d4aa213d4d4926',
    'spsa#1 seed ss': 'd94fa9a7250c8d4c',
    'necga#0 seed 3': '60ab271981abf5e6',
    'necga#0 seed 11': '1cfcb822858d50c0',
    'necga#0 seed ss': '579f20ff6f6375ca',
    'necga#1 seed 3': '0199046a94996d64',
    'necga#1 seed 11': '6090b2f61815f186',
    'necga#1 seed ss': 'd562423efc6e834b',
    'necga#2 seed 3': 'f2285711d63f9615',
    'necga#2 seed 11': 'f3ef46336d167982',
    'necga#2 seed ss': 'abe013e159c7afca',
    'necga#3 seed 3': 'f94d41a3e0f6b720',
    'necga#3 seed 11': '4851b8c3a818f299',
    'necga#3 seed ss': '13635b91f0fde802',
    'cga#0 seed 3': 'bf5c865d353a779b',
    'cga#0 seed 11': '0c91cfae763f1d37',
    'cga#0 seed ss': 'a9a16390e4b2e96e',
    'cga#1 seed 3': 'ec844161fba5114f',
    'cga#1 seed 11': 'bba774bebe13b7a5',
    'cga#1 seed ss': 'b535e1647a1f3ae2',
    'pecga#0 seed 3': 'ee186deb9901c7ea',
    'pecga#0 seed 11': '2063a8eb8bffdfc8',
    'pecga#0 seed ss': '0ae57d625b24733a',
    'rcga#0 seed 3': 'd9dd13d46b228db7',
    'rcga#0 seed 11': '42e17e540f036e96',
    'rcga#0 seed ss': '0084896e698bfeb0',
    'rcga#1 seed 3': '40adddbad3a442cf',
    'rcga#1 seed 11': '9743cc8b5ab76ec9',
    'rcga#1 seed ss': '0f737af5d8ea545a',
    'cmaes#0 seed 3': 'b03249dcaf9ec153',
    'cmaes#0 seed 11': '04a69f0a2dfa416c',
    'cmaes#0 seed ss': 'abce12fa449b2e95',
    'cmaes#1 seed 3': '673a86c23436ad94',
    'cmaes#1 seed 11': 'a7a04ce7bc7bfd28',
    'cmaes#1 seed ss': 'c5f4e28c23448523',
    'tpe#0 seed 3': '93f68ca8ec8472dd',
    'tpe#0 seed 11': 'b3f961b410179f44',
    'tpe#0 seed ss': 'd7dcd8678b22069d',
    'tpe#1 seed 3': '55b0313d76ceba31',
    'tpe#1 seed 11': '664a78896de4b3df',
    'tpe#1 seed ss': '2b53581df5ab1156',
    'safe#0 seed 3': '9463989415c3167a',
    'safe#0 seed 11': '7dd518b829d387c9',
    'safe#0 seed ss': '5d915e736a77b905',
    'safe#1 seed 3': 'ff5048284fc40965',
    'safe#1 seed 11': '082c458d9ee02b0e',
    'safe#1 seed ss': 'd7c5ce50d5166c54',
    'safe#2 seed 3': '04f1052682b10d7f',
    'safe#2 seed 11': 'd0323cd5627e82f7',
    'safe#2 seed ss': '099cb75961677b3f',
    'refusals spsa': '13936e536df248fd',
    'refusals necga': '6afe83e23bd1b841',
    'refusals cga': '632e92a7d7c376e8',
    'refusals pecga': '2f80f7eaf36f2958',
    'refusals rcga': '9f656460550f0c52',
    'refusals cmaes': '1f895b463dc8ca9b',
    'refusals tpe': '0f8d4afd965a8a0c',
    'refusals safe': 'f9cf221a0ff538d8',
    'options': 'bac03e0f979a706f',
}


@pytest.mark.parametrize('name', list(GOLDEN))
def test_golden_block(name):
    fn = dict(blocks())[name]
    assert digest(fn()) == GOLDEN[name]


def test_the_golden_table_covers_every_block():
    assert list(GOLDEN) == [name for name, _ in blocks()]
    assert {a for a, _o, _s in RUNS} == set(ALGOS)
    assert {a for a, _o, s in RUNS if s} == TAKES_START


OLD_CHECKPOINTS = Path(__file__).with_name('golden_optim_checkpoints.json')


def checkpoint_table() -> dict[str, Any]:
    """Per algorithm: a state after 17 evaluations with a candidate pending, and the next
    8 asks (``repr`` floats) after telling ``loss_of``."""
    out: dict[str, Any] = {}
    for algo in ALGOS:
        opt = make_optimizer(algo, 5, 7, start=np.array(START) if algo in TAKES_START else None)
        for step in range(17):
            u = opt.ask()
            opt.tell_measurement(u, loss_of(u, step), aborted_at(step))
        opt.ask()
        state = json.loads(json.dumps(opt.state_dict()))  # (safe's holds its live lists)
        asks = []
        for step in range(17, 25):
            u = opt.ask()
            asks.append(_floats(u))
            opt.tell_measurement(u, loss_of(u, step), aborted_at(step))
        out[algo] = {'state': state, 'asks': asks}
    return out


@pytest.mark.parametrize('algo', ALGOS)
def test_an_old_checkpoint_restores_and_continues(algo):
    saved = json.loads(OLD_CHECKPOINTS.read_text())[algo]
    opt = Optimizer.from_state(saved['state'])
    assert json.dumps(opt.state_dict()) == json.dumps(saved['state'])
    for step, expected in enumerate(saved['asks'], start=17):
        u = opt.ask()
        assert _floats(u) == expected
        opt.tell_measurement(u, loss_of(u, step), aborted_at(step))


if __name__ == '__main__':
    if sys.argv[1:2] == ['--checkpoints']:  # (only ever with the code before the re-cut)
        OLD_CHECKPOINTS.write_text(json.dumps(checkpoint_table(), indent=1) + '\n')
    elif sys.argv[1:2] == ['--digests']:
        for name, fn in blocks():
            print(f'    {name!r}: {digest(fn())!r},')
    else:
        with open(sys.argv[1], 'w') as f:
            for name, fn in blocks():
                f.write(f'== {name}\n')
                for line in fn():
                    f.write(line + '\n')
