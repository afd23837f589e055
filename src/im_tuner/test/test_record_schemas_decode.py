"""im_tuner.record.schemas, decoded: rclpy's CDR bytes of each recorded type read back
through the schema text by two independent readers, and service events as IDL.

The readers are ``rosbags`` (its own .msg parser and CDR deserialiser) and ``mcap_ros2`` (the
MCAP project's dynamic decoder); the CDR bytes come from rclpy's own serialiser, so a schema
that misdescribes a type shows up as wrong or failing decodes. Layout, errors and custom
prefixes: test_record_schemas.py.
"""

from __future__ import annotations

import array
import os
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2._vendor.rosidl_adapter.parser import InvalidResourceName
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

from im_tuner.record import schemas as msgdefs

MsgDefError = msgdefs.MsgDefError
schema_text = msgdefs.schema_text

SEP = '=' * 80


# --- round trip through rclpy's serialiser and two independent readers -------------------------


def _mcap_decoder(type_name: str, text: str) -> Callable[[bytes], Any]:
    """mcap_ros2's decoder for ``text``.

    mcap_ros2 0.6.0 validates the *schema name* with a rosidl_adapter older than service
    introspection: it accepts ``_Request``/``_Response`` but refuses ``Name_Event`` as a message
    name, whatever the text (see test_mcap_ros2_refuses_event_schema_names).  The text itself is
    fine, so event types are decoded under the alias ``pkg/srv/NameEvent``.
    """
    name = type_name
    if type_name.endswith('_Event'):
        name = type_name[: -len('_Event')] + 'Event'
    return generate_dynamic(name, text)[name]


def _rosbags_decode(type_name: str, text: str, data: bytes) -> Any:
    """Parse ``text`` with rosbags into an empty typestore and deserialise ``data``.

    rosbags normalises every name that is not ``pkg/msg/Name`` by inserting ``msg``: a service
    event type ``pkg/srv/Name_Event`` is registered as ``pkg/srv/msg/Name_Event`` (look it up
    by that name), and it resolves a top-level definition's package-less field types in that
    name's folder.  A request/response text uses such types (``Parameter[] parameters``), which
    would become ``pkg/srv/msg/Parameter``; so those are given to rosbags under the two-part
    name they carry inside event schemas, ``pkg/Name_Request`` (-> ``pkg/msg/Name_Request``).
    The event text itself only uses qualified names, so it is unaffected.

    ``Typestore.deserialize_cdr`` insists that the message ends within 3 bytes of the buffer,
    but rclpy's ``serialize_message`` (rmw_fastrtps_cpp ``rmw_serialize``) returns a buffer of
    the type support's *estimated* size, so a few uninitialised bytes may follow the message
    (an empty JointState: 36 bytes of CDR in a 44-byte buffer).  So the same deserialiser is
    called one level down, and it must end inside the buffer.
    """
    if type_name.endswith(('_Request', '_Response')):
        pkg, _, name = type_name.split('/')
        type_name = f'{pkg}/{name}'
    types = get_types_from_msg(text, type_name)
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    assert data[:4] == b'\x00\x01\x00\x00'  # CDR, little endian
    msgdef = store.get_msgdef(normalize_msgtype(type_name))
    message, end = msgdef.deserialize_cdr_le(data[4:], 0, msgdef.cls, store)
    assert 4 + end <= len(data)
    return message


def _plain(value: Any) -> Any:
    """A decoded or rclpy leaf value as plain Python (bytes/char as int, arrays as lists)."""
    if isinstance(value, (bytes, bytearray)) and len(value) == 1:
        return value[0]
    if isinstance(value, (np.ndarray, array.array)):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return value.item()
    return value


def assert_same(expected: Any, decoded: Any, where: str = 'msg') -> None:
    """Every field of the rclpy message ``expected`` equals the decoded one, recursively."""
    if hasattr(expected, 'get_fields_and_field_types'):
        for field in expected.get_fields_and_field_types():
            assert_same(getattr(expected, field), getattr(decoded, field), f'{where}.{field}')
    elif isinstance(expected, (list, tuple)) or (
        isinstance(expected, (np.ndarray, array.array)) and not isinstance(decoded, bytes)
    ):
        got = list(decoded)
        assert len(got) == len(expected), f'{where}: length {len(got)} != {len(expected)}'
        for i, (e, d) in enumerate(zip(expected, got, strict=True)):
            assert_same(e, d, f'{where}[{i}]')
    else:
        assert _plain(decoded) == _plain(expected), f'{where}: {decoded!r} != {expected!r}'


def _stamp(sec: int, nanosec: int) -> Any:
    from builtin_interfaces.msg import Time

    return Time(sec=sec, nanosec=nanosec)


def _event(srv: Any, request: Any, response: Any) -> Any:
    from service_msgs.msg import ServiceEventInfo

    ev = srv.Event()
    ev.info = ServiceEventInfo(
        event_type=ServiceEventInfo.RESPONSE_SENT,
        stamp=_stamp(7, 8),
        client_gid=list(range(1, 17)),
        sequence_number=42,
    )
    ev.request = [request]
    ev.response = [response]
    return ev


def make_float64multiarray() -> Any:
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

    return Float64MultiArray(
        layout=MultiArrayLayout(
            dim=[MultiArrayDimension(label='x', size=3, stride=3)], data_offset=1
        ),
        data=[1.5, -2.25, 3.0e10],
    )


def make_jointstate() -> Any:
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    return JointState(
        header=Header(stamp=_stamp(12, 345), frame_id='base'),
        name=['shaft', 'load'],
        position=[0.125, -1.5],
        velocity=[2.0, 3.0],
        effort=[0.5, -4.0],
    )


def make_diagnosticarray() -> Any:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from std_msgs.msg import Header

    return DiagnosticArray(
        header=Header(stamp=_stamp(1, 2), frame_id='d'),
        status=[
            DiagnosticStatus(
                level=DiagnosticStatus.WARN,
                name='motor',
                message='hot',
                hardware_id='im0',
                values=[KeyValue(key='temp', value='81')],
            )
        ],
    )


def make_clock() -> Any:
    from rosgraph_msgs.msg import Clock

    return Clock(clock=_stamp(5, 600))


def make_parameterevent() -> Any:
    from rcl_interfaces.msg import Parameter, ParameterEvent, ParameterType, ParameterValue

    return ParameterEvent(
        stamp=_stamp(3, 4),
        node='/tuner',
        new_parameters=[
            Parameter(
                name='k_pos',
                value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=0.75),
            )
        ],
        changed_parameters=[
            Parameter(
                name='tags',
                value=ParameterValue(
                    type=ParameterType.PARAMETER_STRING_ARRAY, string_array_value=['a', 'b']
                ),
            )
        ],
        deleted_parameters=[Parameter(name='old')],
    )


def make_log() -> Any:
    from rcl_interfaces.msg import Log

    return Log(
        stamp=_stamp(9, 10),
        level=Log.WARN,
        name='tuner',
        msg='hello',
        file='t.py',
        function='f',
        line=77,
    )


def make_trigger_event() -> Any:
    from std_srvs.srv import Trigger

    return _event(
        Trigger, Trigger.Request(), Trigger.Response(success=True, message='triggered ok')
    )


def make_empty_event() -> Any:
    from std_srvs.srv import Empty

    return _event(Empty, Empty.Request(), Empty.Response())


def make_setparameters_event() -> Any:
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue, SetParametersResult
    from rcl_interfaces.srv import SetParameters

    return _event(
        SetParameters,
        SetParameters.Request(
            parameters=[
                Parameter(
                    name='gains.k_pw',
                    value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=1.25),
                )
            ]
        ),
        SetParameters.Response(results=[SetParametersResult(successful=False, reason='range')]),
    )


def make_getparameters_event() -> Any:
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters

    return _event(
        GetParameters,
        GetParameters.Request(names=['k_pos', 'tau_sm']),
        GetParameters.Response(
            values=[
                ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=-3),
                ParameterValue(type=ParameterType.PARAMETER_BOOL_ARRAY, bool_array_value=[True]),
            ]
        ),
    )


def make_setparameters_request() -> Any:
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    return SetParameters.Request(
        parameters=[
            Parameter(
                name='ff',
                value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value='model'),
            )
        ]
    )


def make_trigger_request() -> Any:
    from std_srvs.srv import Trigger

    return Trigger.Request()


def make_empty() -> Any:
    from std_msgs.msg import Empty

    return Empty()


def check_float64multiarray(m: Any) -> None:
    assert _plain(m.data) == [1.5, -2.25, 3.0e10]
    assert m.layout.dim[0].label == 'x' and m.layout.data_offset == 1


def check_jointstate(m: Any) -> None:
    assert list(m.name) == ['shaft', 'load']
    assert _plain(m.position) == [0.125, -1.5] and _plain(m.effort) == [0.5, -4.0]
    assert m.header.stamp.nanosec == 345 and m.header.frame_id == 'base'


def check_diagnosticarray(m: Any) -> None:
    assert m.status[0].name == 'motor' and m.status[0].values[0].value == '81'


def check_clock(m: Any) -> None:
    assert (m.clock.sec, m.clock.nanosec) == (5, 600)


def check_parameterevent(m: Any) -> None:
    assert m.new_parameters[0].name == 'k_pos'
    assert m.new_parameters[0].value.double_value == 0.75
    assert list(m.changed_parameters[0].value.string_array_value) == ['a', 'b']
    assert m.deleted_parameters[0].name == 'old'


def check_log(m: Any) -> None:
    assert (m.msg, m.line, m.level) == ('hello', 77, 30)


def check_trigger_event(m: Any) -> None:
    assert m.info.event_type == 2 and m.info.sequence_number == 42
    assert len(m.request) == 1
    assert m.response[0].success is True and m.response[0].message == 'triggered ok'


def check_empty_event(m: Any) -> None:
    assert len(m.request) == 1 and len(m.response) == 1 and m.info.sequence_number == 42


def check_setparameters_event(m: Any) -> None:
    assert m.request[0].parameters[0].name == 'gains.k_pw'
    assert m.request[0].parameters[0].value.double_value == 1.25
    assert m.response[0].results[0].reason == 'range'


def check_getparameters_event(m: Any) -> None:
    assert list(m.request[0].names) == ['k_pos', 'tau_sm']
    assert m.response[0].values[0].integer_value == -3
    assert list(m.response[0].values[1].bool_array_value) == [True]


def check_setparameters_request(m: Any) -> None:
    assert m.parameters[0].name == 'ff' and m.parameters[0].value.string_value == 'model'


def check_nothing(m: Any) -> None:
    """Messages without fields: assert_same has compared all there is."""


# (type name, rclpy message factory, spot check of a decoded message)
CASES: list[tuple[str, Callable[[], Any], Callable[[Any], None]]] = [
    ('std_msgs/msg/Float64MultiArray', make_float64multiarray, check_float64multiarray),
    ('sensor_msgs/msg/JointState', make_jointstate, check_jointstate),
    ('diagnostic_msgs/msg/DiagnosticArray', make_diagnosticarray, check_diagnosticarray),
    ('rosgraph_msgs/msg/Clock', make_clock, check_clock),
    ('rcl_interfaces/msg/ParameterEvent', make_parameterevent, check_parameterevent),
    ('rcl_interfaces/msg/Log', make_log, check_log),
    ('std_srvs/srv/Trigger_Event', make_trigger_event, check_trigger_event),
    ('std_srvs/srv/Empty_Event', make_empty_event, check_empty_event),
    ('rcl_interfaces/srv/SetParameters_Event', make_setparameters_event, check_setparameters_event),
    ('rcl_interfaces/srv/GetParameters_Event', make_getparameters_event, check_getparameters_event),
    (
        'rcl_interfaces/srv/SetParameters_Request',
        make_setparameters_request,
        check_setparameters_request,
    ),
    ('std_srvs/srv/Trigger_Request', make_trigger_request, check_nothing),
    ('std_msgs/msg/Empty', make_empty, check_nothing),
]


@pytest.mark.parametrize('type_name,make,spot', CASES, ids=[c[0] for c in CASES])
def test_round_trip_rclpy_to_rosbags_and_mcap_ros2(
    type_name: str, make: Callable[[], Any], spot: Callable[[Any], None]
) -> None:
    from rclpy.serialization import serialize_message

    text = schema_text(type_name)
    original = make()
    data = serialize_message(original)

    by_rosbags = _rosbags_decode(type_name, text, data)
    assert_same(original, by_rosbags)
    spot(by_rosbags)

    by_mcap = _mcap_decoder(type_name, text)(data)
    assert_same(original, by_mcap)
    spot(by_mcap)


def test_mcap_ros2_refuses_event_schema_names() -> None:
    """Pins the mcap_ros2 0.6.0 limitation that _mcap_decoder works around (name, not text)."""
    text = schema_text('std_srvs/srv/Trigger_Event')
    with pytest.raises(InvalidResourceName, match='Trigger_Event'):
        generate_dynamic('std_srvs/srv/Trigger_Event', text)
    # Request/response names carry suffixes it does accept.
    assert 'std_srvs/Trigger_Response' in generate_dynamic('std_srvs/srv/TriggerEvent', text)


# --- service events as IDL: what rosbags' AnyReader needs ---------------------------------------

EVENT_CASES = [c for c in CASES if c[0].endswith('_Event')]


def _idl_store(text: str):
    """A rosbags typestore from a ros2idl schema in rosbag2's sectioned form, parsed as
    rosbags' AnyReader parses it."""
    from rosbags.typesys import get_types_from_idl

    sep = SEP + '\n'
    assert text.startswith(sep + 'IDL: ')
    types: dict = {}
    for section in text.split(sep)[1:]:
        header, idl = section.split('\n', 1)
        assert header.startswith('IDL: ')
        types.update(get_types_from_idl(idl))
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


@pytest.mark.parametrize('type_name,make,spot', EVENT_CASES, ids=[c[0] for c in EVENT_CASES])
def test_service_event_idl_registers_under_its_own_name_and_decodes(
    type_name: str, make: Callable[[], Any], spot: Callable[[Any], None]
) -> None:
    from rclpy.serialization import serialize_message

    encoding, text = msgdefs.schema_for(type_name)
    assert encoding == 'ros2idl' and text == msgdefs.schema_idl(type_name)
    store = _idl_store(text)
    assert type_name in store.fielddefs  # pkg/srv/Name_Event, not pkg/srv/msg/Name_Event
    original = make()
    data = serialize_message(original)
    msgdef = store.get_msgdef(type_name)
    decoded, end = msgdef.deserialize_cdr_le(data[4:], 0, msgdef.cls, store)
    assert 4 + end <= len(data)
    assert_same(original, decoded)
    spot(decoded)


# RIHS01 type hashes of ROS 2 Jazzy (what `ros2 topic info -v` and rosbag2 report; read off
# the endpoints of live services by the recorder, see test_tuner's bag test)
JAZZY_HASHES = {
    'std_srvs/srv/Trigger_Event': (
        'RIHS01_ec4a1d26b0575e61906890342aba9523a2360e9845857c5590fa6e23bc39e1c2'
    ),
    'rcl_interfaces/srv/DescribeParameters_Event': (
        'RIHS01_3deba64c035093033c690184834441551a53128ea2539f71f2596fbc4ed9de43'
    ),
}


@pytest.mark.parametrize('type_name', sorted(JAZZY_HASHES))
def test_service_event_idl_gives_the_ros_type_hash(type_name: str) -> None:
    """AnyReader checks each connection's type_description_hash against the hash it
    recomputes from the schema: the IDL must describe exactly ROS's type."""
    store = _idl_store(msgdefs.schema_idl(type_name))
    assert store.hash_rihs01(type_name) == JAZZY_HASHES[type_name]


def test_service_event_idl_layout() -> None:
    text = msgdefs.schema_idl('rcl_interfaces/srv/DescribeParameters_Event')
    headers = [line[5:] for line in text.splitlines() if line.startswith('IDL: ')]
    assert headers == [
        'rcl_interfaces/srv/DescribeParameters_Event',
        'rcl_interfaces/srv/DescribeParameters',
        'service_msgs/msg/ServiceEventInfo',
        'rcl_interfaces/msg/ParameterDescriptor',
        'builtin_interfaces/msg/Time',
        'rcl_interfaces/msg/FloatingPointRange',
        'rcl_interfaces/msg/IntegerRange',
    ]
    assert '#include' not in text and '@verbatim' not in text
    assert 'sequence<rcl_interfaces::srv::DescribeParameters_Request, 1> request;' in text
    assert msgdefs.schema_for('std_msgs/msg/String')[0] == 'ros2msg'
    with pytest.raises(MsgDefError, match='only service event types'):
        msgdefs.schema_idl('std_msgs/msg/String')
