"""im_tuner.record.schemas: ros2msg schema text, checked by exact layout, its errors and
custom interface prefixes. The decoding of each recorded type by two independent readers,
and service events as IDL: test_record_schemas_decode.py.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from mcap_ros2._dynamic import generate_dynamic
from rosbags.typesys import get_types_from_msg

os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

from im_tuner.record import schemas as msgdefs

MsgDefError = msgdefs.MsgDefError
schema_text = msgdefs.schema_text

SEP = '=' * 80
VENV = Path(sys.prefix)


def share(rel: str) -> str:
    """Verbatim text of an installed interface file, e.g. ``std_msgs/msg/Header.msg``."""
    return (VENV / 'share' / rel).read_text(encoding='utf-8')


def msg_names(text: str) -> list[str]:
    """The ``MSG:`` names in order, asserting each directly follows a separator line."""
    lines = text.split('\n')
    names = []
    for i, line in enumerate(lines):
        if line.startswith('MSG:'):
            assert i > 0 and lines[i - 1] == SEP, f'{line!r} is not preceded by the separator'
            names.append(line[len('MSG: ') :])
    assert sum(line == SEP for line in lines) == len(names)
    return names


# --- layout ----------------------------------------------------------------------------------


def test_float64multiarray_layout_is_exact() -> None:
    text = schema_text('std_msgs/msg/Float64MultiArray')
    top = share('std_msgs/msg/Float64MultiArray.msg')
    assert text.startswith(top)
    assert text.count('MSG: std_msgs/MultiArrayLayout\n') == 1
    assert text.count('MSG: std_msgs/MultiArrayDimension\n') == 1
    assert msg_names(text) == ['std_msgs/MultiArrayLayout', 'std_msgs/MultiArrayDimension']
    # rosbag2's exact form: definitions joined by "\n" (so a blank line before each separator).
    assert text == '\n'.join(
        [
            top,
            SEP,
            'MSG: std_msgs/MultiArrayLayout',
            share('std_msgs/msg/MultiArrayLayout.msg'),
            SEP,
            'MSG: std_msgs/MultiArrayDimension',
            share('std_msgs/msg/MultiArrayDimension.msg'),
        ]
    )


def test_jointstate_has_header_and_time_once_depth_first() -> None:
    text = schema_text('sensor_msgs/msg/JointState')
    assert text.startswith(share('sensor_msgs/msg/JointState.msg'))
    assert text.count('MSG: std_msgs/Header\n') == 1
    assert text.count('MSG: builtin_interfaces/Time\n') == 1
    assert msg_names(text) == ['std_msgs/Header', 'builtin_interfaces/Time']


def test_two_part_message_name_is_the_same_type() -> None:
    assert schema_text('std_msgs/Float64MultiArray') == schema_text(
        'std_msgs/msg/Float64MultiArray'
    )


def test_service_event_form() -> None:
    text = schema_text('rcl_interfaces/srv/SetParameters_Event')
    assert text.startswith(
        'service_msgs/ServiceEventInfo info\n'
        'rcl_interfaces/SetParameters_Request[<=1] request\n'
        'rcl_interfaces/SetParameters_Response[<=1] response\n'
        '\n'
        + SEP
        + '\nMSG: service_msgs/ServiceEventInfo\n'
        + share('service_msgs/msg/ServiceEventInfo.msg')
    )
    assert msg_names(text) == [
        'service_msgs/ServiceEventInfo',
        'builtin_interfaces/Time',
        'rcl_interfaces/SetParameters_Request',
        'rcl_interfaces/Parameter',
        'rcl_interfaces/ParameterValue',
        'rcl_interfaces/SetParameters_Response',
        'rcl_interfaces/SetParametersResult',
    ]
    srv = share('rcl_interfaces/srv/SetParameters.srv')
    request, response = srv.split('\n---\n')
    assert ('MSG: rcl_interfaces/SetParameters_Request\n' + request + '\n' + SEP) in text
    assert ('MSG: rcl_interfaces/SetParameters_Response\n' + response + '\n' + SEP) in text


def test_empty_parts_are_empty_sections() -> None:
    text = schema_text('std_srvs/srv/Trigger_Event')
    response = share('std_srvs/srv/Trigger.srv')[len('---\n') :]
    assert text.endswith(
        'MSG: std_srvs/Trigger_Request\n\n' + SEP + '\nMSG: std_srvs/Trigger_Response\n' + response
    )
    assert schema_text('std_srvs/srv/Empty_Event').endswith(
        'MSG: std_srvs/Empty_Request\n\n' + SEP + '\nMSG: std_srvs/Empty_Response\n'
    )
    assert schema_text('std_srvs/srv/Trigger_Request') == ''
    assert schema_text('std_srvs/srv/Trigger_Response') == response


# --- errors -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    'type_name,searched',
    [
        ('no_such_pkg/msg/Thing', 'share/no_such_pkg/msg/Thing.msg'),
        ('std_msgs/msg/NoSuchType', 'share/std_msgs/msg/NoSuchType.msg'),
        ('std_srvs/srv/NoSuchSrv_Event', 'share/std_srvs/srv/NoSuchSrv.srv'),
        ('std_srvs/srv/NoSuchSrv_Request', 'share/std_srvs/srv/NoSuchSrv.srv'),
    ],
)
def test_unknown_type_names_type_and_file(type_name: str, searched: str) -> None:
    with pytest.raises(MsgDefError) as err:
        schema_text(type_name)
    assert type_name in str(err.value)
    assert str(VENV / searched) in str(err.value)


@pytest.mark.parametrize(
    'type_name',
    [
        'Float64',
        'std_msgs/Float64/x/y',
        '',
        'std_msgs/msg/',
        '/msg/Float64',
        'std_msgs/idl/Float64',
        'std_msgs/msg/Float64.msg',
        'std_srvs/srv/Trigger',
    ],
)
def test_malformed_type_name(type_name: str) -> None:
    with pytest.raises(MsgDefError, match=r'type name|is a service') as err:
        schema_text(type_name)
    assert repr(type_name) in str(err.value) or type_name in str(err.value)


def test_no_prefixes_at_all(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    with pytest.raises(MsgDefError, match='AMENT_PREFIX_PATH'):
        schema_text('std_msgs/msg/Float64')


# --- custom prefixes ----------------------------------------------------------------------------


def write(root: Path, rel: str, text: str) -> None:
    path = root / 'share' / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding='utf-8')


A_MSG = """\
# A uses local types (no package) and std_msgs/Header
uint8 MODE_X=1   # constant: not a dependency
string NAME="a#b"
B first          # local type B
B[] more
std_msgs/Header header
C[<=3] cs
string<=8 tag
int32[4] fixed
"""
B_MSG = 'builtin_interfaces/Time t\nC c\n'
C_MSG = 'int32 x\n'


def test_custom_prefix_resolves_locally_depth_first(tmp_path: Path) -> None:
    write(tmp_path, 'mypkg/msg/A.msg', A_MSG)
    write(tmp_path, 'mypkg/msg/B.msg', B_MSG)
    write(tmp_path, 'mypkg/msg/C.msg', C_MSG)
    text = schema_text('mypkg/msg/A', prefixes=[str(tmp_path), str(VENV)])
    # Depth first, in order of first use: B, then B's own Time and C, then Header (C already out).
    assert msg_names(text) == ['mypkg/B', 'builtin_interfaces/Time', 'mypkg/C', 'std_msgs/Header']
    assert text == '\n'.join(
        [
            A_MSG,
            SEP,
            'MSG: mypkg/B',
            B_MSG,
            SEP,
            'MSG: builtin_interfaces/Time',
            share('builtin_interfaces/msg/Time.msg'),
            SEP,
            'MSG: mypkg/C',
            C_MSG,
            SEP,
            'MSG: std_msgs/Header',
            share('std_msgs/msg/Header.msg'),
        ]
    )
    # Both readers take it (rosbags parses all of it; mcap_ros2 builds every decoder).
    assert set(get_types_from_msg(text, 'mypkg/msg/A')) == {
        'mypkg/msg/A',
        'mypkg/msg/B',
        'mypkg/msg/C',
        'builtin_interfaces/msg/Time',
        'std_msgs/msg/Header',
    }
    assert {'mypkg/msg/A', 'mypkg/B', 'mypkg/C', 'std_msgs/Header'} <= set(
        generate_dynamic('mypkg/msg/A', text)
    )


def test_header_alone_means_std_msgs_header(tmp_path: Path) -> None:
    write(tmp_path, 'mypkg/msg/H.msg', 'Header header\n')
    text = schema_text('mypkg/msg/H', prefixes=[str(tmp_path), str(VENV)])
    assert msg_names(text) == ['std_msgs/Header', 'builtin_interfaces/Time']


def test_first_prefix_with_the_file_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    first, second = tmp_path / 'first', tmp_path / 'second'
    write(first, 'mypkg/msg/A.msg', 'B b\n')  # A only in the first prefix
    write(first, 'mypkg/msg/B.msg', 'int8 from_first\n')
    write(second, 'mypkg/msg/B.msg', 'int8 from_second\n')
    write(second, 'mypkg/msg/A.msg', 'int8 shadowed\n')
    write(second, 'otherpkg/msg/O.msg', 'mypkg/B b\n')  # O only in the second
    assert schema_text('mypkg/msg/A', [str(first), str(second)]) == (
        'B b\n\n' + SEP + '\nMSG: mypkg/B\nint8 from_first\n'
    )
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join([str(first), str(second)]))
    assert schema_text('otherpkg/msg/O').endswith('MSG: mypkg/B\nint8 from_first\n')


def test_custom_service_event(tmp_path: Path) -> None:
    write(tmp_path, 'mypkg/srv/Do.srv', 'Item[] items  # local type\n---\nHeader h\n')
    write(tmp_path, 'mypkg/msg/Item.msg', 'float64 v\n')
    text = schema_text('mypkg/srv/Do_Event', [str(tmp_path), str(VENV)])
    assert msg_names(text) == [
        'service_msgs/ServiceEventInfo',
        'builtin_interfaces/Time',
        'mypkg/Do_Request',
        'mypkg/Item',
        'mypkg/Do_Response',
        'std_msgs/Header',
    ]
    assert 'MSG: mypkg/Do_Request\nItem[] items  # local type\n' + SEP in text


def test_missing_dependency_names_user(tmp_path: Path) -> None:
    write(tmp_path, 'mypkg/msg/A.msg', 'Missing m\n')
    with pytest.raises(MsgDefError) as err:
        schema_text('mypkg/msg/A', [str(tmp_path)])
    assert 'mypkg/Missing' in str(err.value) and 'used by mypkg/A' in str(err.value)
    assert str(tmp_path / 'share/mypkg/msg/Missing.msg') in str(err.value)


@pytest.mark.parametrize(
    'rel,text,type_name,match',
    [
        ('mypkg/msg/A.msg', 'int32\n', 'mypkg/msg/A', 'line 1'),
        ('mypkg/msg/A.msg', '# ok\nfoo/bar/Baz x\n', 'mypkg/msg/A', 'line 2.*foo/bar/Baz'),
        ('mypkg/srv/S.srv', 'int32 a\n', 'mypkg/srv/S_Event', "exactly one '---'"),
        ('mypkg/srv/S.srv', '---\n---\n', 'mypkg/srv/S_Response', "exactly one '---'"),
    ],
)
def test_unparsable_definitions(
    tmp_path: Path, rel: str, text: str, type_name: str, match: str
) -> None:
    write(tmp_path, rel, text)
    with pytest.raises(MsgDefError, match=match) as err:
        schema_text(type_name, [str(tmp_path)])
    assert type_name in str(err.value)
