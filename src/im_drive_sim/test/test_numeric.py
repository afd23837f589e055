"""The numeric baseline's decision (im_drive_sim.numeric.plan), pure: which environment a
process gets on which CPU, and what it says when it cannot hold the baseline; and that
this test process runs on it (conftest.py imports im_drive_sim before numpy)."""

from __future__ import annotations

import pytest

from im_drive_sim import numeric as N

#: flags of an AVX2 CPU (x86-64-v3, no AVX-512) and of an AVX-512 one
V3 = frozenset(
    ['sse4_2', 'popcnt', 'avx', 'avx2', 'bmi1', 'bmi2', 'f16c', 'fma', 'abm', 'movbe', 'xsave']
)
V4 = V3 | {'avx512f', 'avx512bw', 'avx512cd', 'avx512dq', 'avx512vl'}
V2 = frozenset(['sse4_2', 'popcnt', 'cx16', 'lahf_lm'])
HELD_ENV = {
    'NPY_DISABLE_CPU_FEATURES': 'X86_V4,AVX512_ICL,AVX512_SPR',
    'OPENBLAS_CORETYPE': 'Haswell',
    'OPENBLAS_NUM_THREADS': '1',
}


@pytest.mark.parametrize('flags', [V3, V4], ids=['avx2', 'avx512'])
def test_an_x86_64_v3_cpu_or_wider_gets_the_same_environment(flags: frozenset[str]) -> None:
    p = N.plan({}, flags, 'x86_64')
    assert (p.state, p.reason, p.env) == ('held', '', HELD_ENV)


def test_what_the_environment_already_disables_is_kept_and_not_repeated() -> None:
    p = N.plan({'NPY_DISABLE_CPU_FEATURES': 'AVX512_SPR x86_v4'}, V4, 'x86_64')
    assert p.state == 'held'
    assert p.env['NPY_DISABLE_CPU_FEATURES'] == 'AVX512_SPR,x86_v4,AVX512_ICL'


@pytest.mark.parametrize('core', ['Zen', 'SkylakeX', 'haswell', 'Cooperlake', ''])
def test_an_openblas_held_at_or_above_haswell_is_moved_to_haswell(core: str) -> None:
    p = N.plan({'OPENBLAS_CORETYPE': core}, V4, 'x86_64')
    assert p.state == 'held' and p.env['OPENBLAS_CORETYPE'] == 'Haswell'


@pytest.mark.parametrize(
    ('env', 'flags', 'says'),
    [
        ({}, V2, 'the CPU lacks avx, avx2, bmi1, bmi2, f16c, fma, abm, movbe, xsave (x86-64-v3)'),
        (
            {'NPY_DISABLE_CPU_FEATURES': 'X86_V3 X86_V4'},
            V4,
            'NPY_DISABLE_CPU_FEATURES disables X86_V3',
        ),
        ({'NPY_DISABLE_CPU_FEATURES': 'AVX2'}, V3, 'NPY_DISABLE_CPU_FEATURES disables AVX2'),
        (
            {'OPENBLAS_CORETYPE': 'Sandybridge'},
            V4,
            'OPENBLAS_CORETYPE=Sandybridge is below Haswell',
        ),
        ({'OPENBLAS_CORETYPE': 'Nehalem'}, V3, 'OPENBLAS_CORETYPE=Nehalem is below Haswell'),
    ],
)
def test_below_the_baseline_it_runs_natively_on_one_thread_and_says_why(env, flags, says) -> None:
    p = N.plan(env, flags, 'x86_64')
    assert (p.state, p.reason, p.env) == ('below', says, {'OPENBLAS_NUM_THREADS': '1'})


def test_the_switch_turns_it_off_and_a_bad_value_is_one_line() -> None:
    assert N.plan({N.SWITCH: 'off'}, V4, 'x86_64').env == {}
    assert N.plan({N.SWITCH: 'OFF'}, V4, 'x86_64').state == 'off'
    assert N.plan({N.SWITCH: 'x86-64-v3'}, V4, 'x86_64').env == HELD_ENV
    p = N.plan({N.SWITCH: 'avx512'}, V4, 'x86_64')
    assert (p.state, p.env) == ('invalid', {})
    assert p.reason == "IM_NUMERIC_BASELINE='avx512': must be x86-64-v3 (the default) or off"
    assert N.switch_problem({N.SWITCH: ''}) is None


@pytest.mark.parametrize('machine', ['aarch64', 'arm64'])
def test_another_architecture_is_left_alone(machine: str) -> None:
    p = N.plan({}, frozenset({'neon'}), machine)
    assert (p.state, p.env) == ('unsupported', {})
    assert N.plan({}, None, 'x86_64').state == 'unsupported'  # no /proc/cpuinfo


def test_apply_sets_the_plan_in_the_environment_it_is_given() -> None:
    env = {'NPY_DISABLE_CPU_FEATURES': 'AVX512_SPR', 'PATH': '/bin'}
    p = N.apply(env)
    if p.state == 'held':
        assert env == {
            **HELD_ENV,
            'PATH': '/bin',
            'NPY_DISABLE_CPU_FEATURES': p.env['NPY_DISABLE_CPU_FEATURES'],
        }
        assert env['NPY_DISABLE_CPU_FEATURES'] == 'AVX512_SPR,X86_V4,AVX512_ICL'
    else:
        assert p.state in ('below', 'unsupported')


def test_two_statuses_differ_only_in_what_decides_the_bits() -> None:
    a = {'level': N.LEVEL, 'state': 'held', 'reason': '', 'numpy': ['X86_V3'],
         'openblas': ['Haswell x1'], 'cpu': 'Intel Xeon'}  # fmt: skip
    assert N.differs(a, {**a, 'cpu': 'AMD EPYC'}) is None
    other = {**a, 'state': 'off', 'numpy': ['X86_V3', 'X86_V4'], 'openblas': ['SkylakeX x2']}
    said = N.differs(a, other)
    assert said is not None and 'off x86-64-v3 (numpy X86_V3+X86_V4; OpenBLAS SkylakeX x2)' in said
    assert 'the run began held x86-64-v3 (numpy X86_V3; OpenBLAS Haswell x1)' in said
    assert 'before im_tuner recorded it' in str(N.differs(None, a))


def test_this_test_process_runs_on_the_baseline() -> None:
    """conftest.py imports im_drive_sim before numpy: numpy dispatches at X86_V3 at most and
    every loaded OpenBLAS runs Haswell kernels on one thread (on an x86-64-v3 machine; the
    suite's digests are taken there)."""
    st = N.status()
    if N.apply().state == 'below':
        pytest.skip(f'this machine is below the baseline: {st["reason"]}')
    assert st['state'] == 'held', N.describe(st)
    assert st['numpy'] == ['X86_V3']
    assert st['openblas'] and set(st['openblas']) == {'Haswell x1'}
