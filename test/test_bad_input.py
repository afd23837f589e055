"""Every executable x every kind of bad input: one line on stderr, exit 2, nothing changed.

The matrix: for each of the nine executables, a wrong flag, an out-of-range
value, NaN/inf, a wrong type, a missing file, a directory instead of a file and a corrupt
file, plus the cases found broken by hand (corrupt run directories for ``--resume`` and
``report``, bad ``--ros-args --params-file``, a bad controller name...). Each case runs in
its own copy of a work directory (cwd) holding the inputs; afterwards the directory must
be exactly as before (no run directory, bag or JSON left behind, no input modified).

The cases run a few at a time in a module fixture (each is a separate process, most of it
Python start-up: a node's command line is refused before numba and rclpy are imported,
test_a_refusal_of_a_node_imports_nothing_heavy); each case is then its own test, named
after the case.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
PAPER = Path(sys.prefix) / 'share' / 'im_drive_sim' / 'config' / 'paper_750w.yaml'
TUNER_YAML = Path(sys.prefix) / 'share' / 'im_tuner' / 'config' / 'tuner.yaml'
CASE_TIMEOUT = 60.0
DISTANCE_1000 = 'trajectory.distance:=1000.0'

EXES = {
    'drive_sim': ('im_drive_sim', 'drive_sim'),
    'example_drive': ('im_drive_sim', 'example_drive'),
    'controller': ('im_controller', 'controller'),
    'sim_bench': ('im_tuner', 'sim_bench'),
    'drive_host': ('im_tuner', 'drive_host'),
    'check_drive': ('im_drive_sim', 'check_drive'),
    'host_check': ('im_drive_sim', 'host_check'),
    'recorder': ('im_tuner', 'recorder'),
    'report': ('im_tuner', 'report'),
    'study': ('im_tuner', 'study'),
    'tuner': ('im_tuner', 'tuner'),
}
NODES = ('drive_sim', 'example_drive', 'controller', 'sim_bench', 'recorder')


def _params_file_cases(exe: str) -> list[tuple[str, str, list[str]]]:
    """--ros-args --params-file: missing, a directory, not YAML, YAML that is not ROS's."""
    return [
        (exe, f'params-file-{kind}', ['--ros-args', '--params-file', f])
        for kind, f in (
            ('missing', 'missing.yaml'),
            ('directory', 'adir'),
            ('corrupt', 'corrupt.yaml'),
            ('not-ros', 'notros.yaml'),
        )
    ]


def _file_cases(
    exe: str, flag: str, extra: tuple[str, ...] = ()
) -> list[tuple[str, str, list[str]]]:
    return [
        (exe, f'{flag[2:]}-{kind}', [flag, f, *extra])
        for kind, f in (
            ('missing', 'missing.yaml'),
            ('directory', 'adir'),
            ('corrupt', 'corrupt.yaml'),
            ('wrong-yaml', 'notros.yaml'),
        )
    ]


CASES: list[tuple[str, str, list[str]]] = [
    # -- wrong flag, every executable
    *[(exe, 'wrong-flag', ['--no-such-flag']) for exe in EXES],
    # -- drive_sim
    ('drive_sim', 'mode-bad', ['--mode', 'fast']),
    ('drive_sim', 'seed-negative', ['--seed', '-1']),
    ('drive_sim', 'seed-type', ['--seed', 'abc']),
    ('drive_sim', 'max-steps-negative', ['--max-steps', '-5']),
    ('drive_sim', 'p-seed-type', ['--ros-args', '-p', 'seed:=abc']),
    ('drive_sim', 'p-read-only-state-fields', ['--ros-args', '-p', 'state_fields:=[a,b]']),
    *_file_cases('drive_sim', '--drive-config'),
    *_params_file_cases('drive_sim'),
    # -- example_drive
    ('example_drive', 'p-timeout-negative', ['--ros-args', '-p', 'command_timeout:=-1.0']),
    ('example_drive', 'p-timeout-nan', ['--ros-args', '-p', 'command_timeout:=.nan']),
    ('example_drive', 'p-isq-max-type', ['--ros-args', '-p', 'isq_max:=abc']),
    ('example_drive', 'p-isq-max-inf', ['--ros-args', '-p', 'isq_max:=.inf']),
    *_params_file_cases('example_drive'),
    # -- controller
    ('controller', 'mode-bad', ['--mode', 'fast']),
    ('controller', 'p-gain-negative', ['--ros-args', '-p', 'k_pw:=-1.0']),
    ('controller', 'p-gain-nan', ['--ros-args', '-p', 'k_pw:=.nan']),
    ('controller', 'p-gain-inf', ['--ros-args', '-p', 'k_pos:=.inf']),
    ('controller', 'p-gain-type', ['--ros-args', '-p', 'k_pw:=abc']),
    ('controller', 'p-isq-max-above-drive', ['--ros-args', '-p', 'safety.isq_max:=20.0']),
    # a 25 s move in a 1.125 s experiment (config.MOVE_RULE)
    ('controller', 'p-move-longer-than-experiment', ['--ros-args', '-p', DISTANCE_1000]),
    ('controller', 'config-comments-only', ['--drive-config', 'comments.yaml']),
    *_file_cases('controller', '--drive-config'),
    *_params_file_cases('controller'),
    # -- sim_bench
    ('sim_bench', 'seed-negative', ['--seed', '-1']),
    ('sim_bench', 'seed-type', ['--seed', '1.5']),
    ('sim_bench', 'compression-bad', ['--compression', 'gzip']),
    ('sim_bench', 'out-is-a-file', ['--out', 'corrupt.yaml']),
    ('sim_bench', 'processes-seed-negative', ['--processes', '--seed', '-1']),
    ('sim_bench', 'p-isq-max-above-drive', ['--ros-args', '-p', 'safety.isq_max:=20.0']),
    ('sim_bench', 'p-move-longer-than-experiment', ['--ros-args', '-p', DISTANCE_1000]),
    (
        'sim_bench',
        'processes-p-move-longer-than-experiment',
        ['--processes', '--ros-args', '-p', DISTANCE_1000],
    ),
    ('sim_bench', 'out-with-no-record', ['--out', 'newbag', '--no-record']),
    ('sim_bench', 'out-cannot-be-created', ['--out', '/proc/im_tuner_nowhere/bag']),
    ('sim_bench', 'compression-with-no-record', ['--compression', 'zstd', '--no-record']),
    *_file_cases('sim_bench', '--drive-config'),
    *[
        ('sim_bench', 'processes-' + n, a)
        for _e, n, a in _file_cases('sim_bench', '--drive-config', ('--processes',))
    ],
    *_params_file_cases('sim_bench'),
    # -- drive_host
    ('drive_host', 'tuner-timeout-zero', ['--tuner-timeout', '0']),
    ('drive_host', 'tuner-timeout-nan', ['--tuner-timeout', 'nan']),
    ('drive_host', 'timing-tolerance-negative', ['--timing-tolerance', '-1']),
    ('drive_host', 'timing-tolerance-type', ['--timing-tolerance', 'few']),
    # -- host_check
    ('host_check', 'seconds-zero', ['--seconds', '0']),
    ('host_check', 'seconds-nan', ['--seconds', 'nan']),
    ('host_check', 'seconds-too-long', ['--seconds', '7200']),
    ('host_check', 'timing-tolerance-negative', ['--timing-tolerance', '-1']),
    ('host_check', 'spin-above-the-period', ['--spin-us', '300']),
    ('host_check', 'thread-priority-100', ['--thread-priority', '100']),
    ('drive_host', 'drive-unknown-module', ['--drive', 'no_such_module:Drive']),
    ('drive_host', 'drive-missing-library', ['--drive', 'lib:missing.so']),
    ('drive_host', 'model-with-example', ['--drive', 'example', '--model', 'reduced']),
    ('drive_host', 'out-is-a-file', ['--out', 'corrupt.yaml']),
    ('drive_host', 'out-with-no-record', ['--out', 'newbag', '--no-record']),
    ('drive_host', 'out-cannot-be-created', ['--out', '/proc/im_tuner_nowhere/bag']),
    ('drive_host', 'p-isq-max-above-drive', ['--ros-args', '-p', 'safety.isq_max:=20.0']),
    ('drive_host', 'p-unknown', ['--ros-args', '-p', 'no_such_param:=1']),
    ('drive_host', 'drive-hardware-hangs', ['--drive', 'bad_drives:HangingHardware']),
    ('sim_bench', 'p-unknown', ['--ros-args', '-p', 'k_pww:=1.0']),
    *_file_cases('drive_host', '--drive-config'),
    # -- check_drive (all of these before any probing)
    ('check_drive', 'amplitude-negative', ['--amplitude', '-0.5']),
    ('check_drive', 'amplitude-nan', ['--amplitude', 'nan']),
    ('check_drive', 'amplitude-type', ['--amplitude', 'half']),
    ('check_drive', 'timeout-inf', ['--timeout', 'inf']),
    ('check_drive', 'json-directory', ['--json', 'adir']),
    ('check_drive', 'json-in-missing-directory', ['--json', 'nowhere/x.json']),
    ('check_drive', 'thread-priority-range', ['--thread-priority', '100']),
    ('check_drive', 'cpu-affinity-absent', ['--cpu-affinity', '4096']),
    *_file_cases('check_drive', '--drive-config'),
    # -- recorder
    ('recorder', 'chunk-size-huge', ['--chunk-size', str(1 << 50)]),
    ('recorder', 'chunk-size-zero', ['--chunk-size', '0']),
    ('recorder', 'chunk-size-type', ['--chunk-size', '1MB']),
    ('recorder', 'max-chunk-age-nan', ['--max-chunk-age', 'nan']),
    ('recorder', 'max-chunk-age-inf', ['--max-chunk-age', 'inf']),
    ('recorder', 'max-chunk-age-negative', ['--max-chunk-age', '-1']),
    ('recorder', 'compression-bad', ['--compression', 'gzip']),
    ('recorder', 'out-is-a-file', ['--out', 'corrupt.yaml']),
    ('recorder', 'out-cannot-be-created', ['--out', '/proc/im_tuner_nowhere/bag']),
    ('recorder', 'out-not-empty', ['--out', 'run']),
    ('recorder', 'repair-missing', ['--repair', 'missing_bag']),
    ('recorder', 'repair-not-a-bag', ['--repair', 'adir']),
    ('recorder', 'repair-a-file', ['--repair', 'corrupt.yaml']),
    ('recorder', 'repair-with-out', ['--repair', 'run_bad_metadata/bag_0', '--out', 'newbag']),
    ('recorder', 'exclude-empty', ['--exclude-topics', '']),
    ('recorder', 'exclude-space', ['--exclude-topics', '/bad topic!']),
    ('recorder', 'exclude-pattern', ['--exclude-topics', '/drive/*']),
    *_params_file_cases('recorder'),
    # -- report
    ('report', 'no-run', []),
    ('report', 'missing', ['missing_run']),
    ('report', 'a-file', ['corrupt.yaml']),
    ('report', 'not-a-run', ['adir']),
    ('report', 'record-without-loss', ['run_noloss']),
    ('report', 'garbage-results-line', ['run_garbage_line']),
    ('report', 'out-is-a-file', ['run', '--out', 'corrupt.yaml']),
    ('report', 'bags-not-a-bag', ['run', '--bags', 'adir']),
    ('report', 'bags-missing', ['run', '--bags', 'no_such_bag']),
    # found by a new user (2026-11-29): a YAML error spanning lines, a run directory or a
    # bag's subfolder as --out, the default place taken by a file
    ('report', 'run-yaml-not-yaml', ['run_yaml_tab']),
    ('report', 'run-yaml-misspelt-key', ['run_misspelt_budget']),
    ('report', 'out-is-a-run', ['run', '--out', 'run_noloss']),
    ('report', 'out-in-a-bag', ['run', '--out', 'run_bad_metadata/bag_0/sub']),
    ('report', 'default-out-is-a-file', ['run_report_file']),
    # -- study
    ('study', 'runs-zero', ['--runs', '0']),
    ('study', 'runs-type', ['--runs', 'many']),
    ('study', 'budget-negative', ['--budget', '-1']),
    ('study', 'jobs-zero', ['--jobs', '0']),
    ('study', 'jobs-huge', ['--jobs', '100000']),
    ('study', 'satisfactory-nan', ['--satisfactory', 'nan']),
    ('study', 'algos-bad', ['--algos', 'spsa,simplex']),
    ('study', 'out-not-empty', ['--out', 'run']),
    ('study', 'out-is-a-file', ['--out', 'corrupt.yaml']),
    ('study', 'out-cannot-be-created', ['--out', '/proc/im_tuner_nowhere/bag']),
    ('study', 'from-missing', ['--from', 'missing_study']),
    ('study', 'from-not-a-study', ['--from', 'adir']),
    *_file_cases('study', '--params'),
    *_file_cases('study', '--drive-config'),
    # -- tuner: options
    ('tuner', 'budget-zero', ['--budget', '0']),
    ('tuner', 'budget-type', ['--budget', 'ten']),
    ('tuner', 'seed-negative', ['--seed', '-3']),
    ('tuner', 'eval-timeout-nan', ['--eval-timeout', 'nan']),
    ('tuner', 'discovery-timeout-negative', ['--discovery-timeout', '-1']),
    ('tuner', 'discovery-timeout-inf', ['--discovery-timeout', 'inf']),
    ('tuner', 'controller-bad-name', ['--controller', '///bad name']),
    ('tuner', 'out-is-a-file', ['--out', 'corrupt.yaml']),
    ('tuner', 'out-cannot-be-created', ['--out', '/proc/im_tuner_nowhere/bag']),
    ('tuner', 'out-not-empty', ['--out', 'adir_full']),
    ('tuner', 'algo-bad', ['--algo', 'simplex']),
    ('tuner', 'option-of-other-algo', ['--algo', 'spsa', '--opt', 'n=25']),
    ('tuner', 'option-value-type', ['--algo', 'necga', '--opt', 'n=big']),
    ('tuner', 'option-not-key-value', ['--opt', 'sigma0']),
    ('tuner', 'option-key-apart-from-value', ['--opt', 'first', 'none']),
    *_file_cases('tuner', '--opt'),
    # --opt start=none: only spsa, cmaes, tpe (safe would start from an untested random
    # point); a policy's value one of its choices
    ('tuner', 'start-none-safe-default', ['--opt', 'start=none']),
    ('tuner', 'start-none-compact-ga', ['--algo', 'necga', '--opt', 'start=none']),
    ('tuner', 'start-bad-value', ['--algo', 'spsa', '--opt', 'start=random']),
    ('tuner', 'first-bad-value', ['--opt', 'first=always']),
    ('tuner', 'first-of-other-algo', ['--algo', 'cmaes', '--opt', 'first=model']),
    ('tuner', 'drive-config-comments-only', ['--drive-config', 'comments.yaml']),
    ('tuner', 'compression-with-no-record', ['--compression', 'zstd', '--no-record']),
    # --live: what the recorder writes, served; its port and host checked first
    ('tuner', 'live-with-no-record', ['--live', '--no-record']),
    ('tuner', 'live-host-without-live', ['--live-host', '0.0.0.0']),
    ('tuner', 'live-host-not-local', ['--live', '8765', '--live-host', '192.0.2.1']),
    ('tuner', 'live-port-zero', ['--live', '0']),
    ('tuner', 'live-rate-negative', ['--live', '--live-rate', '-5']),
    ('drive_host', 'live-with-no-record', ['--live', '--no-record']),
    ('recorder', 'live-rate-type', ['--live', '--live-rate', 'fast']),
    ('tuner', 'thread-priority-without-realtime', ['--bench', 'inproc', '--thread-priority', '50']),
    ('tuner', 'thread-priority-100', ['--bench', 'realtime', '--thread-priority', '100']),
    ('drive_sim', 'cpu-affinity-absent', ['--cpu-affinity', '4096']),
    ('example_drive', 'thread-priority-type', ['--thread-priority', 'high']),
    # -p reaches the in-process bench's nodes; refused after the run directory was made,
    # which is then removed (the gain's case ended in a traceback, the run directory left)
    ('tuner', 'p-gain-negative', ['--bench', 'inproc', '--ros-args', '-p', 'k_pw:=-1.0']),
    (
        'tuner',
        'p-move-longer-than-experiment',
        ['--bench', 'inproc', '--out', 'newrun', '--ros-args', '-p', DISTANCE_1000],
    ),
    # --drive: checked against docs/real-drive.md's contract (bad_drives.py)
    *[
        ('tuner', f'drive-{name}', ['--bench', 'realtime', '--drive', spec])
        for name, spec in (
            ('ros-node-not-a-drive', 'rclpy.node:Node'),
            ('controller-node', 'im_controller.controller_node:ControllerNode'),
            ('not-hardware', 'io:BytesIO'),
            ('write-signature', 'bad_drives:WriteTakesOne'),
            ('abstract', 'bad_drives:AbstractHardware'),
            ('exits-at-import', 'exits_at_import:Hardware'),
            ('hardware-raises', 'bad_drives:RaisingHardware'),
            ('node-raises', 'bad_drives:RaisingDrive'),
            ('library-missing', 'lib:missing_lib.so'),
            ('library-not-a-library', 'lib:comments.yaml'),
            ('library-empty-path', 'lib:'),
        )
    ],
    ('tuner', 'timing-tolerance-negative', ['--timing-tolerance', '-1']),
    ('tuner', 'timing-tolerance-type', ['--timing-tolerance', 'few']),
    ('tuner', 'p-timing-tolerance-type', ['--ros-args', '-p', 'timing_tolerance:=few']),
    (
        'tuner',
        'timing-tolerance-twice',
        ['--timing-tolerance', '3', '--ros-args', '-p', 'timing_tolerance:=4'],
    ),
    ('tuner', 'resume-with-timing-tolerance', ['--resume', 'run', '--timing-tolerance', '4']),
    (
        'tuner',
        'timing-tolerance-auto-and-p',
        ['--timing-tolerance', 'auto', '--ros-args', '-p', 'timing_tolerance:=4'],
    ),
    ('example_drive', 'hardware-unknown', ['--hardware', 'fpga']),
    ('example_drive', 'hardware-library-missing', ['--hardware', 'lib:missing_lib.so']),
    *_file_cases('tuner', '--params'),
    *_file_cases('tuner', '--drive-config'),
    # -- tuner --resume: every way a run directory can be broken
    ('tuner', 'resume-missing', ['--resume', 'missing_run']),
    ('tuner', 'resume-not-a-run', ['--resume', 'adir']),
    ('tuner', 'resume-results-garbage-line', ['--resume', 'run_garbage_line']),
    ('tuner', 'resume-record-without-loss', ['--resume', 'run_noloss']),
    ('tuner', 'resume-torn-line-then-refused', ['--resume', 'run_torn_and_bad']),
    ('tuner', 'resume-run-yaml-bad-algo', ['--resume', 'run_bad_algo']),
    ('tuner', 'resume-run-yaml-bad-budget', ['--resume', 'run_bad_budget']),
    ('tuner', 'resume-run-yaml-not-yaml', ['--resume', 'run_yaml_tab']),
    ('tuner', 'resume-newer-summary', ['--resume', 'run_newer_summary']),
    ('tuner', 'resume-with-settings', ['--resume', 'run', '--budget', '9']),
    # a run.yaml of safe with start: none (a policy safe does not take)
    ('tuner', 'resume-run-yaml-safe-no-start', ['--resume', 'run_safe_no_start']),
]


#: what the one line must say, for the cases whose reason matters
EXPECT: dict[tuple[str, str], str] = {
    ('tuner', 'live-with-no-record'): '--live serves what the recorder writes to the bag',
    ('tuner', 'live-host-without-live'): '--live-host without --live would be ignored',
    ('tuner', 'live-host-not-local'): '--live-host 192.0.2.1: not an address of this computer',
    ('drive_host', 'live-with-no-record'): '--no-record records none',
    ('recorder', 'live-rate-type'): 'or full or 0 (every message)',
    ('tuner', 'thread-priority-without-realtime'): 'set up the composed real-time loop',
    ('tuner', 'thread-priority-100'): 'must be 0 (off) or 1-99 (SCHED_FIFO), got 100',
    ('drive_sim', 'cpu-affinity-absent'): 'CPU 4096 is not one this process may use',
    ('example_drive', 'thread-priority-type'): "not an integer: 'high'",
    ('controller', 'p-move-longer-than-experiment'): 'takes 25.07 s, longer than the experiment',
    ('controller', 'config-comments-only'): 'no settings (the file holds only comments)',
    ('sim_bench', 'p-move-longer-than-experiment'): 'takes 25.07 s, longer than the experiment',
    ('sim_bench', 'processes-p-move-longer-than-experiment'): 'takes 25.07 s, longer than',
    ('sim_bench', 'out-with-no-record'): '--out newbag is for the bag, and --no-record',
    ('sim_bench', 'out-cannot-be-created'): '--out /proc/im_tuner_nowhere/bag: cannot create it',
    ('drive_host', 'out-cannot-be-created'): '--out /proc/im_tuner_nowhere/bag: cannot create it',
    ('recorder', 'out-cannot-be-created'): '--out /proc/im_tuner_nowhere/bag: cannot create it',
    ('study', 'out-cannot-be-created'): '--out /proc/im_tuner_nowhere/bag: cannot create it',
    ('tuner', 'out-cannot-be-created'): '--out /proc/im_tuner_nowhere/bag: cannot create it',
    ('sim_bench', 'compression-with-no-record'): '--compression zstd is for the bag',
    ('drive_host', 'tuner-timeout-zero'): '--tuner-timeout: must be >= 0.05 s, got 0',
    ('drive_host', 'model-with-example'): "--model is the simulator's",
    ('drive_host', 'p-isq-max-above-drive'): 'isq_max',
    ('drive_host', 'p-unknown'): 'no such parameter: no_such_param',
    ('drive_host', 'drive-hardware-hangs'): 'HangingHardware(config) did not return',
    ('sim_bench', 'p-unknown'): 'no such parameter: k_pww',
    ('recorder', 'repair-with-out'): 'repairs that bag in place and exits: --out would be',
    ('recorder', 'exclude-pattern'): "'/drive/*' is not a ROS topic name",
    ('report', 'out-is-a-run'): 'a run directory (the report never writes into one',
    ('report', 'run-yaml-misspelt-key'): "no budget (other keys: 'budgt': a typo?)",
    ('report', 'out-in-a-bag'): 'a bag folder or in one',
    ('report', 'default-out-is-a-file'): 'exists and is not a directory (the default place',
    ('tuner', 'resume-newer-summary'): 'format version 99',
    ('tuner', 'resume-run-yaml-not-yaml'): "found character '\\t' that cannot start any token",
    ('tuner', 'start-none-safe-default'): '--opt start does not apply to --algo safe',
    ('tuner', 'start-none-compact-ga'): '--opt start does not apply to --algo necga',
    ('tuner', 'start-bad-value'): "spsa option start must be one of 'hand', 'none', got 'random'",
    ('tuner', 'first-bad-value'): "option first must be one of 'identify', 'model', 'none'",
    ('tuner', 'first-of-other-algo'): '--opt first does not apply to --algo cmaes',
    ('tuner', 'option-key-apart-from-value'): '--opt first none: give it as --opt first=none',
    ('tuner', 'drive-config-comments-only'): 'no settings (the file holds only comments)',
    ('tuner', 'compression-with-no-record'): '--compression zstd is for the bag',
    ('tuner', 'p-gain-negative'): 'k_pw',
    ('tuner', 'p-move-longer-than-experiment'): 'takes 25.07 s, longer than the experiment',
    ('tuner', 'drive-ros-node-not-a-drive'): 'Node is a ROS node but not a drive node',
    ('tuner', 'drive-controller-node'): 'ControllerNode is a ROS node but not a drive node',
    ('tuner', 'drive-not-hardware'): 'BytesIO.write(isq_ref, load_torque) is not a valid call',
    ('tuner', 'drive-write-signature'): 'WriteTakesOne.write(isq_ref, load_torque) is not',
    ('tuner', 'drive-abstract'): 'AbstractHardware is abstract',
    ('tuner', 'drive-exits-at-import'): 'importing exits_at_import called sys.exit(3)',
    ('tuner', 'drive-hardware-raises'): (
        'RaisingHardware(config) raised RuntimeError: no inverter on /dev/ttyUSB0 (test)'
    ),
    ('tuner', 'drive-node-raises'): 'RaisingDrive raised OSError: EtherCAT master not found',
    ('tuner', 'drive-library-missing'): 'no such file',
    ('tuner', 'drive-library-not-a-library'): 'cannot load',
    ('tuner', 'drive-library-empty-path'): "expected 'lib:PATH'",
    ('tuner', 'timing-tolerance-negative'): 'must be in [0, 1000000] periods, got -1',
    ('tuner', 'p-timing-tolerance-type'): 'timing_tolerance:=few: an integer >= 0',
    ('tuner', 'timing-tolerance-twice'): '--timing-tolerance 3 and -p timing_tolerance:=4',
    ('tuner', 'resume-with-timing-tolerance'): 'do not also give --timing-tolerance',
    ('tuner', 'timing-tolerance-auto-and-p'): '--timing-tolerance auto and -p timing_tolerance:=4',
    ('tuner', 'timing-tolerance-type'): "not an integer or 'auto': 'few'",
    ('drive_host', 'timing-tolerance-type'): "not an integer or 'auto': 'few'",
    ('host_check', 'seconds-zero'): 'must be >= 0.5 s, got 0',
    ('host_check', 'spin-above-the-period'): '--spin-us',
    ('host_check', 'thread-priority-100'): 'must be 0 (off) or 1-99 (SCHED_FIFO), got 100',
    ('example_drive', 'hardware-unknown'): "expected 'python', 'example' or 'lib:PATH'",
    ('example_drive', 'hardware-library-missing'): 'no such file',
    ('tuner', 'resume-run-yaml-safe-no-start'): "run.yaml: unknown option 'start' for safe",
}

# -- the work directory every case starts from ---------------------------------------------
#: drive classes that break docs/real-drive.md's contract, each in one way
BAD_DRIVES = """
from abc import ABC, abstractmethod

from im_drive_sim.example_drive import ExampleDrive, Hardware


class WriteTakesOne(Hardware):
    def write(self, isq_ref):  # no load torque
        pass


class AbstractHardware(ABC):
    def __init__(self, config):
        pass

    @abstractmethod
    def read(self): ...

    def write(self, isq_ref, load_torque):
        pass


class RaisingHardware(Hardware):
    def __init__(self, config):
        raise RuntimeError('no inverter on /dev/ttyUSB0 (test)')


class HangingHardware(Hardware):
    def __init__(self, config):
        import time

        time.sleep(3600)  # an open that waits on a device for ever


class RaisingDrive(ExampleDrive):
    def __init__(self, **kwargs):
        raise OSError('EtherCAT master not found (test)')
"""


def _corrupt_copy(src: Path, dst: Path, edit) -> None:
    shutil.copytree(src, dst)
    edit(dst)


@pytest.fixture(scope='module')
def template(tmp_path_factory) -> Path:
    """Inputs: files (missing, a directory, garbage, YAML of the wrong shape) and a real
    interrupted tuner run with broken copies of it."""
    root = tmp_path_factory.mktemp('bad_input_template')
    (root / 'adir').mkdir()
    (root / 'adir_full').mkdir()
    (root / 'adir_full' / 'x.txt').write_text('x\n')
    (root / 'corrupt.yaml').write_bytes(b'{{{ : [\x00\xff not yaml\n')
    (root / 'notros.yaml').write_text('- just\n- a list\n')
    (root / 'comments.yaml').write_text('# my drive, to be filled in\n# Ts: 2.0e-4\n')
    (root / 'bad_drives.py').write_text(BAD_DRIVES)
    (root / 'exits_at_import.py').write_text('import sys\n\nsys.exit(3)\n')
    # a real run, cut after its budget of 3 (done) and then made resumable by dropping
    # the last records, as a killed run leaves it
    run = root / 'run'
    proc = subprocess.run(
        [
            ROS2,
            'run',
            'im_tuner',
            'tuner',
            '--algo',
            'necga',
            '--budget',
            '4',
            '--seed',
            '5',
            '--remeasure',
            '0',
            '--no-record',
            '--bench',
            'inproc',
            '--quiet',
            '--out',
            str(run),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = (run / 'results.jsonl').read_text().splitlines(keepends=True)
    (run / 'results.jsonl').write_text(''.join(lines[:3]))
    (run / 'summary.json').unlink()

    def write(name: str, text: str | bytes) -> None:
        def edit(d: Path) -> None:
            (d / name).write_bytes(text if isinstance(text, bytes) else text.encode())

        return edit

    variants = {
        'run_garbage_line': write(
            'results.jsonl', ''.join(lines[:1]) + 'not json at all\n' + ''.join(lines[1:3])
        ),
        'run_noloss': write(
            'results.jsonl',
            ''.join(lines[:1])
            + json.dumps({k: v for k, v in json.loads(lines[1]).items() if k != 'loss'})
            + '\n'
            + ''.join(lines[2:3]),
        ),
        # a torn last line (cut on resume) and a bad record before it (refused)
        'run_torn_and_bad': write(
            'results.jsonl',
            ''.join(lines[:1])
            + json.dumps({k: v for k, v in json.loads(lines[1]).items() if k != 'loss'})
            + '\n'
            + ''.join(lines[2:3])
            + '{"kind": "ev',
        ),
        'run_yaml_tab': write('run.yaml', 'algo: necga\n\tbudget: {\n'),
        'run_newer_summary': write('summary.json', '{"version": 99, "outcome": "done"}\n'),
        'run_report_file': write('report', 'not a directory\n'),
    }
    for name, edit in variants.items():
        _corrupt_copy(run, root / name, edit)

    def run_yaml(name: str, old: str, new: str) -> None:
        def edit(d: Path) -> None:
            p = d / 'run.yaml'
            text = p.read_text()
            assert old in text
            p.write_text(text.replace(old, new, 1))

        _corrupt_copy(run, root / name, edit)

    run_yaml('run_bad_algo', 'algo: necga', 'algo: simplex')

    def safe_no_start(d: Path) -> None:
        p = d / 'run.yaml'
        text = p.read_text()
        assert 'algo: necga' in text and 'options: {}' in text
        p.write_text(
            text.replace('algo: necga', 'algo: safe').replace(
                'options: {}', 'options: {start: none}'
            )
        )

    _corrupt_copy(run, root / 'run_safe_no_start', safe_no_start)
    run_yaml('run_bad_budget', 'budget: 4', 'budget: lots')
    run_yaml('run_misspelt_budget', 'budget: 4', 'budgt: 4')
    # a run with a bag whose metadata.yaml is garbage (for report)
    bag_run = root / 'run_bad_metadata'
    shutil.copytree(run, bag_run)
    (bag_run / 'bag_0').mkdir()
    (bag_run / 'bag_0' / 'metadata.yaml').write_bytes(b'{{{ : [\x00\xff')
    (bag_run / 'bag_0' / 'bag_0_0.mcap').write_bytes(b'\x89MCAP0\r\n')
    return root


def _tree(root: Path) -> dict[str, str]:
    """Every path under ``root`` with a digest of its bytes (directories as 'dir')."""
    out: dict[str, str] = {}
    for p in sorted(root.rglob('*')):
        rel = str(p.relative_to(root))
        out[rel] = 'dir' if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _run_case(template: Path, base: Path, i: int, exe: str, argv: list[str]) -> dict:
    cwd = base / f'case_{i}'
    shutil.copytree(template, cwd, symlinks=True)
    before = _tree(cwd)
    env = dict(os.environ)
    # each case its own DDS domain (of 60, within this worker's 100: conftest.py): a node
    # that wrongly starts must not meet another case, nor the other worker's tests
    env['ROS_DOMAIN_ID'] = str((int(env['ROS_DOMAIN_ID']) + 1 + i % 60) % 233)
    env['ROS_LOG_DIR'] = str(base / f'log_{i}')
    # the case's drive modules (bad_drives.py) importable, and no __pycache__ left beside
    env['PYTHONPATH'] = os.pathsep.join(filter(None, [str(cwd), env.get('PYTHONPATH')]))
    env['PYTHONDONTWRITEBYTECODE'] = '1'
    pkg, name = EXES[exe]
    # its own session: a case that wrongly starts a pool or children is ended whole
    proc = subprocess.Popen(
        [ROS2, 'run', pkg, name, *argv],
        cwd=cwd,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=CASE_TIMEOUT)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        rc = None
    after = _tree(cwd)
    return {
        'rc': rc,
        'stdout': out,
        'stderr': err,
        'created': sorted(set(after) - set(before)),
        'removed': sorted(set(before) - set(after)),
        'changed': sorted(k for k in set(before) & set(after) if before[k] != after[k]),
    }


@pytest.fixture(scope='module')
def outcomes(template: Path, tmp_path_factory, request) -> dict[int, dict]:
    """Runs the selected cases (all, or those picked with -k), three at a time."""
    base = tmp_path_factory.mktemp('bad_input_cases')
    chosen = sorted(
        {
            it.callspec.params['i']
            for it in request.session.items
            if getattr(it, 'originalname', '') == 'test_bad_input_one_line_exit_2_nothing_changed'
        }
    )
    with ThreadPoolExecutor(3) as pool:
        futs = {
            i: pool.submit(_run_case, template, base, i, CASES[i][0], CASES[i][2]) for i in chosen
        }
        return {i: f.result() for i, f in futs.items()}


@pytest.mark.parametrize('i', range(len(CASES)), ids=[f'{exe}-{name}' for exe, name, _a in CASES])
def test_bad_input_one_line_exit_2_nothing_changed(i: int, outcomes: dict[int, dict]) -> None:
    exe, name, argv = CASES[i]
    o = outcomes[i]
    what = (
        f'{exe} {" ".join(argv)}: rc={o["rc"]}\nstderr:\n{o["stderr"][-1500:]}\nstdout:\n'
        f'{o["stdout"][-500:]}'
    )
    assert o['rc'] == 2, what
    assert 'Traceback' not in o['stderr'] + o['stdout'], what
    lines = o['stderr'].strip().splitlines()
    assert len(lines) == 1, what
    assert lines[0].startswith('error: ') and len(lines[0]) < 400, what
    if (exe, name) in EXPECT:
        assert EXPECT[exe, name] in lines[0], what
    if exe == 'check_drive':  # refused before looking for a drive, not for want of one
        assert 'no drive' not in lines[0], what
    assert o['stdout'].strip() == '', what
    assert o['created'] == [] and o['removed'] == [] and o['changed'] == [], (
        f'{what}\ncreated {o["created"]}, removed {o["removed"]}, changed {o["changed"]}'
    )


def test_the_expected_reasons_name_real_cases() -> None:
    assert set(EXPECT) <= {(e, n) for e, n, _a in CASES}


def test_the_matrix_covers_every_executable() -> None:
    """Each executable meets at least: wrong flag, and (where it has one) each file kind."""
    per_exe = {exe: {name for e, name, _a in CASES if e == exe} for exe in EXES}
    assert all('wrong-flag' in names for names in per_exe.values())
    for exe in NODES:
        assert {
            f'params-file-{k}' for k in ('missing', 'directory', 'corrupt', 'not-ros')
        } <= per_exe[exe], exe
    assert len(CASES) == len({(e, n) for e, n, _a in CASES})  # unique ids


@pytest.mark.parametrize('exe', sorted(EXES))
def test_help_of_every_executable_exits_0(exe: str, tmp_path: Path) -> None:
    """`--help` is the first command a user types: usage on stdout, exit 0, nothing made
    (the tuner's ended in a traceback: an unescaped % in an option's help)."""
    pkg, name = EXES[exe]
    proc = subprocess.run(
        [ROS2, 'run', pkg, name, '--help'],
        cwd=tmp_path,
        text=True,
        capture_output=True,
        timeout=CASE_TIMEOUT,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith('usage: ros2 run ') and 'Traceback' not in proc.stderr
    assert proc.stderr == '' and list(tmp_path.iterdir()) == []


# -- refusals that need no ROS graph: fast, nothing heavy imported ----------------------------
#: (argv, what the line says): refused by argparse, the run checks, the option ranges
FAST_REFUSALS = [
    (['--algo', 'nosuch'], "argument --algo: invalid choice: 'nosuch'"),
    (['--opt', 'start=none'], '--opt start does not apply to --algo safe'),
    (['--algo', 'cmaes', '--opt', 'sigma0=2'], 'sigma0'),
    (['--opt', 'grow=1.2', '--opt', 'grow=2'], '--opt grow is given twice'),
    (['--algo', 'tpe', '--budget', '0'], 'argument --budget: must be >= 1, got 0'),
    (['--drive-config', 'comments.yaml'], 'no settings (the file holds only comments)'),
    (['--out', 'full'], '--out full: already exists'),
    (['--no-record', '--compression', 'lz4'], '--compression lz4 is for the bag'),
    (['--opt', 'first=identify', '--no-reference'], 'not with --no-reference; give --opt first='),
]
HEAVY = ('rclpy', 'cma', 'optuna', 'scipy', 'numba', 'matplotlib')


def _heavy_probe(body: str, argv: list[str], cwd: Path) -> tuple[object, list[str], str]:
    """Run ``body`` (Python that sets ``rc`` from ``json.loads(sys.argv[1])``, the command
    line) in a fresh interpreter; its exit code, the HEAVY modules it left loaded, stderr."""
    code = (
        f'import json, runpy, sys\n{body}'
        f'heavy = {HEAVY!r}\n'
        'print(json.dumps([rc, sorted(m for m in heavy if m in sys.modules)]))\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', code, json.dumps(argv)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=CASE_TIMEOUT,
        env={**os.environ, 'PYTHONDONTWRITEBYTECODE': '1'},
    )
    rc, loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    return rc, loaded, proc.stderr


@pytest.mark.parametrize('argv, says', FAST_REFUSALS, ids=[' '.join(a) for a, _s in FAST_REFUSALS])
def test_a_refusal_of_the_tuner_imports_nothing_heavy(argv: list[str], says: str, tmp_path: Path):
    """A bad --algo once took 2.7 s on an idle machine (1.5 s of it importing pycma),
    up to 30 s under load. The tuner parses and checks before it imports rclpy, the numba
    kernels, pycma, optuna, scipy or matplotlib; checked on the modules its main leaves
    loaded (speed itself is for the benchmarks)."""
    (tmp_path / 'full').mkdir()
    (tmp_path / 'full' / 'x.txt').write_text('x\n')
    (tmp_path / 'comments.yaml').write_text('# my drive, to be filled in\n')
    before = _tree(tmp_path)
    body = 'from im_tuner.tuner_node import main\nrc = main(["tuner", *json.loads(sys.argv[1])])\n'
    rc, loaded, err = _heavy_probe(body, argv, tmp_path)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith('error: tuner: ') and says in lines[0], lines[0]
    assert loaded == [], f'{argv}: a refusal imported {loaded}'
    assert _tree(tmp_path) == before


def test_the_controller_refuses_a_move_longer_than_the_experiment_at_run_time(ros_context):
    """set_parameters of a distance (or a combination) whose move does not fit the
    experiment is refused with the reason, nothing changes; the descriptors of the four
    parameters that set the move's time say the rule."""
    from rclpy.parameter import Parameter

    from im_controller.config import MOVE_KEYS, MOVE_RULE
    from im_controller.controller_node import ControllerNode

    node = ControllerNode(context=ros_context)
    try:
        res = node.set_parameters([Parameter('trajectory.distance', value=1000.0)])
        assert not res[0].successful
        assert 'takes 25.07 s, longer than the experiment' in res[0].reason, res[0].reason
        assert node.get_parameter('trajectory.distance').value == math.pi
        # pi rad at 5 rad/s takes 0.637 s: it fits the 1.125 s experiment, not a 0.5 s one
        squeeze = [
            Parameter('trajectory.v_max', value=5.0),
            Parameter('trajectory.duration', value=0.5),
            Parameter('trajectory.load_delay', value=0.4),
        ]
        res_atomic = node.set_parameters_atomically(squeeze)
        assert not res_atomic.successful
        assert 'takes 0.6367 s, longer than the experiment' in res_atomic.reason
        assert node.get_parameter('trajectory.duration').value == 1.125
        assert node.set_parameters(squeeze[:1])[0].successful
        for key in MOVE_KEYS:
            desc = node.describe_parameter(key)
            assert MOVE_RULE in desc.additional_constraints, (key, desc)
    finally:
        node.destroy_node()


#: the node executables' entries (``<pkg>/scripts/<exe>``: ``python -m im_drive_sim.launch
#: <exe> <entry>``)
NODE_ENTRIES = {
    'drive_sim': 'im_drive_sim.drive_sim_main:main',
    'example_drive': 'im_drive_sim.example_drive_main:main',
    'controller': 'im_controller.controller_main:main',
    'sim_bench': 'im_tuner.bench.sim_bench_main:main',
    'recorder': 'im_tuner.record.recorder_main:main',
}


#: a command line each node's parser accepts and the node refuses
NODE_REFUSES = {
    'drive_sim': ['--ros-args', '-p', 'seed:=abc'],
    'example_drive': ['--ros-args', '-p', 'isq_max:=abc'],
    'controller': ['--ros-args', '-p', 'k_pw:=-1.0'],
    'sim_bench': ['--no-record', '--ros-args', '-p', 'safety.isq_max:=20.0'],
    'recorder': ['--repair', 'missing_bag'],
}


@pytest.mark.parametrize('exe', sorted(NODE_ENTRIES))
def test_a_refusal_of_a_node_imports_nothing_heavy(exe: str, tmp_path: Path) -> None:
    """A node's command line is checked before its module (numba kernels, rclpy: about a
    second each, many seconds under load; most of test_bad_input's time) is imported:
    a wrong flag, a bad number and a missing --params-file are refused with the node's
    own line, nothing heavy loaded; an accepted one goes on to the node (it imports
    them: the check would fail if the entry stopped handing over)."""
    module, function = NODE_ENTRIES[exe].split(':')
    body = (
        'import importlib\n'
        'sys.argv = ["x", *json.loads(sys.argv[1])]\n'
        f'rc = getattr(importlib.import_module({module!r}), {function!r})()\n'
    )

    def run(argv: list[str]) -> tuple[object, list[str], str]:
        return _heavy_probe(body, argv, tmp_path)

    for argv, says in (
        (['--no-such-flag'], 'unrecognized arguments: --no-such-flag'),
        (['--ros-args', '--params-file', 'missing.yaml'], '--params-file missing.yaml: no such'),
        (['--drive-config', 'adir'] if exe != 'recorder' else ['--chunk-size', '0'], ''),
    ):
        rc, loaded, err = run(argv)
        (line,) = err.strip().splitlines()
        assert rc == 2 and line.startswith(f'error: {exe}: ') and says in line, err
        assert loaded == [], f'{exe} {argv}: a refusal imported {loaded}'
    # accepted by the parser, refused by the node (a parameter, a missing bag): the node's
    # module was imported
    rc, loaded, err = run(NODE_REFUSES[exe])
    assert rc == 2 and err.startswith(f'error: {exe}') and 'numba' in loaded, (loaded, err)
