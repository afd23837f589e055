"""The package graph reads im_drive_sim <- im_controller <- im_tuner, nothing runs
upward, and each package.xml declares exactly what its modules import (what rosdep on a
ROS machine installs). Static: reads the sources with ``ast``, imports nothing."""

from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

SRC = Path(__file__).resolve().parent.parent / 'src'
PACKAGES = ('im_drive_sim', 'im_controller', 'im_tuner')
#: what each package may import of the others (the graph: drive <- controller <- tuner)
ALLOWED = {
    'im_drive_sim': set(),
    'im_controller': {'im_drive_sim'},
    'im_tuner': {'im_drive_sim', 'im_controller'},
}
#: top-level Python module -> its rosdep key (ROS packages are their own keys)
ROSDEP = {
    'numpy': 'python3-numpy',
    'yaml': 'python3-yaml',
    'numba': 'python3-numba-pip',
    'llvmlite': 'python3-numba-pip',  # numba's own compiler back end, installed with it
    'zstandard': 'python3-zstandard',
    'lz4': 'python3-lz4',
    'matplotlib': 'python3-matplotlib',
    'mcap': 'python3-mcap-pip',
    'mcap_ros2': 'python3-mcap-ros2-support-pip',
    'foxglove': 'python3-foxglove-sdk-pip',  # Foxglove's SDK: the layouts' typed classes
    'scipy': 'python3-scipy',
    'threadpoolctl': 'python3-threadpoolctl',  # the numeric baseline's check
    'cma': 'python3-cma-pip',
    'optuna': 'python3-optuna-pip',
    'pybobyqa': 'python3-py-bobyqa-pip',  # the study's reference row
    'dask': 'python3-dask',
    'distributed': 'python3-distributed',
    'foxglove_websocket': 'python3-foxglove-websocket-pip',  # the live view's server
    'websockets': 'python3-websockets',
}
ROS_PACKAGES = {
    'rclpy',
    'std_msgs',
    'sensor_msgs',
    'diagnostic_msgs',
    'rosgraph_msgs',
    'rcl_interfaces',
    'std_srvs',
    'service_msgs',
    'builtin_interfaces',
    'rosidl_runtime_py',
    'rpyutils',
}


#: declared dependencies no module imports, and why each is needed all the same
RUNTIME_ONLY = {
    'im_tuner': {
        # the recorder writes each recorded type's definition into the MCAP schema, read
        # from the package's share directory (msgdefs): /clock, joint states, the
        # controller's and drive's messages, service events and parameter events
        'rosgraph_msgs',
        'sensor_msgs',
        'std_msgs',
        'service_msgs',
        'rcl_interfaces',
    },
}


def _modules(pkg: str) -> list[Path]:
    root = SRC / pkg / pkg
    return sorted(p for p in root.rglob('*.py') if '__pycache__' not in p.parts)


def _imports(path: Path) -> set[str]:
    """Top-level names of every absolute import in the module (function-level too)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name.split('.')[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split('.')[0])
    return out


def _declared(pkg: str) -> set[str]:
    root = ET.parse(SRC / pkg / 'package.xml').getroot()
    tags = ('depend', 'exec_depend', 'build_export_depend')
    return {e.text.strip() for t in tags for e in root.findall(t) if e.text}


def _needed(pkg: str) -> dict[str, set[str]]:
    """rosdep key -> the modules that import it."""
    need: dict[str, set[str]] = {}
    for path in _modules(pkg):
        for top in _imports(path):
            if top in sys.stdlib_module_names or top == pkg:
                continue
            key = ROSDEP.get(top, top)
            assert key in ROS_PACKAGES or key in PACKAGES or top in ROSDEP, (
                f'{path.relative_to(SRC)} imports {top!r}: add its rosdep key to this test'
            )
            need.setdefault(key, set()).add(str(path.relative_to(SRC / pkg)))
    return need


@pytest.mark.parametrize('pkg', PACKAGES)
def test_no_module_imports_upward(pkg: str) -> None:
    bad = {
        str(p.relative_to(SRC)): sorted(_imports(p) & (set(PACKAGES) - ALLOWED[pkg] - {pkg}))
        for p in _modules(pkg)
    }
    assert {k: v for k, v in bad.items() if v} == {}


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_xml_declares_what_the_package_imports(pkg: str) -> None:
    need, declared = _needed(pkg), _declared(pkg)
    missing = {k: sorted(v) for k, v in need.items() if k not in declared}
    assert missing == {}, f'{pkg}/package.xml lacks exec_depend for {missing}'
    unused = declared - set(need) - RUNTIME_ONLY.get(pkg, set())
    assert unused == set(), f'{pkg}/package.xml declares {sorted(unused)}, which nothing imports'


def test_the_contract_modules_are_pure() -> None:
    """The contracts are importable without rclpy or numba (tools read them without ROS)."""
    for rel in ('im_drive_sim/im_drive_sim/contract.py', 'im_controller/im_controller/contract.py'):
        assert _imports(SRC / rel) <= set(sys.stdlib_module_names), rel
