"""One numeric baseline for every process of the project, ``x86-64-v3``: the same bits on
every x86-64 CPU (what it sets, and why: docs/tuner.md, "The same bits on every machine").
:func:`apply` sets the variables in ``os.environ`` before numpy is imported (``import
im_drive_sim`` calls it), so every child process inherits them; :func:`status` says
whether they hold (``held``, ``off``, ``below``, ``unsupported``, ``invalid``: :class:`Plan`;
``late``: numpy was imported first and runs off the baseline).

Importable without numpy: :func:`plan` is the decision (environment in, environment out);
:func:`status` imports numpy, scipy's BLAS and ``threadpoolctl`` only when asked.
``python -m im_drive_sim.numeric_main`` prints the status; ``--env`` the assignments for a
shell.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping, MutableMapping
from typing import Any, NamedTuple

#: The baseline's name (the x86-64 psABI micro-architecture level).
LEVEL = 'x86-64-v3'
#: The environment variable that turns the baseline off: ``off`` (or ``x86-64-v3``, the
#: default when unset or empty).
SWITCH = 'IM_NUMERIC_BASELINE'
#: numpy 2.4's dispatch targets above x86-64-v3 (``numpy._core._multiarray_umath.
#: __cpu_dispatch__`` minus X86_V3); numpy disables each named one, not what it implies.
NUMPY_ABOVE = ('X86_V4', 'AVX512_ICL', 'AVX512_SPR')
#: numpy's names of x86-64-v3's features: one of them disabled by the environment holds
#: this process below the baseline.
NUMPY_V3 = ('X86_V3', 'AVX', 'AVX2', 'FMA3', 'F16C', 'BMI', 'BMI2', 'LZCNT', 'MOVBE')
#: The CPU flags (/proc/cpuinfo) x86-64-v3 needs (``abm``: LZCNT).
CPU_V3 = ('avx', 'avx2', 'bmi1', 'bmi2', 'f16c', 'fma', 'abm', 'movbe', 'xsave')
#: OpenBLAS's core type at the baseline.
OPENBLAS_CORE = 'Haswell'
#: OpenBLAS core types with at least x86-64-v3's instructions: an environment that holds
#: OpenBLAS at one of these is still at or above the baseline (it is moved to Haswell).
OPENBLAS_V3_OR_ABOVE = frozenset(
    {'haswell', 'zen', 'skylakex', 'cooperlake', 'sapphirerapids', 'excavator'}
)
#: The variables the baseline sets.
VARIABLES = ('NPY_DISABLE_CPU_FEATURES', 'OPENBLAS_CORETYPE', 'OPENBLAS_NUM_THREADS')


class Plan(NamedTuple):  # (not a dataclass: its import slows every executable's start-up)
    """What :func:`plan` decided: ``state`` is ``held`` (the baseline is set), ``off`` (the
    switch), ``below`` (the machine or its environment is below the baseline: native, one
    OpenBLAS thread), ``unsupported`` (not an x86-64 Linux machine: native) or ``invalid``
    (the switch has a value it does not take: nothing set); ``reason`` says why for every
    state but ``held``; ``env``: the variables to set."""

    state: str
    reason: str = ''
    env: dict[str, str] = {}  # noqa: RUF012 (read only)


def switch_problem(environ: Mapping[str, str] | None = None) -> str | None:
    """One line if :data:`SWITCH` holds a value it does not take, else None."""
    value = (os.environ if environ is None else environ).get(SWITCH, '')
    if value.strip().lower() in ('', LEVEL, 'off'):
        return None
    return f'{SWITCH}={value!r}: must be {LEVEL} (the default) or off'


def _cpuinfo(key: str) -> str | None:
    """The first processor's ``key`` line of /proc/cpuinfo ('' if absent); None where
    there is no such file (not Linux)."""
    try:
        with open('/proc/cpuinfo', encoding='ascii', errors='replace') as f:
            for line in f:
                if line.startswith(key):
                    return line.partition(':')[2].strip()
    except OSError:
        return None
    return ''


def cpu_flags() -> frozenset[str] | None:
    """The CPU's flags from /proc/cpuinfo (the first processor's); None where there is no
    such file (not Linux)."""
    text = _cpuinfo('flags')
    return None if text is None else frozenset(text.split())


def plan(environ: Mapping[str, str], flags: frozenset[str] | None, machine: str) -> Plan:
    """The baseline's decision for a process whose environment is ``environ``, on a CPU
    with ``flags`` (:func:`cpu_flags`) and machine type ``machine`` (``os.uname().machine``).
    Pure."""
    problem = switch_problem(environ)
    if problem:
        return Plan('invalid', problem)
    if environ.get(SWITCH, '').strip().lower() == 'off':
        return Plan('off', f'{SWITCH}=off: every library dispatches natively')
    if machine.lower() not in ('x86_64', 'amd64') or flags is None:
        return Plan('unsupported', f'{machine or "this"} machine: the baseline is for x86-64 Linux')
    one_thread = {'OPENBLAS_NUM_THREADS': '1'}
    missing = [f for f in CPU_V3 if f not in flags]
    if missing:
        return Plan('below', f'the CPU lacks {", ".join(missing)} (x86-64-v3)', one_thread)
    disabled = environ.get('NPY_DISABLE_CPU_FEATURES', '').replace(',', ' ').split()
    low = [f for f in disabled if f.upper() in NUMPY_V3]
    if low:
        return Plan('below', f'NPY_DISABLE_CPU_FEATURES disables {", ".join(low)}', one_thread)
    core = environ.get('OPENBLAS_CORETYPE', '').strip()
    if core and core.lower() not in OPENBLAS_V3_OR_ABOVE:
        return Plan('below', f'OPENBLAS_CORETYPE={core} is below {OPENBLAS_CORE}', one_thread)
    upper = {f.upper() for f in disabled}
    features = ','.join([*disabled, *(f for f in NUMPY_ABOVE if f not in upper)])
    return Plan(
        'held',
        env={
            'NPY_DISABLE_CPU_FEATURES': features,
            'OPENBLAS_CORETYPE': OPENBLAS_CORE,
            'OPENBLAS_NUM_THREADS': '1',
        },
    )


#: This process's plan (set by :func:`apply`).
_APPLIED: dict[str, Any] = {}


def apply(environ: MutableMapping[str, str] | None = None) -> Plan:
    """Decide (:func:`plan`) and set the baseline's variables in ``environ`` (this
    process's environment by default): once per process, before numpy is imported for
    it to take effect here; children inherit it either way.  Returns the plan."""
    if environ is None and 'plan' in _APPLIED:
        return _APPLIED['plan']
    env = os.environ if environ is None else environ
    p = plan(env, cpu_flags(), os.uname().machine)
    env.update(p.env)
    if environ is None:
        _APPLIED['plan'] = p
    return p


def _numpy_dispatch() -> list[str]:
    """numpy's dispatch targets enabled in this process."""
    from numpy._core._multiarray_umath import (  # type: ignore[import-not-found]
        __cpu_dispatch__,
        __cpu_features__,
    )

    return [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]


def _blas() -> list[dict[str, Any]]:
    """Every loaded OpenBLAS (numpy's and scipy's): its core type and thread count."""
    with contextlib.suppress(ImportError):  # scipy's own OpenBLAS loads with scipy.linalg
        import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_info

    return [
        {
            'library': os.path.basename(i.get('filepath', '')).split('-')[0],
            'core': i.get('architecture'),
            'threads': i.get('num_threads'),
        }
        for i in threadpool_info()
        if i.get('internal_api') == 'openblas'
    ]


def status() -> dict[str, Any]:
    """This process's numeric baseline as it is (imports numpy): ``level``, ``state``
    (:class:`Plan`'s, or ``late``: numpy was imported first and runs off the baseline),
    ``reason``, ``numpy`` (the dispatch targets enabled) and ``openblas`` (each loaded
    OpenBLAS's core type and threads), ``cpu`` (its model name).  What run.yaml,
    summary.json's sessions and study.json record."""
    p = apply()
    dispatch = _numpy_dispatch()
    blas = _blas()
    state, reason = p.state, p.reason
    if state == 'held':
        off = [t for t in dispatch if t in NUMPY_ABOVE]
        cores = [b for b in blas if b['core'] != OPENBLAS_CORE or b['threads'] != 1]
        if off or cores or 'X86_V3' not in dispatch:
            state = 'late'
            what = off + [f'{b["library"]} {b["core"]} x{b["threads"]}' for b in cores]
            reason = 'numpy was imported before im_drive_sim set the baseline; it runs ' + (
                ', '.join(what) or 'without X86_V3'
            )
    return {
        'level': LEVEL,
        'state': state,
        'reason': reason,
        'numpy': dispatch,
        'openblas': [f'{b["core"]} x{b["threads"]}' for b in blas],
        'cpu': cpu_model(),
    }


#: What decides the bits: two statuses that agree on these give the same results.
_BITS = ('state', 'numpy', 'openblas')


def differs(before: Mapping[str, Any] | None, now: Mapping[str, Any]) -> str | None:
    """One line if ``now`` (:func:`status`) may give other bits than ``before`` (a status
    recorded earlier: a run resumed, a study's worker), else None.  Two ``held`` statuses
    agree whatever their CPUs; an unrecorded ``before`` (a run from before the baseline)
    is said as such."""
    if before is None:
        return f'this session runs {describe(now)}; the run began before im_tuner recorded it'
    if all(before.get(k) == now.get(k) for k in _BITS):
        return None
    return f'this session runs {describe(now)}; the run began {describe(before)}'


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), '' where unknown."""
    return _cpuinfo('model name') or ''


def describe(st: Mapping[str, Any]) -> str:
    """One line of a :func:`status`: ``held x86-64-v3 (numpy X86_V3; OpenBLAS Haswell x1, ..)``."""
    text = (
        f'{st["state"]} {st["level"]} (numpy {"+".join(st["numpy"]) or "baseline"}; '
        f'OpenBLAS {", ".join(st["openblas"]) or "not loaded"})'
    )
    return text + (f': {st["reason"]}' if st.get('reason') else '')
