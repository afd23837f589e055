"""The run log (im_tuner.runlog): every record kind's exact JSON round trip, the lines the
tuner wrote before the run log existed read back byte for byte, format versions, the
refusal of a malformed line, run.yaml and summary.json, the CSV columns -- and
docs/tuner.md's description of the files checked against the record classes.

data/results_v1.jsonl, run_v1.yaml and summary_v1.json were written by the tuner before
the run log (format 1): a fake-bench run with every record kind (reference, evaluations
ok and aborted, a lost result, an off-timing one, one lost in its settle, a
re-measurement) and a simulated-bench tuner run's run.yaml and summary.json.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import itertools
import json
import re
from pathlib import Path

import pytest

from im_controller.config import GAIN_NAMES
from im_tuner.rundir import RunDir, RunDirError
from im_tuner.runlog import (
    Evaluation,
    Lost,
    Record,
    Reference,
    Remeasurement,
    RunConfig,
    Summary,
    Timing,
)
from im_tuner.runlog.columns import CSV_BOOL, CSV_COLUMNS, CSV_FLOAT, CSV_INT, csv_values
from im_tuner.runlog.files import FileError
from im_tuner.runlog.records import (
    FORMAT_VERSION,
    RECORD_TYPES,
    RecordError,
    check_record,
    parse_results,
)

DATA = Path(__file__).with_name('data')
V1_LINES = (DATA / 'results_v1.jsonl').read_text().splitlines()
DOCS = Path(__file__).resolve().parents[3] / 'docs' / 'tuner.md'
#: the record kind of each line of results_v1.jsonl
V1_KINDS = [
    Reference,
    Evaluation,
    Lost,
    Evaluation,
    Timing,
    Lost,
    Evaluation,
    Evaluation,
    Evaluation,
    Remeasurement,
]


# -- records -----------------------------------------------------------------------------------
@pytest.mark.parametrize('i', range(len(V1_LINES)))
def test_a_line_written_before_the_run_log_reads_back_byte_for_byte(i):
    line = V1_LINES[i]
    rec = Record.from_json(line)
    assert type(rec) is V1_KINDS[i] and rec.version == 1
    assert rec.to_json() == line
    assert Record.from_json(rec.to_json()) == rec
    # the dict of the line, and each of its fields an attribute of the record
    d = json.loads(line)
    assert rec.to_dict() == d and list(rec.to_dict()) == list(d)
    assert all(getattr(rec, k) == v for k, v in d.items()) and rec.extra == {}


def test_every_record_kind_is_in_the_fixture_and_carries_its_fields():
    assert set(V1_KINDS) == set(RECORD_TYPES)
    recs = [Record.from_json(x) for x in V1_LINES]
    timing = next(r for r in recs if isinstance(r, Timing))
    assert timing.loss is None and timing.terms is None and timing.aborted is None
    assert timing.off_timing_loss > 0 and timing.periods == {'fresh': 5618, 'held': 7, 'late': 0}
    assert timing.reason == 'timing: 7 held and 0 late of 5625 drive periods'
    lost_timeout, lost_settle = (r for r in recs if isinstance(r, Lost))
    # no result in time: nothing of the drive's timeline, left out of the line
    assert lost_timeout.periods is None and lost_timeout.gains_step is None
    assert '"periods"' not in lost_timeout.to_json() and lost_timeout.steps is None
    assert lost_timeout.sim_s == 0.0 and lost_timeout.experiment_id == 2
    # lost in its settle: it ran (a fault), so its periods are there
    assert lost_settle.steps == 0 and lost_settle.fault is True and lost_settle.periods
    assert all(r.session == 2 for r in recs)
    evals = [r for r in recs if isinstance(r, Evaluation)]
    assert [r.attempt for r in evals] == [1, 2, 3, 1, 1]
    assert any(r.aborted for r in evals) and all(r.u is not None for r in evals)
    # a field of another kind is not the record's; a record is not read as a dict
    ref = recs[0]
    assert ref.u is None and not hasattr(ref, 'best_loss')
    assert not hasattr(ref, 'off_timing_loss') and not hasattr(ref, 'get')
    with pytest.raises(TypeError):
        ref['u']  # type: ignore[index]


def test_the_tuner_writes_the_lines_it_wrote_before_the_run_log(tmp_path):
    """The fake-bench run that made results_v1.jsonl, run again: the same lines, but
    for the wall-clock fields (``time``; a lost attempt's ``wall_s``)."""
    spec = importlib.util.spec_from_file_location('_tuning_fakes', DATA.parent / 'test_tuning.py')
    assert spec is not None and spec.loader is not None
    fakes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fakes)
    bench = fakes.FakeBench(lose={2})
    bench.off_timing = {4}
    measure = bench.measure

    def settle_fault(gains):  # the 6th experiment ends in its settle on a safety fault
        m = measure(gains)
        if len(bench.calls) == 6:
            m = dataclasses.replace(m, aborted=True, steps=0, reason='max_speed', fault=True)
        return m

    bench.measure = settle_fault
    run = fakes.make_run(tmp_path / 'r', budget=5, remeasure=1)
    run.session = 2
    assert run.run(bench) == 'done'
    new = (tmp_path / 'r' / 'results.jsonl').read_text().splitlines()

    def clock_free(line: str) -> dict:
        d = json.loads(line)
        d['time'] = None
        if d['status'] == 'lost' and d['steps'] is None:
            d['wall_s'] = None
        return d

    assert len(new) == len(V1_LINES)
    for a, b in zip(new, V1_LINES, strict=True):
        assert list(json.loads(a)) == list(json.loads(b))  # the same fields, in order
        assert clock_free(a) == clock_free(b)


def test_a_record_made_in_code_round_trips_exactly():
    recs = [
        Evaluation(
            eval=3,
            status='aborted',
            gains={'k_pw': 0.1 + 0.2},
            u=[1e-300, 0.5],
            loss=12.5,
            terms=[1.0, 2.0, 3.0],
            aborted=True,
            best_loss=None,
            attempt=2,
        ),
        Reference(
            eval=-1,
            status='ok',
            gains={'k_pw': 1.0},
            loss=0.98,
            terms=[0.3] * 3,
            aborted=False,
            session=0,
            periods={'fresh': 1, 'held': 2, 'late': 3},
        ),
        Timing(kind='remeasure', eval=4, gains={}, off_timing_loss=0.7, gains_step=9),
        Lost(kind='eval', eval=0, gains={}, u=[0.25], reason='no loss', experiment_id=None),
    ]
    for rec in recs:
        assert Record.from_json(rec.to_json()) == rec
        assert Record.from_json(rec.to_json()).to_json() == rec.to_json()
        assert '"version"' not in rec.to_json()  # format 1 lines carry none
    # fields written only when set (never as null); the others are written as null
    lost = json.loads(recs[3].to_json())
    assert 'session' not in lost and 'sim_s' not in lost and lost['loss'] is None


def test_an_older_sparse_line_reads_and_writes_back_to_the_same_record():
    line = '{"kind": "eval", "eval": 0, "status": "ok", "u": [0.5], "gains": {"k_pw": 1.0}, "loss": 1, "terms": [1, 0, 0], "aborted": false, "note": "x"}'  # noqa: E501
    rec = Record.from_json(line)
    assert isinstance(rec, Evaluation) and rec.loss == 1 and rec.attempt is None
    assert rec.extra == {'note': 'x'}  # a field this format does not know is kept
    again = Record.from_json(rec.to_json())
    assert again == rec and json.loads(rec.to_json())['note'] == 'x'


# -- versions and refusals ---------------------------------------------------------------------
def test_format_versions():
    d = json.loads(V1_LINES[1])
    assert FORMAT_VERSION == 1
    assert Record.from_dict(d | {'version': 1}).version == 1
    for bad in (FORMAT_VERSION + 1, 0, '1', True):
        with pytest.raises(RecordError, match='record format version'):
            Record.from_dict(d | {'version': bad})
    run = (DATA / 'run_v1.yaml').read_text()
    assert RunConfig.from_text(run).version == 1
    with pytest.raises(FileError, match='format version 2'):
        RunConfig.from_text(run + 'version: 2\n')
    summary = json.loads((DATA / 'summary_v1.json').read_text())
    with pytest.raises(FileError, match='format version 2'):
        Summary.from_dict(summary | {'version': 2})


@pytest.mark.parametrize(
    ('change', 'message'),
    [
        (lambda d: d | {'kind': 'evaluation'}, "record kind 'evaluation' is not one of"),
        (lambda d: d | {'status': 'done'}, "record status 'done' is not one of"),
        (lambda d: d | {'eval': 1.0}, "record without an integer 'eval'"),
        (lambda d: d | {'gains': [1.0]}, "record without 'gains'"),
        (lambda d: d | {'u': None}, "evaluation record without 'u'"),
        (lambda d: {k: v for k, v in d.items() if k != 'loss'}, "record without 'loss'"),
        (lambda d: d | {'terms': 'x'}, "record without 'terms'"),
        (lambda d: d | {'aborted': 0}, "record without 'aborted'"),
        (lambda d: d | {'wall_s': '1'}, "non-numeric 'wall_s'"),
        (lambda d: d | {'steps': 1.5}, "non-integer 'steps'"),
        (lambda d: d | {'periods': {'fresh': 1}}, "'periods' that are not"),
        (lambda d: d | {'status': 'timing'}, "timing record without 'off_timing_loss'"),
    ],
)
def test_a_malformed_line_is_refused(change, message):
    d = change(json.loads(V1_LINES[1]))
    assert message in check_record(d)
    with pytest.raises(RecordError, match=re.escape(message)):
        Record.from_json(json.dumps(d))


def test_a_malformed_line_is_refused_naming_it_and_nothing_changes(tmp_path):
    raw = ('\n'.join(V1_LINES[:3]) + '\n').encode()
    recs, end = parse_results(raw + b'{"kind": "ev')  # a torn last line: not read
    assert len(recs) == 3 and end == len(raw)
    for bad, message in [
        (b'[1, 2]\n', 'line 4 is not a JSON record'),
        (b'{"kind": "eval"}\n', 'line 4: record status None'),
    ]:
        with pytest.raises(RecordError, match=re.escape(message)):
            parse_results(raw + bad)
        rd = RunDir(tmp_path)
        (tmp_path / 'results.jsonl').write_bytes(raw + bad + b'{"tor')
        with pytest.raises(RunDirError, match=re.escape(message)):
            rd.read_results(repair=True)
        assert (tmp_path / 'results.jsonl').read_bytes() == raw + bad + b'{"tor'


# -- run.yaml and summary.json -----------------------------------------------------------------
def test_run_yaml_and_summary_read_and_write_back_byte_for_byte(tmp_path):
    text = (DATA / 'run_v1.yaml').read_text()
    cfg = RunConfig.from_text(text)
    assert cfg.to_text() == text and cfg.algo == 'spsa' and cfg.budget == 4
    assert cfg.model is None and 'model' in cfg.to_dict()  # null in the file: kept
    rd = RunDir(tmp_path)
    (tmp_path / 'run.yaml').write_text(text)
    assert rd.read_config() == cfg
    rd.write_run(RunConfig.from_dict(cfg.to_dict() | {'later': [1, 2]}))  # unknown: kept
    # (the file's start: true is no field of RunConfig -- the start is a policy, under
    # options -- and is kept as the unknown one is)
    assert rd.read_config().extra == {'start': True, 'later': [1, 2]}
    assert (tmp_path / 'run.yaml').read_text() == text + 'later: [1, 2]\n'
    stext = (DATA / 'summary_v1.json').read_text()
    s = Summary.from_text(stext)
    assert s.to_text() == stext and s.evaluations == 4 and s.timing == 0
    rd.write_summary(Summary.from_text(stext))
    assert (tmp_path / 'summary.json').read_text() == stext
    assert rd.read_summary() == s
    (tmp_path / 'summary.json').write_text('{"outcome": ')  # a torn one: none
    assert rd.read_summary() is None
    with pytest.raises(FileError, match='not a tuner run file'):
        RunConfig.from_text('- a list\n')


# -- the CSV export ----------------------------------------------------------------------------
def test_the_csv_columns_are_the_record_fields():
    fields = {f.name for t in RECORD_TYPES for f in dataclasses.fields(t)}
    spread = {'term1', 'term2', 'term3', *GAIN_NAMES, *(f'u{i}' for i in range(5))}
    report = {'run', 'bag'}
    assert set(CSV_COLUMNS) <= fields | spread | report
    # the cells' types read back are those of an evaluation's values
    ev = csv_values(Record.from_json(V1_LINES[1]))
    assert set(CSV_BOOL) == {c for c, v in ev.items() if isinstance(v, bool)}
    assert set(CSV_INT) == {c for c, v in ev.items() if type(v) is int}
    assert set(CSV_FLOAT) == {c for c, v in ev.items() if isinstance(v, float)}
    for line in V1_LINES:
        rec = Record.from_json(line)
        vals = csv_values(rec)
        assert set(vals) == set(CSV_COLUMNS) - report
        assert [vals[n] for n in GAIN_NAMES] == [rec.gains[n] for n in GAIN_NAMES]
        assert vals['term1'] == (rec.terms[0] if rec.terms else None)
        assert vals['t_start_ns'] == rec.t_start_ns and vals['status'] == rec.status


# -- docs/tuner.md -----------------------------------------------------------------------------
def _run_dir_section() -> str:
    text = DOCS.read_text()
    a = text.index('## The run directory')
    return text[a : text.index('\n## ', a + 1)]


def _table(section: str, header: str) -> list[list[str]]:
    """The rows (cells) of the Markdown table whose header line starts with ``header``."""
    lines = section[section.index(header) :].splitlines()[2:]
    rows = itertools.takewhile(lambda x: x.startswith('|'), lines)
    return [[c.strip() for c in x.strip('|').split('|')] for x in rows]


def _names(cell: str) -> set[str]:
    return set(re.findall(r'`(\w+)`', cell))


def test_the_docs_describe_every_record_field_and_nothing_else():
    rows = _table(_run_dir_section(), '| field | meaning |')
    documented = set().union(*(_names(r[0]) for r in rows))
    fields = {f.name for t in RECORD_TYPES for f in dataclasses.fields(t)} - {'extra'}
    assert documented == fields, (
        f'in the docs, not a field: {sorted(documented - fields)}; '
        f'a field the docs do not describe: {sorted(fields - documented)}'
    )


def test_the_docs_describe_every_record_kind_with_its_own_fields():
    rows = _table(_run_dir_section(), '| record | `kind` |')
    by_class = {}
    for r in rows:
        name = re.search(r'\(`(\w+)`\)', r[0])
        assert name, r[0]
        by_class[name.group(1)] = r
    assert set(by_class) == {t.__name__ for t in RECORD_TYPES}
    for t in RECORD_TYPES:
        kind_cell, status_cell, own_cell = by_class[t.__name__][1:]
        # its own fields: those its classes below Record declare (kind, status apart)
        own = {
            n
            for c in t.__mro__[: t.__mro__.index(Record)]
            for n in inspect.get_annotations(c)
            if n not in ('kind', 'status', 'STATUSES')
        }
        assert _names(re.sub(r'\(.*?\)', '', own_cell)) == own, t.__name__
        assert _names(status_cell) == set(t.STATUSES), t.__name__
        default_kind = next(f.default for f in dataclasses.fields(t) if f.name == 'kind')
        assert (
            _names(kind_cell) == {default_kind}
            if isinstance(default_kind, str)
            else kind_cell == 'any'
        ), t.__name__


def test_the_docs_list_every_run_yaml_key():
    section = _run_dir_section()
    block = section[section.index('run.yaml ') : section.index('results.jsonl ')]
    listed = set(re.findall(r'\w+', block.replace('run.yaml', '')))
    keys = {f.name for f in dataclasses.fields(RunConfig)} - {'version', 'extra', 'keys'}
    assert listed == keys
