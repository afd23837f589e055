"""The tuner's result message (im_tuner.result_msg) and the tuning loop's record sink.

A fake-bench run (reference, evaluations some of them aborted, a lost one and one off
timing, re-measurements) hands every record to ``TuningRun.on_record`` as results.jsonl
gets it; each record's message names its kind, carries every value the record has as a
string that reads back bit for bit, and says the status with its level and message.
"""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticStatus
from test_tuning import FakeBench, make_run, records

from im_controller.config import GAIN_NAMES
from im_tuner.names import RESULT_QOS, RESULT_TOPIC, controller_topics
from im_tuner.result_msg import record_to_msg
from im_tuner.runlog import Record


def values(rec: Record) -> tuple[DiagnosticStatus, dict[str, str]]:
    msg = record_to_msg(rec, '/tuner')
    assert len(msg.status) == 1
    st = msg.status[0]
    return st, {kv.key: kv.value for kv in st.values}


def test_every_appended_record_reaches_the_sink_in_order(tmp_path):
    bench = FakeBench(lose={3}, abort_above=0.5)
    bench.off_timing = {5}
    got: list[Record] = []
    run = make_run(tmp_path / 'r', 'necga', budget=8, remeasure=2)
    run.on_record = got.append
    assert run.run(bench) == 'done'
    recs = records(tmp_path / 'r')
    assert [r.to_json() for r in got] == [r.to_json() for r in recs]
    assert {r.status for r in recs} == {'ok', 'aborted', 'lost', 'timing'}
    assert {r.kind for r in recs} == {'reference', 'eval', 'remeasure'}
    for rec in recs:
        st, kv = values(rec)
        assert st.name == rec.kind and st.hardware_id == '/tuner'
        assert kv['status'] == rec.status and kv['kind'] == rec.kind
        assert int(kv['eval']) == rec.eval
        assert {n: float(kv[n]) for n in GAIN_NAMES} == rec.gains  # bit for bit
        if rec.experiment_id is None:
            assert 'experiment_id' not in kv
        else:
            assert int(kv['experiment_id']) == rec.experiment_id
        if rec.status in ('ok', 'aborted'):
            assert float(kv['loss']) == rec.loss
            assert [float(x) for x in kv['terms'].split()] == rec.terms
            assert kv['aborted'] == ('true' if rec.aborted else 'false')
        else:
            assert 'loss' not in kv and 'terms' not in kv  # no loss: no value, no point
            assert 'no loss' in st.message and rec.reason and rec.reason in st.message
        if rec.status == 'ok':
            assert (st.level, st.message) == (DiagnosticStatus.OK, 'ok')
        elif rec.status == 'aborted':
            assert st.level == DiagnosticStatus.WARN and st.message.startswith('aborted')
        elif rec.status == 'timing':
            assert st.level == DiagnosticStatus.WARN
            assert float(kv['off_timing_loss']) == rec.off_timing_loss
            assert int(kv['held']) == rec.periods['held'] == 7
        else:
            assert st.level == DiagnosticStatus.STALE
        if rec.kind == 'eval' and rec.u is not None:
            assert [float(x) for x in kv['u'].split()] == rec.u
        if rec.t_end_ns is not None:
            msg = record_to_msg(rec, '/tuner')
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == rec.t_end_ns
        # every field the record has, and nothing else (gains and periods by name)
        own = {k for k, v in rec.to_dict().items() if v is not None}
        flat = own - {'gains', 'periods'} | set(GAIN_NAMES)
        if 'periods' in own:
            flat |= {'fresh', 'held', 'late'}
        assert set(kv) == flat, rec.kind


def test_a_safety_fault_is_an_error_and_an_unmeasured_ripple_window_is_nan():
    rec = Record.from_dict(
        {
            'kind': 'eval',
            'eval': 4,
            'u': [0.5] * 5,
            'gains': dict.fromkeys(GAIN_NAMES, 0.1),
            'status': 'aborted',
            'loss': 12.5,
            'terms': [1.0, 2.0, 3.0],
            'aborted': True,
            'reason': 'overcurrent',
            'fault': True,
            'experiment_id': 9,
            'ripple': {
                'rms_after_move': 0.25,
                'pp_after_move': 1.0,
                'rms_after_load': None,
                'pp_after_load': None,
            },
        }
    )
    st, kv = values(rec)
    assert st.level == DiagnosticStatus.ERROR
    assert st.message == 'aborted (penalised loss): overcurrent'
    assert kv['fault'] == 'true' and kv['reason'] == 'overcurrent'
    r = [float(x) for x in kv['ripple'].split()]
    assert r[:2] == [0.25, 1.0] and all(math.isnan(x) for x in r[2:])


def test_the_topic_follows_the_controllers_namespace_and_keeps_every_record():
    assert controller_topics('/controller')['result'] == '/' + RESULT_TOPIC
    assert controller_topics('/bench1/controller')['result'] == '/bench1/' + RESULT_TOPIC
    assert (RESULT_QOS.history, RESULT_QOS.reliability, RESULT_QOS.durability) == (
        'keep_all',
        'reliable',
        'transient_local',
    )
