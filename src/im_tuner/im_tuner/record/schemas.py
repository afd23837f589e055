"""Complete ROS 2 message definitions (MCAP schema texts) from installed .msg/.srv/.idl files.

:func:`schema_for` returns what an MCAP schema (or a rosbag2 bag) carries for a type, so
that readers without the ROS type support (``rosbags``, ``mcap_ros2``, Foxglove) decode its
CDR messages: ``ros2msg`` for messages and service parts, ``ros2idl`` for service events,
each in rosbag2's layout (docs/recorder.md, "What is in a bag"). Files are looked up as
``<prefix>/share/<pkg>/msg/<Name>.msg`` (``srv/<Name>.srv``, ``.idl``) for each prefix in
turn (default: ``AMENT_PREFIX_PATH``); the first prefix that has the file wins. Pure
standard library: no rclpy needed."""

from __future__ import annotations

import os
import re
from pathlib import Path

SEPARATOR = '=' * 80
"""The line that introduces every dependency's definition."""

PRIMITIVE_TYPES = frozenset(
    {
        'bool',
        'byte',
        'char',
        'float32',
        'float64',
        'int8',
        'uint8',
        'int16',
        'uint16',
        'int32',
        'uint32',
        'int64',
        'uint64',
        'string',
        'wstring',
    }
)

_PART_SUFFIXES = ('_Request', '_Response')
_EVENT_SUFFIX = '_Event'
_PKG_RE = re.compile(r'[a-z][a-z0-9_]*')
_NAME_RE = re.compile(r'[A-Za-z][A-Za-z0-9_]*')
_ARRAY_RE = re.compile(r'\[(?:<=)?[0-9]*\]$')
_BOUNDED_STRING_RE = re.compile(r'^(w?string)<=[0-9]+$')


class MsgDefError(Exception):
    """A type name is malformed, or its definition (or a dependency's) is missing or unparsable."""


# A definition to emit: (package, "msg" or "srv", name),
# e.g. ("std_srvs", "srv", "Trigger_Request").
_Key = tuple[str, str, str]


def schema_text(type_name: str, prefixes: list[str] | None = None) -> str:
    """The complete ``ros2msg`` definition of ``type_name`` (``pkg/msg/Name``, ``pkg/Name``,
    ``pkg/srv/Name_Request``, ``_Response`` or ``_Event``): its text, then each type it uses,
    transitively, once, depth-first in order of first use, after a line of 80 ``=`` and
    ``MSG: pkg/Type``. :class:`MsgDefError` names the type and the files searched."""
    root = _parse_type_name(type_name)
    loader = _Loader.of(type_name, prefixes)
    pkg, kind, name = root
    if kind == 'srv' and name.endswith(_EVENT_SUFFIX):
        service = name[: -len(_EVENT_SUFFIX)]
        loader.srv_parts(pkg, service, type_name)  # fail early, naming the requested type
        top_text = (
            'service_msgs/ServiceEventInfo info\n'
            f'{pkg}/{service}_Request[<=1] request\n'
            f'{pkg}/{service}_Response[<=1] response\n'
        )
        top_deps = [
            ('service_msgs', 'msg', 'ServiceEventInfo'),
            (pkg, 'srv', service + '_Request'),
            (pkg, 'srv', service + '_Response'),
        ]
    else:
        top_text = loader.text(root, type_name)
        top_deps = _dependencies(top_text, pkg, type_name)

    sections = [top_text]
    seen = {f'{pkg}/{name}'}

    def visit(deps: list[_Key], parent: str) -> None:
        for dep in deps:
            short = f'{dep[0]}/{dep[2]}'
            if short in seen:
                continue
            seen.add(short)
            text = loader.text(dep, short, referenced_by=parent)
            sections.extend((SEPARATOR, f'MSG: {short}', text))
            visit(_dependencies(text, dep[0], short), short)

    visit(top_deps, f'{pkg}/{name}')
    return '\n'.join(sections)


def schema_for(type_name: str, prefixes: list[str] | None = None) -> tuple[str, str]:
    """``(encoding, text)`` of the MCAP schema to record ``type_name`` with: ``ros2idl``
    (:func:`schema_idl`) for a service event, whose ``ros2msg`` form rosbags cannot match to
    its type hash; ``ros2msg`` (:func:`schema_text`) otherwise."""
    _pkg, kind, name = _parse_type_name(type_name)
    if kind == 'srv' and name.endswith(_EVENT_SUFFIX):
        return 'ros2idl', schema_idl(type_name, prefixes)
    return 'ros2msg', schema_text(type_name, prefixes)


_INCLUDE_RE = re.compile(
    r'^#include "([a-z][a-z0-9_]*/(?:msg|srv)/[A-Za-z][A-Za-z0-9_]*)\.idl"\s*$', re.M
)
# @verbatim(language="comment", text="..." "...") -- a comment; its strings may hold ')'
_VERBATIM_RE = re.compile(r'@verbatim\s*\((?:[^()"]|"(?:[^"\\]|\\.)*")*\)\s*')


def schema_idl(type_name: str, prefixes: list[str] | None = None) -> str:
    """The ``ros2idl`` schema of a service event type ``pkg/srv/Name_Event`` in rosbag2's
    form: sections ``<80 '='>`` / ``IDL: pkg/kind/Name`` / IDL text, the event struct rosidl
    generates first, then the installed ``share/pkg/srv/Name.idl`` and every ``.idl`` it
    includes, each once, without ``#include`` lines and ``@verbatim`` annotations (comments,
    which rosbags' IDL parser refuses before a struct)."""
    pkg, kind, name = _parse_type_name(type_name)
    if kind != 'srv' or not name.endswith(_EVENT_SUFFIX):
        raise MsgDefError(f'{type_name}: only service event types are written as IDL')
    loader = _Loader.of(type_name, prefixes)
    service = name[: -len(_EVENT_SUFFIX)]
    sections = [
        (
            type_name,
            f'module {pkg} {{\n  module srv {{\n    struct {name} {{\n'
            '      service_msgs::msg::ServiceEventInfo info;\n'
            f'      sequence<{pkg}::srv::{service}_Request, 1> request;\n'
            f'      sequence<{pkg}::srv::{service}_Response, 1> response;\n'
            '    };\n  };\n};\n',
        )
    ]
    seen = {type_name}
    todo = [(f'{pkg}/srv/{service}', type_name), ('service_msgs/msg/ServiceEventInfo', type_name)]
    while todo:
        file_type, parent = todo.pop(0)
        if file_type in seen:
            continue
        seen.add(file_type)
        fpkg, folder, fname = file_type.split('/')
        text = loader.read_file(fpkg, folder, fname + '.idl', file_type, parent)
        todo.extend((inc, file_type) for inc in _INCLUDE_RE.findall(text))
        text = _VERBATIM_RE.sub('', _INCLUDE_RE.sub('', text))
        sections.append((file_type, text))
    return ''.join(f'{SEPARATOR}\nIDL: {n}\n{t}' for n, t in sections)


def _parse_type_name(type_name: str) -> _Key:
    """Split ``pkg/msg/Name``, ``pkg/Name`` or ``pkg/srv/Name_{Request,Response,Event}``."""
    parts = type_name.split('/') if isinstance(type_name, str) else []
    if len(parts) == 2:
        parts.insert(1, 'msg')
    if (
        len(parts) != 3
        or parts[1] not in ('msg', 'srv')
        or not _PKG_RE.fullmatch(parts[0])
        or not _NAME_RE.fullmatch(parts[2])
    ):
        raise MsgDefError(
            f'malformed type name {type_name!r}: expected pkg/msg/Name, pkg/Name or '
            'pkg/srv/Name_Request|_Response|_Event'
        )
    if parts[1] == 'srv' and not parts[2].endswith((*_PART_SUFFIXES, _EVENT_SUFFIX)):
        raise MsgDefError(
            f'{type_name} is a service, not a message: name its _Request, _Response or _Event'
        )
    return parts[0], parts[1], parts[2]


def _dependencies(text: str, package: str, owner: str) -> list[_Key]:
    """Non-primitive field types of a .msg text, as ``(pkg, "msg", Name)``, in order of use."""
    deps: list[_Key] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        typ, *more = line.split(None, 1)
        rest = more[0] if more else ''
        if not rest:
            raise MsgDefError(f'cannot parse the definition of {owner}, line {lineno}: {raw!r}')
        if '=' in rest and _NAME_RE.fullmatch(rest.partition('=')[0].strip()):
            continue  # constant: TYPE NAME=VALUE (constants are always primitive)
        typ = _ARRAY_RE.sub('', typ)
        typ = _BOUNDED_STRING_RE.sub(r'\1', typ)
        if typ in PRIMITIVE_TYPES:
            continue
        if typ == 'Header':
            typ = 'std_msgs/Header'
        dep_pkg, _, dep_name = typ.rpartition('/') if '/' in typ else (package, '/', typ)
        if not _PKG_RE.fullmatch(dep_pkg) or not _NAME_RE.fullmatch(dep_name):
            raise MsgDefError(
                f'cannot parse the definition of {owner}, line {lineno}: bad type {typ!r}'
            )
        deps.append((dep_pkg, 'msg', dep_name))
    return deps


class _Loader:
    """Reads definition files from the first prefix that has them (cached per call)."""

    def __init__(self, prefixes: list[str]) -> None:
        self.prefixes = prefixes
        self._cache: dict[Path, str] = {}

    @classmethod
    def of(cls, type_name: str, prefixes: list[str] | None) -> _Loader:
        """A loader for ``type_name`` over ``prefixes`` (None: ``AMENT_PREFIX_PATH``)."""
        if prefixes is None:
            prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
            if not prefixes:
                raise MsgDefError(f'cannot look up {type_name}: AMENT_PREFIX_PATH is not set')
        return cls(list(prefixes))

    def read_file(self, pkg: str, folder: str, filename: str, what: str, referenced_by: str) -> str:
        """The text of ``share/<pkg>/<folder>/<filename>`` in the first prefix that has it
        (``what`` and ``referenced_by`` name it in the error: MsgDefError)."""
        candidates = [Path(p) / 'share' / pkg / folder / filename for p in self.prefixes]
        for path in candidates:
            if path in self._cache:
                return self._cache[path]
            if path.is_file():
                try:
                    text = path.read_text(encoding='utf-8')
                except (OSError, UnicodeDecodeError) as exc:
                    raise MsgDefError(
                        f'cannot read the definition of {what} from {path}: {exc}'
                    ) from exc
                self._cache[path] = text
                return text
        needed = f' (used by {referenced_by})' if referenced_by else ''
        raise MsgDefError(
            f'no definition of {what}{needed}: searched ' + ', '.join(str(c) for c in candidates)
        )

    def srv_parts(
        self, pkg: str, service: str, what: str, referenced_by: str = ''
    ) -> tuple[str, str]:
        """(request, response) texts of ``share/<pkg>/srv/<service>.srv``."""
        text = self.read_file(pkg, 'srv', service + '.srv', what, referenced_by)
        lines = text.splitlines(keepends=True)
        cuts = [i for i, line in enumerate(lines) if line.strip() == '---']
        if len(cuts) != 1:
            raise MsgDefError(
                f'cannot parse the definition of {what}: {pkg}/srv/{service}.srv needs exactly '
                f"one '---' line, found {len(cuts)}"
            )
        request = ''.join(lines[: cuts[0]])
        request = request[:-1] if request.endswith('\n') else request
        return request, ''.join(lines[cuts[0] + 1 :])

    def text(self, key: _Key, what: str, referenced_by: str = '') -> str:
        """The definition text of a message or of one part of a service."""
        pkg, kind, name = key
        if kind == 'msg':
            return self.read_file(pkg, 'msg', name + '.msg', what, referenced_by)
        is_request = name.endswith(_PART_SUFFIXES[0])
        service = name[: -len(_PART_SUFFIXES[0 if is_request else 1])]
        request, response = self.srv_parts(pkg, service, what, referenced_by)
        return request if is_request else response
